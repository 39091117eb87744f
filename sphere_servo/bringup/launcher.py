"""``launcher``: start the servo pipeline's nodes as separate processes from one YAML config.

    launcher --config special_sphere [--until-converged] [--timeout 120] [--record DIR]

The config is a ROS 2 parameters file (one ``<node>: ros__parameters:`` section per node)
plus a ``launch:`` section read only by the launcher::

    launch:
      include: [arm_sim.yaml]   # merged first (paths relative to this file); later wins
      nodes: [arm_sim, detector, features, servo]
      teach: true               # arm to desired → teach that image → arm to start
      timeout: 120.0            # wall seconds for --until-converged

``--config`` takes a path, or a name looked up in the installed ``share/sphere_servo/config``
and then in the source tree's ``config/``. Executables are resolved as ``ros2 run`` does
(``get_package_prefix('sphere_servo')/lib/sphere_servo/<name>``), falling back to
``python -m sphere_servo.ros.<name>`` when the package is not installed (a source
checkout). Each process's output is forwarded with a ``[name]`` prefix. Ctrl-C (or SIGTERM)
stops the servo first (its last word is a zero twist), then the recorder (while the others
still live: it takes what is still on its way before closing the bag), then the others:
SIGINT, then SIGKILL after 10 s. With ``--record`` the run (teach included) begins once the
recorder reports that it records every topic. With ``--until-converged`` the exit code is 0
when the servo reports ``converged``, 1 on timeout, 3 if a node died, 4 if the teach
sequence failed. On Linux the nodes are terminated (SIGTERM) if the launcher itself dies,
even by SIGKILL; the kernel ties this to the thread that started them, so start a
:class:`Launcher` from a thread that outlives the run.
"""
from __future__ import annotations

import argparse
import collections
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from sphere_servo.pipeline.config import (ConfigError, find_config, load_config,  # noqa: F401
                                          merge, node_params, package_prefix)

MODULES = {'arm_sim': 'sphere_servo.ros.arm_sim', 'detector': 'sphere_servo.ros.detector',
           'features': 'sphere_servo.ros.features', 'servo': 'sphere_servo.ros.servo',
           'record': 'sphere_servo.bag.record'}
STOP_ORDER = ('servo', 'record', 'features', 'detector', 'arm_sim')
RECORD_READY_TIMEOUT = 30.0  # wall s the run waits for the recorder to match every topic
HISTORY_DEPTH = 1000  # the supervisor's subscriptions to the per-frame topics


class LaunchError(ConfigError):
    """The config, an executable or the run cannot be used."""


# --- processes -----------------------------------------------------------------------------
def node_command(name: str) -> list[str]:
    """How ``ros2 run sphere_servo <name>`` would start it, or ``python -m`` from source."""
    prefix = package_prefix()
    if prefix is not None:
        exe = prefix / 'lib' / 'sphere_servo' / name
        if exe.is_file() and os.access(exe, os.X_OK):
            return [str(exe)]
    if name not in MODULES:
        raise LaunchError(f'unknown node {name!r}')
    return [sys.executable, '-m', MODULES[name]]


def interrupt(popen: subprocess.Popen, timeout: float = 10.0) -> int:
    """Stop a process as Ctrl-C does (SIGINT), SIGKILL it after ``timeout`` s; exit code."""
    if popen.poll() is None:
        popen.send_signal(signal.SIGINT)
        try:
            popen.wait(timeout)
        except subprocess.TimeoutExpired:
            popen.kill()
            popen.wait(5)
    return popen.returncode


def _libc():
    """libc for prctl, loaded once in the launcher (the forked child must not load it)."""
    try:
        import ctypes
        return ctypes.CDLL(None, use_errno=True)
    except (OSError, AttributeError):
        return None


_LIBC = _libc() if sys.platform.startswith('linux') else None
PR_SET_PDEATHSIG = 1


def _die_with(parent_pid: int):
    """``preexec_fn`` of a node (Linux): the kernel sends it SIGTERM when the launcher dies,
    even by SIGKILL, so no orphaned node keeps driving the arm (SIGTERM is the nodes' clean
    shutdown: the servo's last word is a zero twist). If the launcher died before this ran,
    the node is terminated at once."""
    libc = _LIBC

    def preexec():
        if libc is not None:
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
            if os.getppid() != parent_pid:
                os.kill(os.getpid(), signal.SIGTERM)
    return preexec


@dataclass
class Child:
    name: str
    popen: subprocess.Popen
    thread: threading.Thread | None = None


def _forward(name: str, stream, out) -> None:
    for line in iter(stream.readline, ''):
        out.write(f'[{name}] {line}' if line.endswith('\n') else f'[{name}] {line}\n')
        out.flush()
    stream.close()


@dataclass
class Launcher:
    """Starts, watches and stops the pipeline described by a merged config."""

    config: dict
    out: object = sys.stdout
    env: dict | None = None  # the children's environment (default: this process's)
    children: dict = field(default_factory=dict)
    params_file: str = ''

    def start(self, extra: dict | None = None) -> None:
        """Start every node of ``launch.nodes`` (``extra``: name → extra argv)."""
        nodes = (self.config.get('launch') or {}).get(
            'nodes', ['arm_sim', 'detector', 'features', 'servo'])
        params = {k: v for k, v in self.config.items() if k != 'launch'}
        fd, self.params_file = tempfile.mkstemp(prefix='sphere_servo_', suffix='.yaml')
        with os.fdopen(fd, 'w') as fh:
            yaml.safe_dump(params, fh)
        for name in nodes:
            cmd = node_command(name) + ['--ros-args', '--params-file', self.params_file]
            self._spawn(name, cmd)
        for name, argv in (extra or {}).items():
            self._spawn(name, node_command(name) + list(argv))

    def restart(self, name: str) -> None:
        """Start ``name`` again with the same parameters (after it died or was killed)."""
        old = self.children[name]
        if old.popen.poll() is None:
            raise LaunchError(f'{name} is still running')
        self._spawn(name, node_command(name) + ['--ros-args', '--params-file',
                                                self.params_file])

    def _spawn(self, name: str, cmd: list[str]) -> None:
        env = dict(self.env if self.env is not None else os.environ, PYTHONUNBUFFERED='1')
        popen = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True, env=env, start_new_session=True,
                                 preexec_fn=_die_with(os.getpid()))
        t = threading.Thread(target=_forward, args=(name, popen.stdout, self.out), daemon=True)
        t.start()
        self.children[name] = Child(name, popen, t)

    def dead(self) -> list[str]:
        """Names of nodes that have exited."""
        return [n for n, c in self.children.items() if c.popen.poll() is not None]

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """Stop every node (servo first), SIGINT then SIGKILL; return the exit codes."""
        order = [n for n in STOP_ORDER if n in self.children] + \
            [n for n in self.children if n not in STOP_ORDER]
        for name in order:
            interrupt(self.children[name].popen, timeout)
        for c in self.children.values():
            if c.thread is not None:
                c.thread.join(2)
        if self.params_file:
            Path(self.params_file).unlink(missing_ok=True)
        return {n: c.popen.returncode for n, c in self.children.items()}


# --- supervision over ROS ------------------------------------------------------------------
class Supervisor:
    """An rclpy node in the launcher: runs the teach sequence, watches the servo's state and,
    if asked, collects the time histories for the figures."""

    def __init__(self, config: dict, collect: bool = False, domain_id: int | None = None):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticStatus
        from geometry_msgs.msg import PoseStamped, TwistStamped
        from sensor_msgs.msg import JointState

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node('launcher', context=self.ctx)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.config = config
        self.state, self.state_values = None, {}
        self.poses: list = []          # (stamp, oMc 4×4)
        self.measurements: list = []   # (stamp, {name: value})
        self.features: list = []       # (stamp, s, s*)
        self.twists: list = []         # (stamp, v (6,))
        self.collect = collect
        self.last_pose = None
        self.last_meas_stamp = -1.0
        self.t_start = 0.0  # stamp of the first image at the start pose
        self.t_enabled = None    # stamp of the first image the enabled servo answered
        self.t_converged = None  # stamp of the first image the servo called converged, after
        #                          t_start, and the servo's iteration count there (it counts
        #                          enabled iterations only: the same from run to run)
        self.iterations_converged = None
        self._clients: dict = {}
        self.recent_poses = collections.deque(maxlen=HISTORY_DEPTH)  # (stamp, oMc)
        self.oMc_taught = None  # ground-truth camera pose of the taught image (teach: true)
        fset = node_params(config, 'servo').get('feature_set', 's_n')
        sub = self.node.create_subscription
        # deep histories: under load Fast DDS repairs what loaded sockets dropped in bursts of
        # up to seconds of messages, which a shallow keep-last history would mostly discard
        sub(DiagnosticStatus, 'servo/state', self._on_state, 10)
        sub(PoseStamped, 'ground_truth/camera_pose', self._on_pose, HISTORY_DEPTH)
        sub(JointState, 'detector/measurement', self._on_meas, HISTORY_DEPTH)
        if collect:
            sub(JointState, f'features/{fset}', self._on_features, HISTORY_DEPTH)
            sub(TwistStamped, 'camera/cmd_vel_stamped', self._on_twist, HISTORY_DEPTH)
        from std_srvs.srv import SetBool
        for service in ('/arm_sim/go_desired', '/features/teach', '/arm_sim/go_start'):
            self.client(service)
        self.client('/servo/enable', SetBool)

    def pose_at(self, t: float | None):
        """The ground-truth pose of the image stamped ``t``, if it has arrived."""
        if t is None:
            return None
        return next((M for s, M in reversed(self.recent_poses) if abs(s - t) < 1e-6), None)

    def final_pose_error(self) -> tuple[float, float] | None:
        """(m, deg) between the taught pose and the ground truth of the image the servo
        first called converged (the newest pose if that one has not arrived, or the servo
        did not converge), or None when nothing was taught or no pose arrived."""
        pose = self.pose_at(self.t_converged)
        if pose is None and self.last_pose is not None:
            pose = self.last_pose[1]
        if self.oMc_taught is None or pose is None:
            return None
        import pinocchio as pin
        cdMc = self.oMc_taught.inverse() * pose
        return (float(np.linalg.norm(cdMc.translation)),
                float(np.degrees(np.linalg.norm(pin.log3(cdMc.rotation)))))

    @staticmethod
    def _t(stamp) -> float:
        return stamp.sec + stamp.nanosec * 1e-9

    def _on_state(self, msg) -> None:
        self.state = msg.message
        self.state_values = vals = {kv.key: kv.value for kv in msg.values}
        if msg.message not in ('servoing', 'converged'):
            return
        try:
            t = float(vals.get('stamp', '-1'))
        except ValueError:
            return
        if t < self.t_start:
            return
        if self.t_enabled is None or t < self.t_enabled:
            self.t_enabled = t
        if msg.message == 'converged' and (self.t_converged is None or t < self.t_converged):
            self.t_converged = t
            self.iterations_converged = int(vals.get('iteration', -1))

    def _on_pose(self, msg) -> None:
        """``last_pose``: the newest ground truth by stamp (a late delivery of an older pose
        must not make the arm look back where it was)."""
        from sphere_servo.ros.conversions import se3_from_pose
        pose = (self._t(msg.header.stamp), se3_from_pose(msg.pose))
        if self.last_pose is None or pose[0] >= self.last_pose[0]:
            self.last_pose = pose
        self.recent_poses.append(pose)
        if self.collect:
            self.poses.append((pose[0], pose[1].homogeneous.copy()))

    def _on_meas(self, msg) -> None:
        t = self._t(msg.header.stamp)
        self.last_meas_stamp = max(self.last_meas_stamp, t)
        if self.collect:
            self.measurements.append((t, dict(zip(msg.name, msg.position))))

    def _on_features(self, msg) -> None:
        if msg.name:
            self.features.append((self._t(msg.header.stamp), np.array(msg.position),
                                  np.array(msg.velocity)))

    def _on_twist(self, msg) -> None:
        tw = msg.twist
        self.twists.append((self._t(msg.header.stamp), np.array(
            [tw.linear.x, tw.linear.y, tw.linear.z, tw.angular.x, tw.angular.y,
             tw.angular.z])))

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.02, max(0.0, end - time.monotonic())))

    def wait(self, pred, timeout: float, alive=lambda: True) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred():
                return True
            if not alive():
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return bool(pred())

    def call(self, service: str, timeout: float = 30.0, enable: bool | None = None):
        """Call a std_srvs/Trigger service (or SetBool with ``enable``); returns the response
        (or raises LaunchError)."""
        from std_srvs.srv import SetBool, Trigger
        srv = Trigger if enable is None else SetBool
        cli = self.client(service, srv)
        if not self.wait(cli.service_is_ready, timeout):
            raise LaunchError(f'service {service} not available after {timeout} s')
        req = srv.Request() if enable is None else SetBool.Request(data=enable)
        fut = cli.call_async(req)
        if not self.wait(fut.done, timeout):
            raise LaunchError(f'service {service} did not answer in {timeout} s')
        return fut.result()

    def client(self, service: str, srv=None):
        """The (kept) client of ``service``: made once, so that discovery of a client made
        early has happened by the time it is called (a fresh client per call took seconds
        to be matched under load, holding the arm at the start pose)."""
        if service not in self._clients:
            if srv is None:
                from std_srvs.srv import Trigger as srv
            self._clients[service] = self.node.create_client(srv, service)
        return self._clients[service]

    def wait_recorder(self, timeout: float, alive) -> str | None:
        """Wait until the recorder records every topic it was asked for (its ``~/ready``
        service); ``None`` when it does, else what it still waits for after ``timeout`` s.
        Under load, the recorder discovers a node's topics up to seconds after the node
        started: a run that began meanwhile would miss its first messages in the bag."""
        end = time.monotonic() + timeout
        while True:
            try:
                res = self.call('/recorder/ready', max(0.5, end - time.monotonic()))
            except LaunchError as exc:
                return str(exc)
            if res.success:
                return None
            if time.monotonic() > end or not alive():
                return res.message
            self.spin(0.1)

    def teach(self, log, alive) -> None:
        """Arm to the desired pose → teach its image → arm to the start pose → enable the
        servo. The servo must be disabled meanwhile (``start_enabled: false``): a teach
        reply can name an image taken before the jump, and a servo acting on it would move
        the arm away from the pose being taught."""
        from sphere_servo.sim.arm import pose_from_xyz_rpy
        cMo_d = pose_from_xyz_rpy(*np.split(np.asarray(
            node_params(self.config, 'arm_sim').get('desired_cMo', [0, 0, 0.45, 0, 0, 0]),
            float), 2))
        res = self.call('/arm_sim/go_desired')
        if not res.success:
            raise LaunchError(f'go_desired failed: {res.message}')
        log(f'arm at the desired pose: {res.message}')
        t_desired = _stamp_in(res.message)  # the first image at the desired pose

        def at_desired():
            if self.last_pose is None or self.last_pose[0] < t_desired - 1e-9:
                return False
            err = (cMo_d * self.last_pose[1]).translation  # cMo_d · oMc ≈ identity
            return float(np.linalg.norm(err)) < 1e-3
        if not self.wait(at_desired, 30.0, alive):
            raise LaunchError('the arm did not reach the desired pose')
        self.oMc_taught = self.last_pose[1]
        end = time.monotonic() + 30.0
        while True:  # teach the first measurement taken at the desired pose
            res = self.call('/features/teach')
            if res.success and _stamp_in(res.message) >= t_desired - 1e-9:
                break
            if time.monotonic() > end or not alive():
                raise LaunchError(f'teach failed: {res.message} (desired pose at '
                                  f'{t_desired:.6f} s, last measurement '
                                  f'{self.last_meas_stamp:.6f} s)')
            self.spin(0.2)
        log(res.message)
        res = self.call('/arm_sim/go_start')
        if not res.success:
            raise LaunchError(f'go_start failed: {res.message}')
        self.t_start = _stamp_in(res.message)  # the first image at the start pose
        if not self.wait(lambda: self.last_pose[0] >= self.t_start - 1e-9 and not at_desired(),
                         30.0, alive):
            raise LaunchError('the arm did not leave the desired pose')
        log(f'arm at the start pose: {res.message}')
        self.enable_servo(log)

    def enable_servo(self, log) -> None:
        res = self.call('/servo/enable', enable=True)
        if not res.success:
            raise LaunchError(f'cannot enable the servo: {res.message}')
        log(res.message)

    def converged(self) -> bool:
        """The servo reports convergence on an image taken after the jump to the start."""
        try:
            stamp = float(self.state_values.get('stamp', '-1'))
        except ValueError:
            return False
        return self.state == 'converged' and stamp >= self.t_start

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)


def _stamp_in(message: str) -> float:
    """The stamp 'sec.nanosec' that ends the features node's teach reply and arm_sim's
    go_* replies; -1 if there is none."""
    try:
        return float(message.rsplit(' ', 1)[-1])
    except ValueError:
        return -1.0


def run(config: dict, until_converged: bool = False, timeout: float | None = None,
        record: str | None = None, collect: bool = False, out=sys.stdout,
        progress_every: float = 1.0, env: dict | None = None):
    """Start the pipeline, teach, servo. Returns ``(exit_code, supervisor, exit_codes)``;
    the (closed) :class:`Supervisor` holds the histories when ``collect``. ``env``: the
    nodes' environment (its ``ROS_DOMAIN_ID`` is also the supervisor's)."""
    def log(msg):
        out.write(f'[launcher] {msg}\n')
        out.flush()
    launch = config.get('launch') or {}
    if launch.get('teach', True) and node_params(config, 'servo').get('start_enabled', True):
        log('config error: teach needs the servo disabled until the arm is at the start '
            'pose; set servo start_enabled: false')
        return 2, None, {}
    timeout = float(timeout if timeout is not None else launch.get('timeout', 120.0))
    launcher = Launcher(config, out=out, env=env)
    domain = (env or os.environ).get('ROS_DOMAIN_ID')
    extra = {}
    if record:
        from sphere_servo.bag.record import DEFAULT_TOPICS
        topics = launch.get('record_topics', list(DEFAULT_TOPICS))
        extra['record'] = ['--output', record, '--topics', *topics]
    sup = None
    code = 0
    interrupted = False

    def on_term(signum, frame):
        raise KeyboardInterrupt
    old_term = signal.signal(signal.SIGTERM, on_term)
    try:
        launcher.start(extra)
        sup = Supervisor(config, collect=collect,
                         domain_id=int(domain) if domain not in (None, '') else None)
        alive = lambda: not launcher.dead()  # noqa: E731
        if record:
            left = sup.wait_recorder(RECORD_READY_TIMEOUT, alive)
            log('recording every topic' if left is None else
                f'warning: the run starts before the recorder is ready: {left}')
        if launch.get('teach', True):
            try:
                sup.teach(log, alive)
            except LaunchError as exc:
                log(f'teach sequence failed: {exc}')
                code = 4 if not launcher.dead() else 3
                return code, sup, launcher.stop()
        elif not node_params(config, 'servo').get('start_enabled', True):
            sup.enable_servo(log)
        t0 = time.monotonic()
        last_print = 0.0
        while True:
            sup.spin(0.05)
            if launcher.dead():
                log(f'node(s) exited: {", ".join(launcher.dead())}')
                code = 3
                break
            now = time.monotonic()
            if now - last_print >= progress_every:
                last_print = now
                v = sup.state_values
                log(f"servo {sup.state}: iteration {v.get('iteration', '?')}, "
                    f"‖s − s*‖ = {v.get('error_norm', '?')}")
            if until_converged and sup.converged():
                log(f'converged after {sup.iterations_converged} iterations')
                # the final error is judged on that image's ground truth (small topics can
                # come late under load)
                sup.wait(lambda: sup.pose_at(sup.t_converged) is not None, 5.0)
                err = sup.final_pose_error()
                if err is not None:
                    log(f'final error against the taught pose: {err[0] * 1e3:.6f} mm, '
                        f'{err[1]:.6f}°')
                break
            if until_converged and now - t0 > timeout:
                log(f'not converged within {timeout} s')
                code = 1
                break
    except KeyboardInterrupt:
        interrupted = True
        log('interrupted: stopping the nodes')
    except LaunchError as exc:
        log(str(exc))
        code = 3
    finally:
        signal.signal(signal.SIGTERM, old_term)
        if sup is not None:
            sup.spin(0.2)
            sup.close()
        codes = launcher.stop()
        bad = {n: c for n, c in codes.items() if c not in (0, None)}
        if bad:
            log(f'exit codes: {bad}')
    if interrupted:
        code = 130 if until_converged else 0
    return code, sup, codes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description='start the sphere_servo pipeline from a config')
    ap.add_argument('--config', default='special_sphere', help='config path or name')
    ap.add_argument('--until-converged', action='store_true',
                    help='exit 0 when the servo converges, non-zero on failure/timeout')
    ap.add_argument('--timeout', type=float, default=None, help='wall seconds (default: '
                    'launch.timeout of the config, or 120)')
    ap.add_argument('--record', metavar='DIR', help='record a rosbag2 into DIR')
    args = ap.parse_args(argv)
    try:
        config = load_config(find_config(args.config))
    except LaunchError as exc:
        print(f'launcher: {exc}', file=sys.stderr)
        return 2
    code, _, _ = run(config, args.until_converged, args.timeout, args.record)
    return code


if __name__ == '__main__':
    sys.exit(main())
