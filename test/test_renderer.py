"""Ray-cast renderer against the analytic geometry (core.measurement, DESIGN.md §2)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import mark_visible
from sphere_servo.core.targets import balloon, cc_target, special_sphere
from sphere_servo.vision.backgrounds import Distractor
from sphere_servo.vision.renderer import Renderer

CAM = CameraIntrinsics()
BG = 40                                     # the 'flat' background level


def analytic_disc(cMo, target):
    """(H, W) bool: pixel centres inside the silhouette cone ``(bᵀx̄)² ≥ cos²θ ‖x̄‖²``."""
    cO = np.asarray(cMo.translation)
    b = cO / np.linalg.norm(cO)
    cos2 = 1 - (target.radius / np.linalg.norm(cO)) ** 2
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    x, y = (u - CAM.u0) / CAM.px, (v - CAM.v0) / CAM.py
    return (b[0] * x + b[1] * y + b[2]) ** 2 >= cos2 * (x * x + y * y + 1)


def colour_mask(img, rgb, tol=0.08):
    ch = img / np.maximum(img.sum(axis=2, keepdims=True), 1)
    c = np.asarray(rgb, float) / sum(rgb)
    return (np.linalg.norm(ch - c, axis=2) < tol) & (img.max(axis=2) > 60)


@pytest.mark.parametrize('seed', range(5))
def test_silhouette_matches_the_analytic_conic(seed):
    rng = np.random.default_rng(seed)
    target = special_sphere()
    d = rng.uniform(0.25, 1.0)
    ray = np.array([rng.uniform(-.2, .2), rng.uniform(-.15, .15), 1.0])
    cMo = pin.SE3(pin.exp3(rng.normal(size=3)), ray / np.linalg.norm(ray) * d)
    img = Renderer(CAM, target, background='flat').render(cMo)
    truth = analytic_disc(cMo, target)
    mask = img.max(axis=2) > BG + 30    # dark side ≥ ambient·albedo ≫ background
    iou = np.count_nonzero(mask & truth) / np.count_nonzero(mask | truth)
    assert iou > 0.98, iou


def test_edges_are_anti_aliased():
    target = special_sphere()
    cMo = pin.SE3(np.eye(3), np.array([0.01, 0.0, 0.4]))
    img = Renderer(CAM, target, background='flat').render(cMo).astype(int)
    row = img[240, :, 0]
    # between background (40) and the body there are intermediate levels at the limb
    inter = np.count_nonzero((row > BG + 5) & (row < row.max() * 0.5))
    assert inter >= 1


def test_dark_side_stays_well_above_background():
    target = special_sphere()
    cMo = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.4]))
    ren = Renderer(CAM, target, background='flat', light_dir=(1.0, 0.0, 0.0))  # side light
    img = ren.render(cMo)
    disc = analytic_disc(cMo, target)
    inner = disc & np.roll(disc, 3, 1) & np.roll(disc, -3, 1) & np.roll(disc, 3, 0) \
        & np.roll(disc, -3, 0)
    assert img.max(axis=2)[inner].min() > BG + 60


def test_far_side_mark_hidden_and_near_side_mark_shown():
    target = special_sphere()
    ren = Renderer(CAM, target, background='flat')
    front = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.4]))           # marks face the camera
    back = pin.SE3(pin.exp3(np.array([np.pi, 0, 0])), np.array([0.0, 0.0, 0.4]))
    assert mark_visible(front, target, 'P2') and not mark_visible(back, target, 'P2')
    assert colour_mask(ren.render(front), target.colors['P2']).sum() > 50
    assert colour_mask(ren.render(back), target.colors['P2']).sum() == 0


def test_mark_is_foreshortened():
    """A cap seen obliquely covers fewer pixels than the same cap seen frontally."""
    target = special_sphere()
    ren = Renderer(CAM, target, background='flat')
    n1 = target.oP1 / np.linalg.norm(target.oP1)
    # rotate so that P1 faces the camera (−z), then tilt it by 60°
    R0 = pin.Quaternion.FromTwoVectors(n1, np.array([0, 0, -1.0])).matrix()
    areas, expect = [], []
    for tilt in (0.0, np.radians(60)):
        cMo = pin.SE3(pin.exp3(np.array([0, tilt, 0])) @ R0, np.array([0, 0, 0.4]))
        areas.append(colour_mask(ren.render(cMo), target.colors['P1']).sum())
        # solid angle of a small patch: cos(incidence) / distance²
        P = cMo.act(target.oP1)
        n = cMo.rotation @ n1
        expect.append(-(n @ P) / np.linalg.norm(P) ** 3)
    ratio = (areas[1] / areas[0]) / (expect[1] / expect[0])
    assert 0.85 < ratio < 1.15, ratio


def test_cc_tip_occluded_when_behind_the_sphere():
    target = cc_target()
    ren = Renderer(CAM, target, background='flat')
    tip = target.colors['P2']
    rng = np.random.default_rng(1)
    seen = {True: 0, False: 0}
    for _ in range(400):
        cMo = pin.SE3(pin.exp3(rng.normal(size=3) * 2), np.array([0.0, 0.0, 0.4]))
        vis = mark_visible(cMo, target, 'P3')
        if seen[vis] >= 3:
            continue
        # only clear cases: tip well hidden or well in view (not half-occluded)
        P3 = cMo.act(target.oP2)
        q = P3 / np.linalg.norm(P3)
        cO = cMo.translation
        ang = np.degrees(np.arccos(q @ cO / np.linalg.norm(cO)))
        edge = np.degrees(np.arcsin(target.radius / np.linalg.norm(cO)))
        if abs(ang - edge) < 3:
            continue
        n = colour_mask(ren.render(cMo), tip).sum()
        assert (n > 20) if vis else (n == 0), (vis, n)
        seen[vis] += 1
    assert seen[True] == 3 and seen[False] == 3


def test_deterministic_given_seed():
    target = special_sphere()
    cMo = pin.SE3(np.eye(3), np.array([0.02, 0.0, 0.5]))
    a = Renderer(CAM, target, noise_sigma=3.0, seed=7).render(cMo)
    b = Renderer(CAM, target, noise_sigma=3.0, seed=7).render(cMo)
    c = Renderer(CAM, target, noise_sigma=3.0, seed=8).render(cMo)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)


def test_background_is_not_flat_and_options_apply():
    target = special_sphere()
    behind = pin.SE3(np.eye(3), np.array([0.0, 0.0, -1.0]))
    bg = Renderer(CAM, target).render(behind)
    assert bg.shape == (480, 640, 3) and bg.dtype == np.uint8
    assert bg.std() > 3
    cMo = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.5]))
    bright = Renderer(CAM, target, background='flat').render(cMo)
    dim = Renderer(CAM, target, background='flat', gain=0.6).render(cMo)
    assert dim[240, 320].max() < 0.7 * bright[240, 320].max()
    blur = Renderer(CAM, target, background='flat', blur_sigma=2.0).render(cMo)
    assert np.abs(np.diff(blur[240].astype(int), axis=0)).max() \
        < np.abs(np.diff(bright[240].astype(int), axis=0)).max()
    with pytest.raises(ValueError):
        Renderer(CAM, target, noise_sigma=-1.0)
    with pytest.raises(ValueError):
        Renderer(CAM, target).render(pin.SE3(np.eye(3), np.array([np.nan, 0, 1.0])))


def test_balloon_silhouette_is_wider_along_its_long_axis():
    target = balloon(axes=(0.08, 0.04, 0.04))
    img = Renderer(CAM, target, background='flat').render(
        pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.5])))
    mask = img.max(axis=2) > BG + 30
    w = np.count_nonzero(mask.any(axis=0))
    h = np.count_nonzero(mask.any(axis=1))
    # semi-axes 0.08 and 0.04 at 0.5 m, px = 600: ≈ 192 and 96 px
    assert abs(w - 2 * 600 * 0.08 / 0.5) < 6 and abs(h - 2 * 600 * 0.04 / 0.5) < 6


@pytest.mark.parametrize('kind', ['checker', 'noise'])
def test_two_level_textures_have_their_levels_and_soft_edges(kind):
    """max(R, G, B) of a two-level texture is lo or hi, box-filtered at the edges."""
    target = special_sphere()
    behind = pin.SE3(np.eye(3), np.array([0.0, 0.0, -1.0]))
    img = Renderer(CAM, target, background=kind, levels=(40, 70), texture_px=20,
                   seed=3).render(behind)
    V = img.max(axis=2).astype(int)
    lo, hi = np.abs(V - 40) <= 1, np.abs(V - 70) <= 1
    assert lo.mean() > 0.3 and hi.mean() > 0.3, (lo.mean(), hi.mean())
    mixed = (V > 42) & (V < 68)
    assert 0.005 < mixed.mean() < 0.2, mixed.mean()             # anti-aliased edges
    other = Renderer(CAM, target, background=kind, levels=(40, 70), texture_px=20,
                     seed=4).render(behind)
    assert np.mean(other != img) > 0.1                           # the seed moves it
    with pytest.raises(ValueError, match='levels'):
        Renderer(CAM, target, background=kind, levels=(40, 300))


def test_distractors_are_drawn_where_they_project_and_behind_the_target():
    target = special_sphere()
    ball = Distractor('sphere', (-0.1, 0.05, 0.6), 0.04, (250, 250, 250))
    disc = Distractor('disc', (0.12, -0.08, 0.7), 0.05, (200, 250, 200))
    # the target in front of part of the ball
    cMo = pin.SE3(np.eye(3), np.array([-0.03, 0.05, 0.45]))
    ren = Renderer(CAM, target, background='flat', distractors=[ball, disc])
    img = ren.render(cMo).astype(int)
    empty = Renderer(CAM, target, background='flat', distractors=[ball, disc]).render(
        pin.SE3(np.eye(3), np.array([0.0, 0.0, -1.0]))).astype(int)
    ball_mask = analytic_disc(pin.SE3(np.eye(3), np.asarray(ball.centre)), special_sphere(0.04))
    seen = empty.max(axis=2) > BG + 30
    inter = np.count_nonzero(seen & ball_mask)
    # the disc is a little larger than the ball of its radius: compare the ball only
    near_ball = np.zeros_like(seen)
    near_ball[:, :320] = True
    iou = inter / np.count_nonzero((seen & near_ball) | ball_mask)
    assert iou > 0.98, iou
    # the flat disc has its colour inside, no shading
    (u, v), = CAM.project(np.asarray(disc.centre)[None])
    np.testing.assert_array_equal(empty[int(v), int(u)], (200, 250, 200))
    # the target covers the ball where they overlap (the ball is drawn behind it): there
    # the image is the target's alone, away from its anti-aliased rim
    alone = Renderer(CAM, target, background='flat').render(cMo).astype(int)
    body = analytic_disc(cMo, target)
    inner = body & np.roll(body, 2, 0) & np.roll(body, -2, 0) & np.roll(body, 2, 1) \
        & np.roll(body, -2, 1)
    overlap = inner & ball_mask
    assert np.count_nonzero(overlap) > 200
    np.testing.assert_array_equal(img[overlap], alone[overlap])
    assert np.any(img[ball_mask & ~body] != alone[ball_mask & ~body])
    with pytest.raises(ValueError, match='in front'):
        Distractor('sphere', (0.0, 0.0, 0.01), 0.05)
    with pytest.raises(ValueError, match='kind'):
        Distractor('cube', (0.0, 0.0, 1.0), 0.05)


@pytest.mark.parametrize('deg', [5.0, 9.0, 15.0])
def test_cap_radius_comes_from_the_target(deg):
    """A cap facing the camera images as a disc of radius ≈ f r sin ρ / (d − r cos ρ)."""
    target = special_sphere(mark_radius_deg=deg)
    n1 = target.oP1 / np.linalg.norm(target.oP1)
    R = pin.Quaternion.FromTwoVectors(n1, np.array([0, 0, -1.0])).matrix()
    d = 0.4
    img = Renderer(CAM, target, background='flat').render(pin.SE3(R, np.array([0, 0, d])))
    # coverage of each pixel near the cap: pixel = a·mark + b·body (least squares), a/(a+b)
    rho, r = np.radians(deg), target.radius
    R_px = CAM.px * r * np.sin(rho) / (d - r * np.cos(rho))
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    near = np.hypot(u - CAM.u0, v - CAM.v0) < R_px + 4
    M = np.column_stack([target.colors['P1'], target.colors['body']]).astype(float)
    ab = np.linalg.lstsq(M, img[near].astype(float).T, rcond=None)[0]
    area = np.clip(ab[0] / (ab[0] + ab[1]), 0, 1).sum()
    assert abs(area / (np.pi * R_px ** 2) - 1) < 0.05, (area, np.pi * R_px ** 2)
