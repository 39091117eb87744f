"""
The pipeline's transport floor: three relays that do no work, on the pipeline's topics.

``python -m benchmarks.relay detector|features|servo|single``

Each relay stands for a node of the image → twist path and answers each message at once
with an empty message of what that node publishes, the header passed on: ``detector``
``camera/image_raw`` → ``detector/measurement`` (JointState), ``features``
``detector/measurement`` → ``features/s_n`` (JointState), ``servo`` ``features/s_n`` →
``camera/cmd_vel`` (TwistStamped), with the nodes' QoS (:mod:`sphere_servo.ros.qos`) and
executor. ``servo`` notes its clock right after publishing − the image stamp (the servo's
``image_age``); ``single`` runs the three and the feeder on one executor (``--rate``). The
process with the ``servo`` relay prints ``{"first": s}`` when the first message came
through, and on SIGINT one JSON line ``{"stamps": [s, ...], "latency_ms": [...]}``. With
images from ``benchmarks.feeder``, the latency is the floor of the pipeline's image stamp →
twist publish: the three DDS hops and three Python callbacks, without the nodes' work.
"""
from __future__ import annotations

import argparse
import json
import sys

ROLES = ('detector', 'features', 'servo')


def relay_node(role: str, latencies: list[tuple[float, float]]):
    """Return the relay node of ``role``; rclpy must be initialised."""
    from geometry_msgs.msg import TwistStamped
    from rclpy.node import Node
    from sensor_msgs.msg import Image, JointState
    from sphere_servo.ros.qos import COMMAND, PIPELINE, SENSOR

    kind_in, topic_in, qos_in, kind_out, topic_out, qos_out = {
        'detector': (Image, 'camera/image_raw', SENSOR,
                     JointState, 'detector/measurement', PIPELINE),
        'features': (JointState, 'detector/measurement', PIPELINE,
                     JointState, 'features/s_n', PIPELINE),
        'servo': (JointState, 'features/s_n', PIPELINE,
                  TwistStamped, 'camera/cmd_vel', COMMAND)}[role]

    class Relay(Node):
        """A relay (see the module docstring); the servo's prints its figures at the end."""

        def on_shutdown(self):
            if role == 'servo':
                print(json.dumps({'stamps': [t for t, _ in latencies],
                                  'latency_ms': [round(x, 4) for _, x in latencies]}),
                      flush=True)
    node = Relay(f'relay_{role}')
    pub = node.create_publisher(kind_out, topic_out, qos_out)
    clock = node.get_clock()

    def on_message(msg):
        pub.publish(kind_out(header=msg.header))
        if role == 'servo':
            st = msg.header.stamp
            t = st.sec + st.nanosec * 1e-9
            latencies.append((t, clock.now().nanoseconds * 1e-6 - t * 1e3))
            if len(latencies) == 1:
                print(json.dumps({'first': t}), flush=True)
    node.create_subscription(kind_in, topic_in, on_message, qos_in)
    return node


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('role', choices=(*ROLES, 'single'))
    ap.add_argument('--rate', type=float, default=30.0, help='single: frames per second')
    args, ros = ap.parse_known_args(argv)
    from sphere_servo.ros.params import run
    latencies: list[tuple[float, float]] = []  # (stamp s, latency ms)
    roles = ROLES if args.role == 'single' else (args.role,)

    def nodes():
        made = [relay_node(r, latencies) for r in reversed(roles)]  # consumers first
        if args.role == 'single':
            from benchmarks.feeder import feeder_node
            made.insert(0, feeder_node(args.rate))  # made last, shut down first
        return made
    run(nodes, f'relay {args.role}', [sys.argv[0], *ros])


if __name__ == '__main__':
    main()
