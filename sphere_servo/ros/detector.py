"""
``detector``: camera image → the sphere's ellipse and the marks' image points.

Subscribes
    ``camera/image_raw``    sensor_msgs/Image       rgb8, bgr8, mono8, rgba8 or bgra8
                            (``image_transport: compressed``: ``camera/image_raw/compressed``,
                            sensor_msgs/CompressedImage, JPEG or PNG)
    ``camera/camera_info``  sensor_msgs/CameraInfo  intrinsics (k, d, distortion_model),
                            binning_x/binning_y and roi (the image a crop and/or decimation
                            of the calibrated one, as image_proc's crop_decimate publishes:
                            image_geometry's convention); the latest one is used
Publishes (header = the image's header, so stamps flow through the pipeline)
    ``detector/measurement``  sensor_msgs/JointState  named values, see
                              :mod:`sphere_servo.ros.vectors`; empty = no sphere
    ``detector/overlay``      sensor_msgs/Image       the frame with the detection drawn
                              (only with ``publish_overlay``), for rqt_image_view / Foxglove
    ``~/state``               diagnostic_msgs/DiagnosticArray  per image, its header:
                              ``waiting | found | not found | rejected``; values images,
                              found, not_found, rejected (counts), camera, reason
    ``/diagnostics``          the same status, on change and at 1 Hz

A bad image (unsupported encoding, ``step``/``data`` lengths that disagree, zero size), a
missing or refused ``camera_info`` (an impossible K, an unknown distortion model, a binning
or roi no image has, a camera_info of another size than the image, both sizes logged with
the binning and roi that made the camera's, a non-zero distortion the detector does not
apply) is logged as a clear error and answered with an empty measurement
(target lost, so the servo stops); the node keeps running. The logic is
:class:`~sphere_servo.pipeline.detector.DetectorCore`'s.

``intrinsics_error`` = relative errors (px, py, u0, v0) applied to the received intrinsics:
the paper's calibration-error experiment is ``[0.35, 0.30, -0.25, 0.27]``.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from sphere_servo.pipeline.common import Refusal
from sphere_servo.pipeline.detector import binning_roi, DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.ros.conversions import image_from_array
from sphere_servo.ros.diagnostics import StatusPublisher
from sphere_servo.ros.guard import guarded
from sphere_servo.ros.logs import ThrottledLog
from sphere_servo.ros.params import declare_all, install_set_callback, run
from sphere_servo.ros.qos import camera_reader, writer
from sphere_servo.ros.vectors import measurement_msg
from sphere_servo.vision.draw import draw_detection

HARDWARE_ID = 'camera'  # the eye-in-hand camera whose images the detector reads


class DetectorNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('detector', **kwargs)
        self.core = DetectorCore(declare_all(self, DetectorParams))
        install_set_callback(self, lambda: self.core.params,
                             lambda p: setattr(self.core, 'params', p))
        self.pub = self.create_publisher(JointState, 'detector/measurement',
                                         writer('detector/measurement'))
        self.pub_overlay = self.create_publisher(Image, 'detector/overlay',
                                                 writer('detector/overlay'))
        self.status = StatusPublisher(self, HARDWARE_ID, self.core.status())
        self.log = ThrottledLog(self.get_logger())
        qos, events = camera_reader(self, self.core.params.image_reliability, self.log)
        self.create_subscription(CameraInfo, 'camera/camera_info', self._on_info, qos,
                                 event_callbacks=events)
        if self.core.params.image_transport == 'compressed':
            self.create_subscription(CompressedImage, 'camera/image_raw/compressed',
                                     self._on_compressed, qos, event_callbacks=events)
        else:
            self.create_subscription(Image, 'camera/image_raw', self._on_image, qos,
                                     event_callbacks=events)

    @guarded
    def _on_info(self, msg: CameraInfo) -> None:
        cam = self.core.on_camera_info(msg.width, msg.height, msg.k, msg.d,
                                       msg.distortion_model, **binning_roi(msg))
        if isinstance(cam, Refusal):
            self.log.error(f'bad camera_info, ignored: {cam.reason}')

    @guarded
    def _on_image(self, msg: Image) -> None:
        self._answer(self.core.on_image(msg.height, msg.width, msg.step, msg.encoding,
                                        msg.data), msg.header)

    @guarded
    def _on_compressed(self, msg: CompressedImage) -> None:
        self._answer(self.core.on_compressed(msg.format, msg.data), msg.header)

    def _answer(self, out, header) -> None:
        """Publish the measurement of one image (empty unless found), its overlay, status."""
        if out.status is DetectStatus.REJECTED:
            self.log.error(f'image rejected: {out.reason}')
        elif out.status is DetectStatus.NOT_FOUND:
            self.log.warn(f'sphere not detected: {out.reason}')
        self.pub.publish(measurement_msg(out.measurement, header))
        if self.core.params.publish_overlay and out.detection is not None:
            img = out.image
            rgb = img if out.encoding == 'rgb8' else (
                img[..., ::-1] if out.encoding == 'bgr8' else np.dstack([img] * 3))
            self.pub_overlay.publish(image_from_array(draw_detection(rgb, out.detection),
                                                      header))
        self.status.update(self.core.status(), header)

    def go_safe(self, msg=None) -> None:
        """Publish an empty measurement (target lost) for the image whose callback failed."""
        if isinstance(msg, (Image, CompressedImage)):
            self.pub.publish(measurement_msg(None, msg.header))


def main(args=None):
    run(DetectorNode, 'detector', args)


if __name__ == '__main__':
    main()
