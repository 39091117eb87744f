"""
The sphere measured on the projection sphere (issue 18): the small-circle fit.

Exact silhouettes (whole, partial, cut by the image border, 80°+ off the axis) give b and
r_δ to < 1e-9 through every camera model's lift; the fit agrees with the conic path on a
pinhole camera; it degrades in proportion to pixel noise and rejects outliers; degenerate
input is refused. The marks' back-projection (DESIGN.md §2) gives ground truth through each
model's lift.
"""
from __future__ import annotations

import math

from camera_cases import angle, MODELS, rays_at, small_circle
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera
from sphere_servo.core.geometry import normalize
from sphere_servo.core.measurement import (cRo_special, depth_ratio, MeasurementError,
                                           P_over_r, sphere_from_conic, SphereMeasurement)
from sphere_servo.core.small_circle import fit_small_circle, MIN_POINTS, sphere_from_rays
from sphere_servo.core.targets import special_sphere


def errors(sph: SphereMeasurement, b, r_delta) -> tuple[float, float]:
    """Angle between the fitted and true ``b`` (rad) and the relative error of r_δ."""
    b = normalize(np.asarray(b, dtype=float))
    return float(angle(sph.b[None], b[None])[0]), abs(sph.r_delta / r_delta - 1.0)


def off_axis(deg: float, az: float = 0.3) -> np.ndarray:
    """Return the unit vector ``deg`` degrees off the optical axis at azimuth ``az``."""
    return rays_at(np.array([math.radians(deg)]), np.array([az]))[0]


# --- exact points ----------------------------------------------------------------------------
@pytest.mark.parametrize('b_deg, theta, arc', [
    (0.0, 0.1, 2 * math.pi),           # centred
    (40.0, 0.25, 2 * math.pi),
    (85.0, 0.05, 2 * math.pi),         # a far-off-axis sphere
    (100.0, 0.3, 2 * math.pi),         # behind the image plane (a wide camera sees it)
    (10.0, 1e-3, 2 * math.pi),         # a far sphere: r_δ = 0.001
    (20.0, 1.45, 2 * math.pi),         # a near sphere: r_δ = 0.993
    (30.0, 0.2, math.radians(60)),     # partial arcs
    (85.0, 0.1, math.radians(20)),
])
def test_recovers_b_and_r_delta_from_exact_points(b_deg, theta, arc):
    b = off_axis(b_deg)
    fit = fit_small_circle(small_circle(b, theta, 80, seed=1, arc=(0.5, 0.5 + arc)))
    eb, er = errors(fit.sphere, b, math.sin(theta))
    assert eb < 1e-9 and er < 1e-9
    assert fit.inliers.all() and fit.rms < 1e-12 and fit.sphere.quality < 1e-9
    assert fit.theta == pytest.approx(theta, abs=1e-12)


@pytest.mark.parametrize('name', MODELS)
def test_exact_silhouettes_through_each_models_lift(name):
    """
    Fit silhouettes seen through each model, from the axis to the edge of the field.

    Silhouette rays → the model's pixels (only those in the image: a silhouette cut by the
    border) → lift → fit.
    """
    cam = MODELS[name]
    rng = np.random.default_rng(11)
    tested = cut = 0
    for _ in range(40):
        theta = rng.uniform(0.02, 0.35)
        b = off_axis(rng.uniform(0.0, math.degrees(cam.max_angle - theta) - 2.0),
                     rng.uniform(0, 2 * math.pi))
        q = small_circle(b, theta, 300, seed=int(rng.integers(1 << 30)))
        q = q[cam.valid(q)]
        uv = cam.project(q)
        uv = uv[cam.in_image(uv) & cam.lift_where(uv).ok]
        if len(uv) < 30:
            continue
        cut += len(uv) < 0.98 * len(q)
        eb, er = errors(sphere_from_rays(cam.lift(uv)), b, math.sin(theta))
        assert eb < 1e-9 and er < 1e-9
        tested += 1
    corners = [[-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5]]
    border_cuts_the_field = cam.lift_where(corners).ok.any()
    assert tested >= 15 and (cut >= 3 or not border_cuts_the_field)


def test_a_sphere_80_degrees_off_axis_on_a_fisheye_cut_by_the_border():
    cam = FisheyeCamera()
    b, theta = off_axis(84.0, az=math.pi / 2), 0.15           # towards the bottom border
    q = small_circle(b, theta, 400, seed=2)
    uv = cam.project(q)
    inside = cam.in_image(uv)
    assert 0.2 < inside.mean() < 0.9 and (q[inside][:, 2] < 0).any()   # cut, and past 90°
    eb, er = errors(sphere_from_rays(cam.lift(uv[inside])), b, math.sin(theta))
    assert eb < 1e-9 and er < 1e-9


def test_the_refinement_minimises_the_angular_residuals():
    # rays alternately δ inside and outside the circle: the geometric fit is the circle
    # itself, the algebraic plane through them is not (mean cos(θ ± δ) = cos θ cos δ)
    b, theta, delta = off_axis(50.0), 0.3, 0.05
    phi = np.linspace(0.0, 2.0 * math.pi, 60, endpoint=False)
    e1 = normalize(np.cross(b, [0.0, 0.0, 1.0]))
    e2 = np.cross(b, e1)
    t = theta + delta * (-1.0) ** np.arange(60)
    ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    q = np.cos(t)[:, None] * b + np.sin(t)[:, None] * ring
    fit = fit_small_circle(q, tol=1.0)
    assert abs(fit.theta - theta) < 1e-12 and errors(fit.sphere, b, 1.0)[0] < 1e-12
    assert fit.rms == pytest.approx(delta, rel=1e-9)
    # on noisy rays, every small change of (b, θ) raises Σ (φ_i − θ)²
    rng = np.random.default_rng(16)
    q = small_circle(b, theta, 100, seed=7) + rng.normal(0.0, 1e-3, (100, 3))
    fit = fit_small_circle(q, tol=1.0)
    qn = q / np.linalg.norm(q, axis=1)[:, None]

    def cost(bb, th):
        return float(np.sum((angle(qn, np.broadcast_to(normalize(bb), qn.shape)) - th) ** 2))

    best = cost(fit.sphere.b, fit.theta)
    for _ in range(50):
        d = rng.normal(0.0, 1e-5, 4)
        assert cost(fit.sphere.b + d[:3], fit.theta + d[3]) > best


# --- the conic path ----------------------------------------------------------------------------
def fit_conic_dlt(xy: np.ndarray) -> np.ndarray:
    """Algebraic conic through (N, 2) normalized points: the null vector of the design matrix."""
    x, y = xy[:, 0], xy[:, 1]
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c, d, e, f = np.linalg.svd(D)[2][-1]
    return np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])


def test_agrees_with_the_conic_path_on_a_pinhole_camera():
    cam = CameraIntrinsics()
    rng = np.random.default_rng(12)
    for _ in range(20):
        theta = rng.uniform(0.03, 0.3)
        b = off_axis(rng.uniform(0.0, 25.0), rng.uniform(0, 2 * math.pi))
        uv = cam.project(small_circle(b, theta, 200, seed=int(rng.integers(1 << 30))))
        xy = (uv - [cam.u0, cam.v0]) / [cam.px, cam.py]         # K⁻¹, independently
        conic = sphere_from_conic(fit_conic_dlt(xy))
        circle = sphere_from_rays(cam.lift(uv))
        assert errors(circle, conic.b, conic.r_delta)[0] < 1e-9
        assert errors(circle, conic.b, conic.r_delta)[1] < 1e-9
        # with 0.3 px of noise both estimate the same sphere (within their own errors)
        noisy = uv + rng.normal(0.0, 0.3, uv.shape)
        xy = (noisy - [cam.u0, cam.v0]) / [cam.px, cam.py]
        conic = sphere_from_conic(fit_conic_dlt(xy))
        circle = sphere_from_rays(cam.lift(noisy))
        eb, er = errors(circle, conic.b, conic.r_delta)
        assert eb < 2e-4 and er < 2e-2


# --- noise and outliers ------------------------------------------------------------------------
@pytest.mark.parametrize('cam', [CameraIntrinsics(), FisheyeCamera(), UnifiedCamera()],
                         ids=lambda c: type(c).__name__)
def test_degrades_in_proportion_to_pixel_noise(cam):
    rng = np.random.default_rng(13)
    b, theta = off_axis(30.0), 0.2
    q = small_circle(b, theta, 150, seed=3)
    uv = cam.project(q)
    med = {}
    for sigma in (0.03, 0.3, 3.0):
        e = [errors(sphere_from_rays(cam.lift(uv + rng.normal(0, sigma, uv.shape))), b,
                    math.sin(theta)) for _ in range(30)]
        med[sigma] = np.median(np.array(e), axis=0)
    # angular noise of a pixel on this silhouette, and the fit's expected b error
    dq = np.linalg.norm(cam.lift_jacobian(uv), axis=1).mean() * 0.3
    for k in (0, 1):
        assert med[0.3][k] < 5.0 * dq / math.sqrt(len(q)) / (math.sin(theta) if k else 1.0)
        assert 3.0 < med[0.3][k] / med[0.03][k] < 30.0
        assert 3.0 < med[3.0][k] / med[0.3][k] < 30.0


def test_rejects_outliers_like_the_conic_fit():
    cam = CameraIntrinsics()
    rng = np.random.default_rng(14)
    b, theta = off_axis(15.0), 0.15
    q = small_circle(b, theta, 200, seed=4)
    uv = cam.project(q) + rng.normal(0.0, 0.2, (200, 2))
    # a lump on the contour (a mark's notch, the CC stick): 15 % of the points, 4–20 px out
    lump = np.arange(200) < 30
    out = normalize(np.mean(uv[lump], axis=0) - cam.project(b[None])[0])
    uv[lump] += rng.uniform(4.0, 20.0, (30, 1)) * out
    fit = fit_small_circle(cam.lift(uv), tol=0.3 / cam.px)
    eb, er = errors(fit.sphere, b, math.sin(theta))
    assert eb < 1e-4 and er < 2e-3
    assert not fit.inliers[lump].any() and fit.inliers[~lump].mean() > 0.95
    naive = fit_small_circle(cam.lift(uv), rounds=0)
    assert errors(naive.sphere, b, math.sin(theta))[0] > 10 * eb
    # weights: the lump given weight 0 is ignored even without rejection rounds
    weighted = fit_small_circle(cam.lift(uv), (~lump).astype(float), rounds=0)
    assert errors(weighted.sphere, b, math.sin(theta))[0] < 1e-4
    assert not weighted.inliers[lump].any()


# --- refusals ---------------------------------------------------------------------------------
@pytest.mark.parametrize('rays, match', [
    (small_circle((0, 0, 1), 0.2, MIN_POINTS - 1, seed=5), 'needs 5 rays'),
    (np.vstack([small_circle((0, 0, 1), 0.2, 20, seed=5), [[np.nan, 0, 1]]]), 'NaN'),
    (np.vstack([small_circle((0, 0, 1), 0.2, 20, seed=5), [[0, 0, 0]]]), 'zero length'),
    (small_circle((1, 0, 0), math.pi / 2, 50, seed=5), 'great circle'),   # an image line
    (small_circle((0.3, 0, 1), math.pi / 2, 50, seed=5, arc=(0, 0.3)), 'great circle'),
    (np.tile([[0.1, 0.2, 1.0]], (20, 1)), 'do not span a circle'),
    (np.column_stack([np.linspace(-1, 1, 20), np.zeros(20), np.ones(20)]), 'great circle'),
    (np.zeros((20, 2)), 'shape'),
])
def test_refuses_degenerate_input(rays, match):
    with pytest.raises(MeasurementError, match=match):
        fit_small_circle(rays)


def test_refuses_bad_weights():
    q = small_circle((0, 0, 1), 0.2, 20, seed=6)
    for w in (np.ones(19), np.full(20, np.nan), -np.ones(20)):
        with pytest.raises(MeasurementError, match='weights'):
            fit_small_circle(q, w)
    with pytest.raises(MeasurementError, match='consistent'):
        fit_small_circle(q, np.r_[np.ones(4), np.zeros(16)])


# --- the marks through each model's lift ----------------------------------------------------
@pytest.mark.parametrize('name', MODELS)
def test_mark_back_projection_through_each_models_lift_gives_ground_truth(name):
    cam, target = MODELS[name], special_sphere()
    r = target.radius
    rng = np.random.default_rng(15)
    done = 0
    for _ in range(200):
        cO = rng.uniform(0.15, 0.8) * off_axis(rng.uniform(0, math.degrees(cam.max_angle)
                                                           - 25.0), rng.uniform(0, 6.3))
        b, r_delta = cO / np.linalg.norm(cO), r / np.linalg.norm(cO)
        # the marked −z cap faces the camera (target z along b), then a random spin and tilt
        z = b
        x = normalize(np.cross(z, rng.normal(size=3)))
        cRo = pin.exp3(0.4 * rng.normal(size=3)) @ np.column_stack([x, np.cross(z, x), z])
        cMo = pin.SE3(cRo, cO)
        marks = {k: cMo.act(p) for k, p in target.marks().items()}
        if not all((cRo @ target.surface_normal(target.marks()[k])) @ cP < 0
                   for k, cP in marks.items()) or not cam.valid(np.array([*marks.values()])).all():
            continue
        sil = small_circle(b, math.asin(r_delta), 200, seed=done)
        sphere = sphere_from_rays(cam.lift(cam.project(sil[cam.valid(sil)])))
        q = {k: cam.lift(cam.project(cP[None]))[0] for k, cP in marks.items()}
        for k, cP in marks.items():
            assert abs(depth_ratio(sphere, q[k]) - np.linalg.norm(cP) / r) < 1e-8
            assert np.abs(P_over_r(sphere, q[k]) - cP / r).max() < 1e-8
        exact = cRo_special(SphereMeasurement(b, r_delta), normalize(marks['P1']),
                            normalize(marks['P2']))
        assert np.abs(cRo_special(sphere, q['P1'], q['P2']) - exact).max() < 1e-8
        done += 1
    assert done >= 20
