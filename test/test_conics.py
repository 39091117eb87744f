"""
Conic algebra (core.conics) against ground truth it did not make. DESIGN.md §2.

The truth: points sampled on parametric ellipses, OpenCV's own ellipse fit, the camera
model's pixel ↔ normalized map, and ray–body intersections for the silhouettes.
"""
from __future__ import annotations

import cv2
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.conics import (conic_bbox, conic_from_moments, conic_from_rotated_rect,
                                      conic_normalized_to_pixels, conic_pixels_to_normalized,
                                      ConicError, ellipse_params, ellipsoid_silhouette,
                                      fit_circular_cone, fit_conic, sampson_distance,
                                      sphere_silhouette)

CAM = CameraIntrinsics(px=610.0, py=590.0, u0=331.0, v0=236.0)


def ellipse_points(cx, cy, a, b, ang, n=64):
    """(n, 2) points of the ellipse of centre (cx, cy), semi-axes a (along ang) and b."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ca, sa = np.cos(ang), np.sin(ang)
    return np.column_stack([cx + a * ca * np.cos(t) - b * sa * np.sin(t),
                            cy + a * sa * np.cos(t) + b * ca * np.sin(t)])


def on_conic(C, xy):
    """Algebraic value of (N, 2) points on C, relative to the conic's scale."""
    X = np.column_stack([xy, np.ones(len(xy))])
    return np.einsum('ni,ij,nj->n', X, C, X) / np.linalg.norm(C)


def test_conic_helpers_recover_an_ellipse():
    """
    Recover a rotated, off-centre ellipse with fit_conic, sampson_distance, ellipse_params.

    Exact on noiseless points of a 240° arc whatever the scale of the coordinates (pixels
    or normalized); the Sampson distance is the geometric one near the curve.
    """
    t = np.linspace(0.0, 2 * np.pi, 37, endpoint=False)[:25]         # a 240° arc
    for (cx, cy), (a, b), ang in (((412.3, 171.9), (63.0, 41.5), 0.7),
                                  ((0.21, -0.13), (0.08, 0.05), -1.1)):
        ca, sa = np.cos(ang), np.sin(ang)
        xy = np.column_stack([cx + a * ca * np.cos(t) - b * sa * np.sin(t),
                              cy + a * sa * np.cos(t) + b * ca * np.sin(t)])
        C = fit_conic(xy)
        assert abs(np.linalg.norm(C) - 1.0) < 1e-12
        assert np.abs(sampson_distance(C, xy)).max() < 1e-9 * a
        (ecx, ecy), (ea, eb), eang = ellipse_params(C)
        np.testing.assert_allclose([ecx, ecy, ea, eb], [cx, cy, a, b], rtol=1e-9, atol=1e-9 * a)
        assert abs(np.sin(eang - ang)) < 1e-9
        # a point δ outside along the normal at t = 0: Sampson ≈ ±δ
        n = np.array([ca / a, sa / a])
        n /= np.linalg.norm(n)
        delta = 1e-3 * b
        d = sampson_distance(C, (xy[:1] + delta * n))
        assert abs(abs(d[0]) - delta) < 1e-2 * delta


def test_ellipse_params_refuses_what_is_not_a_real_ellipse():
    hyperbola = np.diag([1.0, -1.0, -1.0])
    imaginary = np.diag([1.0, 1.0, 1.0])            # x² + y² + 1 = 0
    parabola = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -0.5], [0.0, -0.5, 0.0]])
    for C in (hyperbola, imaginary, parabola, np.zeros((3, 3)), np.full((3, 3), np.nan)):
        assert ellipse_params(C) is None
    assert conic_bbox(hyperbola) is None and conic_bbox(imaginary) is None


def test_rotated_rect_conic_is_the_ellipse_opencv_fits():
    """cv2.fitEllipse's RotatedRect (full axes, degrees) → the conic its points lie on."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        cx, cy = rng.uniform(50, 600), rng.uniform(50, 400)
        a, b = rng.uniform(10, 80, 2)
        xy = ellipse_points(cx, cy, a, b, rng.uniform(-np.pi, np.pi))
        (rcx, rcy), (w, h), deg = cv2.fitEllipse(xy.astype(np.float32))
        C = conic_from_rotated_rect(rcx, rcy, w, h, deg)
        # float32 input: OpenCV's fit is good to ~1e-4 px
        assert np.abs(sampson_distance(C, xy)).max() < 2e-3 * max(a, b)
        e = ellipse_params(C)
        assert sorted(e.semi_axes) == pytest.approx(sorted((a, b)), rel=1e-4)


def test_bbox_is_the_extent_of_the_ellipse():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.uniform(5, 90, 2)
        cx, cy, ang = rng.uniform(-300, 300), rng.uniform(-300, 300), rng.uniform(-4, 4)
        xy = ellipse_points(cx, cy, a, b, ang, n=20000)
        C = fit_conic(xy[::500])
        C *= rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 10.0)       # any scale and sign
        box = conic_bbox(C)
        expect = (xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max())
        # the dense sampling misses the extreme by ≤ a·(π/20000)²/2
        np.testing.assert_allclose(box, expect, atol=1e-6 * max(a, b) + 1e-7)
        assert all(lo <= hi for lo, hi in zip(box[::2], box[1::2]))


def test_pixels_and_normalized_conics_map_the_same_points():
    """A conic's points mapped by the camera model lie on the mapped conic, both ways."""
    rng = np.random.default_rng(2)
    for _ in range(20):
        uv = ellipse_points(rng.uniform(100, 500), rng.uniform(100, 380),
                            *rng.uniform(10, 90, 2), rng.uniform(-4, 4))
        C_px = fit_conic(uv) * rng.choice([-1.0, 1.0]) * 7.0
        C_n = conic_pixels_to_normalized(C_px, CAM.px, CAM.py, CAM.u0, CAM.v0)
        assert abs(np.linalg.norm(C_n) - 1.0) < 1e-12
        xy = CAM.pixel_to_normalized(uv)
        assert np.abs(on_conic(C_n, xy)).max() < 1e-9
        back = conic_normalized_to_pixels(C_n, CAM.px, CAM.py, CAM.u0, CAM.v0)
        assert abs(np.linalg.norm(back) - 1.0) < 1e-12
        np.testing.assert_allclose(back, C_px / np.linalg.norm(C_px), atol=1e-9)
        # and the normalized → pixels direction on points built in normalized coordinates
        xy2 = ellipse_points(*rng.uniform(-0.3, 0.3, 2), *rng.uniform(0.02, 0.2, 2), 0.3)
        C2_px = conic_normalized_to_pixels(fit_conic(xy2), CAM.px, CAM.py, CAM.u0, CAM.v0)
        assert np.abs(on_conic(C2_px, CAM.normalized_to_pixel(xy2))).max() < 1e-9


def test_conic_from_moments_refuses_a_degenerate_blob():
    with pytest.raises(ConicError, match='positive definite'):
        conic_from_moments(np.zeros(2), np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(ValueError):
        conic_from_moments(np.array([np.nan, 0.0]), np.eye(2))


def _random_pose(rng, dist=(0.3, 1.5)):
    ray = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), 1.0])
    return pin.SE3(pin.exp3(rng.normal(size=3) * 2.0),
                   ray / np.linalg.norm(ray) * rng.uniform(*dist))


def _rays(rng, C, n=4000):
    """Random normalized rays (n, 3) around the conic's ellipse (2.5× its box)."""
    x0, x1, y0, y1 = conic_bbox(C)
    cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, 1.25 * (x1 - x0), 1.25 * (y1 - y0)
    return np.column_stack([rng.uniform(cx - hx, cx + hx, n), rng.uniform(cy - hy, cy + hy, n),
                            np.ones(n)])


def _inside(C, rays, centre_ray):
    """Which rays the conic says are inside the silhouette (the centre's side)."""
    val = np.einsum('ni,ij,nj->n', rays, C, rays)
    return val * float(centre_ray @ C @ centre_ray) > 0


def test_ellipsoid_silhouette_separates_the_rays_that_hit_the_body():
    """Inside the conic ⇔ the camera ray meets the ellipsoid (ray-cast in its frame)."""
    rng = np.random.default_rng(3)
    axes = np.array([0.06, 0.055, 0.045])
    for _ in range(30):
        cMo = _random_pose(rng)
        C = ellipsoid_silhouette(cMo, axes)
        assert abs(np.linalg.norm(C) - 1.0) < 1e-12
        rays = _rays(rng, C)
        # ray s·d in the target frame, scaled to the unit sphere: p' = (o + s Rᵀ d)/axes
        oMc = cMo.inverse()
        o = oMc.translation / axes
        d = (rays @ oMc.rotation.T) / axes
        bb = d @ o
        disc = bb * bb - (d * d).sum(axis=1) * (o @ o - 1.0)
        hit = (disc > 0) & (bb < 0)
        inside = _inside(C, rays, cMo.translation)
        clear = np.abs(disc) > 1e-6 * np.abs(disc).max()   # not on the limb itself
        assert hit[clear].any() and (~hit[clear]).any()
        np.testing.assert_array_equal(inside[clear], hit[clear])


def test_sphere_silhouette_is_the_ellipsoid_one_of_equal_axes():
    rng = np.random.default_rng(4)
    for _ in range(20):
        cMo = _random_pose(rng)
        r = rng.uniform(0.02, 0.2)
        S = sphere_silhouette(cMo.translation, r)
        E = ellipsoid_silhouette(cMo, np.full(3, r))
        S = S / np.linalg.norm(S)
        np.testing.assert_allclose(S * np.sign(S[2, 2] * E[2, 2]), E, atol=1e-9)
        # and its rays: inside ⇔ the ray meets the ball
        rays = _rays(rng, S)
        cO = cMo.translation
        bq = rays @ cO
        disc = bq * bq - (rays * rays).sum(axis=1) * (cO @ cO - r * r)
        clear = np.abs(disc) > 1e-6 * np.abs(disc).max()
        np.testing.assert_array_equal(_inside(S, rays, cO)[clear], (disc > 0)[clear])


def test_silhouettes_refuse_a_camera_inside_the_body():
    with pytest.raises(ConicError, match='inside'):
        sphere_silhouette(np.array([0.0, 0.0, 0.05]), 0.06)
    with pytest.raises(ConicError, match='inside'):
        ellipsoid_silhouette(pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.05])),
                             np.array([0.02, 0.02, 0.06]))


def test_circular_cone_fits_the_rays_of_a_ball_silhouette():
    """Rays to the occluding circle of a ball (plain geometry) give b and cos θ back."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        cO = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.3, 1.0)])
        r = 0.05
        d = np.linalg.norm(cO)
        n = cO / d
        e1 = np.cross(n, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        a = rng.uniform(0, 2 * np.pi, 60)
        P = cO * (1 - (r / d) ** 2) + r * np.sqrt(1 - (r / d) ** 2) * (
            np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
        q = (P / np.linalg.norm(P, axis=1, keepdims=True)).T
        b, c = fit_circular_cone(q)
        np.testing.assert_allclose(b, n, atol=1e-9)
        assert c == pytest.approx(np.sqrt(1 - (r / d) ** 2), abs=1e-12)
        b2, c2 = fit_circular_cone(-q[:, ::-1] * -1)             # order does not matter
        np.testing.assert_allclose(b2, n, atol=1e-9)
        assert c2 >= 0
