"""``detector``: camera image → the sphere's ellipse and the marks' image points.

Subscribes
    ``camera/image_raw``    sensor_msgs/Image       rgb8, bgr8 or mono8
    ``camera/camera_info``  sensor_msgs/CameraInfo  intrinsics (k); the latest one is used
Publishes (header = the image's header, so stamps flow through the pipeline)
    ``detector/measurement``  sensor_msgs/JointState  named values, see
                              :mod:`sphere_servo.ros.vectors`; empty = no sphere
    ``detector/overlay``      sensor_msgs/Image       the frame with the detection drawn
                              (only with ``publish_overlay``), for rqt_image_view / Foxglove

A bad image (unsupported encoding, ``step``/``data`` lengths that disagree, zero size) or
a missing ``camera_info`` is logged as a clear error and answered with an empty measurement
(target lost, so the servo stops); the node keeps running.

``intrinsics_error`` = relative errors (px, py, u0, v0) applied to the received intrinsics:
the paper's calibration-error experiment is ``[0.35, 0.30, -0.25, 0.27]``.
"""
from __future__ import annotations

import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import make_target
from sphere_servo.ros.conversions import image_from_array
from sphere_servo.ros.params import Param, declare_all, install_set_callback, run
from sphere_servo.ros.vectors import measurement_msg
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.draw import draw_detection
from sphere_servo.vision.image import image_from_buffer

PARAMS = {
    'target_kind': Param('special', 'target whose colours and marks to look for',
                         choices=('special', 'cc', 'balloon'), read_only=True),
    'intrinsics_error': Param([0.0, 0.0, 0.0, 0.0], 'relative errors (px, py, u0, v0) '
                              'applied to camera_info (calibration-error experiment)', size=4,
                              read_only=True),
    'publish_overlay': Param(False, 'publish detector/overlay (costs a copy and a draw)'),
}


class DetectorNode(Node):
    """See the module docstring."""

    def __init__(self):
        super().__init__('detector')
        self.p = declare_all(self, PARAMS)
        install_set_callback(self, PARAMS, self.p.__setitem__)
        target = make_target(self.p['target_kind'])
        self.detector = Detector.for_target(target)
        self.camera: CameraIntrinsics | None = None
        self.pub = self.create_publisher(JointState, 'detector/measurement', 100)
        self.pub_overlay = self.create_publisher(Image, 'detector/overlay', 2)
        self.create_subscription(CameraInfo, 'camera/camera_info', self._on_info, 10)
        self.create_subscription(Image, 'camera/image_raw', self._on_image, 10)
        self.frames = 0
        self._last_error = ('', 0.0)

    def _error(self, text: str) -> None:
        """Log an error; a repeat of the same text is logged at most once a second."""
        now = time.monotonic()
        if text != self._last_error[0] or now - self._last_error[1] > 1.0:
            self.get_logger().error(text)
            self._last_error = (text, now)

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            cam = CameraIntrinsics.from_camera_info_fields(msg.width, msg.height, msg.k, msg.d)
            ex, ey, eu, ev = self.p['intrinsics_error']
            self.camera = cam.with_error(px=ex, py=ey, u0=eu, v0=ev)
        except ValueError as exc:
            self.camera = None
            self.get_logger().error(f'bad camera_info, ignored: {exc}',
                                    throttle_duration_sec=2.0)

    def _on_image(self, msg: Image) -> None:
        self.frames += 1
        det = None
        try:
            img = image_from_buffer(msg.height, msg.width, msg.step, msg.encoding, msg.data)
            if self.camera is None:
                raise ValueError('no valid camera_info received yet')
            det = self.detector.detect(img, msg.encoding, self.camera)
            if not det.found:
                self.get_logger().warn(f'sphere not detected: {det.reason}',
                                       throttle_duration_sec=2.0)
        except ValueError as exc:
            self._error(f'image rejected: {exc}')
        self.pub.publish(measurement_msg(det, msg.header))
        if self.p['publish_overlay'] and det is not None:
            rgb = img if msg.encoding == 'rgb8' else (
                img[..., ::-1] if msg.encoding == 'bgr8' else np.dstack([img] * 3))
            self.pub_overlay.publish(image_from_array(draw_detection(rgb, det), msg.header))


def main(args=None):
    run(DetectorNode, 'detector', args)


if __name__ == '__main__':
    main()
