"""
Named, stamped float64 vectors on ``sensor_msgs/JointState``.

A ``common_interfaces`` type with a header, whose fields ``ros2 topic echo`` prints next to
their names. The layouts are :mod:`sphere_servo.pipeline.vectors`'s:

- ``detector/measurement``: ``name`` the measurement's names, ``position`` its values;
  empty = the sphere was not detected.
- ``features/<set>``: ``name`` the set's labels (FEATURE_NAMES), ``position`` s,
  ``velocity`` s*, ``effort`` s − s*; empty = the target or a mark is lost.

Every message carries the header of the image it was derived from.
"""
from __future__ import annotations

from sensor_msgs.msg import JointState
from sphere_servo.pipeline.vectors import (FEATURE_NAMES, features_from_vectors, Measurement,
                                           SetFeatures)
from sphere_servo.vision.detector import Detection
from std_msgs.msg import Header


def measurement_msg(det: Detection | Measurement | None, hdr: Header) -> JointState:
    """Build ``detector/measurement`` of a detection or a measurement (None: empty)."""
    m = det if isinstance(det, Measurement) else Measurement.from_detection(det)
    return JointState(header=hdr, name=list(m.names), position=list(m.values))


def measurement_from_msg(msg) -> Measurement:
    """Read the measurement of a ``detector/measurement`` message (rclpy or rosbags)."""
    return Measurement.of(msg.name, msg.position)


def features_msg(name: str, hdr: Header, s=None, s_star=None) -> JointState:
    """Build ``features/<name>``: s, s*, s − s*; empty when ``s`` is None (target lost)."""
    msg = JointState(header=hdr)
    if s is None:
        return msg
    msg.name = list(FEATURE_NAMES[name])
    msg.position = [float(v) for v in s]
    msg.velocity = [float(v) for v in s_star]
    msg.effort = [float(a - b) for a, b in zip(s, s_star)]
    return msg


def features_from_msg(msg: JointState, name: str) -> SetFeatures | None:
    """Read s and s* of a features message (None: target lost); MeasurementError if malformed."""
    return features_from_vectors(name, msg.name, msg.position, msg.velocity)
