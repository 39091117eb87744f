"""
Benchmark of the arm simulator (issue 4).

Rows (``run()`` returns them as dicts with name, value, unit, baseline, baseline_name,
ratio = value / baseline, target):

- ``arm_sim lockstep cycle``: median wall time of one lockstep cycle, measured around the
  node's command callback in-process: DLS mapping + integrate one period + render 640×480
  + build the Image (and the other messages) + publish them, with a subscriber on the image
  topic so that the message is really serialised and delivered. Baseline: the renderer alone
  on the same poses. Target ≤ 10 ms.
- ``arm_sim realtime rate``: images per wall second received by a subscriber in the same
  process over N seconds of the 30 Hz real-time mode (N = 3 quick, 60 full). Baseline: the
  nominal 30 Hz. Target 30 Hz ± 2 %.

``python -m benchmarks.bench_arm [--quick]`` prints the rows as a table.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time

import numpy as np


def _params(mode: str) -> list:
    from rclpy.parameter import Parameter
    return [Parameter('clock_mode', value=mode), Parameter('velocity_scale', value=0.5),
            Parameter('hand_eye', value=[0.0, -0.04, 0.02, 0.0, 0.0, 0.0])]


def _row(name, value, unit, baseline, baseline_name, target) -> dict:
    return {'name': name, 'value': float(value), 'unit': unit, 'baseline': float(baseline),
            'baseline_name': baseline_name, 'ratio': float(value) / float(baseline),
            'target': target}


@contextlib.contextmanager
def _sim(mode: str):
    """
    Run an in-process ``ArmSim`` in ``mode`` and a sink node; yield ``(sim, sink, executor)``.

    Both are on their own context and executor.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from sphere_servo.ros.arm_sim import ArmSim

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        sim = ArmSim(context=ctx, parameter_overrides=_params(mode))
        sink = rclpy.create_node('bench_arm_sink', context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(sink)
        yield sim, sink, ex
        sim.destroy_node()
        sink.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def bench_lockstep_cycle(n: int) -> dict:
    from geometry_msgs.msg import Twist
    from sensor_msgs.msg import Image

    with _sim('lockstep') as (sim, sink, ex):
        sink.create_subscription(Image, 'camera/image_raw', lambda m: None, 10)
        deadline = time.monotonic() + 5.0
        while sim.pub_image.get_subscription_count() == 0 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        cmd = Twist()
        cmd.linear.x, cmd.linear.z, cmd.angular.z = 0.01, 0.02, 0.05
        cycle, render = [], []
        for _ in range(n):
            t0 = time.perf_counter()
            sim._on_cmd(cmd)
            cycle.append(time.perf_counter() - t0)
            cMo = sim.core.arm.cMo()
            t0 = time.perf_counter()
            sim.core.renderer.render(cMo)
            render.append(time.perf_counter() - t0)
            ex.spin_once(timeout_sec=0.0)  # deliver (outside the timed part)
    return _row('arm_sim lockstep cycle (integrate+render+publish 640x480)',
                1e3 * statistics.median(cycle), 'ms', 1e3 * statistics.median(render),
                'renderer alone', '<= 10 ms')


def bench_realtime_rate(seconds: float) -> dict:
    from sensor_msgs.msg import Image

    stamps = []
    with _sim('realtime') as (sim, sink, ex):
        sink.create_subscription(Image, 'camera/image_raw',
                                 lambda m: stamps.append(time.monotonic()), 50)
        ex.add_node(sim)
        end = time.monotonic() + seconds + 1.0  # 1 s to settle discovery
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
    s = np.array(stamps)
    s = s[s >= s[-1] - seconds] if len(s) else s
    rate = (len(s) - 1) / (s[-1] - s[0]) if len(s) > 1 else 0.0
    return _row(f'arm_sim realtime rate over {seconds:g} s', rate, 'Hz', 30.0,
                'nominal camera_rate', '30 Hz +/- 2 %')


def run(quick: bool = False) -> list[dict]:
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return [bench_lockstep_cycle(60 if quick else 300),
            bench_realtime_rate(3.0 if quick else 60.0)]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='short runs')
    rows = run(quick=ap.parse_args(argv).quick)
    for r in rows:
        print(f"{r['name']:<62} {r['value']:9.3f} {r['unit']:<3} "
              f"(baseline {r['baseline_name']}: {r['baseline']:.3f}, ratio {r['ratio']:.2f}; "
              f"target {r['target']})")


if __name__ == '__main__':
    main()
