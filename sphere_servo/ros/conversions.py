"""
ROS message ↔ ndarray / Pinocchio conversions shared by the nodes (no cv_bridge).

Direction ndarray → message only for images (the detector owns Image → ndarray with its
validation). Everything else both ways:

- :func:`image_from_array`      (H, W, 3) uint8 rgb / (H, W) uint8 mono → ``sensor_msgs/Image``
- :func:`camera_info_from_intrinsics`  :class:`CameraIntrinsics` → ``sensor_msgs/CameraInfo``
- :func:`pose_from_se3` / :func:`se3_from_pose`   ``pin.SE3`` ↔ ``geometry_msgs/Pose``
- :func:`twist_to_array` / :func:`twist_from_array`  ``geometry_msgs/Twist`` ↔ (6,) ``(v, ω)``
- :func:`stamp_from_seconds` / :func:`seconds_from_stamp`  ``builtin_interfaces/Time`` ↔ float;
  :func:`stamp_from_ns`  int nanoseconds (the cores' stamps) → ``builtin_interfaces/Time``
"""
from __future__ import annotations

import array

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, Twist
import numpy as np
import pinocchio as pin
from sensor_msgs.msg import CameraInfo, Image
from sphere_servo.pipeline.common import NS, STAMP_END_NS
from std_msgs.msg import Header

_ENCODINGS = {3: 'rgb8', 1: 'mono8'}


def stamp_from_ns(ns: int) -> Time:
    """Build the ``builtin_interfaces/Time`` of ``0 ≤ ns < STAMP_END_NS`` nanoseconds."""
    if not 0 <= ns < STAMP_END_NS:  # rclpy would wrap a larger sec silently
        raise ValueError(f'a stamp needs a time in [0, {STAMP_END_NS}) ns, got {ns} ns')
    return Time(sec=ns // NS, nanosec=ns % NS)


def stamp_from_seconds(t: float) -> Time:
    """Build the ``builtin_interfaces/Time`` of ``t`` ≥ 0 seconds (nanoseconds rounded)."""
    if not np.isfinite(t) or t < 0:
        raise ValueError(f'a stamp needs a finite time >= 0, got {t}')
    return stamp_from_ns(int(round(t * 1e9)))


def seconds_from_stamp(stamp: Time) -> float:
    """Return a stamp in seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def header(t: float, frame_id: str) -> Header:
    """Build a header stamped ``t`` seconds."""
    return Header(stamp=stamp_from_seconds(t), frame_id=frame_id)


def image_from_array(img: np.ndarray, hdr: Header, encoding: str | None = None) -> Image:
    """
    Build a ``sensor_msgs/Image`` from a C-contiguous-able uint8 array.

    (H, W, 3) → ``rgb8`` (default; pass ``encoding='bgr8'`` for OpenCV order), (H, W) or
    (H, W, 1) → ``mono8``. The bytes are copied once (``array('B')``, which rclpy
    serialises without a per-element check). Raises ``ValueError`` on another dtype or
    shape.
    """
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise ValueError(f'image must be uint8, got {img.dtype}')
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in _ENCODINGS or img.shape[0] == 0 \
            or img.shape[1] == 0:
        raise ValueError(f'image must be (H, W), (H, W, 1) or (H, W, 3), got {img.shape}')
    h, w, ch = img.shape
    msg = Image(header=hdr, height=h, width=w, encoding=encoding or _ENCODINGS[ch],
                is_bigendian=0, step=w * ch)
    data = array.array('B')
    data.frombytes(np.ascontiguousarray(img).tobytes())
    msg.data = data
    return msg


def camera_info_from_intrinsics(camera, hdr: Header) -> CameraInfo:
    """Build the ``sensor_msgs/CameraInfo`` of a camera (its ``to_camera_info_fields``)."""
    return CameraInfo(header=hdr, **camera.to_camera_info_fields())


def pose_from_se3(M: pin.SE3) -> Pose:
    """``geometry_msgs/Pose`` (position + unit quaternion) of ``M``."""
    q = pin.Quaternion(M.rotation)
    q.normalize()
    p = Pose()
    p.position.x, p.position.y, p.position.z = (float(v) for v in M.translation)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (
        float(q.x), float(q.y), float(q.z), float(q.w))
    return p


def se3_from_pose(p: Pose) -> pin.SE3:
    """
    Return the ``pin.SE3`` of a pose (the inverse of :func:`pose_from_se3`).

    Raises ``ValueError`` on a non-finite pose or a quaternion of norm ≈ 0 (it is
    normalised otherwise).
    """
    o = p.orientation
    qv = np.array([o.x, o.y, o.z, o.w], dtype=float)
    t = np.array([p.position.x, p.position.y, p.position.z], dtype=float)
    if not (np.all(np.isfinite(qv)) and np.all(np.isfinite(t))):
        raise ValueError('pose contains NaN or inf')
    n = np.linalg.norm(qv)
    if n < 1e-9:
        raise ValueError('pose quaternion has zero norm')
    q = pin.Quaternion(qv[3] / n, qv[0] / n, qv[1] / n, qv[2] / n)  # (w, x, y, z)
    return pin.SE3(q.toRotationMatrix(), t)


def twist_to_array(msg: Twist) -> np.ndarray:
    """(6,) ``(v, ω)`` = (linear.x, .y, .z, angular.x, .y, .z); not checked for NaN."""
    return np.array([msg.linear.x, msg.linear.y, msg.linear.z,
                     msg.angular.x, msg.angular.y, msg.angular.z], dtype=float)


def twist_from_array(v) -> Twist:
    """``geometry_msgs/Twist`` from (6,) ``(v, ω)``."""
    v = np.asarray(v, dtype=float).ravel()
    if v.shape != (6,):
        raise ValueError(f'a twist needs 6 values, got {v.size}')
    t = Twist()
    t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z = (
        float(x) for x in v)
    return t
