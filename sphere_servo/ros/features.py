"""
``features``: measurements → the paper's feature sets and their desired values.

Subscribes
    ``detector/measurement``  sensor_msgs/JointState  (see :mod:`sphere_servo.ros.vectors`)
    ``camera/camera_info``    sensor_msgs/CameraInfo  the camera's field (for the check of the
                              measurements), and its K for ``desired_source: image``; with
                              its binning and roi, as the detector's; best effort with
                              ``image_reliability: best_effort`` (as the detector)
Publishes
    ``features/<set>``          sensor_msgs/JointState  for each set in ``sets`` (default
                                s_n): ``position`` = s, header = the image's; empty = target
                                or a mark lost. Nothing is published before a desired is set.
    ``features/<set>/desired``  sensor_msgs/JointState  s* (``position``), once per teach;
                                header = that of the image it was taught from (a zero stamp
                                for ``desired_source`` pose or image); reliable,
                                transient-local, depth 1: a late subscriber gets it
    ``~/state``                 diagnostic_msgs/DiagnosticArray  per measurement, its header:
                                ``waiting | no desired | tracking | target lost |
                                refused``; values sets, desired_source, stamp,
                                desired_stamp, reason
    ``/diagnostics``            the same status, on change and at 1 Hz
Services
    ``~/teach``               std_srvs/Trigger  the latest measurement becomes the desired
                              one (teach by showing); the new desired is published on
                              ``features/<set>/desired`` before the reply

Desired features (``desired_source``): ``teach`` (default; kept in ``desired_file`` if set,
and published again by a restarted node), ``pose`` (``desired_cMo``) or ``image``
(``desired_image``): see :mod:`sphere_servo.pipeline.features`, whose
:class:`~sphere_servo.pipeline.features.FeaturesCore` holds the logic, the check of every
measurement included: a physically impossible one is answered with empty features and an
error log naming the quantity.
"""
from __future__ import annotations

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, JointState
from sphere_servo.pipeline.common import Refusal, stamp_ns
from sphere_servo.pipeline.detector import binning_roi
from sphere_servo.pipeline.features import DesiredSource, FeaturesCore
from sphere_servo.pipeline.params import FeaturesParams
from sphere_servo.ros.conversions import stamp_from_ns
from sphere_servo.ros.diagnostics import StatusPublisher
from sphere_servo.ros.guard import guarded, guarded_service
from sphere_servo.ros.logs import ThrottledLog
from sphere_servo.ros.params import declare_all, run
from sphere_servo.ros.qos import camera_reader, PIPELINE, writer
from sphere_servo.ros.vectors import (DESIRED_QOS, desired_topic, features_msg,
                                      measurement_from_msg)
from std_msgs.msg import Header
from std_srvs.srv import Trigger

HARDWARE_ID = 'camera'  # the eye-in-hand camera whose images the features come from


class FeaturesNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('features', **kwargs)
        self.core = FeaturesCore(declare_all(self, FeaturesParams))
        self.pubs = {name: self.create_publisher(JointState, f'features/{name}',
                                                 writer('features/<set>'))
                     for name in self.core.names}
        self.pubs_desired = {name: self.create_publisher(JointState, desired_topic(name),
                                                         DESIRED_QOS)
                             for name in self.core.names}
        self.status = StatusPublisher(self, HARDWARE_ID, self.core.status())
        self.log = ThrottledLog(self.get_logger())
        self.last_header: Header | None = None  # of the latest measurement
        self.create_subscription(JointState, 'detector/measurement', self._on_measurement,
                                 PIPELINE)
        self.create_service(Trigger, '~/teach', self._srv_teach)
        qos, events = camera_reader(self, self.core.params.image_reliability, self.log)
        self.create_subscription(CameraInfo, 'camera/camera_info', self._on_info, qos,
                                 event_callbacks=events)
        if self.core.has_desired:  # a pose (no image of the run: a zero stamp) or a kept one
            self._publish_desired(Header(stamp=stamp_from_ns(self.core.desired_stamp_ns),
                                         frame_id=self.core.desired_frame_id))
        elif self.core.source is not DesiredSource.IMAGE:
            self.get_logger().info('waiting for ~/teach to set the desired features')

    def _publish_desired(self, hdr: Header) -> None:
        for name, s_star in self.core.desired_features().items():
            self.pubs_desired[name].publish(features_msg(name, hdr, s_star))
        self.get_logger().info(self.core.describe_desired())

    @guarded
    def _on_info(self, msg: CameraInfo) -> None:
        out = self.core.on_camera_info(msg.width, msg.height, msg.k, msg.d,
                                       msg.distortion_model, **binning_roi(msg))
        if isinstance(out, Refusal):
            self.log.error(out.reason)
        elif out is not None:  # a file, not an image of the run: a zero stamp
            self._publish_desired(Header(stamp=stamp_from_ns(0), frame_id=msg.header.frame_id))

    @guarded_service
    def _srv_teach(self, request, response):
        taught = self.core.teach()
        response.success, response.message = taught.success, taught.message
        if taught.success:  # the taught image is the latest measurement's
            self._publish_desired(self.last_header)
        return response

    @guarded
    def _on_measurement(self, msg: JointState) -> None:
        st = msg.header.stamp
        self.last_header = msg.header
        out = self.core.on_measurement(stamp_ns(st.sec, st.nanosec), measurement_from_msg(msg),
                                       msg.header.frame_id)
        if out is not None:
            if out.violation is not None:
                self.log.error(f'measurement refused, features empty: {out.lost}')
            elif out.lost:
                self.log.warn(f'target lost: {out.lost}')
            for name, pub in self.pubs.items():
                fs = out.values.get(name)
                pub.publish(features_msg(name, msg.header, None if fs is None else fs.s))
        self.status.update(self.core.status(), msg.header)

    def go_safe(self, msg=None) -> None:
        """Publish empty features (target lost) for the measurement whose callback failed."""
        if isinstance(msg, JointState) and self.core.has_desired:
            for name, pub in self.pubs.items():
                pub.publish(features_msg(name, msg.header))


def main(args=None):
    run(FeaturesNode, 'features', args)


if __name__ == '__main__':
    main()
