"""
Named, stamped float64 vectors on ``sensor_msgs/JointState``.

A ``common_interfaces`` type with a header, whose fields ``ros2 topic echo`` prints next to
their names. The layouts are :mod:`sphere_servo.pipeline.vectors`'s:

- ``detector/measurement``: ``name`` the measurement's names, ``position`` its values;
  empty = the sphere was not detected.
- ``features/<set>``: ``name`` the set's labels (FEATURE_NAMES), ``position`` s;
  empty = the target or a mark is lost. ``velocity`` and ``effort`` are empty.
- ``features/<set>/desired``: the same labels, ``position`` s*.

Every message carries the header of the image it was derived from (the desired: of the
image it was taught from).
"""
from __future__ import annotations

from array import array

from sensor_msgs.msg import JointState
from sphere_servo.core.measurement import MeasurementError
from sphere_servo.pipeline.vectors import FEATURE_NAMES, features_from_vectors, Measurement
from sphere_servo.ros.qos import LATCHED
from sphere_servo.vision.detector import Detection
from std_msgs.msg import Header

# the desired features: the last one kept for late subscribers (``ros2 topic echo`` needs
# ``--qos-durability transient_local`` to see it)
DESIRED_QOS = LATCHED
#: the servo's ``~/enabled`` (std_msgs/Bool), latched the same way: a late subscriber
#: (arm_sim, which refuses its jumps while the servo is enabled) gets the current mode
ENABLED_QOS = DESIRED_QOS


def desired_topic(name: str) -> str:
    """Return the (relative) topic of a set's desired features, ``features/<name>/desired``."""
    return f'features/{name}/desired'


def measurement_msg(det: Detection | Measurement | None, hdr: Header) -> JointState:
    """Build ``detector/measurement`` of a detection or a measurement (None: empty)."""
    m = det if isinstance(det, Measurement) else Measurement.from_detection(det)
    # an array('d') is taken as it is; a list is checked value by value (on the image path)
    return JointState(header=hdr, name=list(m.names), position=array('d', m.values))


def measurement_from_msg(msg) -> Measurement:
    """Read the measurement of a ``detector/measurement`` message (rclpy or rosbags)."""
    return Measurement.of(msg.name, msg.position)


def features_msg(name: str, hdr: Header, s=None) -> JointState:
    """Build ``features/<name>`` (or its desired): s; empty when ``s`` is None (target lost)."""
    msg = JointState(header=hdr)
    if s is None:
        return msg
    msg.name = list(FEATURE_NAMES[name])
    msg.position = array('d', s)
    return msg


def features_from_msg(msg, name: str):
    """Read s of a features message, (n,) or None (target lost); MeasurementError if malformed."""
    return features_from_vectors(name, msg.name, msg.position)


def desired_from_msg(msg, name: str):
    """Read s* (n,) of a ``features/<name>/desired`` message; MeasurementError if malformed."""
    s_star = features_from_vectors(name, msg.name, msg.position)
    if s_star is None:
        raise MeasurementError(f'a desired {name} message without values')
    return s_star
