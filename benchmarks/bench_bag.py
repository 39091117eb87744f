"""
Benchmark of rosbag2 recording and replay (issue 6).

Rows (``run()`` returns dicts with name, value, unit, baseline, baseline_name,
ratio = value / baseline, target):

- ``record 640x480 rgb8 @60 Hz: drops``: messages published by this process at 60 Hz for
  N s (N = 3 quick, 10 full) minus those in the bag the ``record`` process wrote (MCAP).
  Baseline: the number published. Target 0.
- ``record 640x480 rgb8 @60 Hz: recorder CPU``: CPU time of the recorder process (user +
  system, from /proc/<pid>/stat) over the publishing window divided by that window's wall
  time, in cores. Baseline: one core. Target < 1.
- ``record: publisher achieved rate``: what this process really published per second
  (the drops figure only means something if it is close to 60). Baseline: 60 Hz.
- ``replay --max-rate: images/s``: messages per second the ``replay`` process reports for
  the recorded bag at max rate (publishing plus waiting for the reliable acknowledgements),
  with a Python subscriber in this process. Baseline: the required 100 images/s.
  Target ≥ 100.

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


def run(quick: bool = False) -> list[dict]:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from sphere_servo.bag.bagio import bag, summary

    seconds, hz = (3.0, 60.0) if quick else (10.0, 60.0)
    domain = 1 + (os.getpid() * 13 + 5) % 100
    env = _env(domain)
    tmp = Path(tempfile.mkdtemp(prefix='bench_bag_'))
    out = tmp / 'bag'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('bench_bag', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    rows: list[dict] = []
    rec = None
    try:
        # --- record ---------------------------------------------------------------------
        pub = node.create_publisher(Image, TOPIC, 10)
        rec_log = open(tmp / 'record.log', 'w+')
        rec = subprocess.Popen([sys.executable, '-m', 'sphere_servo.bag.record', '-o',
                                str(out), '--topics', TOPIC], env=env, stdout=rec_log,
                               stderr=subprocess.STDOUT)
        if not _spin_until(executor, lambda: pub.get_subscription_count() > 0, 20.0):
            raise RuntimeError('recorder never subscribed')
        _spin_until(executor, lambda: False, 0.5)
        img = Image(height=H, width=W, encoding='rgb8', step=W * 3)
        frames = [array.array('B', bytes([k]) * (W * H * 3)) for k in range(4)]
        n = int(seconds * hz)
        cpu0, t0 = _cpu_seconds(rec.pid), time.monotonic()
        for i in range(n):
            img.data = frames[i % 4]
            img.header.frame_id = str(i)
            pub.publish(img)
            delay = t0 + (i + 1) / hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        t_pub = time.monotonic() - t0
        time.sleep(0.5)  # the last frames in flight
        cpu1, t1 = _cpu_seconds(rec.pid), time.monotonic()
        rec.send_signal(signal.SIGINT)
        rec.wait(30)
        with bag(out) as reader:
            recorded = summary(reader)['message_count']
        rows.append(_row(f'record {W}x{H} rgb8 @{hz:.0f} Hz: drops', n - recorded, 'msgs', n,
                         'published', '== 0'))
        rows.append(_row(f'record {W}x{H} rgb8 @{hz:.0f} Hz: recorder CPU',
                         (cpu1 - cpu0) / (t1 - t0), 'cores', 1.0, 'one core', '< 1'))
        rows.append(_row('record: publisher achieved rate', n / t_pub, 'Hz', hz, 'nominal',
                         f'~{hz:.0f}'))

        # --- replay ---------------------------------------------------------------------
        received = []
        node.create_subscription(Image, '/bench/replayed', received.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
                                 raw=True)
        rep = subprocess.Popen([sys.executable, '-m', 'sphere_servo.bag.replay', str(out),
                                '--max-rate', '--wait-for-subscribers', '20',
                                '--remap', f'{TOPIC}:=/bench/replayed'], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        _spin_until(executor, lambda: rep.poll() is not None, 120.0)
        _spin_until(executor, lambda: len(received) >= recorded, 2.0)
        text = rep.communicate(timeout=30)[0]
        m = re.search(r'published (\d+) messages in ([\d.]+) s', text)
        if rep.returncode != 0 or m is None:
            raise RuntimeError(f'replay failed:\n{text}')
        rows.append(_row('replay --max-rate: images/s', int(m[1]) / float(m[2]), 'img/s',
                         100.0, 'required', '>= 100'))
    finally:
        if rec is not None and rec.poll() is None:
            rec.kill()
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
        print(f"{r['name']:<46} {r['value']:10.3f} {r['unit']:<6} (baseline "
              f"{r['baseline_name']}: {r['baseline']:.3f}, ratio {r['ratio']:.3f}; "
              f"target {r['target']})")


if __name__ == '__main__':
    main()
