"""
Adversarial frames for the detector, from the independent renderer: right or nothing.

Classes of frame, seeded: the sphere cut by the image border (its centre near or beyond
it), its marks cut by the border, clipped whites (an over-exposed frame), an opaque bar in
front, vignetting, a lighting gradient, JPEG blocks, salt-and-pepper noise, motion blur, a
far target, a background textured in the body's colour, two targets. A frame may give "not
found"; a found sphere and every visible mark must be where the truth (the pose) puts them.

Tolerances, from the pixel error of a limb and a cap's rim (``f`` = 600 px):

- the sphere: its centre's direction ``b`` and its cone's half-angle ``asin r_δ`` within
  2 px / f rad each (2 px on the limb at the image centre, less off axis);
- a mark: its ray within 3 px / f rad of the true centre's (the sphere's 2 px, plus a
  cap's rim to 1 px).
"""
from __future__ import annotations

import math

import cv2
from independent_render import Camera, Checker, render
from independent_scenes import (incidence, random_light, random_rotation, target_ball,
                                textured_background)
import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import special_sphere
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.reasons import Reason

TARGET = special_sphere()
CAM = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
INTR = CameraIntrinsics(600.0, 600.0, 320.0, 240.0, 640, 480)
SPHERE_TOL = 2.0 / CAM.fx       # rad
MARK_TOL = 3.0 / CAM.fx         # rad


def angle(a, b) -> float:
    """Angle (rad) between two vectors."""
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b)))


def pose(rng, dist=(0.25, 1.0), uv=None, facing=True):
    """Draw (R, t): the centre's pixel uniform (or from ``uv(rng)``), marks facing if asked."""
    while True:
        d = rng.uniform(*dist)
        u, v = (rng.uniform(0, CAM.width), rng.uniform(0, CAM.height)) if uv is None \
            else uv(rng)
        ray = np.array([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, 1.0])
        t = ray / np.linalg.norm(ray) * d
        R = random_rotation(rng)
        if not facing or all(incidence(R, t, oP) < math.radians(70)
                             for oP in (TARGET.oP1, TARGET.oP2)):
            return R, t


def near_border(rng):
    """Return a centre pixel within 30 px inside to 60 px outside the left or right border."""
    u = rng.choice([rng.uniform(-60, 30), rng.uniform(CAM.width - 30, CAM.width + 60)])
    return u, rng.uniform(0, CAM.height)


def true_mark_rays(R, t) -> dict:
    """Name → the unit ray of the cap's centre (the surface point of the mark)."""
    out = {}
    for name, oP in (('P1', TARGET.oP1), ('P2', TARGET.oP2)):
        P = R @ (oP / np.linalg.norm(oP) * TARGET.radius) + t
        out[name] = P / np.linalg.norm(P)
    return out


def errors(det, R, t) -> tuple[float, float, dict]:
    """Measure the found sphere's b and half-angle errors and each mark's, in rad."""
    b = t / np.linalg.norm(t)
    rd = TARGET.radius / np.linalg.norm(t)
    eb = angle(det.sphere.b, b)
    eth = abs(math.asin(det.sphere.r_delta) - math.asin(rd))
    em = {n: angle(det.marks[n].ray, q) for n, q in true_mark_rays(R, t).items()
          if det.marks.get(n) is not None and det.marks[n].visible}
    return eb, eth, em


def wrong(det, R, t) -> str:
    """Say why a found detection is off the truth; empty if it is right or not found."""
    if not det.found:
        return ''
    eb, eth, em = errors(det, R, t)
    bad = []
    if eb > SPHERE_TOL or eth > SPHERE_TOL:
        bad.append(f'sphere b {eb * CAM.fx:.2f} px, half-angle {eth * CAM.fx:.2f} px')
    bad += [f'{n} {e * CAM.fx:.2f} px' for n, e in em.items() if e > MARK_TOL]
    return ', '.join(bad)


def degrade(img: np.ndarray, kind: str, rng) -> np.ndarray:
    """Apply one class of degradation to an rgb8 frame."""
    x = img.astype(np.float32)
    H, W = x.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    if kind == 'saturated':             # over-exposed: every level × 1.5–3, clipped
        x *= rng.uniform(1.5, 3.0)
    elif kind == 'vignetting':          # cos⁴ of the off-axis angle, and a dimmer frame
        r = np.hypot(u - CAM.cx, v - CAM.cy) / CAM.fx
        x *= (np.cos(np.arctan(r)) ** 4 * rng.uniform(0.4, 1.0))[..., None]
    elif kind == 'gradient':            # a linear light ramp ±30–80 % across the frame
        a = rng.uniform(0, 2 * math.pi)
        ramp = ((u - CAM.cx) * math.cos(a) + (v - CAM.cy) * math.sin(a)) / 400
        g = 1 + rng.uniform(0.3, 0.8) * ramp
        x *= g[..., None]
    elif kind == 'salt_pepper':
        p, m = rng.uniform(0.005, 0.05), rng.random((H, W))
        x[m < p / 2] = 0
        x[m > 1 - p / 2] = 255
    elif kind == 'jpeg':
        _, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(5, 30))])
        x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32)
    elif kind == 'motion_blur':         # a line kernel of 5–25 px
        n, a = int(rng.integers(5, 25)), rng.uniform(0, math.pi)
        k = np.zeros((n, n), np.float32)
        c = (n - 1) / 2
        for s in np.linspace(-c, c, 4 * n):
            k[int(round(c + s * math.sin(a))), int(round(c + s * math.cos(a)))] = 1
        x = cv2.filter2D(x, -1, k / k.sum())
    elif kind == 'bar':                 # an opaque bar in front, 6–80 px wide
        a, w = rng.uniform(0, math.pi), rng.uniform(3, 40)
        c0 = rng.uniform(0, W), rng.uniform(0, H)
        d = np.abs((u - c0[0]) * math.sin(a) - (v - c0[1]) * math.cos(a))
        x[d < w] = (rng.uniform(0, 255, 3) if rng.random() < 0.5
                    else np.full(3, rng.uniform(20, 250)))
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def frames(kind: str, n: int, seed: int):
    """Yield ``n`` seeded frames ``(image, R, t)`` of one class."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        bg = textured_background(rng)
        if kind == 'border':
            R, t = pose(rng, uv=near_border, facing=False)
        elif kind == 'far':
            R, t = pose(rng, dist=(2.0, 12.0), facing=False)
        else:
            R, t = pose(rng)
        if kind == 'body_texture':      # a checkerboard about the body's own level
            lv = max(TARGET.colors['body'])
            bg = Checker(lv * rng.uniform(0.5, 0.9), lv * rng.uniform(0.95, 1.1),
                         float(rng.uniform(6, 40)), float(rng.uniform(0, 3)))
        img = render(CAM, [target_ball(TARGET, R, t)], bg, random_light(rng), rng=rng)
        if kind not in ('border', 'far', 'body_texture'):
            img = degrade(img, kind, rng)
        yield img, R, t


def judge(seq) -> tuple[list, int, list]:
    """Detect frames ``(image, R, t)``: the wrong ones (index, why), the found count, all."""
    det = Detector.for_target(TARGET)
    bad, found, out = [], 0, []
    for i, (img, R, t) in enumerate(seq):
        d = det.detect(img, 'rgb8', INTR)
        found += d.found
        why = wrong(d, R, t)
        if why:
            bad.append((i, why))
        out.append(d)
    return bad, found, out


def run(kind: str, n: int, seed: int) -> tuple[list, int]:
    """Detect every frame of a class; return the wrong ones (index, why) and the found count."""
    return judge(frames(kind, n, seed))[:2]


# --- the sphere cut by the border ---------------------------------------------------------
def test_a_sphere_cut_by_the_border_is_measured_within_the_limb_tolerance():
    """
    A sphere whose centre is near or beyond the border, a short arc of its limb in view.

    A general conic (5 parameters) fitted to that arc measured s_n,t 2–4 % off with a
    0.08 px residual; the sphere's cone (3 parameters) fits it right.
    """
    bad, found = run('border', 60, 2)
    assert found >= 25, found
    assert not bad, bad


# --- a mark cut by the border -------------------------------------------------------------
def test_a_mark_cut_by_the_image_border_is_lost_not_measured_from_its_visible_part():
    """
    A cap whose centre is beyond the border: its visible sliver's mean is not its centre.

    The frame (the sphere's centre 16 px inside the left border, P2's centre at u = −23)
    gave P2 at u = 0.3, 17 px off, as a whole mark.
    """
    *_, (img, R, t) = frames('border', 53, 2)
    uv = INTR.project(true_mark_rays(R, t)['P2'][None])[0]
    assert uv[0] < -10.0                             # P2's centre is outside the image
    d = Detector.for_target(TARGET).detect(img, 'rgb8', INTR)
    assert d.found and not wrong(d, R, t), wrong(d, R, t)
    m = d.marks['P2']
    assert not m.visible and m.missing.reason is Reason.MARK_CUT_BY_BORDER, m


# --- degraded frames ----------------------------------------------------------------------
def test_clipped_whites_do_not_move_a_mark():
    """
    An over-exposed frame: a mark's saturated inside is no longer its colour.

    Only its anti-aliased rim was classified (68 px of a ~900 px cap) and measured as the
    whole mark, 12 px off; a whole cap must cover most of the painted cap's area.
    """
    for seed in (2, 3):
        bad, found = run('saturated', 60, seed)
        assert found >= 30, found
        assert not bad, (seed, bad)


@pytest.mark.parametrize('kind', ['bar', 'vignetting', 'gradient', 'jpeg', 'salt_pepper',
                                  'motion_blur', 'far', 'body_texture'])
def test_degraded_frames_give_the_truth_or_nothing(kind):
    bad, _ = run(kind, 30, 7)
    assert not bad, bad


def test_two_targets_give_one_of_them_wholly_never_a_mix():
    """
    Two special spheres in view: the sphere and both marks of the same one, or nothing.

    (Which one is the candidate search's order: two identical targets are not told apart.)
    """
    rng = np.random.default_rng(5)
    det = Detector.for_target(TARGET)
    whole = 0
    for _ in range(30):
        bg = textured_background(rng)
        (R1, t1), (R2, t2) = pose(rng), pose(rng)
        if np.linalg.norm(t1 - t2) < 3 * TARGET.radius:
            continue
        img = render(CAM, [target_ball(TARGET, R1, t1), target_ball(TARGET, R2, t2)], bg,
                     random_light(rng), rng=rng)
        d = det.detect(img, 'rgb8', INTR)
        if d.found:
            w1, w2 = wrong(d, R1, t1), wrong(d, R2, t2)
            assert not w1 or not w2, (w1, w2)
            whole += all(m.visible for m in d.marks.values())
    assert whole >= 15, whole
