"""
The named vectors the nodes exchange, without ROS: the measurement and the feature sets.

The ros layer carries them on ``sensor_msgs/JointState`` (name, position, velocity,
effort); here they are plain tuples and arrays.

Measurement (``detector/measurement``)::

    names     b_x b_y b_z r_delta quality ellipse_u ellipse_v ellipse_major ellipse_minor
              ellipse_angle  then, for each *visible* mark M ∈ {P1, P2, P3}:
              M_u M_v M_qx M_qy M_qz
    values    b: unit vector to the sphere centre, camera frame; r_delta = r/‖O‖; ellipse in
              pixels, full axes, angle in degrees; M_u, M_v pixels; M_q unit vector of the
              mark, camera frame

    No names: the sphere was not detected in that image.

Features (``features/<set>``, set ∈ {s_n, s, s_cc}): the set's labels (FEATURE_NAMES) and
s; no names: the target or a mark is lost, the servo must stop. Desired features
(``features/<set>/desired``): the same labels and s*.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sphere_servo.core.features import feature_names, FEATURE_SETS
from sphere_servo.core.measurement import MeasurementError, Observation, SphereMeasurement
from sphere_servo.core.targets import mark_names
from sphere_servo.core.validation import Bound, check_array, check_number, refuse
from sphere_servo.vision.detector import Detection

SPHERE_NAMES = ('b_x', 'b_y', 'b_z', 'r_delta', 'quality', 'ellipse_u', 'ellipse_v',
                'ellipse_major', 'ellipse_minor', 'ellipse_angle')
MARK_FIELDS = ('u', 'v', 'qx', 'qy', 'qz')
FEATURE_NAMES = {name: feature_names(name) for name in FEATURE_SETS}


@dataclass(frozen=True)
class Measurement:
    """The detector's named values for one image (no names: no sphere)."""

    names: tuple[str, ...] = ()
    values: tuple[float, ...] = ()

    @classmethod
    def of(cls, names: Sequence[str], values: Sequence[float]) -> Measurement:
        """Build a measurement from a message's name and position fields (float64 values)."""
        return cls(tuple(names), tuple(values))

    @classmethod
    def from_detection(cls, det: Detection | None) -> Measurement:
        """Build the measurement of a :class:`Detection` (None or not found: empty)."""
        if det is None or not det.found:
            return cls()
        sph = det.sphere
        (uc, vc), (a1, a2), ang = det.ellipse_px
        names = list(SPHERE_NAMES)
        values = [*sph.b.tolist(), sph.r_delta, float(det.quality), uc, vc, max(a1, a2),
                  min(a1, a2), ang]
        for name, mark in sorted(det.marks.items()):
            if mark.visible and mark.uv_px is not None:
                names += [f'{name}_{f}' for f in MARK_FIELDS]
                values += [*map(float, mark.uv_px), *mark.q.tolist()]
        return cls(tuple(names), tuple(float(v) for v in values))

    def as_dict(self) -> dict[str, float]:
        """
        Map name → value; MeasurementError when the message is malformed.

        Malformed: names and values that do not pair up, a name empty or given twice (which
        of its values would be the image's?).
        """
        if len(self.names) != len(self.values):
            raise MeasurementError(f'measurement has {len(self.names)} names but '
                                   f'{len(self.values)} values')
        vals = dict(zip(self.names, self.values))
        if len(vals) != len(self.names) or '' in vals:
            bad = sorted(n for n, k in Counter(self.names).items() if k > 1 or not n)
            refuse(MeasurementError, 'measurement names', bad, Bound.SHAPE,
                   'each name non-empty and given once')
        return vals

    def observation(self, kind: str) -> Observation:
        """
        Return the :class:`Observation` for ``kind`` ('special': P1, P2; 'cc': P1, P3).

        Raises :class:`MeasurementError` when the sphere or one of the two marks is
        missing (the target is lost), or a value is not finite, in any field, even one
        not used here (refused: the error's ``violation`` names it); :meth:`as_dict`'s
        refusals of a malformed message. The physical bounds are
        :func:`~sphere_servo.core.measurement.validated_observation`'s.
        """
        vals = self.as_dict()
        if not vals:
            raise MeasurementError('sphere not detected')
        try:
            b = np.array([vals['b_x'], vals['b_y'], vals['b_z']])
            r_delta = vals['r_delta']
        except KeyError as exc:
            raise MeasurementError(f'measurement lacks {exc.args[0]}') from None
        b = check_array(MeasurementError, 'b', b, (3,))
        r_delta = check_number(MeasurementError, 'r_delta', r_delta)
        q = {}
        for name in mark_names(kind):
            try:
                q[name] = np.array([vals[f'{name}_qx'], vals[f'{name}_qy'],
                                    vals[f'{name}_qz']])
            except KeyError:
                raise MeasurementError(f'mark {name} is not visible') from None
            q[name] = check_array(MeasurementError, f'{name} ray', q[name], (3,))
        for name, v in vals.items():  # the fields not used too: no detector sends a NaN
            check_number(MeasurementError, name, v)
        return Observation(SphereMeasurement(b, float(r_delta), vals.get('quality', 0.0)), q,
                           kind)


@dataclass(slots=True)
class SetFeatures:
    """One feature set's values for one image: s and s* (n,)."""

    s: np.ndarray
    s_star: np.ndarray

    @property
    def error(self) -> np.ndarray:
        """Return s − s*."""
        return self.s - self.s_star


def features_from_vectors(name: str, names: Sequence[str],
                          values: Sequence[float]) -> np.ndarray | None:
    """
    Read the values of set ``name`` from its labels and values (None: no labels, target lost).

    Raises :class:`MeasurementError` on labels that are not the set's or lengths that
    disagree.
    """
    if not len(names):
        return None
    if tuple(names) != FEATURE_NAMES[name]:
        raise MeasurementError(f'expected features {FEATURE_NAMES[name]}, got {tuple(names)}')
    if len(values) != len(names):
        raise MeasurementError(f'features message has {len(names)} names but {len(values)} '
                               'values')
    return np.array(values, dtype=float)
