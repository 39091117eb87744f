"""
Adversarial inputs for the red/blue swap check (``sphere_servo/vision/swap.py``).

An rgb8 buffer labelled bgr8 turns the special sphere's red P1 and blue P2 into each other;
the detector must then report no mark more than 2 px from where the right label puts it
(nor one the right label does not report), and must never refuse a rightly labelled frame
with ``COLOURS_SWAPPED`` (the servo would stop for nothing). Each class of input is a
scene family of the independent renderer (test/independent_render.py: its own shading,
supersampling, textures, lights, noise) or of the project's renderer (the CC target, the
balloon), 12 seeded frames, passed through an image transform (white balance and coloured
light, gamma, exposure, sensor noise, chroma subsampling, JPEG, Bayer demosaicing, motion
blur, black level), then detected three ways: rgb8 (the truth), the same buffer labelled
bgr8 (the swap) and converted to bgr8 and labelled so (a right bgr8 camera).

The strict xfails are the classes no colour rule can decide, with the figures that say why
(README, "Detection").
"""
from __future__ import annotations

import functools
import math

import cv2
from independent_render import background_image, Ball, Disc, Flat, Light, render
from independent_scenes import (CAMERAS, random_light, random_poses, target_ball,
                                textured_background, wide_scenes)
import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import balloon, cc_target, special_sphere
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.poses import random_poses as project_poses
from sphere_servo.vision.reasons import Reason
from sphere_servo.vision.renderer import Renderer
from wide_cameras import twin, WIDE

# about a minute of rendering and detection on two cores
pytestmark = pytest.mark.slow

ICAM = CAMERAS['vga_f600']
CAM = CameraIntrinsics()
SP = special_sphere()
N = 12
RED, BLUE = (220, 30, 30), (30, 60, 220)


# --- image transforms on uint8 rgb ----------------------------------------------------------
def _u8(x) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _gains(g):
    return lambda im: _u8(im.astype(np.float32) * np.float32(g))


def _gamma(g):
    return lambda im: _u8(255.0 * (im / 255.0) ** g)


def _noise(sigma):
    return lambda im: _u8(im + np.random.default_rng(0).normal(0.0, sigma, im.shape))


def _chroma(fy: int):
    """Chroma (YCrCb) averaged over 2 × ``fy`` pixels and interpolated back (4:2:0, 4:2:2)."""
    def t(im):
        ycc = cv2.cvtColor(im, cv2.COLOR_RGB2YCrCb)
        h, w = im.shape[:2]
        for c in (1, 2):
            small = cv2.resize(ycc[..., c], (w // 2, h // fy), interpolation=cv2.INTER_AREA)
            ycc[..., c] = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        return cv2.cvtColor(ycc, cv2.COLOR_YCrCb2RGB)
    return t


def _jpeg(q: int):
    def t(im):
        _, buf = cv2.imencode('.jpg', im[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, q])
        return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    return t


def _bayer(code):
    """RGGB mosaic of the frame, then OpenCV's demosaicing (a raw camera's pipeline)."""
    def t(im):
        raw = np.empty(im.shape[:2], np.uint8)
        raw[0::2, 0::2], raw[0::2, 1::2] = im[0::2, 0::2, 0], im[0::2, 1::2, 1]
        raw[1::2, 0::2], raw[1::2, 1::2] = im[1::2, 0::2, 1], im[1::2, 1::2, 2]
        return np.ascontiguousarray(cv2.cvtColor(raw, code))
    return t


def _blur(n: int, deg: float):
    k = np.zeros((n, n), np.float32)
    k[n // 2] = 1.0
    k = cv2.warpAffine(k, cv2.getRotationMatrix2D((n / 2 - 0.5, n / 2 - 0.5), deg, 1.0), (n, n))
    return lambda im: cv2.filter2D(im, -1, k / k.sum())


def _chain(*ts):
    return lambda im: functools.reduce(lambda x, t: t(x), ts, im)


T = {'id': lambda im: im, 'warm': _gains((1.2, 1.0, 0.8)), 'cool': _gains((0.8, 1.0, 1.2)),
     'green': _gains((0.9, 1.15, 0.9)), 'magenta': _gains((1.15, 0.85, 1.15)),
     'gamma0.6': _gamma(0.6), 'gamma1.5': _gamma(1.5), 'gamma2.2': _gamma(2.2),
     'over1.6': _gains((1.6,) * 3), 'over2.5': _gains((2.5,) * 3),
     'under0.35': _gains((0.35,) * 3), 'noise5': _noise(5.0), 'noise10': _noise(10.0),
     'c420': _chroma(2), 'c422': _chroma(1), 'jpeg80': _jpeg(80), 'jpeg50': _jpeg(50),
     'bayer': _bayer(cv2.COLOR_BayerBG2RGB), 'bayer_ea': _bayer(cv2.COLOR_BayerBG2RGB_EA),
     'blur5': _blur(5, 30.0), 'black20': lambda im: _u8((im - 20.0) * 255.0 / 235.0),
     'warm_over': _chain(_gains((1.2, 1.0, 0.8)), _gains((1.6,) * 3)),
     'jpeg70_bayer': _chain(_bayer(cv2.COLOR_BayerBG2RGB), _jpeg(70))}


# --- scene families -------------------------------------------------------------------------
def _scenes(target, seed, dist=(0.25, 1.0), maxinc=70.0, light=None, extra=None):
    """Frames of the independent renderer: textured background, a light, sensor noise."""
    rng = np.random.default_rng(seed + 7919)
    for R, t in random_poses(ICAM, target, N, seed, maxinc, dist=dist):
        bg = textured_background(rng)
        objs = [target_ball(target, R, t)] + ([] if extra is None else extra(rng, R, t))
        yield render(ICAM, objs, bg, random_light(rng) if light is None else light(rng),
                     rng=rng)


def _two_lights(target, seed, c1, c2):
    """Yield frames lit by a key light of colour ``c1`` and a fill light of colour ``c2``."""
    rng = np.random.default_rng(seed + 17)
    black = Flat((0.0, 0.0, 0.0))
    for R, t in random_poses(ICAM, target, N, seed, 70.0):
        bg = textured_background(rng)
        objs = [target_ball(target, R, t)]
        d1 = np.array([rng.uniform(-0.9, 0.9), rng.uniform(-0.9, 0.9), -1.0])
        d2 = np.array([-d1[0], -d1[1], -0.6])
        key = render(ICAM, objs, black, Light(direction=d1 / np.linalg.norm(d1),
                                              ambient=0.2, diffuse=0.6), noise=None)
        fill = render(ICAM, objs, black, Light(direction=d2 / np.linalg.norm(d2),
                                               ambient=0.15, diffuse=0.5, specular=0.0),
                      noise=None)
        # coverage of the sphere (white, flat lit): where the background shows through
        cover = render(ICAM, [Ball(objs[0].centre, objs[0].radius, (255.0,) * 3)], black,
                       Light(ambient=1.0, diffuse=0.0, specular=0.0), noise=None) / 255.0
        img = key * np.float32(c1) + fill * np.float32(c2) \
            + (1.0 - cover) * background_image(ICAM, bg)
        img += rng.standard_normal(img.shape) * np.sqrt(2.25 + 0.02 * np.maximum(img, 0.0))
        yield _u8(img)


def _beside(colours, kind='ball', size=0.35):
    """Balls (or discs facing the camera) of ``colours`` touching the sphere's image."""
    def extra(rng, R, t):
        r, b = SP.radius, t / np.linalg.norm(t)
        e1 = np.cross(b, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(b, e1)
        out = []
        for c in colours:
            a = rng.uniform(0.0, 2.0 * math.pi)
            C = t + (math.cos(a) * e1 + math.sin(a) * e2) * r * (1.0 + size) * 1.05 - b * r * 0.5
            out.append(Ball(C, size * r, c) if kind == 'ball'
                       else Disc(C, -C / np.linalg.norm(C), size * r, c))
        return out
    return extra


def _occluder(rng, R, t):
    """Return a dark disc between the camera and P1, covering part of it."""
    C = 0.8 * (R @ SP.oP1 + t)
    e = np.cross(C, [0.0, 0.0, 1.0])
    return [Disc(C + e / np.linalg.norm(e) * 0.004, -C / np.linalg.norm(C), 0.0096,
                 (60.0, 60.0, 60.0))]


def _colours(p1, p2, body=(235, 235, 225)):
    return special_sphere(colors={'body': body, 'P1': p1, 'P2': p2})


def _project(target, seed):
    """Frames of the project's renderer (the CC target's stick, the balloon's ellipsoid)."""
    ren = Renderer(CAM, target, background='noise', levels=(30, 80), noise_sigma=2.0, seed=seed)
    return [ren.render(M) for M in project_poses(target, CAM, N, seed)]


def _specular(rng):
    d = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), -1.0])
    return Light(direction=d / np.linalg.norm(d), specular=0.5, shininess=8.0)


FAMILIES = {
    'plain': lambda: (SP, CAM, _scenes(SP, 101)),
    'far': lambda: (SP, CAM, _scenes(SP, 102, dist=(1.4, 3.5))),
    'specular': lambda: (SP, CAM, _scenes(SP, 103, light=_specular)),
    'grazing': lambda: (SP, CAM, _scenes(SP, 104, maxinc=89.0)),
    'beside_mark_balls': lambda: (SP, CAM, _scenes(SP, 105, extra=_beside([RED, BLUE]))),
    'beside_mark_discs': lambda: (SP, CAM, _scenes(
        SP, 106, extra=_beside([RED, BLUE], 'disc', 0.5))),
    'beside_swapped_balls': lambda: (SP, CAM, _scenes(SP, 107, extra=_beside(
        [(220, 60, 30), (30, 30, 220)]))),
    'occluded': lambda: (SP, CAM, _scenes(SP, 108, extra=_occluder)),
    'lights_warm_cool': lambda: (SP, CAM, _two_lights(SP, 109, (1.25, 1.0, 0.7),
                                                      (0.7, 0.9, 1.3))),
    'lights_green_magenta': lambda: (SP, CAM, _two_lights(SP, 110, (0.8, 1.2, 0.8),
                                                          (1.2, 0.8, 1.2))),
    'lights_red_cyan': lambda: (SP, CAM, _two_lights(SP, 111, (1.4, 0.9, 0.7),
                                                     (0.6, 1.0, 1.3))),
    'body_yellow': lambda: _coloured(112, RED, BLUE, (240, 225, 170)),
    'body_blue': lambda: _coloured(113, RED, BLUE, (200, 215, 240)),
    'body_pink': lambda: _coloured(114, RED, BLUE, (240, 215, 215)),
    'sym_red_blue': lambda: _coloured(115, RED, (30, 30, 220)),
    'near_sym_red_blue': lambda: _coloured(116, RED, (30, 45, 220)),
    'orange_cyan': lambda: _coloured(117, (230, 120, 30), (30, 140, 220)),
    'green_magenta': lambda: _coloured(118, (40, 200, 40), (200, 40, 200)),
    'sym_violet_pink': lambda: _coloured(119, (150, 30, 220), (220, 30, 150)),
    'orange_red_blue': lambda: _coloured(120, (220, 60, 30), (30, 30, 220)),
    'yellow_blue': lambda: _coloured(121, (220, 200, 30), BLUE),
    'sym_yellow_body': lambda: _coloured(123, RED, (30, 30, 220), (240, 225, 170)),
    'fisheye': lambda: (SP, WIDE['fisheye'], (im for im, _, _ in wide_scenes(
        twin(WIDE['fisheye']), SP, N, 124, bank=4))),
    'catadioptric': lambda: (SP, WIDE['catadioptric'], (im for im, _, _ in wide_scenes(
        twin(WIDE['catadioptric']), SP, N, 125, bank=4))),
    'cc': lambda: (cc_target(), CAM, _project(cc_target(), 126)),
    'balloon': lambda: (balloon(), CAM, _project(balloon(), 127)),
}


def _coloured(seed, p1, p2, body=(235, 235, 225)):
    t = _colours(p1, p2, body)
    return t, CAM, _scenes(t, seed)


@functools.lru_cache(maxsize=None)
def family(name: str):
    """Render a family once per session: its target, camera and frames."""
    target, cam, frames = FAMILIES[name]()
    return target, cam, tuple(frames)


# --- the judgement --------------------------------------------------------------------------
def _refused(d) -> bool:
    return d.not_detected is not None and d.not_detected.reason is Reason.COLOURS_SWAPPED


def failures(fam: str, transform: str) -> tuple[list, int]:
    """
    Return the class's failures and how many frames had a mark under the right label.

    A failure: ``(frame, 'refused')`` for a right label refused, ``(frame, name, px)`` for
    a mark the swapped label puts ``px`` from where the right label does (None: nowhere).
    """
    target, cam, frames = family(fam)
    det = Detector.for_target(target)
    out, with_marks = [], 0
    for i, img in enumerate(frames):
        img = T[transform](img)
        ref = det.detect(img, 'rgb8', cam)
        as_bgr = det.detect(np.ascontiguousarray(img[..., ::-1]), 'bgr8', cam)
        if _refused(ref) or _refused(as_bgr):
            out.append((i, 'refused'))
        # the same buffer labelled bgr8: red reads as blue and blue as red
        d = det.detect(img, 'bgr8', cam)
        for k, m in d.marks.items():
            r = ref.marks[k]
            if not m.visible:
                continue
            px = None if not r.visible else round(float(np.hypot(*(m.uv_px - r.uv_px))), 1)
            if px is None or px > 2.0:
                out.append((i, k, px))
        with_marks += any(m.visible for m in ref.marks.values())
    return out, with_marks


#: (family, transform) classes the check must get right. The gamma, two-light and
#: near-symmetric classes failed before the check used log-chromaticity directions and a
#: body sampled out to the limb (gamma 1.5: 11 of 12 plain frames moved a mark 23-37 px
#: or reported P1 at P2's place; near-symmetric colours: 6 of 12 clean frames)
DECIDED = [(f, t) for f, ts in {
    'plain': ('id', 'warm', 'cool', 'green', 'magenta', 'gamma0.6', 'gamma1.5', 'gamma2.2',
              'over1.6', 'over2.5', 'under0.35', 'noise5', 'noise10', 'c420', 'c422',
              'jpeg80', 'jpeg50', 'bayer', 'bayer_ea', 'blur5', 'black20', 'jpeg70_bayer'),
    'far': ('id', 'warm', 'cool', 'green', 'magenta', 'over1.6', 'under0.35', 'noise5',
            'c420', 'c422'),
    'specular': ('id', 'warm', 'magenta', 'gamma1.5', 'over1.6', 'c420', 'jpeg80'),
    'grazing': ('id', 'warm', 'green', 'gamma1.5', 'over1.6', 'noise5', 'jpeg80', 'bayer'),
    'beside_mark_balls': ('id', 'warm', 'cool', 'gamma1.5', 'jpeg50', 'bayer'),
    'beside_mark_discs': ('id', 'warm', 'cool', 'gamma2.2', 'jpeg50', 'bayer'),
    'beside_swapped_balls': ('id', 'warm', 'cool', 'green', 'magenta', 'jpeg50'),
    'occluded': ('id', 'warm', 'green', 'gamma1.5', 'c420', 'jpeg80', 'bayer'),
    'lights_warm_cool': ('id', 'green', 'magenta', 'gamma1.5', 'jpeg80'),
    'lights_green_magenta': ('id', 'cool', 'green', 'magenta', 'under0.35', 'c422'),
    'lights_red_cyan': ('id', 'magenta', 'gamma1.5', 'c420'),
    'body_yellow': ('id', 'warm', 'cool', 'magenta', 'gamma1.5', 'jpeg50'),
    'body_blue': ('id', 'warm', 'cool', 'green', 'gamma1.5', 'jpeg80'),
    'body_pink': ('id', 'warm', 'cool', 'green', 'gamma1.5', 'jpeg80'),
    'near_sym_red_blue': ('id', 'warm', 'cool', 'green', 'magenta', 'gamma1.5', 'over1.6',
                          'c420', 'c422', 'jpeg50', 'bayer', 'noise10'),
    'orange_cyan': ('id', 'cool', 'green', 'magenta', 'c420', 'bayer'),
    'green_magenta': ('id', 'warm', 'cool', 'gamma1.5', 'jpeg50'),
    'orange_red_blue': ('id', 'warm', 'cool', 'gamma1.5', 'jpeg50'),
    'yellow_blue': ('id', 'warm', 'cool', 'gamma1.5'),
    # red and blue that are each other's swap, told apart by a yellowish body only
    'sym_yellow_body': ('id', 'cool', 'green', 'magenta'),
    'fisheye': ('id', 'warm', 'cool', 'gamma1.5', 'c420', 'bayer'),
    'catadioptric': ('id', 'warm', 'cool', 'gamma1.5', 'c420', 'bayer'),
    'cc': ('id', 'warm', 'cool', 'gamma1.5', 'jpeg80'),
    'balloon': ('id', 'warm', 'cool', 'gamma1.5', 'jpeg80'),
}.items() for t in ts]


@pytest.mark.parametrize('fam,transform', DECIDED, ids=[f'{f}-{t}' for f, t in DECIDED])
def test_the_swap_moves_no_mark_and_the_right_label_is_kept(fam, transform):
    bad, with_marks = failures(fam, transform)
    assert not bad, bad


#: the classes no colour rule decides, and why (README, "Detection"): strict xfails, each
#: with the figures measured on its frames
UNDECIDABLE = {
    ('sym_red_blue', 'id'):
        'P2 (30, 30, 220) is P1 swapped: the swapped frame is the image of the target turned '
        "180 deg about the axis through O between its marks, but for the grey body's 4 % "
        'B-R tilt, the size of a white-balance error (hypotheses 1.1 deg apart, red/blue '
        '20 deg): 12 of 12 frames move both marks 20-54 px',
    ('sym_violet_pink', 'id'):
        "violet (150, 30, 220) and pink (220, 30, 150) are each other's swap (2.3 deg "
        'apart): 12 of 12 frames move both marks 19-91 px',
    ('lights_green_magenta', 'warm_over'):
        'a warm cast (1.2, 1, 0.8) with 1.6x exposure clips every body sample, so the cast '
        'is not measured: the right P1 reads (255, 53, 35), 11 deg from red and 9 deg from '
        'swapped blue, and the swapped frame mirrors it: 7 of 11 frames move P2 23-41 px or '
        'report it where the right label has none',
    ('body_pink', 'warm_over'):
        'the same clipped body under a warm cast: 6 of 12 frames move P2 24-56 px',
    ('far', 'noise10'):
        'marks of 4-15 px at 1.4-3.5 m under noise of sigma 10: the core colour is the '
        'median of 1-4 pixels and the noise is the size of the 30-count green difference '
        'between P1 and swapped P2 (a right P1 read (136, 40, 32), 8 deg from red, 12 deg '
        'from swapped blue): 4 of 8 frames move a mark 5-12 px',
    ('orange_cyan', 'over1.6'):
        'orange (230, 120, 30) swapped is 5.3 deg from cyan (30, 140, 220) (red/blue: '
        '20 deg) and 1.6x exposure clips both at 255: 10 of 12 frames move marks 22-55 px',
    ('catadioptric', 'jpeg50'):
        'JPEG (q 50, 4:2:0) of a small target bleeds the red P1 into the small blue P2, which '
        "reads (33, 35, 151): r = g, swapped red's signature (17 deg from blue, 3 deg from "
        'swapped red); with P1 not measured nothing outvotes it: 2 of 4 frames refused',
}


@pytest.mark.parametrize('fam,transform', [
    pytest.param(f, t, marks=pytest.mark.xfail(strict=True, reason=why), id=f'{f}-{t}')
    for (f, t), why in UNDECIDABLE.items()])
def test_what_no_colour_tells(fam, transform):
    bad, with_marks = failures(fam, transform)
    assert not bad, bad


def test_the_classes_are_not_vacuous():
    """Most classes have marks under the right label: the assertions above say something."""
    seen = {f: failures(f, 'id')[1] for f in FAMILIES}
    assert all(n >= 5 for n in seen.values()), seen
