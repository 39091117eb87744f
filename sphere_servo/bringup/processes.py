"""
The launcher's processes: start the pipeline's nodes, watch them, stop them in order.

Each node of the scenario starts with ``--ros-args`` and every params file of the scenario,
in order (``--params-file A --params-file B``: B overrides what it sets), as the launch file
starts them. Executables are resolved as ``ros2 run`` does
(``get_package_prefix('sphere_servo')/lib/sphere_servo/<name>``), falling back to
``python -m sphere_servo.ros.<name>`` when the package is not installed (a source
checkout). Each process's output is forwarded with a ``[name]`` prefix. :meth:`Launcher.stop`
stops the servo first (its last word is a zero twist), then the recorder (while the others
still live: it takes what is still on its way before closing the bag), then the others:
SIGINT, then SIGKILL after 10 s. On Linux the nodes are terminated (SIGTERM) if the
launcher itself dies, even by SIGKILL (``PR_SET_PDEATHSIG``); the kernel ties this to the
thread that started them, so start a :class:`Launcher` from a thread that outlives the run.
The last lines each node printed are kept: :meth:`Launcher.deaths` tells why a node exited
in its own words (``[features] refused to start: …``). The launcher writes no file of its
own (the nodes read the scenario's params files where they are), so a launcher killed
with SIGKILL leaves nothing behind.

``nice`` is added to each node's niceness before it starts: a negative one puts the
pipeline's callbacks before other work on a loaded CPU. Each node has a session of its own,
so the niceness is given to the session's autogroup too (:func:`renice_session`): where the
kernel schedules by autogroup, the CPU is shared between sessions by that alone.

Every process gets the shipped Fast DDS profile (``middleware_env`` of
:mod:`sphere_servo.pipeline.middleware`) unless its environment names a profile of its own
or another rmw. With ``single_process`` the scenario's nodes run as one process,
``pipeline`` (:mod:`~sphere_servo.bringup.single`), stopped first as the servo is.

:func:`check_environment` refuses, before anything starts, an environment in which no node
could work: a ``ROS_DOMAIN_ID`` that is not a decimal integer in 0…232 (rcl reads ``010``
as octal 8 and ``0x10`` as 16, so the supervisor and the nodes would be on different
domains; above 232 Fast DDS has no port and the process exits at its first node), a Fast
DDS profile that is not a readable XML file (Fast DDS would log an error and run on its
defaults), an ``RMW_IMPLEMENTATION`` that rcl cannot load (it exits at once with 102).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
import os
import signal
import subprocess
import sys
import threading
import time

from sphere_servo.pipeline.config import ConfigError, package_prefix, Scenario
from sphere_servo.pipeline.middleware import environment_problem, middleware_env, RMW

MODULES = {'arm_sim': 'sphere_servo.ros.arm_sim', 'detector': 'sphere_servo.ros.detector',
           'features': 'sphere_servo.ros.features', 'servo': 'sphere_servo.ros.servo',
           'record': 'sphere_servo.bag.record', 'pipeline': 'sphere_servo.bringup.single'}
STOP_ORDER = ('servo', 'pipeline', 'record', 'features', 'detector', 'arm_sim')
SINGLE = 'pipeline'  # the one process of --single-process (sphere_servo.bringup.single)
LAST_LINES = 20  # lines of each node's output kept, to say why it exited


class LaunchError(ConfigError):
    """The config, an executable or the run cannot be used."""


RMW_PROBE = 'from rclpy.utilities import get_rmw_implementation_identifier as g; print(g())'


def check_environment(env) -> None:
    """
    Refuse (LaunchError, one line) an environment in which no node could work.

    :func:`~sphere_servo.pipeline.middleware.environment_problem` (the domain, the Fast DDS
    profiles); another ``RMW_IMPLEMENTATION`` must be one rcl loads: that is tried in a
    child process, since rcl ends the process that loads it otherwise.
    """
    problem = environment_problem(env)
    if problem is not None:
        raise LaunchError(problem)
    rmw = env.get('RMW_IMPLEMENTATION') or RMW
    if rmw == RMW:
        return
    probe = subprocess.run([sys.executable, '-c', RMW_PROBE], env=dict(env), text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    if probe.returncode != 0 or probe.stdout.split()[-1:] != [rmw]:
        said = ' '.join(probe.stdout.split()[-40:]).split(', at /')[0]
        raise LaunchError(f'RMW_IMPLEMENTATION={rmw!r} cannot be used here (exit code '
                          f'{probe.returncode}): {said or "no output"}')


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
    """Load libc for prctl, once in the launcher (the forked child must not load it)."""
    try:
        import ctypes
        return ctypes.CDLL(None, use_errno=True)
    except (OSError, AttributeError):
        return None


_LIBC = _libc() if sys.platform.startswith('linux') else None
PR_SET_PDEATHSIG = 1


AUTOGROUP = '/proc/self/autogroup'
AUTOGROUP_TRIES = 30  # 0.1 s apart: without CAP_SYS_ADMIN the kernel takes one change per 0.1 s


def renice_session(increment: int = 0) -> int:
    """
    Add ``increment`` to this process's niceness and give the result to its autogroup.

    For a process that has just made a session of its own (``setsid``: a new autogroup, at
    nice 0). With the kernel's autogroup scheduling (``CONFIG_SCHED_AUTOGROUP``, on unless
    ``/proc/sys/kernel/sched_autogroup_enabled`` is 0) the CPU is shared between autogroups
    first, by the autogroup's nice, and a process's own niceness only orders it within its
    autogroup: alone in a session, a process at nice 19 took as much CPU beside another
    program as one at 0. Returns the niceness. A refused niceness (a negative one without
    CAP_SYS_NICE) raises PermissionError, as ``os.nice`` does; without ``/proc/self/autogroup``
    there is nothing more to do.
    """
    value = os.nice(increment)
    if value == 0 or not os.path.exists(AUTOGROUP):
        return value
    for _ in range(AUTOGROUP_TRIES):
        try:
            fd = os.open(AUTOGROUP, os.O_WRONLY)
            try:
                os.write(fd, str(value).encode())
            finally:
                os.close(fd)
            return value
        except BlockingIOError:  # EAGAIN: another change within 0.1 s on this machine
            time.sleep(0.1)
    raise BlockingIOError(f'the kernel refused the autogroup nice {value} {AUTOGROUP_TRIES} '
                          'times (EAGAIN)')


def die_with(parent_pid: int, nice: int = 0):
    """
    Return the ``preexec_fn`` of a node (Linux) that dies with the launcher, at ``nice``.

    For a process started in a session of its own (``start_new_session``).

    The kernel sends the node SIGTERM when the launcher dies, even by SIGKILL, so no
    orphaned node keeps driving the arm (SIGTERM is the nodes' clean shutdown: the servo's
    last word is a zero twist). If the launcher died before this ran, the node is
    terminated at once. ``nice`` is added to the node's niceness before it runs, so every
    thread it makes has it, and the result given to its session (:func:`renice_session`; a
    negative one needs root or CAP_SYS_NICE: PermissionError).
    """
    libc = _LIBC

    def preexec():
        renice_session(nice)
        if libc is not None:
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
            if os.getppid() != parent_pid:
                os.kill(os.getpid(), signal.SIGTERM)
    return preexec


@dataclass
class Child:
    """A node's process, the thread forwarding its output, and its last lines."""

    name: str
    popen: subprocess.Popen
    thread: threading.Thread | None = None
    last: collections.deque = field(
        default_factory=lambda: collections.deque(maxlen=LAST_LINES))

    def why(self) -> str:
        """Return the node's own account of its exit: its refusal, or its last line."""
        lines = [ln for ln in self.last if ln.strip()]
        said = next((ln for ln in reversed(lines) if 'refused to start' in ln), None)
        return said or (lines[-1] if lines else 'it printed nothing')


def _forward(child: Child, stream, out) -> None:
    for line in iter(stream.readline, ''):
        line = line.rstrip('\n')
        child.last.append(line)
        out.write(f'[{child.name}] {line}\n')
        out.flush()
    stream.close()


def ros_args(scenario: Scenario) -> list[str]:
    """Return ``--ros-args --params-file F …`` of the scenario's params files, in order."""
    args = ['--ros-args']
    for path in scenario.params_files:
        args += ['--params-file', str(path)]
    return args


@dataclass
class Launcher:
    """Starts, watches and stops the nodes of a scenario."""

    scenario: Scenario
    out: object = sys.stdout
    env: dict | None = None  # the children's environment (default: this process's)
    children: dict = field(default_factory=dict)
    single_process: bool = False  # the nodes in one process, SINGLE
    nice: int = 0  # added to every node's niceness (negative: before other work on the CPU)

    def start(self, extra: dict | None = None) -> None:
        """Start every node of the scenario (``extra``: name → argv of other executables)."""
        for name in (SINGLE,) if self.single_process else self.scenario.nodes:
            self._spawn(name, self._command(name))
        for name, argv in (extra or {}).items():
            self._spawn(name, node_command(name) + list(argv))

    def _command(self, name: str) -> list[str]:
        nodes = list(self.scenario.nodes) if name == SINGLE else []
        return node_command(name) + nodes + ros_args(self.scenario)

    def restart(self, name: str) -> None:
        """Start ``name`` again with the same parameters (after it died or was killed)."""
        old = self.children[name]
        if old.popen.poll() is None:
            raise LaunchError(f'{name} is still running')
        self._spawn(name, self._command(name))

    def _spawn(self, name: str, cmd: list[str]) -> None:
        # the shipped Fast DDS profile unless the environment names its own (or another rmw)
        try:
            env = middleware_env(self.env if self.env is not None else os.environ)
        except FileNotFoundError as exc:
            raise LaunchError(str(exc)) from None
        env['PYTHONUNBUFFERED'] = '1'
        try:
            popen = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env, start_new_session=True,
                                     preexec_fn=die_with(os.getpid(), self.nice))
        except subprocess.SubprocessError as exc:  # what preexec_fn raised: os.nice refused
            raise LaunchError(f'cannot start {name} at nice {self.nice:+d} (a higher '
                              f'priority needs root or CAP_SYS_NICE): {exc}') from None
        child = Child(name, popen)
        child.thread = threading.Thread(target=_forward, args=(child, popen.stdout, self.out),
                                        daemon=True)
        child.thread.start()
        self.children[name] = child

    def dead(self) -> list[str]:
        """Names of nodes that have exited."""
        return [n for n, c in self.children.items() if c.popen.poll() is not None]

    def stop_one(self, name: str, timeout: float = 10.0) -> int | None:
        """Stop ``name`` (SIGINT, then SIGKILL) if it was started; return its exit code."""
        child = self.children.get(name)
        return None if child is None else interrupt(child.popen, timeout)

    def deaths(self) -> str:
        """Say which nodes exited, with their exit codes and their own last words."""
        out = []
        for name in self.dead():
            c = self.children[name]
            if c.thread is not None:
                c.thread.join(2)  # its last lines are still on their way
            code = c.popen.returncode
            how = f' ({signal.Signals(-code).name})' if code < 0 and -code in \
                signal.valid_signals() else ''
            out.append(f'{name} exited with code {code}{how}: {c.why()}')
        return '; '.join(out)

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """Stop every node (servo first), SIGINT then SIGKILL; return the exit codes."""
        order = [n for n in STOP_ORDER if n in self.children] + \
            [n for n in self.children if n not in STOP_ORDER]
        for name in order:
            interrupt(self.children[name].popen, timeout)
        for c in self.children.values():
            if c.thread is not None:
                c.thread.join(2)
        return {n: c.popen.returncode for n, c in self.children.items()}
