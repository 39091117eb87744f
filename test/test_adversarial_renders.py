"""
Adversarial renders for the detector, from the independent renderer: the truth or nothing.

Classes the other adversarial tests do not cover, seeded, with the truth from the scene:

- a second body-coloured sphere (no marks) overlapping the target's image, in front of it
  or behind it;
- a thin cable across the sphere through a mark: of a random colour, or of a mark's colour
  (dark or bright);
- a gamma curve (1.6–2.6), or one of 0.4–2.5 with under- or over-exposure and strong
  sensor noise;
- the whole frame degraded: defocus, very low JPEG quality with chroma subsampling,
  lateral chromatic aberration (the red and blue channels shifted by up to 1.5 px each
  way), a white balance off by ±40 % per channel, a strong specular highlight.

A frame may give "not found" or a mark not visible; a found sphere and every visible mark
must be where the truth puts them, within the tolerances of
``test_adversarial_detector`` (its :func:`wrong`: the sphere's direction and half-angle
within 2 px / f, a mark's ray within 3 px / f).
"""
from __future__ import annotations

import math

import cv2
from independent_render import Ball, Light, render
from independent_scenes import random_light, target_ball, textured_background
import numpy as np
import pytest

from sphere_servo.vision.reasons import Reason
from test_adversarial_detector import CAM, judge, pose, TARGET, true_mark_rays


def _hides(ball: Ball, P: np.ndarray) -> bool:
    """Tell whether ``ball`` lies on the line of sight to the point P, in front of it."""
    d = P / np.linalg.norm(P)
    c = np.asarray(ball.centre, float)
    tc = float(d @ c)
    return 0 < tc < np.linalg.norm(P) and np.linalg.norm(c - tc * d) < ball.radius


def twin(rng, t) -> Ball:
    """Draw a body-coloured ball (0.6–1.4 r) overlapping the target's image, nearer or not."""
    d = float(np.linalg.norm(t))
    e = np.cross(t / d, rng.normal(size=3))
    e /= np.linalg.norm(e)
    scale = rng.uniform(0.8, 1.3)
    C = t + e * TARGET.radius * rng.uniform(1.0, 1.9)
    return Ball(C / np.linalg.norm(C) * d * scale, TARGET.radius * rng.uniform(0.6, 1.4),
                TARGET.colors['body'])


def twin_frames(n: int, seed: int):
    """
    Yield frames ``(image, R, t)`` of the target and an overlapping body-coloured ball.

    Of ``n`` drawn, those where the ball does not hide both marks: with no mark in view, a
    lone markless sphere is what the detector may publish as the target.
    """
    rng = np.random.default_rng(seed)
    for _ in range(n):
        bg = textured_background(rng)
        R, t = pose(rng)
        light = random_light(rng)
        ball = twin(rng, t)
        img = render(CAM, [target_ball(TARGET, R, t), ball], bg, light, rng=rng)
        if not all(_hides(ball, q * np.linalg.norm(t)) for q in true_mark_rays(R, t).values()):
            yield img, R, t


def cable(x: np.ndarray, rng, through: np.ndarray, colour: np.ndarray) -> np.ndarray:
    """Draw an anti-aliased straight cable 1–6 px wide through the pixel ``through``."""
    H, W = x.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    a, w = rng.uniform(0, math.pi), rng.uniform(0.5, 3.0)
    d = np.abs((u - through[0]) * math.sin(a) - (v - through[1]) * math.cos(a))
    cov = np.clip(w - d + 0.5, 0, 1)[..., None]
    return x * (1 - cov) + colour * cov


def _shift(ch: np.ndarray, M) -> np.ndarray:
    return cv2.warpAffine(ch, np.float32(M), (ch.shape[1], ch.shape[0]),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def degrade(x: np.ndarray, kind: str, rng, R, t) -> np.ndarray:
    """Apply one class of degradation to a float rgb frame."""
    if kind in ('cable', 'mark_cable'):
        name = 'P1' if rng.random() < 0.5 else 'P2'
        through = CAM.project(true_mark_rays(R, t)[name][None])[0] + rng.uniform(-5, 5, 2)
        col = rng.uniform(0, 255, 3) if kind == 'cable' else \
            np.asarray(TARGET.colors[name], float) * rng.uniform(0.4, 1.0)
        x = cable(x, rng, through, col)
    elif kind == 'defocus':
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(1.0, 5.0))
    elif kind == 'exposure':            # gain 0.25–3, gamma 0.4–2.5, noise σ 2–10
        gain = math.exp(rng.uniform(math.log(0.25), math.log(3.0)))
        x = 255 * np.clip(x * gain / 255, 0, 1) ** rng.uniform(0.4, 2.5)
        x += rng.normal(0, rng.uniform(2, 10), x.shape)
    elif kind == 'gamma':               # a gamma curve of 1.6–2.6 (the frame not sRGB)
        x = 255 * np.clip(x / 255, 0, 1) ** rng.uniform(1.6, 2.6)
    elif kind in ('chromatic', 'chromatic_strong'):    # red and blue shifted opposite ways
        a = 1.5 if kind == 'chromatic' else 2.5
        dx, dy = rng.uniform(-a, a, 2)
        x[..., 0] = _shift(x[..., 0], [[1, 0, dx], [0, 1, dy]])
        x[..., 2] = _shift(x[..., 2], [[1, 0, -dx], [0, 1, -dy]])
    elif kind == 'white_balance':
        x *= rng.uniform(0.6, 1.4, 3)
    elif kind == 'jpeg_low':
        img = np.clip(np.rint(x), 0, 255).astype(np.uint8)
        _, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(2, 12))])
        x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def frames(kind: str, n: int, seed: int):
    """Yield ``n`` seeded frames ``(image, R, t)`` of one class."""
    if kind == 'twin':
        yield from twin_frames(n, seed)
        return
    rng = np.random.default_rng(seed)
    for _ in range(n):
        bg = textured_background(rng)
        R, t = pose(rng)
        light = random_light(rng)
        if kind == 'specular':          # a strong, sharp or broad highlight
            light = Light(direction=light.direction, specular=rng.uniform(0.3, 0.9),
                          shininess=rng.uniform(8, 80))
        img = render(CAM, [target_ball(TARGET, R, t)], bg, light, rng=rng)
        yield degrade(img.astype(np.float32), kind, rng, R, t), R, t


def run(kind: str, n: int, seed: int) -> tuple[list, int, list]:
    """Detect every frame of a class: the wrong ones (index, why), the found count, all."""
    return judge(frames(kind, n, seed))


# --- a second body-coloured sphere overlapping the target ---------------------------------
def test_a_body_coloured_sphere_overlapping_the_target_is_not_published_as_it():
    """
    A markless body-coloured ball beside the target, their images overlapping.

    The ball in front hid the target's outline and won as a sphere without marks (its
    marks "not found"): published 74–137 px off in direction, 15–22 px in half-angle.
    Behind a larger target, it won with the target's P2, seen at its limb, as its own:
    96 px off. A sphere that lacks marks whose colours are seen beside it is ambiguous.
    """
    bad, found, dets = run('twin', 60, 3)
    assert not bad, bad
    assert found >= 5, found
    beside = [d for d in dets if not d.found and d.not_detected.reason is Reason.AMBIGUOUS]
    assert beside, 'no frame was refused as ambiguous'


# --- a cable across the sphere --------------------------------------------------------------
@pytest.mark.parametrize('seed', [1, 3])
def test_a_cable_of_a_marks_colour_across_it_does_not_move_the_mark(seed):
    """
    A thin cable of a mark's colour (dark or bright) through that mark.

    The cable joined the mark's blob, whose filled convex hull (cap and cable) was then
    measured as a cap cut by the limb: 2 and 7 of 40 frames (seeds 1, 3) published a
    mark 5–47 px off. A mark whose pixels spread beyond the cap its centre predicts is
    lost; the frame is then mostly refused (the mark's colour is seen beside the sphere).
    """
    bad, _, _ = run('mark_cable', 40, seed)
    assert not bad, bad


def test_a_cable_across_a_mark_gives_the_truth_or_nothing():
    """A cable of a random colour through a mark: an occluder, not part of the mark."""
    bad, found, _ = run('cable', 40, 1)
    assert not bad, bad
    assert found >= 15, found


# --- a gamma curve ------------------------------------------------------------------------
@pytest.mark.parametrize('kind,seed', [('gamma', 1), ('exposure', 6)])
def test_a_gamma_curve_does_not_move_a_cap_cut_by_the_limb(kind, seed):
    """
    A frame through a gamma curve (with a gain and noise, for 'exposure').

    The marks' coverage is unmixed linearly from the mark's and the body's colours: under
    a gamma curve the mixed pixels on a cap's rim are misjudged, and a cap cut by the limb,
    measured from its rim, came out wrong: here P1 4.9 and 3.7 px ('gamma'), 5.7 and
    3.3 px ('exposure') off; γ = 2.2 alone, 4–9 marks in 50 frames, 3.1–8.2 px. A
    rim-fitted cap must cover at least ``min_seen`` of the visible part its centre
    predicts (0.98–1.02 on linear frames, 0.13–0.67 on those wrong ones).
    """
    bad, _, _ = run(kind, 40, seed)
    assert not bad, bad


# --- whole-frame degradations ---------------------------------------------------------------
@pytest.mark.parametrize('kind', ['defocus', 'jpeg_low', 'chromatic', 'white_balance',
                                  'specular'])
def test_degraded_frames_give_the_truth_or_nothing(kind):
    """Defocus, JPEG at quality 2–11, chromatic aberration, white balance, a highlight."""
    bad, _, _ = run(kind, 25, 11)
    assert not bad, bad


@pytest.mark.xfail(strict=True, reason='chromatic aberration of ±2.5 px per channel (red and '
                   'blue 5 px apart) widens the silhouette along the shift: sphere b '
                   '2.19–2.29 px off (tolerance 2), half-angle up to 2.28 px, in 4 of 160 '
                   'frames (seeds 1–4): the edge is of V = max(R, G, B), the union of the '
                   'shifted channels')
def test_strong_chromatic_aberration_gives_the_truth_or_nothing():
    """Red and blue shifted by up to 2.5 px each way: the sphere within its tolerance."""
    bad, _, _ = run('chromatic_strong', 40, 2)
    assert not bad, bad
