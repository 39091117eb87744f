"""
Benchmark of the ROS pipeline's latency against the bare image hop (issues 5 and 17).

Side by side in one run, idle and under a CPU load of two busy processes (rows ``+2 busy``),
each case in fresh processes, each process (the busy ones too, as unrelated programs) in a
session of its own as the launcher starts the nodes (with the kernel's autogroup
scheduling, CPU time is shared between sessions first), 640×480 rgb8 at 30 Hz, reliable,
discovery on localhost:

- the bare two-process image hop (``benchmarks.hop``) with Fast DDS's defaults and with the
  shipped profile (``config/fastdds.xml``), and the bare one-process hop with the profile
  (publisher and subscriber nodes on one executor): publish → callback;
- the pipeline with the profile, three processes (``detector``, ``features``, ``servo``;
  images from a feeder process, ``benchmarks.feeder``): image stamp → twist publish, the
  servo's ``image_age`` (its clock right after it published the twist − the stamp taken
  right before the image was published: three DDS hops and the three callbacks);
- the pipeline in single-process mode, as ``launcher --single-process`` runs the nodes
  (detector, features and servo on the EventsExecutor; the feeder, which stands for
  arm_sim, on arm_sim's classic executor on a thread of its own): the same figure;
- twist *arrival* in this process − image stamp (one hop more), for information;
- the floor of the same path (``benchmarks.relay``): three relays that answer each message
  at once with an empty one on the pipeline's topics, QoS and executor, in three processes
  and in one: the hops and callbacks without the nodes' work, for information.

Median, p95, p99 and max, each with its baseline beside it and the ratio. Targets: the
profiled hop ≤ 0.5× the default hop; the 3-process pipeline ≤ 2× the profiled two-process
hop at the median and ≤ 3× at p99; single-process ≤ 1.5× the one-process hop (median);
with and without the load. The pipeline again with its processes at nice −10 (``launcher
--nice -10``, as root), the same targets: its callbacks then come before the busy processes'
work. Then a 60 Hz camera, both modes, idle and loaded: frames the servo left unanswered
(target 0; those without a measurement too: dropped before the detector's answer), and the
resident memory of each node process.

``python -m benchmarks.bench loop [--quick]`` prints the table.
"""
from __future__ import annotations

from contextlib import nullcontext
import os
from pathlib import Path
import select
import signal
import subprocess
import sys
import time

from benchmarks.bench_transport import _last_json, _rows, busy_load, hop, own_session
from benchmarks.hop import hop_env
import numpy as np

NODES = ('detector', 'features', 'servo')
DRAIN = 1.0  # s: frames sent this close to the end may still be on their way
NICE = -10  # the rows with the nodes before the load (launcher --nice -10)


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


def _start(mode: str, rate: float, env: dict, nice: int = 0) -> dict[str, subprocess.Popen]:
    """Start the pipeline's processes: ``processes`` (3 nodes + feeder) or ``single``."""
    def popen(cmd, out=subprocess.DEVNULL):
        return subprocess.Popen([sys.executable, *cmd], env=env, stdout=out,
                                stderr=subprocess.DEVNULL, text=True, **own_session(nice))
    feeder = ['-m', 'benchmarks.feeder', 'feeder' if mode == 'processes' else 'single',
              '--rate', str(rate)]
    procs = {'feeder': popen(feeder, subprocess.PIPE)}
    if mode == 'processes':
        procs.update({n: popen(['-m', f'sphere_servo.ros.{n}']) for n in NODES})
    elif mode != 'single':
        raise ValueError(f'mode must be processes or single, not {mode!r}')
    return procs


def _stop(procs: dict[str, subprocess.Popen]) -> None:
    """SIGINT every process still running; kill one that does not end in 10 s."""
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def pipeline(mode: str, rate: float = 30.0, seconds: float = 10.0,
             domain: int | None = None, nice: int = 0, count_measured: bool = False) -> dict:
    """
    Run the pipeline on the feeder's far-pose frames for ``seconds``; return what it measured.

    ``nice`` is added to the niceness of the pipeline's processes (the feeder's too), as
    ``launcher --nice`` does; a negative one needs root (``subprocess.SubprocessError``).
    This process takes ``detector/measurement`` until the first one came, and through the
    run only with ``count_measured`` (the 60 Hz rows): a subscriber more wakes up on the
    path measured, beside the features node.

    ``{'latency_ms': image stamp → twist publish, 'arrival_ms': → twist arrival here,
    'sent': frames in the window, 'received': of those, answered by a twist, 'measured': of
    those, with a detector measurement here (``count_measured``), 'rss': MiB}``.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import JointState
    from sphere_servo.ros.qos import COMMAND, MONITOR, observer, PIPELINE
    from std_srvs.srv import Trigger

    domain = domain if domain is not None else 1 + (os.getpid() * 17 + 5) % 100
    env = hop_env(domain, True)
    procs = _start(mode, rate, env, nice)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('bench_loop', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ages, arrivals, answered, measured = [], [], set(), []

    def t_of(h) -> float:
        return h.stamp.sec + h.stamp.nanosec * 1e-9

    def on_twist(m):
        t = t_of(m.header)
        if t > 0.0:  # the watchdog's answer no image
            answered.add(t)
            arrivals.append(time.time() - t)

    def on_state(m):
        st = m.status[0]
        age = {kv.key: kv.value for kv in st.values}.get('image_age')
        if st.message == 'servoing' and age not in (None, ''):
            ages.append(float(age))
    node.create_subscription(TwistStamped, 'camera/cmd_vel', on_twist, observer(COMMAND))
    node.create_subscription(DiagnosticArray, 'servo/state', on_state, observer(MONITOR))
    sub_measured = node.create_subscription(JointState, 'detector/measurement',
                                            lambda m: measured.append(m), observer(PIPELINE))
    clients = [node.create_client(Trigger, s) for s in ('/features/teach', '/bench_feeder/far')]

    def spin(until, timeout: float, what: str):
        end = time.monotonic() + timeout
        while not until():
            if time.monotonic() > end or any(p.poll() is not None for p in procs.values()):
                raise RuntimeError(f'{mode}: {what} not within {timeout} s')
            ex.spin_once(timeout_sec=0.02)

    def call(cli):
        fut = cli.call_async(Trigger.Request())
        spin(fut.done, 10.0, f'an answer of {cli.srv_name}')
        return fut.result()
    try:
        spin(lambda: all(c.service_is_ready() for c in clients) and measured, 60.0,
             'the nodes and the first measurement')
        while not call(clients[0]).success:  # teach the desired frame
            ex.spin_once(timeout_sec=0.1)
        call(clients[1])
        if not count_measured:  # one subscriber less on the path measured
            node.destroy_subscription(sub_measured)
        spin(lambda: len(ages) > 5, 10.0, 'servoing on the far frames')
        for history in (ages, arrivals, answered):
            history.clear()
        t0 = time.time()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        t1 = time.time() - DRAIN
        end = time.monotonic() + DRAIN
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        rss = {n: _rss_mb(p.pid) for n, p in procs.items()}
        procs['feeder'].send_signal(signal.SIGINT)
        stamps = _last_json(procs['feeder'].communicate(timeout=30)[0], 'feeder')['stamps']
    finally:
        _stop(procs)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    window = [t for t in stamps if t0 <= t < t1]
    if not ages or not window:
        raise RuntimeError(f'{mode}: nothing measured ({len(ages)} twists, {len(window)} frames)')
    return {'latency_ms': np.array(ages) * 1e3, 'arrival_ms': np.array(arrivals) * 1e3,
            'sent': len(window), 'received': sum(t in answered for t in window), 'rss': rss,
            'measured': len(set(window) & {t_of(m.header) for m in measured})}


def relay_floor(mode: str, rate: float = 30.0, seconds: float = 10.0,
                domain: int | None = None, warmup: float = 1.0) -> dict:
    """
    Run the relays of ``benchmarks.relay`` on the feeder's frames; return their latency.

    ``mode``: ``processes`` (feeder and three relays, four processes) or ``single`` (one);
    the frames of the first ``warmup`` s after the first one came through are left out.
    ``{'latency_ms', 'sent', 'received'}`` (sent = received: the floor's time, not losses).
    """
    domain = domain if domain is not None else 1 + (os.getpid() * 19 + 7) % 100
    env = hop_env(domain, True)
    relay = [sys.executable, '-m', 'benchmarks.relay']
    cmds = {'servo': [*relay, 'servo'], 'features': [*relay, 'features'],
            'detector': [*relay, 'detector'],
            'feeder': [sys.executable, '-m', 'benchmarks.feeder', 'feeder', '--rate', str(rate)]}
    if mode == 'single':
        cmds = {'servo': [*relay, 'single', '--rate', str(rate)]}
    elif mode != 'processes':
        raise ValueError(f'mode must be processes or single, not {mode!r}')
    procs = {n: subprocess.Popen(c, env=env, text=True, stderr=subprocess.DEVNULL,
                                 stdout=subprocess.PIPE if n == 'servo' else subprocess.DEVNULL,
                                 **own_session())
             for n, c in cmds.items()}
    try:
        if not select.select([procs['servo'].stdout], [], [], 60.0)[0]:
            raise RuntimeError(f'relay floor, {mode}: no frame came through in 60 s')
        first = procs['servo'].stdout.readline()  # EOF ('') if it died before
        t0 = _last_json(first, 'relay servo')['first'] + warmup
        time.sleep(warmup + seconds)
        procs['servo'].send_signal(signal.SIGINT)
        res = _last_json(procs['servo'].communicate(timeout=30)[0], 'relay servo')
    finally:
        _stop(procs)
    lat = np.array([x for t, x in zip(res['stamps'], res['latency_ms']) if t >= t0])
    if lat.size == 0:
        raise RuntimeError(f'relay floor, {mode}: no frame came through')
    return {'latency_ms': lat, 'sent': lat.size, 'received': lat.size}


def _unanswered_rows(label: str, r: dict) -> list[dict]:
    """Return the frames without a twist, and (where they went) those without a measurement."""
    return [{'name': f'loop at 60 Hz, {label}: frames without a {what}',
             'value': float(r['sent'] - r[key]), 'unit': 'frames',
             'baseline': float(r['sent']), 'baseline_name': 'frames published',
             'ratio': r[key] / max(1, r['sent']), 'target': target}
            for what, key, target in (('twist', 'received', '0 (ratio 1.0)'),
                                      ('measurement', 'measured', 'information'))]


def _raised(seconds: float) -> dict[str, dict]:
    """Run both modes with the nodes at nice :data:`NICE` (``launcher --nice``), if permitted."""
    try:
        return {'3 processes': pipeline('processes', seconds=seconds, nice=NICE),
                'single process': pipeline('single', seconds=seconds, nice=NICE)}
    except subprocess.SubprocessError as exc:  # os.nice refused: not root, no CAP_SYS_NICE
        print(f'[bench] loop: the rows at nice {NICE} left out: {exc}', flush=True)
        return {}


def run(quick: bool = False) -> list[dict]:
    seconds = 4.0 if quick else 10.0
    rows = []
    for load in (False, True):
        tag = ' +2 busy' if load else ''
        with busy_load(2, own_sessions=True) if load else nullcontext():
            default = hop(2, False, seconds=seconds)
            profiled = hop(2, True, seconds=seconds)
            inproc = hop(1, True, seconds=seconds)
            procs = pipeline('processes', seconds=seconds)
            single = pipeline('single', seconds=seconds)
            floor = {m: relay_floor(m, seconds=seconds) for m in ('processes', 'single')}
            raised = _raised(seconds)
        rows += _rows(f'loop: bare hop, 2 processes, defaults{tag}', default, None, None,
                      'baseline')
        rows += _rows(f'loop: bare hop, 2 processes, profile{tag}', profiled, default,
                      'defaults', '≤ 0.5× defaults')
        rows += _rows(f'loop: bare hop, 1 process, profile{tag}', inproc, None, None,
                      'baseline')
        targets = {0: '≤ 2× (median)', 2: '≤ 3× (p99)'}
        for k, row in enumerate(_rows(f'loop: image stamp → twist publish, 3 processes{tag}',
                                      procs, profiled, 'profiled 2-process hop', '')):
            row['target'] = targets.get(k, row['target'] or 'information')
            rows.append(row)
        rows += _rows(f'loop: image stamp → twist publish, single process{tag}', single,
                      inproc, '1-process hop', '≤ 1.5× (median)')
        rows += _rows(f'loop: relay floor (no work), 3 processes{tag}', floor['processes'],
                      profiled, 'profiled 2-process hop', 'information (the floor)')[:-1]
        rows += _rows(f'loop: relay floor (no work), single process{tag}', floor['single'],
                      inproc, '1-process hop', 'information (the floor)')[:-1]
        for mode, r in raised.items():
            label = f'loop: image stamp → twist publish, {mode}, nodes at nice {NICE}{tag}'
            if mode == 'single process':
                rows += _rows(label, r, inproc, '1-process hop', '≤ 1.5× (median)')
                continue
            for k, row in enumerate(_rows(label, r, profiled, 'profiled 2-process hop', '')):
                row['target'] = targets.get(k, row['target'] or 'information')
                rows.append(row)
        arrival = {'latency_ms': procs['arrival_ms'], 'sent': procs['sent'],
                   'received': procs['received']}
        rows += _rows(f'loop: image stamp → twist arrival here, 3 processes{tag}', arrival,
                      profiled, 'profiled 2-process hop', 'information (one hop more)')[:-1]
    for load in (False, True):
        tag = ', +2 busy' if load else ''
        with busy_load(2, own_sessions=True) if load else nullcontext():
            r60 = {m: pipeline(m, 60.0, seconds, count_measured=True)
                   for m in ('processes', 'single')}
        rows += _unanswered_rows(f'3 processes{tag}', r60['processes']) + \
            _unanswered_rows(f'single process{tag}', r60['single'])
        if not load:
            rows += [{'name': f'RSS {name} (60 Hz, {mode})', 'value': mb, 'unit': 'MiB',
                      'baseline': None, 'baseline_name': None, 'ratio': None,
                      'target': 'printed'}
                     for mode, r in r60.items() for name, mb in r['rss'].items()]
    return rows


if __name__ == '__main__':
    from benchmarks.bench import main
    sys.exit(main(['loop', *sys.argv[1:]]))
