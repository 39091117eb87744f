"""
A bare sensor_msgs/Image hop: a publisher, a subscriber, or both in one process.

``python -m benchmarks.hop pub|sub|both [--rate 30] [--seconds 5] [--width 640 --height 480]``

The processes the transport benchmark and the two-host test start (none of the nodes' code
in the loop). Every image is a message built anew from the same pixels by
:func:`~sphere_servo.ros.conversions.image_from_array`, as arm_sim and
``benchmarks.feeder`` build each frame's (one message published again and again is slower to
publish in one process), and stamped with the publisher's ROS clock (the system clock) right
before ``publish``; the subscriber takes the same clock first thing in its callback, so on one
host ``arrival − stamp`` is the hop's latency (serialisation, transport, executor, conversion
to Python).

- ``pub``: waits until a subscription is matched (``--match-timeout``, exit 3 if none), then
  publishes ``--warmup`` seconds of frames with frame_id ``warmup`` (not counted) and
  ``--seconds`` of frames with frame_id ``hop``; keeps spinning ``--linger`` s so that
  reliable repairs can still go out; prints one JSON line ``{"sent": n, "rate": hz}``.
- ``sub``: until SIGINT/SIGTERM (or ``--max-seconds``), records each ``hop`` frame; prints
  one JSON line ``{"received": n, "latency_ms": [...]}``. ``--stream`` also prints, as it
  goes, ``{"arrival": wall s, "stamp": s}`` for every frame (warm-up ones too), flushed.
- ``both``: the two nodes in one process on one executor (rclpy has no intra-process
  communication; Fast DDS delivers between endpoints of one participant without a transport);
  prints ``{"sent": n, "rate": hz, "received": m, "latency_ms": [...]}``.

Every process spins on the nodes' executor (:func:`sphere_servo.ros.executors.make_executor`)
and allocates as the nodes do (:func:`sphere_servo.pipeline.allocator.keep_heap`, as
:func:`sphere_servo.ros.params.run` calls it), so the hop is the floor the pipeline is
compared with.
QoS: reliable or best effort (``--qos``), keep last ``--depth``, volatile. :func:`hop_env` is
the environment to start these processes with.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import signal
import sys
import time

from sphere_servo.pipeline.middleware import profile_env, PROFILE_VARIABLES, RMW

REPO = Path(__file__).resolve().parents[1]


def hop_env(domain: int, profile: bool, discovery: str = 'LOCALHOST') -> dict[str, str]:
    """
    Return the environment of a hop process: this process's, with Fast DDS set up for the hop.

    Its own ``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE``, rmw_fastrtps_cpp, the
    shipped profile (``profile``) or none at all (Fast DDS's defaults, whatever the caller's
    environment names), and the repository on ``PYTHONPATH``.
    """
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE=discovery,
               PYTHONUNBUFFERED='1', RMW_IMPLEMENTATION=RMW)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    env.pop('ROS_LOCALHOST_ONLY', None)
    for name in PROFILE_VARIABLES:
        env.pop(name, None)
    if profile:
        env.update(profile_env())
    return env


def _qos(kind: str, depth: int):
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    reliability = {'reliable': ReliabilityPolicy.RELIABLE,
                   'best_effort': ReliabilityPolicy.BEST_EFFORT}[kind]
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=reliability)


def _seconds(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('role', choices=('pub', 'sub', 'both'))
    ap.add_argument('--topic', default='hop/image_raw')
    ap.add_argument('--rate', type=float, default=30.0, help='images per second')
    ap.add_argument('--seconds', type=float, default=5.0, help='measured publishing time')
    ap.add_argument('--warmup', type=float, default=0.5, help='uncounted frames first (s)')
    ap.add_argument('--linger', type=float, default=1.5, help='spin after the last frame (s)')
    ap.add_argument('--width', type=int, default=640)
    ap.add_argument('--height', type=int, default=480)
    ap.add_argument('--qos', choices=('reliable', 'best_effort'), default='reliable')
    ap.add_argument('--depth', type=int, default=10)
    ap.add_argument('--match-timeout', type=float, default=30.0)
    ap.add_argument('--max-seconds', type=float, default=600.0, help='sub: stop after (s)')
    ap.add_argument('--stream', action='store_true', help='sub: print every arrival')
    args = ap.parse_args(argv)
    if args.rate <= 0 or args.width <= 0 or args.height <= 0 or args.depth <= 0:
        ap.error('--rate, --width, --height and --depth must be positive')

    import rclpy
    import numpy as np
    from sensor_msgs.msg import Image
    from sphere_servo.pipeline.allocator import keep_heap
    from sphere_servo.ros.conversions import image_from_array
    from sphere_servo.ros.executors import make_executor
    from std_msgs.msg import Header

    keep_heap()  # as the nodes' run() does: without it a subscriber faults each image in anew
    rclpy.init()
    stop = {'now': False}

    def _stop(*_):
        stop['now'] = True
    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    qos = _qos(args.qos, args.depth)
    executor = make_executor()  # the nodes' executor: the floor they are compared with
    out: dict = {}
    latencies: list[float] = []

    if args.role in ('sub', 'both'):
        sub_node = rclpy.create_node('hop_sub')
        clock = sub_node.get_clock()

        def on_image(msg):
            now = clock.now().nanoseconds * 1e-9
            stamp = _seconds(msg.header.stamp)
            if msg.header.frame_id == 'hop':
                latencies.append((now - stamp) * 1e3)
            if args.stream:
                print(json.dumps({'arrival': time.time(), 'stamp': stamp,
                                  'frame_id': msg.header.frame_id}), flush=True)
        sub_node.create_subscription(Image, args.topic, on_image, qos)
        executor.add_node(sub_node)

    if args.role in ('pub', 'both'):
        pub_node = rclpy.create_node('hop_pub')
        pub = pub_node.create_publisher(Image, args.topic, qos)
        executor.add_node(pub_node)
        n = 3 * args.width * args.height
        pixels = np.frombuffer(bytes(range(256)) * (n // 256) + bytes(n % 256), np.uint8)
        pixels = pixels.reshape(args.height, args.width, 3)
        deadline = time.monotonic() + args.match_timeout
        while pub.get_subscription_count() == 0 and not stop['now']:
            if time.monotonic() > deadline:
                print(json.dumps({'error': f'no subscription matched in {args.match_timeout} s'}),
                      flush=True)
                return 3
            executor.spin_once(timeout_sec=0.05)
        n_warm = int(round(args.warmup * args.rate))
        n_total = n_warm + int(round(args.seconds * args.rate))
        t0 = time.monotonic()
        sent = 0
        for k in range(n_total):
            if stop['now']:
                break
            while True:  # serve callbacks until this frame's time
                wait = t0 + k / args.rate - time.monotonic()
                if wait <= 0:
                    break
                executor.spin_once(timeout_sec=wait)
            msg = image_from_array(pixels, Header(frame_id='warmup' if k < n_warm else 'hop'))
            msg.header.stamp = pub_node.get_clock().now().to_msg()
            pub.publish(msg)
            sent += k >= n_warm
        elapsed = time.monotonic() - t0 - n_warm / args.rate
        out.update(sent=sent, rate=(sent - 1) / elapsed if sent > 1 and elapsed > 0 else 0.0)
        end = time.monotonic() + args.linger
        while time.monotonic() < end and not stop['now']:
            executor.spin_once(timeout_sec=0.05)
    else:
        end = time.monotonic() + args.max_seconds
        while not stop['now'] and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)

    if args.role in ('sub', 'both'):
        out.update(received=len(latencies), latency_ms=[round(x, 4) for x in latencies])
    print(json.dumps(out), flush=True)
    executor.shutdown()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
