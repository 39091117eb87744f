"""
``launcher``: start the servo pipeline's nodes as separate processes from a scenario file.

    launcher --config special_sphere [--until-converged] [--timeout 120] [--record DIR]
             [--single-process] [--nice N]

A scenario (``config/scenarios/<name>.yaml``, see :mod:`sphere_servo.pipeline.config`) names
the nodes, their plain ROS 2 params files (``config/params/*.yaml``, given to every node in
order) and the run: ``teach`` (arm to desired → teach that image → arm to start → enable the
servo), ``timeout`` (wall seconds for ``--until-converged``), ``record_topics``.
``--config`` (alias ``--scenario``) takes a path, or a name looked up in the installed
``share/sphere_servo/config/scenarios`` and then in the source tree's ``config/scenarios``.
The nodes run as processes
(:mod:`~sphere_servo.bringup.processes`: how they are found, forwarded, stopped, and
terminated if the launcher dies; ``--single-process``: all of them in one process, on one
executor, :mod:`~sphere_servo.bringup.single`); an rclpy node in the launcher
(:mod:`~sphere_servo.bringup.supervisor`) runs the teach sequence and watches the servo.
``--nice N`` adds N to every node's niceness: ``--nice -10`` (root or CAP_SYS_NICE) keeps the
loop's latency near the idle machine's while other processes load the CPU (``make bench``).
Ctrl-C (or SIGTERM) stops the servo first (its last word is a zero twist), then the recorder,
then the others. With ``--record`` the run (teach included) begins once the recorder
reports that it records every topic. With ``--until-converged`` the exit code
(:class:`ExitCode`) is 0 when the servo reports ``converged``, 1 on timeout, 3 if a node
died, 4 if the teach sequence failed; 2 is a bad config. The nodes and the launcher's own
node use the shipped Fast DDS profile unless the environment names another
(:mod:`sphere_servo.pipeline.middleware`).

Before anything starts, the scenario is checked as each node would check it
(:func:`preflight`: its parameters, an unknown name included, and what its core refuses at
start: a missing ``desired_image``, an unreachable ``start_cMo``, …), and a refusal is the
node's own line with exit code 2; so are a scenario without nodes or with a node named
twice, a params section that names no node (:func:`check_scenario`), a timeout that is not
a finite number of seconds > 0, and an environment in which no node could work (a bad
``ROS_DOMAIN_ID``, Fast DDS profile or ``RMW_IMPLEMENTATION``:
:func:`~sphere_servo.bringup.processes.check_environment`). A node that exits during the
start-up or the run ends it at once (exit 3), with that node's exit code and last words.
Nodes of the pipeline's names already on the domain (another pipeline's: two arms, two
servos on one set of topics) are refused (exit 2, nothing started): at once when one of
them reports on ``/diagnostics`` (it runs), else once they outlast a killed process's
linger; two of one name during the run (another pipeline
joined) end it (exit 3). The run (the teach sequence and its jumps) begins once every node
has reported on ``/diagnostics``; the arm never jumps unless the servo runs.
"""
from __future__ import annotations

import argparse
from enum import IntEnum
import math
import os
import signal
import sys
import time

from sphere_servo.bringup.processes import check_environment, Launcher, LaunchError
from sphere_servo.bringup.supervisor import Supervisor
from sphere_servo.pipeline.arm_sim import ArmSimCore
from sphere_servo.pipeline.config import ConfigError, read_yaml, Scenario, scenario
from sphere_servo.pipeline.detector import DetectorCore
from sphere_servo.pipeline.features import FeaturesCore
from sphere_servo.pipeline.middleware import middleware_env
from sphere_servo.pipeline.params import NODE_PARAMS
from sphere_servo.pipeline.servo import ServoCore

RECORD_READY_TIMEOUT = 30.0  # wall s the run waits for the recorder to match every topic
RECORDER_IDLE_TIMEOUT = 8.0  # wall s the end of a run waits for the late messages to come
STARTUP_TIMEOUT = 60.0       # wall s the nodes have to start (the servo's first state)
DISCOVERY_WAIT = 1.0         # wall s to hear the nodes already on the domain, before a start
LIVE_WAIT = 2.5              # wall s to hear one of them on /diagnostics (1 Hz): it runs
STALE_WAIT = 25.0            # wall s for such nodes to go: Fast DDS drops a killed process's
#                              participant after its lease (10 s with config/fastdds.xml, 20 s
#                              with Fast DDS's defaults: a node a user started without it)
#: what each node builds at start from its parameters: its core refuses what it cannot use
NODE_CORES = {'arm_sim': ArmSimCore, 'detector': DetectorCore, 'features': FeaturesCore,
              'servo': ServoCore}


class NotStarted(LaunchError):
    """The launch is refused before any node started (exit 2): the domain, the middleware."""


class DomainShared(LaunchError):
    """Another node of one of the pipeline's names joined the domain during the run (exit 3)."""


class ExitCode(IntEnum):
    """The launcher's exit codes (``--until-converged``; a plain run exits OK when stopped)."""

    OK = 0             # converged, or stopped by the user without --until-converged
    TIMEOUT = 1        # not converged within the timeout
    BAD_CONFIG = 2     # the config cannot be found, read or used
    NODE_DIED = 3      # a node exited, or the run could not go on (a service missing)
    TEACH_FAILED = 4   # the teach sequence failed while every node lived
    INTERRUPTED = 130  # Ctrl-C or SIGTERM during --until-converged (128 + SIGINT)


def check_scenario(sc: Scenario) -> str:
    """
    Return why the launcher cannot start ``sc`` as its nodes would read it ('' if it can).

    No node (nothing would run), a node named twice (two processes of one name: two servos
    driving one arm), a params file section that names none of the nodes (``sevro:``, a
    wildcard other than ``/**``): the nodes would ignore it, and run on their defaults.
    """
    if not sc.nodes:
        return 'no nodes: nothing would run'
    twice = sorted({n for n in sc.nodes if sc.nodes.count(n) > 1})
    if twice:
        return f'node(s) {twice} named twice (two processes of one name)'
    known = {'/**'} | {k for n in NODE_PARAMS for k in (n, f'/{n}')}
    for path in sc.params_files:
        other = sorted(str(k) for k in read_yaml(path) if k not in known)
        if other:
            return (f'{path}: section(s) {other} name no node of the pipeline (use '
                    f'{sorted(NODE_PARAMS)}, /<node> or /**): the nodes would ignore them')
    return ''


def preflight(sc: Scenario) -> str:
    """
    Return the line the first node of ``sc`` that would refuse to start prints ('' if none).

    Each node's parameters are built as the node builds them (unknown names refused), then
    its core, which refuses what it cannot use at start, with the node's own message.
    """
    for node in sc.nodes:
        try:
            NODE_CORES[node](NODE_PARAMS[node].from_mapping(sc.node_params(node), strict=True))
        except (ValueError, TypeError, OSError) as exc:  # ParameterError, GeometryError
            return f'[{node}] refused to start: {" ".join(str(exc).split())}'
    return ''


def run(sc: Scenario, until_converged: bool = False, timeout: float | None = None,
        record: str | None = None, collect: bool = False, out=sys.stdout,
        progress_every: float = 1.0, env: dict | None = None,
        single_process: bool = False,
        nice: int = 0) -> tuple[ExitCode, Supervisor | None, dict[str, int]]:
    """
    Start the pipeline, teach, servo.

    Returns ``(exit code, supervisor, the nodes' exit codes)``; the (closed)
    :class:`~sphere_servo.bringup.supervisor.Supervisor` holds the histories when
    ``collect``. ``env``: the nodes' environment (its ``ROS_DOMAIN_ID`` is also the
    supervisor's). ``single_process``: the nodes in one process (:mod:`.single`); ``nice``:
    added to every node's niceness.
    """
    def log(msg):
        out.write(f'[launcher] {msg}\n')
        out.flush()
    start_enabled = sc.node_params('servo').get('start_enabled', True)
    if sc.teach and start_enabled:
        log(f'scenario error ({sc.path}): teach needs the servo disabled until the arm is at '
            'the start pose; set servo start_enabled: false in its params')
        return ExitCode.BAD_CONFIG, None, {}
    if sc.teach and 'servo' not in sc.nodes:
        log(f'scenario error ({sc.path}): teach needs the servo among the nodes (the arm '
            'never jumps without a live servo)')
        return ExitCode.BAD_CONFIG, None, {}
    refused = check_scenario(sc) or preflight(sc)
    if refused:
        log(f'scenario error ({sc.path}), nothing started: {refused}')
        return ExitCode.BAD_CONFIG, None, {}
    timeout = float(timeout if timeout is not None else sc.timeout)
    if not (math.isfinite(timeout) and timeout > 0):  # nan: a run that never times out
        log(f'timeout must be a finite number of seconds > 0, got {timeout}; nothing started')
        return ExitCode.BAD_CONFIG, None, {}
    try:
        check_environment(env if env is not None else os.environ)
    except LaunchError as exc:
        log(f'environment error, nothing started: {exc}')
        return ExitCode.BAD_CONFIG, None, {}
    from sphere_servo.ros.params import StopFlag  # rclpy: only once the rmw is known to load
    launcher = Launcher(sc, out=out, env=env, single_process=single_process, nice=nice)
    domain = (env or os.environ).get('ROS_DOMAIN_ID')
    extra = {}
    if record:
        from sphere_servo.bag.record import DEFAULT_TOPICS
        topics = list(sc.record_topics or DEFAULT_TOPICS)
        extra['record'] = ['--output', record, '--topics', *topics]
    sup = None
    code = ExitCode.OK
    interrupted = False
    # Ctrl-C and SIGTERM only set a flag; the supervisor raises KeyboardInterrupt between two
    # callbacks (one raised asynchronously inside rclpy's C++ take was lost: see ros.params)
    stop = StopFlag()
    old_handlers = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    watched = list(sc.nodes) + (['recorder'] if record else [])
    try:
        try:
            sup = Supervisor(sc, collect=collect,
                             domain_id=int(domain) if domain not in (None, '') else None,
                             stop=lambda: stop.requested)
        except RuntimeError as exc:  # rclpy's RCLError: ROS_STATIC_PEERS=@@@, …
            said = ' '.join(str(exc).split()).split(', at /')[0]
            raise NotStarted(f"the launcher's node cannot be made here, nothing started: "
                             f'{said}') from None
        sup.spin(DISCOVERY_WAIT)  # the nodes already there: another pipeline, or a killed one's
        # a live node reports on /diagnostics every second: refused at once; a killed
        # process's leftovers are silent, and waited for until their lease ends
        live = sup.present(watched) and sup.wait(
            lambda: set(sup.present(watched)) & sup.heard, LIVE_WAIT)
        if sup.present(watched) and not live:
            log(f'ROS_DOMAIN_ID {domain or 0} has the node(s) {sup.present(watched)}: waiting '
                f"up to {STALE_WAIT:g} s for them to go (a killed process's linger)")
        if live or (sup.present(watched)
                    and not sup.wait(lambda: not sup.present(watched), STALE_WAIT)):
            raise NotStarted(f'ROS_DOMAIN_ID {domain or 0} already has the node(s) '
                             f'{sup.present(watched)} (another pipeline runs there): nothing '
                             'started; stop it or use another ROS_DOMAIN_ID')
        launcher.start(extra)

        def alive():
            twice = sup.doubles(watched)
            if twice:  # two arms, two servos: their topics would be mixed
                raise DomainShared(f'two nodes named {twice} on ROS_DOMAIN_ID {domain or 0}: '
                                   'another pipeline joined the domain; stopping')
            return not launcher.dead()
        if not sup.wait_nodes(sc.nodes, STARTUP_TIMEOUT, alive):  # every node runs
            raise LaunchError(f'nodes not started within {STARTUP_TIMEOUT:g} s: '
                              f'{sorted(set(sc.nodes) - sup.heard)}')
        if record:
            left = sup.wait_recorder(RECORD_READY_TIMEOUT, alive)
            log('recording every topic' if left is None else
                f'warning: the run starts before the recorder is ready: {left}')
        if sc.teach:
            try:
                sup.teach(log, alive)
            except DomainShared:
                raise
            except LaunchError as exc:
                dead = launcher.deaths()
                log(f'teach sequence failed: {dead or exc}')
                code = ExitCode.NODE_DIED if dead else ExitCode.TEACH_FAILED
                return code, sup, launcher.stop()
        elif not start_enabled:
            sup.enable_servo(log)
        t0 = time.monotonic()
        last_print = 0.0
        while True:
            sup.spin(0.05)
            if not alive():
                log(f'node(s) exited: {launcher.deaths()}')
                code = ExitCode.NODE_DIED
                break
            now = time.monotonic()
            if now - last_print >= progress_every:
                last_print = now
                v = sup.state_values
                state = None if sup.state is None else sup.state.value
                log(f"servo {state}: iteration {v.get('iteration', '?')}, "
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
                code = ExitCode.TIMEOUT
                break
    except KeyboardInterrupt:
        interrupted = True
        log('interrupted: stopping the nodes')
    except NotStarted as exc:
        log(str(exc))
        code = ExitCode.BAD_CONFIG
    except DomainShared as exc:
        log(str(exc))
        code = ExitCode.NODE_DIED
    except LaunchError as exc:
        dead = launcher.deaths()
        log(f'node(s) exited during start-up: {dead}' if dead else str(exc))
        code = ExitCode.NODE_DIED
    finally:  # a Ctrl-C or SIGTERM from here on is ignored: the nodes stop in their order
        if sup is not None:
            sup.stop = lambda: False  # the last messages still come in
            if record and not interrupted:  # the servo first (its last word: a zero twist),
                #                              then the messages still on their way
                launcher.stop_one('servo')
                left = sup.wait_recorder(RECORDER_IDLE_TIMEOUT, lambda: True, '/recorder/idle')
                if left is not None:
                    log(f'warning: stopping the recorder while messages still come: {left}')
            sup.spin(0.2)
            sup.close()
        codes = launcher.stop()
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
        bad = {n: c for n, c in codes.items() if c not in (0, None)}
        if bad:
            log(f'exit codes: {bad}')
    if interrupted:
        code = ExitCode.INTERRUPTED if until_converged else ExitCode.OK
    return code, sup, codes


def main(argv=None) -> int:
    """Run the launcher's command line; return its exit code."""
    ap = argparse.ArgumentParser(description='start the sphere_servo pipeline from a scenario')
    ap.add_argument('--config', '--scenario', dest='scenario', default='special_sphere',
                    help='scenario path or name (config/scenarios/<name>.yaml)')
    ap.add_argument('--until-converged', action='store_true',
                    help='exit 0 when the servo converges, non-zero on failure/timeout')
    ap.add_argument('--timeout', type=float, default=None, help='wall seconds (default: '
                    "the scenario's timeout)")
    ap.add_argument('--record', metavar='DIR', help='record a rosbag2 into DIR')
    ap.add_argument('--single-process', action='store_true',
                    help='run the nodes in one process (no message leaves it; latency: README)')
    ap.add_argument('--nice', type=int, default=0, metavar='N',
                    help="add N to the nodes' niceness (negative: a higher priority, as root "
                    'or with CAP_SYS_NICE)')
    args = ap.parse_args(argv)
    try:
        sc = scenario(args.scenario)
        # before the supervisor's participant exists: Fast DDS reads the profile then
        os.environ.update(middleware_env(os.environ))
    except (ConfigError, FileNotFoundError) as exc:
        print(f'launcher: {exc}', file=sys.stderr)
        return ExitCode.BAD_CONFIG
    code, _, _ = run(sc, args.until_converged, args.timeout, args.record, out=sys.stdout,
                     single_process=args.single_process, nice=args.nice)
    return code


if __name__ == '__main__':
    sys.exit(main())
