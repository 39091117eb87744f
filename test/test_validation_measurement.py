"""
Validation of a measurement from outside (issue 14, items 3 and 4): every bound at and past.

The accepted side comes from exact observations of random poses and from the real renderer
and detector (data the validation did not make); the refused side is built deliberately,
a little past each bound.
"""
from __future__ import annotations

import math

from core_poses import camera_at, CMO_DESIRED, random_visible_poses
import numpy as np
import pytest
from sphere_servo.core.camera_models import FisheyeCamera
from sphere_servo.core.geometry import normalize
from sphere_servo.core.measurement import (depth_ratio, LIMB_TOL, MeasurementError,
                                           Observation, observe, P_over_r, PINHOLE_FIELD,
                                           R_DELTA_MIN, SphereMeasurement,
                                           validated_observation, validated_sphere)
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.core.validation import Bound, UNIT_TOL

Z = np.array([0.0, 0.0, 1.0])


def _refused(fn, bound: Bound, quantity: str):
    """Call ``fn``; it must raise MeasurementError with ``bound`` naming ``quantity``."""
    with pytest.raises(MeasurementError) as info:
        fn()
    v = info.value.violation
    assert v is not None and v.bound is bound, str(info.value)
    assert quantity in v.quantity and quantity in str(info.value)
    return info.value


def _ray(alpha: float, azimuth: float = 0.0) -> np.ndarray:
    """Return the unit ray at ``alpha`` rad from the optical axis."""
    return np.array([math.sin(alpha) * math.cos(azimuth), math.sin(alpha) * math.sin(azimuth),
                     math.cos(alpha)])


def _off_b(b: np.ndarray, angle: float) -> np.ndarray:
    """Return the unit ray at ``angle`` rad from ``b``."""
    side = normalize(np.cross(b, [0.0, 1.0, 0.0] if abs(b[1]) < 0.9 else [1.0, 0.0, 0.0]))
    return math.cos(angle) * b + math.sin(angle) * side


# --- the sphere --------------------------------------------------------------------------
def test_exact_observations_of_random_poses_pass():
    for target in (special_sphere(), cc_target()):
        for cMo in random_visible_poses(target, 40, seed=3):
            obs = observe(cMo, target)
            out = validated_observation(obs)
            np.testing.assert_array_equal(out.sphere.b, obs.sphere.b)
            assert out.sphere.r_delta == obs.sphere.r_delta and out.q.keys() == obs.q.keys()


@pytest.mark.parametrize('scale, ok', [(1 + 0.9 * UNIT_TOL, True), (1 - 0.9 * UNIT_TOL, True),
                                       (1 + 1.1 * UNIT_TOL, False), (1 - 1.1 * UNIT_TOL, False),
                                       (2.0, False), (0.0, False)])
def test_b_must_be_a_unit_vector(scale, ok):
    sph = SphereMeasurement(scale * Z, 0.1)
    if ok:
        assert validated_sphere(sph).r_delta == 0.1
    else:
        _refused(lambda: validated_sphere(sph), Bound.UNIT, '‖b‖')


@pytest.mark.parametrize('b', [[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 1.0]])
def test_b_must_be_three_finite_numbers(b):
    with pytest.raises(MeasurementError, match='b'):
        validated_sphere(SphereMeasurement(np.array(b), 0.1))


@pytest.mark.parametrize('r_delta, ok', [
    (R_DELTA_MIN, True), (0.5, True), (1 - 1e-12, True),
    (0.99 * R_DELTA_MIN, False), (0.0, False), (-0.1, False), (1.0, False), (1.5, False),
    (np.nan, False), (np.inf, False)])
def test_r_delta_is_within_its_physical_range(r_delta, ok):
    sph = SphereMeasurement(Z.copy(), r_delta)
    if ok:
        assert validated_sphere(sph).r_delta == r_delta
    else:
        _refused(lambda: validated_sphere(sph), Bound.FINITE if not np.isfinite(r_delta)
                 else Bound.RANGE, 'r_delta')


@pytest.mark.parametrize('alpha', [0.3, 0.9, 1.3])
def test_pinhole_field_is_b_z_greater_than_r_delta(alpha):
    # the silhouette cone's edge at asin(r_δ) + α from the axis: on the image plane iff < 90°
    b = _ray(alpha, 0.7)
    for eps, ok in ((1e-9, True), (-1e-9, False)):
        r_delta = math.sin(math.pi / 2 - alpha - eps)
        assert (b[2] > r_delta) == ok
        sph = SphereMeasurement(b, r_delta)
        if ok:
            validated_sphere(sph)
        else:
            _refused(lambda: validated_sphere(sph), Bound.FIELD, 'silhouette')


def test_a_wide_field_camera_passes_its_own_field():
    fish = FisheyeCamera()
    sph = SphereMeasurement(_ray(math.radians(120.0)), 0.2)   # centre 120° off the axis
    _refused(lambda: validated_sphere(sph), Bound.FIELD, 'silhouette')   # a pinhole cannot
    assert validated_sphere(sph, field=fish.max_angle).r_delta == 0.2
    edge = math.radians(120.0) + math.asin(0.2)
    validated_sphere(sph, field=edge + 1e-9)
    _refused(lambda: validated_sphere(sph, field=edge - 1e-9), Bound.FIELD, 'silhouette')
    for bad in (0.0, -1.0, math.pi + 1e-6, np.nan):
        with pytest.raises(MeasurementError, match='field'):
            validated_sphere(sph, field=bad)


@pytest.mark.parametrize('quality', [-1e-9, np.nan, np.inf])
def test_quality_is_finite_and_non_negative(quality):
    with pytest.raises(MeasurementError, match='quality'):
        validated_sphere(SphereMeasurement(Z.copy(), 0.1, quality))


# --- item 3: r_delta = 0 no longer divides by zero ------------------------------------------
@pytest.mark.parametrize('r_delta', [0.0, -0.2, 1.0, np.nan])
def test_depth_ratio_refuses_an_impossible_r_delta_cleanly(r_delta):
    sph = SphereMeasurement(Z.copy(), r_delta)
    _refused(lambda: depth_ratio(sph, Z), Bound.RANGE, 'r_delta')
    _refused(lambda: sph.s_nt, Bound.RANGE, 'r_delta')


def test_depth_ratio_refuses_a_ray_away_from_the_sphere():
    sph = SphereMeasurement(Z.copy(), 0.1)
    _refused(lambda: depth_ratio(sph, _ray(math.pi / 2 + 0.1)), Bound.GEOMETRY, 'bᵀq')


# --- the marks ---------------------------------------------------------------------------
def _obs_with(name: str, q: np.ndarray, kind: str = 'special') -> Observation:
    target = special_sphere() if kind == 'special' else cc_target()
    obs = observe(CMO_DESIRED, target)
    marks = dict(obs.q)
    marks[name] = q
    return Observation(obs.sphere, marks, obs.kind)


@pytest.mark.parametrize('name', ['P1', 'P2'])
def test_a_surface_mark_lies_on_the_visible_cap(name):
    obs = observe(CMO_DESIRED, special_sphere())
    b, limb = obs.sphere.b, math.asin(obs.sphere.r_delta)
    for extra, ok in ((0.0, True), (0.99 * LIMB_TOL, True), (1.01 * LIMB_TOL, False),
                      (0.2, False)):
        o = _obs_with(name, _off_b(b, limb + extra))
        if ok:
            validated_observation(o)
        else:
            err = _refused(lambda: validated_observation(o), Bound.GEOMETRY, name)
            assert 'cap' in str(err)
            # what the unchecked formula does with it: a finite, clamped depth (no sign of
            # the error), which is why the check exists
            assert np.isfinite(depth_ratio(o.sphere, o.q[name]))
    o = _obs_with(name, _off_b(b, limb + 0.02))
    validated_observation(o, limb_tol=0.03)
    _refused(lambda: validated_observation(o, limb_tol=0.01), Bound.GEOMETRY, name)


@pytest.mark.parametrize('scale, bound', [(1 + 1.1 * UNIT_TOL, Bound.UNIT),
                                          (1 - 1.1 * UNIT_TOL, Bound.UNIT)])
def test_mark_rays_are_unit(scale, bound):
    q1 = observe(CMO_DESIRED, special_sphere()).q['P1']
    validated_observation(_obs_with('P1', (1 + 0.9 * UNIT_TOL) * q1))
    _refused(lambda: validated_observation(_obs_with('P1', scale * q1)), bound, 'P1 ray')


@pytest.mark.parametrize('q', [[np.nan, 0.0, 1.0], [0.0, -np.inf, 1.0], [0.0, 1.0]])
def test_mark_rays_are_finite_three_vectors(q):
    with pytest.raises(MeasurementError, match='P2 ray'):
        validated_observation(_obs_with('P2', np.array(q)))


def test_mark_names_and_kind_are_those_of_the_target():
    obs = observe(CMO_DESIRED, special_sphere())
    _refused(lambda: validated_observation(_obs_with('P3', obs.q['P2'])), Bound.RANGE,
             'mark name')
    _refused(lambda: validated_observation(Observation(obs.sphere, obs.q, 'balloon')),
             Bound.RANGE, 'target kind')
    lost = validated_observation(Observation(obs.sphere, {'P1': obs.q['P1']}, obs.kind))
    assert list(lost.q) == ['P1']     # a missing mark is lost, not invalid


def test_the_cc_tip_rule():
    target = cc_target()
    obs = observe(CMO_DESIRED, target)
    validated_observation(obs)
    sph, q1 = obs.sphere, obs.q['P1']
    # the tip on P1 itself: no stick
    _refused(lambda: validated_observation(_obs_with('P3', q1.copy(), 'cc')), Bound.GEOMETRY,
             'P3 − P1')
    # a tip ray that meets P1's tangent plane behind the camera: q3·d < 0
    d = sph.s_nt - P_over_r(sph, q1)
    q3 = normalize(q1 - 1.5 * (q1 @ d) * d / (d @ d))
    assert q3 @ d < 0
    _refused(lambda: validated_observation(_obs_with('P3', q3, 'cc')), Bound.GEOMETRY, 'P3')
    # a tip ray parallel to the tangent plane
    q3 = normalize(q1 - (q1 @ d) * d / (d @ d))
    _refused(lambda: validated_observation(_obs_with('P3', q3, 'cc')), Bound.GEOMETRY, 'P3')
    # the tip may be seen anywhere in front, even outside the sphere's silhouette
    far = validated_observation(observe(camera_at([0.05, -0.02, -0.4]), target))
    assert 'P3' in far.q


def test_real_detections_pass_the_validation():
    # renderer + detector (marks back-projected on the estimated sphere, some cut by the
    # limb): the tolerances must not refuse what a real image gives
    from sphere_servo.core.camera import CameraIntrinsics
    from sphere_servo.vision.detector import Detector
    from sphere_servo.vision.renderer import Renderer
    cam = CameraIntrinsics()
    for target in (special_sphere(), cc_target()):
        ren, det = Renderer(cam, target), Detector.for_target(target)
        n = 0
        for cMo in random_visible_poses(target, 12, seed=11, camera=cam):
            d = det.detect(ren.render(cMo), 'rgb8', cam)
            if not d.found:
                continue
            q = {k: m.q for k, m in d.marks.items() if m.visible}
            validated_observation(Observation(d.sphere, q, target.kind))
            n += 1
        assert n >= 8


def test_the_message_names_quantity_and_value():
    err = _refused(lambda: validated_sphere(SphereMeasurement(Z.copy(), 1.25)), Bound.RANGE,
                   'r_delta')
    assert str(err).startswith('r_delta = 1.25 ') and '≤ r_delta < 1' in str(err)
    assert err.violation.value == 1.25 and PINHOLE_FIELD == math.pi / 2
