"""
Bad input to the core (issue 2).

Every case gives a defined result or a clear ValueError, never a NaN silently propagated
into a twist.
"""
from __future__ import annotations

from core_poses import camera_at, CMO_DESIRED
import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.control import ControlError, Controller
from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import (
    depth_ratio, mark_visible, MeasurementError, Observation, observe, sphere_from_conic,
    SphereMeasurement, unit_ray)
from sphere_servo.core.targets import cc_target, special_sphere, Target


def test_marks_on_the_far_side_are_reported_hidden():
    target = special_sphere()
    behind = camera_at([0.0, 0.0, 0.5])  # looking at the unmarked +z cap
    with pytest.raises(MeasurementError, match='hidden'):
        observe(behind, target)
    obs = observe(behind, target, require_visible=False)
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    # a far-side direction is interpreted on the visible side: finite, defined features
    assert np.all(np.isfinite(fs.features(obs)))


def _segment_hits_sphere(cMo, target, oP) -> bool:
    """Independent occlusion check: sample the segment camera → point."""
    cP, cO = cMo.act(oP), cMo.translation
    pts = np.linspace(0.0, 0.999, 5000)[:, None] * cP
    return bool(np.any(np.linalg.norm(pts - cO, axis=1) < target.radius * (1 - 1e-6)))


def test_cc_tip_occlusion_matches_ray_sampling():
    target = cc_target()
    oP3 = target.marks()['P3']
    hidden = camera_at(-0.4 * oP3 / np.linalg.norm(oP3))
    assert _segment_hits_sphere(hidden, target, oP3)
    assert not mark_visible(hidden, target, 'P3')
    with pytest.raises(MeasurementError, match='hidden'):
        observe(hidden, target)
    rng = np.random.default_rng(1)
    for _ in range(300):
        d = rng.normal(size=3)
        cMo = camera_at(0.4 * d / np.linalg.norm(d))
        assert mark_visible(cMo, target, 'P3') == (not _segment_hits_sphere(cMo, target, oP3))
        # P3 lies in the tangent plane at P1: it can only be hidden when P1 is
        if mark_visible(cMo, target, 'P1'):
            assert mark_visible(cMo, target, 'P3')


@pytest.mark.parametrize('C', [
    np.zeros((3, 3)),
    np.diag([1.0, 1.0, 1.0]),            # no real points
    np.diag([1.0, -1.0, -1.0]),          # hyperbola-like: b would be the x axis (not ahead)
    np.diag([1.0, 1.0, -1.0]) * 0,       # zero
    np.outer([0, 0, 1.0], [0, 0, 1.0]),  # rank one
    np.diag([1.0, -1.0, 0.0]),           # degenerate pair of lines
    np.full((3, 3), np.nan),
    np.eye(2),                           # wrong shape
])
def test_degenerate_conic_is_a_clear_error(C):
    with pytest.raises(ValueError):
        sphere_from_conic(C)


@pytest.mark.parametrize('xy', [[np.inf, 0.0], [0.0, -np.inf], [np.nan, 0.2]])
def test_point_at_infinity_is_a_clear_error(xy):
    with pytest.raises(GeometryError, match='NaN or inf'):
        unit_ray(np.array(xy))


def test_mark_just_outside_the_silhouette_is_clamped():
    sph = SphereMeasurement(b=np.array([0.0, 0.0, 1.0]), r_delta=0.1)
    edge = np.arcsin(0.1)
    for extra in (0.0, 1e-4, 1e-2):
        ang = edge + extra
        q = np.array([np.sin(ang), 0.0, np.cos(ang)])
        rho = depth_ratio(sph, q)
        assert np.isfinite(rho)
        # clamped to the tangent point's depth: cos φ / r_δ
        assert rho == pytest.approx(np.cos(ang) / 0.1)


def test_nan_observation_never_reaches_the_twist():
    target = special_sphere()
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    ctrl = Controller(fs, target.radius)
    good = observe(pin.SE3(np.eye(3), np.array([0.01, 0.0, 0.5])), target)
    bad = Observation(SphereMeasurement(np.array([np.nan, 0, 1.0]), 0.1), good.q, good.kind)
    with pytest.raises(ValueError):
        ctrl.compute(bad)
    lost = Observation(good.sphere, {'P1': good.q['P1']}, good.kind)
    with pytest.raises(MeasurementError, match='P2 is not visible'):
        ctrl.compute(lost)


def test_singular_configuration_is_a_control_error_not_nan():
    target = special_sphere()
    fs = make_feature_set('s', observe(CMO_DESIRED, target))
    ctrl = Controller(fs, target.radius)
    ctrl.L_hat = lambda obs, s=None: np.zeros((6, 6))  # force a singular L̂
    with pytest.raises(ControlError, match='singular'):
        ctrl.compute(observe(pin.SE3(np.eye(3), np.array([0.01, 0.0, 0.5])), target))


@pytest.mark.parametrize('kw', [{'px': np.nan}, {'px': -1.0}, {'width': 0},
                                {'dist': (0.0, 0.0)}])
def test_bad_intrinsics_are_refused(kw):
    with pytest.raises(ValueError):
        CameraIntrinsics(**kw)


@pytest.mark.parametrize('radius', [0.0, -1.0, np.nan])
def test_bad_target_radius_is_refused(radius):
    with pytest.raises(ValueError, match='radius'):
        Target('special', radius, [0, 0, -1.0], [0, 1.0, 0])


def test_camera_inside_the_sphere_is_an_error():
    with pytest.raises(MeasurementError, match='inside'):
        observe(pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.01])), special_sphere())


def test_fast_linalg_equals_numpy_and_reports_singular():
    from sphere_servo.core import linalg
    rng = np.random.default_rng(4)
    for _ in range(50):
        A = rng.normal(size=(6, 6))
        b = rng.normal(size=6)
        assert np.allclose(linalg.solve(A, b), np.linalg.solve(A, b), rtol=1e-12, atol=1e-12)
        S = rng.normal(size=(3, 3))
        S = S + S.T
        w, V = linalg.eigh(S)
        w2, _ = np.linalg.eigh(S)
        assert np.allclose(w, w2) and np.allclose(S @ V, V * w)
    with pytest.raises(np.linalg.LinAlgError):
        linalg.solve(np.zeros((6, 6)), np.ones(6))
