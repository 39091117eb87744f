"""
The launcher's rclpy node: runs the teach sequence, watches the servo, collects histories.

The servo's state comes from its ``~/state`` (``/servo/state``, a DiagnosticArray whose
header is that of the image answered): the status message is read as a
:class:`~sphere_servo.pipeline.servo.ServoState`. The taught image's stamp comes from the
desired features' header (``features/<set>/desired``, transient-local), not from a reply.
"""
from __future__ import annotations

import collections
import time

import numpy as np

from sphere_servo.bringup.processes import LaunchError
from sphere_servo.pipeline.common import NS, stamp_ns, stamp_text
from sphere_servo.pipeline.config import Scenario
from sphere_servo.pipeline.servo import ServoState

HISTORY_DEPTH = 1000  # the supervisor's subscriptions to the per-frame topics


class Supervisor:
    """
    An rclpy node in the launcher: the teach sequence, the servo's state, the histories.

    It runs the teach sequence, watches the servo's state (``state``: a
    :class:`~sphere_servo.pipeline.servo.ServoState`, None before the first status or after
    an unknown one) and, if asked, collects the time histories for the figures.
    """

    def __init__(self, sc: Scenario, collect: bool = False, domain_id: int | None = None,
                 stop=lambda: False):
        """
        Subscribe and make the service clients.

        ``stop()`` true: the next :meth:`spin` or :meth:`wait` raises KeyboardInterrupt
        (between two callbacks, never inside one).
        """
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, TwistStamped
        from sensor_msgs.msg import JointState
        from sphere_servo.ros.qos import COMMAND, DIAGNOSTICS, MONITOR, observer, PIPELINE
        from sphere_servo.ros.vectors import DESIRED_QOS, desired_topic

        self.rclpy = rclpy
        self.stop = stop
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node('launcher', context=self.ctx)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.scenario = sc
        self.state: ServoState | None = None
        self.state_values: dict[str, str] = {}
        self.state_image = None  # stamp (s) of the image the latest state answered (None: none)
        self.poses: list = []          # (stamp, oMc 4×4)
        self.measurements: list = []   # (stamp, {name: value})
        self.features: list = []       # (stamp, s, s* of the latest desired)
        self.twists: list = []         # (stamp, v (6,)) of the twists that answer an image
        self.desired = None            # (stamp ns, s*) of the latest desired features
        self.desired_count = 0
        self.collect = collect
        self.last_pose = None
        self.last_meas_stamp = -1.0
        self.t_start = 0.0  # stamp of the first image at the start pose
        self.state_stamp = -1.0  # newest image stamp the servo reported a state for
        self.t_enabled = None    # stamp of the first image the enabled servo answered
        self.t_converged = None  # stamp of the first image the servo called converged, after
        #                          t_start, and the servo's iteration count there (it counts
        #                          enabled iterations only: the same from run to run)
        self.iterations_converged = None
        self._clients: dict = {}
        self.recent_poses = collections.deque(maxlen=HISTORY_DEPTH)  # (stamp, oMc)
        self.oMc_taught = None  # ground-truth camera pose of the taught image (teach: true)
        self.heard: set[str] = set()  # nodes whose status came on /diagnostics: they run
        fset = sc.node_params('servo').get('feature_set', 's_n')
        sub = self.node.create_subscription
        # deep histories: under load Fast DDS repairs what loaded sockets dropped in bursts of
        # up to seconds of messages, which a shallow keep-last history would mostly discard
        monitor, pipeline = observer(MONITOR, HISTORY_DEPTH), observer(PIPELINE, HISTORY_DEPTH)
        sub(DiagnosticArray, 'servo/state', self._on_state, monitor)
        sub(DiagnosticArray, '/diagnostics', self._on_diagnostics,
            observer(DIAGNOSTICS, HISTORY_DEPTH))
        sub(JointState, desired_topic(fset), self._on_desired, DESIRED_QOS)
        sub(PoseStamped, 'ground_truth/camera_pose', self._on_pose, monitor)
        sub(JointState, 'detector/measurement', self._on_meas, pipeline)
        if collect:
            sub(JointState, f'features/{fset}', self._on_features, pipeline)
            sub(TwistStamped, 'camera/cmd_vel', self._on_twist, observer(COMMAND, HISTORY_DEPTH))
        from std_srvs.srv import SetBool
        for service in ('/arm_sim/go_desired', '/features/teach', '/arm_sim/go_start'):
            self.client(service)
        self.client('/servo/enable', SetBool)

    def pose_at(self, t: float | None):
        """Return the ground-truth pose of the image stamped ``t``, if it has arrived."""
        if t is None:
            return None
        return next((M for s, M in reversed(self.recent_poses) if abs(s - t) < 1e-6), None)

    def final_pose_error(self) -> tuple[float, float] | None:
        """
        Return (m, deg) between the taught pose and the pose the servo converged at.

        That is the ground truth of the image the servo first called converged (the newest
        pose if that one has not arrived, or the servo did not converge); None when nothing
        was taught or no pose arrived.
        """
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
        from sphere_servo.ros.diagnostics import state_of
        got = state_of(msg)
        if got is None:
            return
        message, self.state_values = got
        try:
            self.state = ServoState(message)
        except ValueError:
            self.state = None
            self.node.get_logger().warn(f'unknown servo state {message!r}',
                                        throttle_duration_sec=5.0)
        ns = stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
        self.state_image = t = ns / NS if ns else None  # a zero stamp answers no image
        if t is None:
            return
        self.state_stamp = max(self.state_stamp, t)
        if self.state not in (ServoState.SERVOING, ServoState.CONVERGED):
            return
        if t < self.t_start:
            return
        if self.t_enabled is None or t < self.t_enabled:
            self.t_enabled = t
        if self.state is ServoState.CONVERGED and (self.t_converged is None
                                                   or t < self.t_converged):
            self.t_converged = t
            self.iterations_converged = int(self.state_values.get('iteration', -1))

    def _on_diagnostics(self, msg) -> None:
        """Note the nodes that report: each names its status ``<node>: state``."""
        for st in msg.status:
            self.heard.add(st.name.split(':', 1)[0])

    def graph(self) -> collections.Counter:
        """Return how many nodes of each name the domain's graph has (namespace ``/``)."""
        return collections.Counter(n for n, ns in self.node.get_node_names_and_namespaces()
                                   if ns == '/')

    def present(self, names) -> list[str]:
        """Return the nodes of ``names`` that are on the domain already (before a start)."""
        seen = self.graph()
        return sorted(n for n in set(names) if seen[n] > 0)

    def doubles(self, names) -> list[str]:
        """Return the nodes of ``names`` that the domain has twice or more."""
        seen = self.graph()
        return sorted(n for n in set(names) if seen[n] > 1)

    def wait_nodes(self, names, timeout: float, alive) -> bool:
        """Wait until every node of ``names`` has reported on /diagnostics (False if not)."""
        return self.wait(lambda: set(names) <= self.heard, timeout, alive)

    def _on_pose(self, msg) -> None:
        """
        Keep the poses; ``last_pose`` is the newest ground truth by stamp.

        A late delivery of an older pose must not make the arm look back where it was.
        """
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

    def _on_desired(self, msg) -> None:
        self.desired = (stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec),
                        np.array(msg.position))
        self.desired_count += 1

    def _on_features(self, msg) -> None:
        if msg.name and self.desired is not None:
            self.features.append((self._t(msg.header.stamp), np.array(msg.position),
                                  self.desired[1]))

    def _on_twist(self, msg) -> None:
        t = self._t(msg.header.stamp)
        if t == 0.0:  # the watchdog's: it answers no image
            return
        tw = msg.twist
        self.twists.append((t, np.array([tw.linear.x, tw.linear.y, tw.linear.z, tw.angular.x,
                                         tw.angular.y, tw.angular.z])))

    def _spin_once(self, timeout: float) -> None:
        if self.stop():
            raise KeyboardInterrupt
        self.executor.spin_once(timeout_sec=timeout)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._spin_once(min(0.02, max(0.0, end - time.monotonic())))

    def wait(self, pred, timeout: float, alive=lambda: True) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred():
                return True
            if not alive():
                return False
            self._spin_once(0.02)
        return bool(pred())

    def call(self, service: str, timeout: float = 30.0, enable: bool | None = None,
             alive=lambda: True):
        """
        Call a Trigger service (SetBool with ``enable``); the response, or LaunchError.

        ``alive()`` false (a node exited) ends the wait at once.
        """
        from std_srvs.srv import SetBool, Trigger
        srv = Trigger if enable is None else SetBool
        cli = self.client(service, srv)
        if not self.wait(cli.service_is_ready, timeout, alive):
            raise LaunchError(f'service {service} not available after {timeout} s'
                              if alive() else f'service {service}: a node exited')
        req = srv.Request() if enable is None else SetBool.Request(data=enable)
        fut = cli.call_async(req)
        if not self.wait(fut.done, timeout, alive):
            raise LaunchError(f'service {service} did not answer in {timeout} s'
                              if alive() else f'service {service}: a node exited')
        return fut.result()

    def client(self, service: str, srv=None):
        """
        Return the (kept) client of ``service``.

        It is made once, so that discovery of a client made early has happened by the time
        it is called (a fresh client per call took seconds to be matched under load, holding
        the arm at the start pose).
        """
        if service not in self._clients:
            if srv is None:
                from std_srvs.srv import Trigger as srv
            self._clients[service] = self.node.create_client(srv, service)
        return self._clients[service]

    def wait_recorder(self, timeout: float, alive, service: str = '/recorder/ready',
                      ) -> str | None:
        """
        Wait until the recorder records every topic it was asked for (its ``~/ready``).

        Returns ``None`` when it does, else what it still waits for after ``timeout`` s.
        Under load, the recorder discovers a node's topics up to seconds after the node
        started: a run that began meanwhile would miss its first messages in the bag.
        ``service='/recorder/idle'`` waits instead until nothing new has reached the
        recorder for a while: under load Fast DDS delivers small topics seconds late, and a
        recorder interrupted before they came would cut them from the bag.
        """
        end = time.monotonic() + timeout
        while True:
            try:
                res = self.call(service, max(0.5, end - time.monotonic()))
            except LaunchError as exc:
                return str(exc)
            if res.success:
                return None
            if time.monotonic() > end or not alive():
                return res.message
            self.spin(0.1)

    def teach(self, log, alive) -> None:
        """
        Teach: arm to the desired pose → teach its image → arm to the start → enable servo.

        The servo must be disabled meanwhile (``start_enabled: false``): a teach can take an
        image from before the jump (it is then taught again), and a servo acting on it would
        move the arm away from the pose being taught (arm_sim refuses the jumps anyway while
        the servo is enabled). The arm jumps only once the servo has reported a state, and
        while no node has exited (``alive``). The servo is enabled once it holds the
        desired features of the image taught last (its state's ``desired_stamp``).
        """
        from sphere_servo.sim.arm import pose_from_xyz_rpy
        cMo_d = pose_from_xyz_rpy(*np.split(np.asarray(
            self.scenario.node_params('arm_sim').get('desired_cMo', [0, 0, 0.45, 0, 0, 0]),
            float), 2))
        if not self.wait(lambda: self.state is not None, 60.0, alive):  # a live servo first
            raise LaunchError('the servo did not report a state: no jump without a live servo')
        res = self.jump('/arm_sim/go_desired', alive)
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
            count = self.desired_count
            res = self.call('/features/teach', alive=alive)
            # the new desired, on its topic, carries the taught image's header
            if res.success and self.wait(lambda: self.desired_count > count, 5.0, alive) \
                    and self.desired[0] / NS >= t_desired - 1e-9:
                break
            if time.monotonic() > end or not alive():
                raise LaunchError(f'teach failed: {res.message} (desired pose at '
                                  f'{t_desired:.6f} s, last measurement '
                                  f'{self.last_meas_stamp:.6f} s)')
            self.spin(0.2)
        taught = stamp_text(self.desired[0])
        log(f'desired features taught from the image stamped {taught}')
        res = self.jump('/arm_sim/go_start', alive)
        if not res.success:
            raise LaunchError(f'go_start failed: {res.message}')
        self.t_start = _stamp_in(res.message)  # the first image at the start pose
        if not self.wait(lambda: self.last_pose[0] >= self.t_start - 1e-9 and not at_desired(),
                         30.0, alive):
            raise LaunchError('the arm did not leave the desired pose')
        log(f'arm at the start pose: {res.message}')
        # the servo's sim clock may still lag the jump: enabled before it has answered a
        # start-pose image, it would answer (and count) a frame from the desired pose
        if not self.wait(lambda: self.state_stamp >= self.t_start - 1e-9, 30.0, alive):
            raise LaunchError('the servo did not answer an image of the start pose')
        if not self.wait(lambda: self.state_values.get('desired_stamp') == taught, 30.0, alive):
            raise LaunchError(f'the servo did not get the desired features taught from the '
                              f'image stamped {taught} (it holds '
                              f"{self.state_values.get('desired_stamp', 'none')})")
        self.enable_servo(log, alive)

    def jump(self, service: str, alive):
        """Call an arm_sim jump, only while the servo lives (it has spoken, no node died)."""
        if self.state is None or not alive():
            raise LaunchError(f'{service} not called: no jump of the arm without a live servo')
        return self.call(service, alive=alive)

    def enable_servo(self, log, alive=lambda: True) -> None:
        res = self.call('/servo/enable', enable=True, alive=alive)
        if not res.success:
            raise LaunchError(f'cannot enable the servo: {res.message}')
        log(res.message)

    def converged(self) -> bool:
        """Tell whether the servo reports convergence on an image taken after the jump."""
        return self.state is ServoState.CONVERGED and self.state_image is not None \
            and self.state_image >= self.t_start

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)


def _stamp_in(message: str) -> float:
    """
    Read the stamp 'sec.nanosec' that ends an arm_sim go_* service reply (-1 if none).

    arm_sim's jumps end their reply with the stamp of the first image at the new pose.
    """
    try:
        return float(message.rsplit(' ', 1)[-1])
    except ValueError:
        return -1.0
