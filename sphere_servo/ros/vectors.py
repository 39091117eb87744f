"""Named, stamped float64 vectors on ``sensor_msgs/JointState`` (a ``common_interfaces`` type
with a header whose fields ``ros2 topic echo`` prints next to their names).

Measurement (``detector/measurement``; header = the image's header)::

    name      b_x b_y b_z r_delta quality ellipse_u ellipse_v ellipse_major ellipse_minor
              ellipse_angle  then, for each *visible* mark M ∈ {P1, P2, P3}:
              M_u M_v M_qx M_qy M_qz
    position  the values (b: unit vector to the sphere centre, camera frame; r_delta = r/‖O‖;
              ellipse in pixels, full axes, angle in degrees; M_u, M_v pixels; M_q unit
              vector of the mark, camera frame)

    An empty ``name`` means *the sphere was not detected* in that image.

Features (``features/<set>``, set ∈ {s_n, s, s_cc}; header = the image's header)::

    name      the set's labels (FEATURE_NAMES)
    position  s        velocity  s*        effort  s − s*

    An empty ``name`` means *the target or a mark is lost*: the servo must stop.
"""
from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

from sphere_servo.core.features import FEATURE_SETS, feature_names
from sphere_servo.core.measurement import (MeasurementError, Observation,
                                           SphereMeasurement)
from sphere_servo.core.targets import mark_names
from sphere_servo.vision.detector import Detection

SPHERE_NAMES = ('b_x', 'b_y', 'b_z', 'r_delta', 'quality', 'ellipse_u', 'ellipse_v',
                'ellipse_major', 'ellipse_minor', 'ellipse_angle')
MARK_FIELDS = ('u', 'v', 'qx', 'qy', 'qz')
FEATURE_NAMES = {name: feature_names(name) for name in FEATURE_SETS}


def measurement_msg(det: Detection | None, hdr: Header) -> JointState:
    """``detector/measurement`` from a :class:`Detection` (None or not found → empty)."""
    msg = JointState(header=hdr)
    if det is None or not det.found:
        return msg
    sph = det.sphere
    (uc, vc), (a1, a2), ang = det.ellipse_px
    names = list(SPHERE_NAMES)
    values = [*sph.b.tolist(), sph.r_delta, float(det.quality), uc, vc, max(a1, a2),
              min(a1, a2), ang]
    for name, mark in sorted(det.marks.items()):
        if mark.visible and mark.uv_px is not None:
            names += [f'{name}_{f}' for f in MARK_FIELDS]
            values += [*map(float, mark.uv_px), *mark.q.tolist()]
    msg.name = names
    msg.position = [float(v) for v in values]
    return msg


def measurement_values(msg: JointState) -> dict[str, float]:
    """name → value of a measurement message (empty when the sphere was not detected)."""
    if len(msg.name) != len(msg.position):
        raise MeasurementError(f'measurement has {len(msg.name)} names but '
                               f'{len(msg.position)} values')
    return dict(zip(msg.name, msg.position))


def observation_from_measurement(msg: JointState, kind: str) -> Observation:
    """:class:`Observation` for ``kind`` ('special': P1, P2; 'cc': P1, P3). Raises
    :class:`MeasurementError` when the sphere or one of the two marks is missing, or a value
    is not finite."""
    vals = measurement_values(msg)
    if not vals:
        raise MeasurementError('sphere not detected')
    try:
        b = np.array([vals['b_x'], vals['b_y'], vals['b_z']])
        r_delta = vals['r_delta']
    except KeyError as exc:
        raise MeasurementError(f'measurement lacks {exc.args[0]}') from None
    if not (np.all(np.isfinite(b)) and np.isfinite(r_delta)):
        raise MeasurementError('measurement of the sphere is not finite')
    q = {}
    for name in mark_names(kind):
        try:
            q[name] = np.array([vals[f'{name}_qx'], vals[f'{name}_qy'], vals[f'{name}_qz']])
        except KeyError:
            raise MeasurementError(f'mark {name} is not visible') from None
        if not np.all(np.isfinite(q[name])):
            raise MeasurementError(f'mark {name} is not finite')
    return Observation(SphereMeasurement(b, float(r_delta), vals.get('quality', 0.0)), q, kind)


def features_msg(name: str, hdr: Header, s=None, s_star=None) -> JointState:
    """``features/<name>``: s, s*, s − s*; empty when ``s`` is None (target lost)."""
    msg = JointState(header=hdr)
    if s is None:
        return msg
    msg.name = list(FEATURE_NAMES[name])
    msg.position = [float(v) for v in s]
    msg.velocity = [float(v) for v in s_star]
    msg.effort = [float(a - b) for a, b in zip(s, s_star)]
    return msg


def features_from_msg(msg: JointState, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(s, s*) from a features message, or None when it says the target is lost. Raises
    :class:`MeasurementError` on a malformed message (wrong names or lengths)."""
    if not msg.name:
        return None
    if tuple(msg.name) != FEATURE_NAMES[name]:
        raise MeasurementError(f'expected features {FEATURE_NAMES[name]}, got {tuple(msg.name)}')
    if len(msg.position) != len(msg.name) or len(msg.velocity) != len(msg.name):
        raise MeasurementError('features message has inconsistent lengths')
    return np.array(msg.position, dtype=float), np.array(msg.velocity, dtype=float)
