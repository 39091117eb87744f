"""
A camera for the loop benchmark: rendered 640×480 rgb8 frames at a fixed rate, wall-stamped.

``python -m benchmarks.feeder feeder --rate 30``: the feeder alone (the images of the
3-process pipeline: ``detector``, ``features`` and ``servo`` run as their own processes).
``python -m benchmarks.feeder single --rate 30``: the feeder, ``detector``, ``features``
and ``servo`` in one process, as ``launcher --single-process`` runs the pipeline
(:func:`sphere_servo.ros.params.run`, consumers constructed first).

The feeder stands for arm_sim: it publishes ``camera/camera_info`` then ``camera/image_raw``
(arm_sim's order and writer QoS, :func:`sphere_servo.ros.qos.writer`) from a wall timer,
each frame a message built anew, both stamped with the system clock right before they are
published, so that the servo's ``image_age`` (its clock at the twist's publication − the
image stamp) is the pipeline's image stamp → twist publish latency; and it takes the twists of
``camera/cmd_vel`` with their ``MessageInfo``, as arm_sim does, so that it spins on the
executor arm_sim gets (:mod:`sphere_servo.ros.executors`: in one process, apart from the
other nodes, on a thread of its own). It shows the desired pose until
``/bench_feeder/far`` (std_srvs/Trigger) is called, then the far pose (nothing moves: the
servo answers every frame with the same twist). On exit it prints one JSON line
``{"stamps": [...]}``: the stamps (s) of every far-pose frame it sent.
"""
from __future__ import annotations

import argparse
import json
import sys


def feeder_node(rate: float):
    """Return the feeder node (see the module docstring); rclpy must be initialised."""
    from rclpy.node import Node
    from geometry_msgs.msg import TwistStamped
    from sensor_msgs.msg import CameraInfo, Image
    from sphere_servo.core.camera import CameraIntrinsics
    from sphere_servo.core.targets import special_sphere
    from sphere_servo.experiments.scenarios import CMO_DESIRED, CMO_FAR_START
    from sphere_servo.ros.conversions import camera_info_from_intrinsics, image_from_array
    from sphere_servo.ros.qos import COMMAND, writer
    from sphere_servo.vision.renderer import Renderer
    from std_msgs.msg import Header
    from std_srvs.srv import Trigger

    class Feeder(Node):
        """The feeder (see the module docstring)."""

        def __init__(self):
            super().__init__('bench_feeder')
            self.camera = CameraIntrinsics()
            renderer = Renderer(self.camera, special_sphere())
            self.frames = [renderer.render(p) for p in (CMO_DESIRED, CMO_FAR_START)]
            self.far = False
            self.stamps: list[float] = []
            self.pub_info = self.create_publisher(CameraInfo, 'camera/camera_info',
                                                  writer('camera/camera_info'))
            self.pub_image = self.create_publisher(Image, 'camera/image_raw',
                                                   writer('camera/image_raw'))
            self.create_service(Trigger, '~/far', self._go_far)
            self.create_timer(1.0 / rate, self._tick)
            # with their MessageInfo, as arm_sim takes them (see the module docstring)
            self.twists = 0
            self.create_subscription(TwistStamped, 'camera/cmd_vel', self._on_twist, COMMAND)

        def _on_twist(self, msg, info):
            self.twists += 1

        def _go_far(self, request, response):
            self.far = response.success = True
            return response

        def _tick(self):
            img = self.frames[self.far]
            hdr = Header(frame_id='camera_optical_frame')
            msg = image_from_array(img, hdr)
            info = camera_info_from_intrinsics(self.camera, hdr)
            hdr.stamp = self.get_clock().now().to_msg()
            msg.header.stamp = info.header.stamp = hdr.stamp
            # the camera_info first, as arm_sim publishes it: the image finds its own
            self.pub_info.publish(info)
            self.pub_image.publish(msg)
            if self.far:
                self.stamps.append(hdr.stamp.sec + hdr.stamp.nanosec * 1e-9)

        def on_shutdown(self):
            print(json.dumps({'stamps': self.stamps}), flush=True)

    return Feeder()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('mode', choices=('feeder', 'single'))
    ap.add_argument('--rate', type=float, default=30.0, help='frames per second')
    args, ros = ap.parse_known_args(argv)
    if args.rate <= 0:
        ap.error('--rate must be positive')
    from sphere_servo.ros.params import run

    def nodes():
        if args.mode == 'feeder':
            return feeder_node(args.rate)
        from sphere_servo.bringup.single import node_classes
        return [cls() for cls in node_classes(['servo', 'features', 'detector'])] \
            + [feeder_node(args.rate)]
    run(nodes, f'bench {args.mode}', [sys.argv[0], *ros])


if __name__ == '__main__':
    main()
