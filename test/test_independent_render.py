"""
The independent renderer (test/independent_render.py) against plain geometry.

Its images are the detector's ground truth in test_detector_independent.py, so they are
checked here on their own: silhouette areas and centroids against the analytic ellipse of
the sphere's cone, cap areas against the projected cap, noise and texture statistics.
"""
from __future__ import annotations

import math

from independent_render import Ball, Camera, Cap, Checker, Flat, Light, NoiseTexture, render
from independent_scenes import CAMERAS, random_poses, target_ball
import numpy as np
import pytest

from sphere_servo.core.targets import special_sphere

UNIFORM = Light(ambient=1.0, diffuse=0.0, specular=0.0)      # colour = albedo: coverage


def ellipse_of_ball(cam: Camera, cO: np.ndarray, r: float):
    """Area (px²) and centre (px) of a ball's image: the conic of its cone, in pixels."""
    b = cO / np.linalg.norm(cO)
    cos2 = 1 - (r / np.linalg.norm(cO)) ** 2
    C = np.outer(b, b) - cos2 * np.eye(3)                    # normalized coordinates
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    Cp = Ki.T @ C @ Ki
    A = Cp[:2, :2]
    c = -np.linalg.solve(A, Cp[:2, 2])
    k = c @ A @ c - Cp[2, 2]
    return math.pi * abs(k) / math.sqrt(np.linalg.det(A)), c


@pytest.mark.parametrize('name', sorted(CAMERAS))
def test_silhouette_area_and_centroid_match_the_cone(name):
    cam = CAMERAS[name]
    rng = np.random.default_rng(4)
    for _ in range(4):
        u, v = rng.uniform(0.3, 0.7) * cam.width, rng.uniform(0.3, 0.7) * cam.height
        ray = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        cO = ray / np.linalg.norm(ray) * rng.uniform(0.3, 1.0)
        img = render(cam, [Ball(cO, 0.05, (255, 255, 255))], Flat((0, 0, 0)), UNIFORM,
                     noise=None).astype(float)
        cover = img[..., 0] / 255.0
        area, centre = ellipse_of_ball(cam, cO, 0.05)
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        got = np.array([(cover * uu).sum(), (cover * vv).sum()]) / cover.sum()
        assert abs(cover.sum() / area - 1) < 2e-3, (cover.sum(), area)
        assert np.hypot(*(got - centre)) < 0.02, (got, centre)


def test_a_cap_facing_the_camera_has_its_projected_area():
    cam = CAMERAS['vga_f600']
    for deg in (5.0, 9.0, 15.0):
        rho, r, d = math.radians(deg), 0.05, 0.4
        cap = Cap(np.array([0, 0, -1.0]), rho, (0, 0, 0))
        img = render(cam, [Ball(np.array([0, 0, d]), r, (255, 255, 255), (cap,))],
                     Flat((255, 255, 255)), UNIFORM, noise=None).astype(float)
        dark = 1.0 - img[..., 0] / 255.0                     # the cap's coverage
        # the cap's rim is a circle of radius r sin ρ at depth d − r cos ρ
        expect = math.pi * (cam.fx * r * math.sin(rho) / (d - r * math.cos(rho))) ** 2
        assert abs(dark.sum() / expect - 1) < 0.01, (deg, dark.sum(), expect)


def test_noise_is_signal_dependent_and_seeded():
    cam = Camera(600.0, 600.0, 32.0, 24.0, 64, 48)
    a = render(cam, [], Flat((200, 200, 200)), noise=(1.5, 0.02),
               rng=np.random.default_rng(1)).astype(float)
    b = render(cam, [], Flat((20, 20, 20)), noise=(1.5, 0.02),
               rng=np.random.default_rng(1)).astype(float)
    assert a.std() == pytest.approx(math.sqrt(1.5 ** 2 + 0.02 * 200), rel=0.1)
    assert b.std() == pytest.approx(math.sqrt(1.5 ** 2 + 0.02 * 20), rel=0.1)
    c = render(cam, [], Flat((200, 200, 200)), noise=(1.5, 0.02),
               rng=np.random.default_rng(1))
    np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize('tex', [Checker(40, 70, 16.0, 0.3), NoiseTexture(40, 70, 20.0, 5)])
def test_textures_take_their_two_levels(tex):
    cam = Camera(600.0, 600.0, 160.0, 120.0, 320, 240)
    V = render(cam, [], tex, noise=None).max(axis=2).astype(int)
    assert (V == 40).mean() > 0.3 and (V == 70).mean() > 0.3
    assert ((V > 40) & (V < 70)).mean() > 0.01                 # box-filtered edges


def test_poses_keep_the_sphere_in_view_and_the_marks_facing_the_camera():
    target = special_sphere()
    cam = CAMERAS['vga_px450_py480']
    for R, t in random_poses(cam, target, 20, seed=2):
        assert 0.25 <= np.linalg.norm(t) <= 1.0
        img = render(cam, [target_ball(target, R, t)], Flat((0, 0, 0)), UNIFORM, noise=None)
        on = img.max(axis=2) > 0
        assert not (on[0].any() or on[-1].any() or on[:, 0].any() or on[:, -1].any())
        for oP in (target.oP1, target.oP2):
            n, P = R @ (oP / np.linalg.norm(oP)), R @ oP + t
            assert -n @ P / np.linalg.norm(P) > math.cos(math.radians(70.0))
