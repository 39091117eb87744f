"""
Benchmark of rosbag2 recording and replay (issues 6 and 16).

Rows (``run()`` returns dicts with name, value, unit, baseline, baseline_name,
ratio = value / baseline, target), for each storage (MCAP, sqlite3):

- ``record <storage> 640x480 rgb8 @60 Hz: drops``: messages published by this process at
  60 Hz for N s (N = 3 quick, 10 full) minus those in the bag the ``record`` process wrote.
  Baseline: the number published. Target 0.
- ``… recorder CPU``: CPU time of the recorder process (user + system, from
  /proc/<pid>/stat) over the publishing window divided by that window's wall time, in cores.
  Baseline: one core. Target < 1.
- ``… Ctrl-C to exit``: wall time from SIGINT to the recorder's exit (the bag closed).
  Baseline: the required 1 s. Target < 1.
- ``… SIGKILL: newest recovered message's age``: the recorder is killed while the stream
  goes on, ``reindex`` recovers the bag; how long before the kill the newest recovered image
  was published. Baseline: the commit window (0.5 s); target ≤ commit window + delivery.
- ``record: publisher achieved rate``: what this process really published per second
  (the drops figure only means something if it is close to 60). Baseline: 60 Hz.
- ``replay --max-rate: images/s``: messages per second the ``replay`` process reports for
  the recorded MCAP bag at max rate (publishing plus waiting for the reliable
  acknowledgements), with a Python subscriber in this process. Baseline: the required 100
  images/s. Target ≥ 100.

``python -m benchmarks.bench_bag [--quick]`` prints the rows as a table.
"""
from __future__ import annotations

import argparse
import array
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import tempfile
import time

REPO = Path(__file__).resolve().parents[1]
TOPIC = '/bench/image_raw'
W, H = 640, 480


def _row(name, value, unit, baseline, baseline_name, target) -> dict:
    return {'name': name, 'value': float(value), 'unit': unit, 'baseline': float(baseline),
            'baseline_name': baseline_name,
            'ratio': float(value) / float(baseline) if baseline else None, 'target': target}


def _cpu_seconds(pid: int) -> float:
    """Return utime + stime of a process, from /proc/<pid>/stat (fields 14 and 15)."""
    text = Path(f'/proc/{pid}/stat').read_text()
    fields = text[text.rindex(')') + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _env(domain: int) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    return env


def _spin_until(executor, pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        executor.spin_once(timeout_sec=0.02)
    return pred()


def _record(executor, node, env, tmp: Path, storage: str, seconds: float, hz: float,
            kill: bool) -> tuple[dict, Path]:
    """
    Record ``seconds`` of 60 Hz images; stop with SIGINT (or SIGKILL + reindex).

    Each run has a topic of its own: a killed recorder's subscription stays matched until
    its lease expires, and would count as "the recorder subscribed" for the next run.
    """
    from sensor_msgs.msg import Image

    from sphere_servo.bag.bagio import bag, summary
    out = tmp / f'{storage}{"_killed" if kill else ""}'
    topic = f'{TOPIC}_{out.name}'
    pub = node.create_publisher(Image, topic, 10)
    log = open(tmp / f'{out.name}.log', 'w+')
    rec = subprocess.Popen([sys.executable, '-m', 'sphere_servo.bag.record', '-o', str(out),
                            '--storage', storage, '--topics', topic], env=env, stdout=log,
                           stderr=subprocess.STDOUT)
    try:
        if not _spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0):
            raise RuntimeError('recorder never subscribed')
        _spin_until(executor, lambda: False, 0.5)
        img = Image(height=H, width=W, encoding='rgb8', step=W * 3)
        frames = [array.array('B', bytes([k]) * (W * H * 3)) for k in range(4)]
        n = int(seconds * hz)
        sent = []
        cpu0, t0 = _cpu_seconds(rec.pid), time.monotonic()
        for i in range(n):
            img.data = frames[i % 4]
            img.header.frame_id = str(i)
            sent.append(time.time_ns())
            pub.publish(img)
            delay = t0 + (i + 1) / hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        t_pub = time.monotonic() - t0
        res = {'sent': n, 'rate': n / t_pub, 'topic': topic}
        if kill:
            t_kill = time.time_ns()
            rec.kill()
            rec.wait(30)
            r = subprocess.run([sys.executable, '-m', 'sphere_servo.bag.repair', str(out)],
                               env=env, capture_output=True, text=True, timeout=300)
            if r.returncode != 0:
                raise RuntimeError(f'reindex failed:\n{r.stdout}{r.stderr}')
            with bag(out) as reader:
                newest = max(int(reader.deserialize(raw, c.msgtype).header.frame_id)
                             for c, _, raw in reader.messages())
            res['age'] = (t_kill - sent[newest]) / 1e9
            return res, out
        time.sleep(0.5)  # the last frames in flight
        cpu1, t1 = _cpu_seconds(rec.pid), time.monotonic()
        t_sig = time.monotonic()
        rec.send_signal(signal.SIGINT)
        rec.wait(30)
        res['exit'] = time.monotonic() - t_sig
        res['cpu'] = (cpu1 - cpu0) / (t1 - t0)
        with bag(out) as reader:
            res['recorded'] = summary(reader)['message_count']
        return res, out
    finally:
        if rec.poll() is None:
            rec.kill()
        log.close()
        node.destroy_publisher(pub)  # no reliable resends to a killed recorder


def run(quick: bool = False) -> list[dict]:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    seconds, hz = (3.0, 60.0) if quick else (10.0, 60.0)
    domain = 1 + (os.getpid() * 13 + 5) % 100
    env = _env(domain)
    tmp = Path(tempfile.mkdtemp(prefix='bench_bag_'))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('bench_bag', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    rows: list[dict] = []
    try:
        # --- record ---------------------------------------------------------------------
        rates, bags = [], {}
        for storage in ('mcap', 'sqlite3'):
            res, out = _record(executor, node, env, tmp, storage, seconds, hz, kill=False)
            name = f'record {storage} {W}x{H} rgb8 @{hz:.0f} Hz'
            rows.append(_row(f'{name}: drops', res['sent'] - res['recorded'], 'msgs',
                             res['sent'], 'published', '== 0'))
            rows.append(_row(f'{name}: recorder CPU', res['cpu'], 'cores', 1.0, 'one core',
                             '< 1'))
            rows.append(_row(f'{name}: Ctrl-C to exit', res['exit'], 's', 1.0, 'required',
                             '< 1'))
            rates.append(res['rate'])
            bags[storage] = (out, res['recorded'], res['topic'])

        # --- replay ---------------------------------------------------------------------
        received = []
        node.create_subscription(Image, '/bench/replayed', received.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
                                 raw=True)
        mcap_bag, recorded, mcap_topic = bags['mcap']
        rep = subprocess.Popen([sys.executable, '-m', 'sphere_servo.bag.replay', str(mcap_bag),
                                '--max-rate', '--wait-for-subscribers', '20',
                                '--remap', f'{mcap_topic}:=/bench/replayed'], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        _spin_until(executor, lambda: rep.poll() is not None, 120.0)
        _spin_until(executor, lambda: len(received) >= recorded, 2.0)
        text = rep.communicate(timeout=30)[0]
        m = re.search(r'published (\d+) messages in ([\d.]+) s', text)
        if rep.returncode != 0 or m is None:
            raise RuntimeError(f'replay failed:\n{text}')
        replay = _row('replay --max-rate: images/s', int(m[1]) / float(m[2]), 'img/s',
                      100.0, 'required', '>= 100')

        # --- SIGKILL, last: a killed participant lingers in the graph until its lease ends
        for storage in ('mcap', 'sqlite3'):
            res, _ = _record(executor, node, env, tmp, storage, min(seconds, 3.0), hz,
                             kill=True)
            rows.append(_row(f"record {storage}: SIGKILL: newest recovered message's age",
                             res['age'], 's', 0.5, 'commit window', '<= 0.5 + delivery'))
            rates.append(res['rate'])
        rows.append(_row('record: publisher achieved rate', min(rates), 'Hz', hz, 'nominal',
                         f'~{hz:.0f}'))
        rows.append(replay)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='short runs')
    for r in run(quick=ap.parse_args(argv).quick):
        print(f"{r['name']:<60} {r['value']:10.3f} {r['unit']:<6} (baseline "
              f"{r['baseline_name']}: {r['baseline']:.3f}, ratio {r['ratio']:.3f}; "
              f"target {r['target']})")


if __name__ == '__main__':
    main()
