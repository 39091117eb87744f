"""
``features``: measurements → the paper's feature sets, their desired values and errors.

Subscribes
    ``detector/measurement``  sensor_msgs/JointState  (see :mod:`sphere_servo.ros.vectors`)
    ``camera/camera_info``    sensor_msgs/CameraInfo  only for ``desired_source: image``
Publishes (header = the image's header)
    ``features/<set>``        sensor_msgs/JointState  for each set in ``sets`` (default s_n):
                              position = s, velocity = s*, effort = s − s*; empty = target or
                              a mark lost. Nothing is published before a desired is set.
Services
    ``~/teach``               std_srvs/Trigger  the latest measurement becomes the desired
                              one (teach by showing)

Desired features (``desired_source``): ``teach`` (default), ``pose`` (``desired_cMo``) or
``image`` (``desired_image``): see :mod:`sphere_servo.pipeline.features`, whose
:class:`~sphere_servo.pipeline.features.FeaturesCore` holds the logic.
"""
from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, JointState
from sphere_servo.pipeline.common import Refusal, stamp_ns
from sphere_servo.pipeline.features import DesiredSource, FeaturesCore
from sphere_servo.pipeline.params import FeaturesParams
from sphere_servo.ros.params import declare_all, run
from sphere_servo.ros.vectors import features_msg, measurement_from_msg
from std_srvs.srv import Trigger


class FeaturesNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('features', **kwargs)
        self.core = FeaturesCore(declare_all(self, FeaturesParams))
        self.pubs = {name: self.create_publisher(JointState, f'features/{name}', 100)
                     for name in self.core.names}
        self.create_subscription(JointState, 'detector/measurement', self._on_measurement, 10)
        self.create_service(Trigger, '~/teach', self._srv_teach)
        if self.core.has_desired:
            self.get_logger().info(self.core.describe_desired())
        elif self.core.source is DesiredSource.IMAGE:
            self._info_sub = self.create_subscription(CameraInfo, 'camera/camera_info',
                                                      self._on_info_for_image, 10)
        else:
            self.get_logger().info('waiting for ~/teach to set the desired features')

    def _on_info_for_image(self, msg: CameraInfo) -> None:
        out = self.core.on_camera_info(msg.width, msg.height, msg.k, msg.d)
        if isinstance(out, Refusal):
            self.get_logger().error(out.reason, throttle_duration_sec=5.0)
        elif out is not None:
            self.get_logger().info(self.core.describe_desired())

    def _srv_teach(self, request, response):
        taught = self.core.teach()
        response.success, response.message = taught.success, taught.message
        if taught.success:
            self.get_logger().info(self.core.describe_desired())
        return response

    def _on_measurement(self, msg: JointState) -> None:
        st = msg.header.stamp
        out = self.core.on_measurement(stamp_ns(st.sec, st.nanosec), measurement_from_msg(msg))
        if out is None:
            return
        if out.lost:
            self.get_logger().warn(f'target lost: {out.lost}', throttle_duration_sec=2.0)
        for name, pub in self.pubs.items():
            fs = out.values.get(name)
            pub.publish(features_msg(name, msg.header, *((fs.s, fs.s_star) if fs else ())))


def main(args=None):
    run(FeaturesNode, 'features', args)


if __name__ == '__main__':
    main()
