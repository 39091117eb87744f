"""
Central camera models (issue 18): lift, project, their Jacobians, the field.

Round trips over each model's whole field, up to its edge; Jacobians against finite
differences; the fisheye against OpenCV's ``cv2.fisheye`` and plumb_bob against
``cv2.projectPoints`` / ``cv2.undistortPoints`` (independent implementations); the unified
model against Mei's equations written out here. (CameraInfo: test_camera_info.py.)
"""
from __future__ import annotations

import math

from camera_cases import angle, field_rays, MODELS, rays_at
import cv2
import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera
from sphere_servo.core.geometry import GeometryError

KB = (0.05, -0.01, 0.003, -0.0005)
TERM = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


# --- round trips ---------------------------------------------------------------------------
@pytest.mark.parametrize('name', MODELS)
def test_lift_inverts_project_over_the_whole_field(name):
    cam = MODELS[name]
    q = field_rays(cam, 20000, seed=1)
    uv = cam.project(q * np.random.default_rng(2).uniform(0.1, 10.0, (len(q), 1)))
    assert np.abs(uv - cam.project(q)).max() <= 1e-9 * (1.0 + np.abs(uv).max())
    q2 = cam.lift(uv)
    assert np.allclose(np.linalg.norm(q2, axis=1), 1.0, atol=1e-14)
    assert angle(q, q2).max() < 1e-9


@pytest.mark.parametrize('name', MODELS)
def test_project_inverts_lift_over_the_image_and_the_field(name):
    cam = MODELS[name]
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.linspace(-0.5, cam.width - 0.5, 81),
                                np.linspace(-0.5, cam.height - 0.5, 61)), -1).reshape(-1, 2)
    lifted = cam.lift_where(grid)
    if isinstance(cam, CameraIntrinsics) or (isinstance(cam, UnifiedCamera) and cam.xi <= 1):
        assert lifted.ok.all()       # the natural field covers the whole plane
    assert lifted.ok.mean() > 0.4
    assert np.isnan(lifted.rays[~lifted.ok]).all()
    # and every pixel the field reaches, beyond the image too
    field_px = cam.project(field_rays(cam, 5000, seed=4))
    uv = np.vstack([grid[lifted.ok], field_px, rng.uniform(0, 1, (2000, 2)) * cam.width])
    uv = uv[cam.lift_where(uv).ok]
    assert len(uv) > 7000
    back = cam.project(cam.lift(uv))
    scale = 1.0 + np.abs(uv - [cam.u0, cam.v0]).max(axis=1)
    assert (np.abs(back - uv).max(axis=1) / scale).max() < 1e-9


# --- Jacobians -----------------------------------------------------------------------------
@pytest.mark.parametrize('name', MODELS)
def test_project_jacobian_matches_finite_differences(name):
    cam = MODELS[name]
    q = field_rays(cam, 300, seed=5, edge=0.98)
    P = q * np.random.default_rng(6).uniform(0.2, 5.0, (len(q), 1))
    J = cam.project_jacobian(P)
    h = 1e-6 * np.linalg.norm(P, axis=1)[:, None]
    Jn = np.stack([(cam.project(P + h * e) - cam.project(P - h * e)) / (2 * h)
                   for e in np.eye(3)], axis=2)
    rel = np.abs(J - Jn).max(axis=(1, 2)) / np.abs(Jn).max(axis=(1, 2))
    assert rel.max() < 1e-5
    assert np.abs(np.einsum('nij,nj->ni', J, P)).max() < 1e-9 * np.abs(J).max()  # scale-free


@pytest.mark.parametrize('name', MODELS)
def test_lift_jacobian_matches_finite_differences(name):
    cam = MODELS[name]
    uv = cam.project(field_rays(cam, 300, seed=7, edge=0.98))
    J = cam.lift_jacobian(uv)
    h = 2e-6 * (1.0 + np.abs(uv - [cam.u0, cam.v0]).max(axis=1))[:, None]
    Jn = np.stack([(cam.lift(uv + h * e) - cam.lift(uv - h * e)) / (2 * h)
                   for e in np.eye(2)], axis=2)
    rel = np.abs(J - Jn).max(axis=(1, 2)) / np.abs(Jn).max(axis=(1, 2))
    assert rel.max() < 1e-5
    assert np.abs(np.einsum('ni,nij->nj', cam.lift(uv), J)).max() < 1e-12  # tangent to S²


# --- the field -----------------------------------------------------------------------------
@pytest.mark.parametrize('name', MODELS)
def test_valid_field_ends_at_max_angle_and_outside_is_refused(name):
    cam = MODELS[name]
    phi = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
    assert cam.valid(rays_at(np.full(16, cam.max_angle * 0.9), phi)).all()
    inside = rays_at(np.full(16, cam.max_angle * (1 - 1e-6)), phi)
    assert cam.valid(inside).mean() > 0.4            # tangential terms: sooner in some
    beyond = rays_at(np.full(16, min(cam.max_angle * (1 + 1e-6) + 1e-9, math.pi)), phi)
    assert not cam.valid(beyond).any()
    with pytest.raises(GeometryError, match='outside the field|behind'):
        cam.project(beyond)
    with pytest.raises(GeometryError, match='outside the field'):
        cam.project_jacobian(beyond)
    assert not cam.valid(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.nan, 0, 1],
                                   [np.inf, 0, 1]])).any()
    assert cam.valid([[1e300, 1e300, 1e300], [0.0, 0.0, 1e-320]]).all()   # scale is free
    assert not cam.lift_where([[np.nan, 10.0], [np.inf, 0.0], [1e300, 1e300]]).ok.any()
    with pytest.raises(GeometryError, match='not the image of a ray'):
        cam.lift([[np.nan, 10.0]])


def test_field_of_view_of_each_model():
    assert MODELS['pinhole'].max_angle == pytest.approx(math.pi / 2)
    assert MODELS['fisheye'].max_angle == pytest.approx(math.pi)       # 360°: θ_d = θ
    assert MODELS['catadioptric'].max_angle == pytest.approx(math.acos(-0.9))
    assert MODELS['parabolic'].max_angle == pytest.approx(math.pi)
    assert MODELS['unified_fisheye'].max_angle == pytest.approx(math.acos(-1 / 1.6))
    # the fisheye sees 190° across the image's height, the pinhole's fold is its edge
    fish = MODELS['fisheye']
    top = fish.lift([[fish.u0, -0.5], [fish.u0, fish.height - 0.5]])
    assert math.degrees(np.arccos(top[:, 2]).sum()) > 180.0
    bob = MODELS['plumb_bob']
    k1, k2, _, _, k3 = bob.dist
    s = np.roots([7 * k3, 5 * k2, 3 * k1, 1.0])
    s = s.real[(abs(s.imag) < 1e-12) & (s.real > 0)].min()
    assert bob.max_angle == pytest.approx(math.atan(math.sqrt(s)))


def test_fisheye_lift_refuses_pixels_outside_its_image_circle():
    cam = FisheyeCamera(px=60.0, py=60.0)             # image circle 60·π = 188 px
    rim = 60.0 * math.pi                              # θ = π: the pole behind the camera
    L = cam.lift_where([[cam.u0 + 0.999 * rim, cam.v0], [cam.u0 + 1.001 * rim, cam.v0]])
    assert L.ok.tolist() == [True, False]
    with pytest.raises(GeometryError):
        cam.lift([[0.0, 0.0]])


def test_pinhole_project_refuses_a_ray_beyond_the_fold_it_would_fold_into_the_image():
    cam = MODELS['plumb_bob']
    beyond = rays_at(np.array([cam.max_angle + 0.1]), np.array([0.3]))
    folded = cam.normalized_to_pixel(beyond[:, :2] / beyond[:, 2:])   # the old answer: in
    L = cam.lift_where(folded)                         # the image, where another ray is
    assert cam.in_image(folded)[0] and L.ok[0] and angle(L.rays, beyond)[0] > 1.0
    with pytest.raises(GeometryError, match='outside the field'):
        cam.project(beyond)
    with pytest.raises(GeometryError, match='behind'):
        cam.project([[0.0, 0.0, -1.0]])


# --- independent references ----------------------------------------------------------------
def test_fisheye_matches_opencv_fisheye():
    cam = FisheyeCamera(px=190.0, py=185.0, u0=322.0, v0=236.0, dist=KB)
    rng = np.random.default_rng(8)
    q = rays_at(rng.uniform(0, math.radians(89.5), 3000), rng.uniform(0, 2 * math.pi, 3000))
    K, D = cam.K, np.array(KB)
    uv_cv, _ = cv2.fisheye.projectPoints(2.0 * q.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                         K, D)
    uv_cv = uv_cv.reshape(-1, 2)
    assert np.abs(cam.project(q) - uv_cv).max() < 1e-9
    sel = q[:, 2] > math.cos(math.radians(80))        # cv2's undistort is accurate to ~80°
    xy_cv = cv2.fisheye.undistortPoints(uv_cv[sel].reshape(-1, 1, 2), K, D,
                                        criteria=TERM).reshape(-1, 2)
    ql = cam.lift(uv_cv[sel])
    assert np.abs(ql[:, :2] / ql[:, 2:] - xy_cv).max() < 1e-9


def test_fisheye_beyond_90_degrees_matches_kannala_brandt():
    cam = FisheyeCamera(px=190.0, py=185.0, u0=322.0, v0=236.0, dist=KB)
    rng = np.random.default_rng(9)
    theta = rng.uniform(math.radians(85), cam.max_angle * 0.999, 2000)
    phi = rng.uniform(0, 2 * math.pi, 2000)
    q = rays_at(theta, phi)
    k1, k2, k3, k4 = KB
    td = theta * (1 + k1 * theta ** 2 + k2 * theta ** 4 + k3 * theta ** 6 + k4 * theta ** 8)
    ref = np.column_stack([190.0 * td * np.cos(phi) + 322.0, 185.0 * td * np.sin(phi) + 236.0])
    assert np.abs(cam.project(q) - ref).max() < 1e-9
    assert angle(cam.lift(ref), q).max() < 1e-9


def mei_project(P, xi, gamma, center, dist):
    """Mei & Rives (2007): sphere, ξ shift, pinhole, radial-tangential distortion, K."""
    Xs = P / np.linalg.norm(P, axis=1)[:, None]
    x, y = Xs[:, 0] / (Xs[:, 2] + xi), Xs[:, 1] / (Xs[:, 2] + xi)
    k1, k2, p1, p2 = dist
    rho2 = x * x + y * y
    radial = 1 + k1 * rho2 + k2 * rho2 ** 2
    xd = x * radial + 2 * p1 * x * y + p2 * (rho2 + 2 * x * x)
    yd = y * radial + p1 * (rho2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([gamma[0] * xd + center[0], gamma[1] * yd + center[1]])


def mei_lift_undistorted(uv, xi, gamma, center):
    """Mei's lifting of an undistorted point: ``X_s = (λx, λy, λ − ξ)``."""
    x, y = (uv[:, 0] - center[0]) / gamma[0], (uv[:, 1] - center[1]) / gamma[1]
    r2 = x * x + y * y
    lam = (xi + np.sqrt(1 + (1 - xi * xi) * r2)) / (r2 + 1)
    return np.column_stack([lam * x, lam * y, lam - xi])


@pytest.mark.parametrize('xi', [0.0, 0.5, 0.9, 1.0, 1.4])
def test_unified_matches_mei_equations(xi):
    dist = (-0.08, 0.015, 0.0008, -0.0004)
    cam = UnifiedCamera(px=280.0, py=270.0, u0=318.0, v0=243.0, xi=xi, dist=dist)
    rng = np.random.default_rng(10)
    theta = rng.uniform(0, 0.95 * cam.max_angle, 3000)
    P = rays_at(theta, rng.uniform(0, 2 * math.pi, 3000)) * rng.uniform(0.5, 4, (3000, 1))
    P = P[cam.valid(P)]
    ref = mei_project(P, xi, (280.0, 270.0), (318.0, 243.0), dist)
    assert np.abs(cam.project(P) - ref).max() <= 1e-9 * (1 + np.abs(ref).max())
    assert angle(cam.lift(ref), P / np.linalg.norm(P, axis=1)[:, None]).max() < 1e-9
    plain = UnifiedCamera(px=280.0, py=270.0, u0=318.0, v0=243.0, xi=xi)
    uv = plain.project(P[theta[:len(P)] < 0.8 * plain.max_angle])
    ref = mei_lift_undistorted(uv, xi, (280.0, 270.0), (318.0, 243.0))
    assert np.abs(plain.lift(uv) - ref).max() < 1e-9


def test_plumb_bob_matches_opencv_and_the_existing_api():
    cam = MODELS['plumb_bob']
    grid = np.stack(np.meshgrid(np.linspace(0, 639, 41), np.linspace(0, 479, 31)),
                    -1).reshape(-1, 2)
    q = cam.lift(grid)
    xy_cv = cv2.undistortPoints(grid.reshape(-1, 1, 2), cam.K, np.array(cam.dist), None, None,
                                None, TERM).reshape(-1, 2)
    assert np.abs(q[:, :2] / q[:, 2:] - xy_cv).max() < 1e-12
    uv_cv, _ = cv2.projectPoints(3.0 * q.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K,
                                 np.array(cam.dist))
    assert np.abs(cam.project(3.0 * q) - uv_cv.reshape(-1, 2)).max() < 1e-9
    xy = cam.pixel_to_normalized(grid)                  # the existing API says the same
    assert np.abs(q[:, :2] / q[:, 2:] - xy).max() < 1e-12
    assert np.abs(cam.normalized_to_pixel(xy) - grid).max() < 1e-9
