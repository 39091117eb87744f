"""
Adversarial ``detector/measurement`` messages for the features core: malformed name lists.

The measurement is built by hand from an exact observation (``observe``) of the target at a
known pose, as a ``sensor_msgs/JointState`` carries it (names, float64 positions), so a
message that is accepted gives the features of that pose.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sphere_servo.core.geometry import se3
from sphere_servo.core.measurement import MeasurementError, observe
from sphere_servo.core.validation import Bound
from sphere_servo.pipeline.features import DESIRED_FORMAT, FeaturesCore, FeaturesState
from sphere_servo.pipeline.params import FeaturesParams, ParameterError
from sphere_servo.pipeline.vectors import MARK_FIELDS, Measurement, SPHERE_NAMES


def core(**over) -> FeaturesCore:
    return FeaturesCore(FeaturesParams.from_mapping({'desired_source': 'pose', **over}))


OBS = observe(se3(np.eye(3), [0.02, -0.01, 0.5]), core().target)


def fields() -> tuple[list[str], list[float]]:
    """Return the names and values the detector would publish for OBS."""
    names = list(SPHERE_NAMES)
    values = [*OBS.sphere.b.tolist(), OBS.sphere.r_delta, 0.01, 330.0, 230.0, 120.0, 119.0,
              3.0]
    for mark, q in sorted(OBS.q.items()):
        names += [f'{mark}_{f}' for f in MARK_FIELDS]
        values += [300.0, 200.0, *q.tolist()]
    return names, values


def test_the_measurement_of_the_pose_gives_its_features():
    """The baseline: the well-formed message is tracked and gives the pose's s_n."""
    c = core()
    out = c.on_measurement(10, Measurement.of(*fields()))
    assert not out.lost and c.status().state is FeaturesState.TRACKING
    s_nt = OBS.sphere.b / OBS.sphere.r_delta
    assert np.allclose(out.values['s_n'].s[:3], s_nt, atol=1e-12)


def _refused(meas: Measurement, needle: str) -> None:
    c = core()
    out = c.on_measurement(10, meas)
    assert out.lost and needle in out.lost, out.lost
    assert out.violation is not None, out.lost  # refused (an error), not a lost target
    assert c.status().state is FeaturesState.REFUSED


@pytest.mark.parametrize('name, delta', [
    ('r_delta', 1e-4),  # both values physical: which one is the image's?
    ('P1_qx', 0.0),     # the same value twice is still a message no detector sends
    ('b_z', 0.0),
])
def test_a_name_given_twice_is_refused(name, delta):
    """
    A JointState whose names repeat one is malformed; the last value must not silently win.

    The lengths agree (one more name, one more value), so only the repeat tells.
    """
    names, values = fields()
    i = names.index(name)
    _refused(Measurement.of(names + [name], values + [values[i] + delta]), name)
    with pytest.raises(MeasurementError) as err:
        Measurement.of(names + [name], values + [values[i] + delta]).as_dict()
    assert err.value.violation.bound is Bound.SHAPE


@pytest.mark.parametrize('name, value', [
    ('ellipse_u', math.nan), ('ellipse_angle', math.inf), ('P1_u', -math.inf),
    ('P2_v', math.nan), ('ellipse_major', 1e309),
])
def test_a_non_finite_value_in_any_field_is_refused(name, value):
    """
    The pixel fields do not enter the features, but a NaN there is a corrupt message.

    The detector never publishes one; its other numbers cannot be trusted either.
    """
    names, values = fields()
    values[names.index(name)] = value
    _refused(Measurement.of(names, values), name)


def test_an_empty_name_is_refused():
    names, values = fields()
    _refused(Measurement.of(names + [''], values + [1.0]), "''")


def test_a_kept_desired_with_nan_is_refused_at_start(tmp_path):
    """JSON accepts NaN and Infinity literals: a desired_file holding one is not a desired."""
    names, values = fields()
    values[names.index('ellipse_v')] = math.nan
    path = tmp_path / 'desired.json'
    path.write_text(json.dumps({'format': DESIRED_FORMAT, 'stamp': '1.000000000',
                                'stamp_ns': 10**9, 'frame_id': 'camera_optical_frame',
                                'target_kind': 'special', 'names': names,
                                'values': values}))
    assert 'NaN' in path.read_text()
    with pytest.raises(ParameterError, match='ellipse_v'):
        core(desired_source='teach', desired_file=str(path))


#: the first stamp builtin_interfaces/Time cannot carry (sec is an int32)
TIME_END_NS = 2**31 * 10**9


def _kept(tmp_path, stamp_ns: int):
    names, values = fields()
    path = tmp_path / 'desired.json'
    path.write_text(json.dumps({'format': DESIRED_FORMAT, 'stamp': '', 'stamp_ns': stamp_ns,
                                'frame_id': 'camera_optical_frame',
                                'target_kind': 'special', 'names': names,
                                'values': values}))
    return str(path)


def test_a_kept_desired_stamped_at_the_last_time_a_header_carries_is_read(tmp_path):
    c = core(desired_source='teach', desired_file=_kept(tmp_path, TIME_END_NS - 1))
    assert c.desired_stamp_ns == TIME_END_NS - 1 and c.has_desired


@pytest.mark.parametrize('stamp_ns', [TIME_END_NS, (2**40 + 5) * 10**9, 2**63])
def test_a_kept_desired_stamped_beyond_a_header_is_refused(tmp_path, stamp_ns):
    """
    Its stamp is published in the desired's header, whose sec is an int32.

    rclpy does not check the range: (2^40 + 5) s serializes as 5 s, a stamp of another
    image, with no error anywhere.
    """
    with pytest.raises(ParameterError, match='stamp_ns'):
        core(desired_source='teach', desired_file=_kept(tmp_path, stamp_ns))


@pytest.mark.parametrize('ns', [TIME_END_NS, (2**40 + 5) * 10**9])
def test_a_stamp_beyond_a_header_is_not_published_wrapped(ns):
    """``stamp_from_ns`` refuses what ``builtin_interfaces/Time`` would wrap silently."""
    pytest.importorskip('rclpy')
    from sphere_servo.ros.conversions import stamp_from_ns
    t = stamp_from_ns(TIME_END_NS - 1)
    assert (t.sec, t.nanosec) == (2**31 - 1, 999_999_999)
    with pytest.raises(ValueError, match='stamp'):
        stamp_from_ns(ns)
