"""
The detector's logic without ROS: camera_info → the camera, an image buffer → a detection.

:class:`DetectorCore` holds the camera of the latest usable ``camera_info`` — its model
(``distortion_model`` plumb_bob, equidistant or unified, built by
:func:`~sphere_servo.core.camera_models.camera_from_camera_info_fields`; the detector
applies each model's distortion) with ``intrinsics_error`` applied to its intrinsics:
relative errors (px, py, u0, v0), the paper's calibration-error experiment is
``[0.35, 0.30, -0.25, 0.27]`` — and runs the vision layer's
:class:`~sphere_servo.vision.detector.Detector` on each image. The camera is that of the
published image: a camera_info's ``binning_x``, ``binning_y`` and ``roi`` (image_proc's
crop_decimate, a driver's hardware binning) make it the calibrated camera reduced as
image_geometry does (:func:`~sphere_servo.core.camera_models.camera_info_reduction`); only
raw images are taken (``roi.do_rectify`` is not used). A camera_info is *refused*
(no camera, and why) when :func:`camera_from_info` refuses it: a K no camera has (not
finite, skew, ``fx = 1e300``, a focal length ≤ 0, a principal point far off the image), an
unknown distortion model, a binning or roi that no image has (not a whole number ≥ 0, an
roi leaving the calibrated image or of zero width only, an image of no pixel) or that
leaves a camera no image has (a focal length under 1 % of the reduced image's larger side:
named with the binning that divided it, e.g. 1×96 of 640×480 with fy = 610), or an
``intrinsics_error`` that makes the camera impossible (the error is named). An image is
*rejected*, the result says why and its measurement is empty (target lost, so the servo
stops), on a bad buffer (unsupported encoding, ``step``/``data`` lengths that disagree,
zero size), no usable camera, or a camera the detector cannot use for it
(:func:`detector_camera`: another size than the image's, named with the binning and roi
that made the camera's, or a model whose distortion the detector does not apply).
:meth:`DetectorCore.status` is the node's status: the latest image's outcome.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence, Set as AbstractSet
from dataclasses import dataclass
from enum import Enum
from functools import lru_cache

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import (camera_from_camera_info_fields,
                                             camera_info_reduction, check_camera_for_image,
                                             FisheyeCamera, reduced_camera, UnifiedCamera)
from sphere_servo.core.central import CentralCamera
from sphere_servo.core.targets import make_target
from sphere_servo.core.types import Image
from sphere_servo.pipeline.common import Level, NodeStatus, Refusal
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.vision.compressed import decode_compressed
from sphere_servo.vision.detector import Detection, Detector, image_from_buffer
from sphere_servo.vision.image import ALPHA_ENCODINGS, ENCODINGS, without_alpha


NO_CAMERA = 'no valid camera_info received yet'
#: the image encodings the detector node takes
INPUTS = ENCODINGS + tuple(ALPHA_ENCODINGS)
#: the camera models whose distortion the detector applies: it lifts the silhouette's edge
#: and the marks through the model onto the unit sphere. A model not in it is refused,
#: never silently measured as a distortion-free pinhole.
DISTORTION_APPLIED: frozenset[type] = frozenset({CameraIntrinsics, FisheyeCamera,
                                                 UnifiedCamera})


def binning_roi(info) -> dict:
    """
    Return the ``binning_x``, ``binning_y`` and ``roi`` keywords of :func:`camera_from_info`.

    ``info``: a ``sensor_msgs/CameraInfo`` (rclpy's or rosbags': the same fields); ``roi`` as
    (x_offset, y_offset, width, height).
    """
    r = info.roi
    return {'binning_x': info.binning_x, 'binning_y': info.binning_y,
            'roi': (r.x_offset, r.y_offset, r.width, r.height)}


def camera_from_info(width: int, height: int, k: Sequence[float], d: Sequence[float] | None,
                     intrinsics_error: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
                     distortion_model: str = 'plumb_bob', *, binning_x: int = 0,
                     binning_y: int = 0, roi: Sequence[int] | None = None
                     ) -> CentralCamera | Refusal:
    """
    Return the camera of camera_info fields with ``intrinsics_error`` applied, or why not.

    The model is :func:`~sphere_servo.core.camera_models.camera_from_camera_info_fields`'s
    (which refuses a K or a distortion no camera has); ``with_error`` names the error
    parameter that makes the camera impossible. ``binning_x``, ``binning_y`` and ``roi`` =
    (x_offset, y_offset, width, height) (defaults: none, the image is the calibrated one;
    :func:`binning_roi` reads them from a message) make it the camera of the reduced image
    (:func:`~sphere_servo.core.camera_models.camera_info_reduction`, image_geometry's
    convention); ``intrinsics_error`` applies to the received, calibrated intrinsics, before
    the reduction. A camera_info comes with every image, almost always the same one: equal
    fields give the same (immutable) camera or refusal without building it again, and the
    same object, so what is derived from a camera (the detector's lift tables) is kept too.
    """
    try:
        roi = roi if roi is None or isinstance(roi, (AbstractSet, Mapping)) else tuple(roi)
        key = (width, height, tuple(float(x) for x in k),
               None if d is None else tuple(float(x) for x in d),
               tuple(float(x) for x in intrinsics_error), str(distortion_model),
               binning_x, binning_y, roi)
        # the whole numbers' types too: equal values of another type are another key
        # (False == 0 and Decimal(640) == 640, refused, must not take their cached camera)
        types = tuple(type(v) for v in (width, height, binning_x, binning_y, *(roi or ())))
        hash(key)
    except (TypeError, ValueError):  # not numbers: the builder says what is wrong
        return _camera_from_info(width, height, k, d, intrinsics_error, distortion_model,
                                 binning_x, binning_y, roi)
    return _camera_from_key(types, *key)


def camera_from_msg(info, intrinsics_error: Sequence[float] = (0.0, 0.0, 0.0, 0.0)
                    ) -> CentralCamera | Refusal:
    """Return :func:`camera_from_info` of a whole ``sensor_msgs/CameraInfo`` (rclpy, rosbags)."""
    return camera_from_info(info.width, info.height, info.k, info.d, intrinsics_error,
                            info.distortion_model, **binning_roi(info))


@lru_cache(maxsize=16)
def _camera_from_key(types, *key):
    return _camera_from_info(*key)


def _camera_from_info(width, height, k, d, intrinsics_error, distortion_model, binning_x,
                      binning_y, roi):
    try:
        reduction = camera_info_reduction(width, height, binning_x, binning_y, roi)
        cam = camera_from_camera_info_fields(width, height, k, d, distortion_model)
        ex, ey, eu, ev = intrinsics_error
        return reduced_camera(cam.with_error(px=ex, py=ey, u0=eu, v0=ev), reduction)
    except ValueError as exc:  # CameraError and ValueError of the numbers
        return Refusal(str(exc))


def detector_camera(camera: CentralCamera, width: int, height: int) -> CentralCamera:
    """
    Return ``camera`` if the detector can measure a ``width × height`` image with it.

    The one place of that rule (CameraError otherwise, naming both sizes or the model and
    its coefficients): the camera's size is the image's, and its distortion is one the
    detector applies (:data:`DISTORTION_APPLIED`).
    """
    return check_camera_for_image(camera, width, height,
                                  applies_distortion=type(camera) in DISTORTION_APPLIED)


class DetectStatus(Enum):
    """What became of one image (and ``waiting``, the node's state before its first image)."""

    FOUND = 'found'          # the sphere's conic was measured (marks may still be missing)
    NOT_FOUND = 'not found'  # a valid image without the sphere
    REJECTED = 'rejected'    # a bad buffer, or no camera yet: nothing was detected
    WAITING = 'waiting'      # no image yet


LEVELS = {DetectStatus.FOUND: Level.OK, DetectStatus.NOT_FOUND: Level.WARN,
          DetectStatus.REJECTED: Level.ERROR, DetectStatus.WAITING: Level.OK}


@dataclass(frozen=True)
class DetectorOutput:
    """
    The detector's answer to one image.

    image      the decoded image (H, W, 3) or (H, W) in ``encoding``; None when rejected.
    detection  None when rejected.
    reason     why not found or rejected ('' when found).
    encoding   ``image``'s: the message's, ``rgb8``/``bgr8`` for ``rgba8``/``bgra8`` (alpha
               dropped); '' when rejected.
    """

    status: DetectStatus
    image: Image | None = None
    detection: Detection | None = None
    reason: str = ''
    encoding: str = ''

    @property
    def measurement(self) -> Measurement:
        """Return what is published: the detection's values, empty unless found."""
        return Measurement.from_detection(self.detection)


class DetectorCore:
    """The ``detector`` node's logic (see the module docstring)."""

    def __init__(self, params: DetectorParams):
        self.params = params
        self.detector = Detector.for_target(make_target(params.target_kind))
        self.camera: CentralCamera | None = None
        self.refused = ''  # why the latest camera_info was refused ('' if it was not)
        self.last: DetectorOutput | None = None
        self.counts = {status: 0 for status in DetectStatus if status is not DetectStatus.WAITING}

    def status(self) -> NodeStatus:
        """
        Return the node's status: the latest image's outcome, and counts.

        Values: ``images``, ``found``, ``not_found``, ``rejected`` (counts so far), ``camera``
        (``yes`` once a usable camera_info came), ``camera_refused`` (why the latest
        camera_info was refused, if it was), ``reason`` (why the latest image gave no
        sphere).
        """
        state = DetectStatus.WAITING if self.last is None else self.last.status
        values = {'images': str(sum(self.counts.values())),
                  **{k.name.lower(): str(n) for k, n in self.counts.items()},
                  'camera': 'yes' if self.camera is not None else 'no'}
        if self.refused:
            values['camera_refused'] = self.refused
        if self.last is not None and self.last.reason:
            values['reason'] = self.last.reason
        return NodeStatus(state, LEVELS[state], values)

    def on_camera_info(self, width: int, height: int, k: Sequence[float],
                       d: Sequence[float] | None, distortion_model: str = 'plumb_bob', *,
                       binning_x: int = 0, binning_y: int = 0,
                       roi: Sequence[int] | None = None) -> CentralCamera | Refusal:
        """
        Take the camera of a camera_info; a refused one leaves no camera, and says why.

        ``binning_x``, ``binning_y``, ``roi``: as :func:`camera_from_info`. Should reading it
        fail in a way not foreseen (an exception), no camera is left either: the images wait
        for the next camera_info rather than being measured with the previous one.
        """
        self.camera, self.refused = None, 'the latest camera_info could not be read'
        cam = camera_from_info(width, height, k, d, self.params.intrinsics_error,
                               distortion_model, binning_x=binning_x, binning_y=binning_y,
                               roi=roi)
        refused = isinstance(cam, Refusal)
        self.camera = None if refused else cam
        self.refused = cam.reason if refused else ''
        return cam

    def on_image(self, height: int, width: int, step: int, encoding: str,
                 data) -> DetectorOutput:
        """Detect in one image buffer (``sensor_msgs/Image`` fields) with the latest camera."""
        return self._counted(self.detect(height, width, step, encoding, data, self.camera))

    def on_compressed(self, fmt: str, data) -> DetectorOutput:
        """Detect in one ``sensor_msgs/CompressedImage`` (format, data) with the latest camera."""
        return self._counted(self.detect_compressed(fmt, data, self.camera))

    def _counted(self, out: DetectorOutput) -> DetectorOutput:
        self.last = out
        self.counts[out.status] += 1
        return out

    def detect(self, height: int, width: int, step: int, encoding: str, data,
               camera: CentralCamera | None) -> DetectorOutput:
        """
        Detect in one image buffer with ``camera``.

        Rejected when the buffer cannot be read, when ``camera`` is None (no usable
        camera_info yet), and when the detector cannot use it for this image
        (:func:`detector_camera`).
        """
        try:
            img, encoding = without_alpha(
                image_from_buffer(height, width, step, encoding, data, encodings=INPUTS),
                encoding)
        except ValueError as exc:
            return DetectorOutput(DetectStatus.REJECTED, reason=str(exc))
        return self.detect_image(img, encoding, camera)

    def detect_compressed(self, fmt: str, data,
                          camera: CentralCamera | None) -> DetectorOutput:
        """
        Detect in one compressed image (:mod:`~sphere_servo.vision.compressed`).

        No image larger than ``camera``'s is decoded: it could only be refused, after seconds
        and gigabytes for a decompression bomb.
        """
        try:
            img, encoding = decode_compressed(
                fmt, data, None if camera is None else (camera.width, camera.height))
        except ValueError as exc:
            return DetectorOutput(DetectStatus.REJECTED, reason=str(exc))
        return self.detect_image(img, encoding, camera)

    def detect_image(self, img: Image, encoding: str,
                     camera: CentralCamera | None) -> DetectorOutput:
        """Detect in a decoded ``rgb8``/``bgr8``/``mono8`` image with ``camera``."""
        try:
            if camera is None:
                raise ValueError(NO_CAMERA)
            det = self.detector.detect(img, encoding,
                                       detector_camera(camera, img.shape[1], img.shape[0]))
        except ValueError as exc:
            return DetectorOutput(DetectStatus.REJECTED, reason=str(exc))
        return DetectorOutput(DetectStatus.FOUND if det.found else DetectStatus.NOT_FOUND,
                              img, det, det.reason, encoding)
