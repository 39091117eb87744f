"""
Adversarial camera_info fields: refused with a reason, or a model that is right.

Classes of field at and past their bounds: ξ = 0, just below, at and just above 1, large
and huge (to the largest float); focal lengths far apart (fx ≠ fy by 10³); the principal
point at a corner; a 1 × 1 image; k1..k4 drawn about the values where the distortion
folds within the image; a fractional image size. An accepted model is checked against
its closed form written out here (Kannala–Brandt, Mei, plumb_bob), not against itself:
every pixel of the image its lift accepts is imaged back at that pixel by the closed form,
and every pixel it declines is beyond the increasing branch of the closed form's radius.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import (camera_from_camera_info_fields, FisheyeCamera,
                                             UnifiedCamera)
from sphere_servo.core.central import CameraError
from sphere_servo.pipeline.common import Refusal
from sphere_servo.pipeline.detector import camera_from_info


def K(fx, fy, cx, cy) -> list:
    return [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


# --- the closed forms ----------------------------------------------------------------------
def radtan(m, k1, k2, p1, p2, k3=0.0):
    x, y = m[:, 0], m[:, 1]
    r2 = x * x + y * y
    L = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return np.column_stack([x * L + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                            y * L + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])


def distorted(cam, q):
    """Return the distorted normalized points of unit rays ``q`` by the closed form."""
    if isinstance(cam, FisheyeCamera):
        th = np.arctan2(np.hypot(q[:, 0], q[:, 1]), q[:, 2])
        ph = np.arctan2(q[:, 1], q[:, 0])
        k1, k2, k3, k4 = cam.dist
        td = th * (1 + k1 * th ** 2 + k2 * th ** 4 + k3 * th ** 6 + k4 * th ** 8)
        return np.column_stack([td * np.cos(ph), td * np.sin(ph)])
    if isinstance(cam, UnifiedCamera):
        return radtan(q[:, :2] / (q[:, 2:] + cam.xi), *cam.dist)
    return radtan(q[:, :2] / q[:, 2:], *cam.dist)


def pixels(cam, q):
    md = distorted(cam, q)
    return np.column_stack([cam.px * md[:, 0] + cam.u0, cam.py * md[:, 1] + cam.v0])


def field_end(cam) -> float:
    """Angle from the axis where the model's natural field ends (rad)."""
    if isinstance(cam, FisheyeCamera):
        return math.pi
    if isinstance(cam, UnifiedCamera):
        return math.acos(-min(cam.xi, 1.0 / cam.xi)) if cam.xi > 0 else math.pi / 2
    return math.pi / 2


def reach(cam) -> tuple[float, bool]:
    """
    Return the largest distorted radius on the increasing branch, and whether it folds.

    The radius along the axis' azimuth 0, sampled densely up to the natural field's end,
    until it first stops increasing.
    """
    th = np.linspace(0.0, field_end(cam), 200001)[:-1]
    q = np.column_stack([np.sin(th), np.zeros_like(th), np.cos(th)])
    with np.errstate(all='ignore'):
        r = distorted(cam, q)[:, 0]
    dec = np.flatnonzero(~(np.diff(r) > 0))
    return float(r[:dec[0] + 1].max() if dec.size else np.nanmax(r)), bool(dec.size)


def image_grid(cam, n=241):
    u = np.linspace(-0.5, cam.width - 0.5, min(cam.width + 1, n))
    v = np.linspace(-0.5, cam.height - 0.5, min(cam.height + 1, n))
    return np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)


def far_corner(cam) -> float:
    W, H = cam.width - 0.5, cam.height - 0.5
    return max(math.hypot((cu - cam.u0) / cam.px, (cv - cam.v0) / cam.py)
               for cu in (-0.5, W) for cv in (-0.5, H))


# --- the bounds of each field --------------------------------------------------------------
BOUNDS = {
    **{f'unified xi={xi:g}': (640, 480, K(300, 300, 320, 240), [xi, 0, 0, 0, 0], 'unified')
       for xi in (0.0, 1e-9, 0.5, 1 - 1e-9, 1.0, 1 + 1e-12, 1 + 1e-9, 1 + 1e-6, 1.01, 2.0)},
    **{f'unified xi={xi:g} gamma scaled': (640, 480, K(300 * (1 + xi), 300 * (1 + xi), 320, 240),
                                           [xi, -0.1, 0.02, 0.0, 0.0], 'unified')
       for xi in (2.0, 10.0, 1e3)},
    'unified xi=0.9 corner pp': (640, 480, K(300, 300, 639.5, 479.5), [0.9, 0, 0, 0, 0],
                                 'unified'),
    'fisheye fx >> fy': (640, 480, K(3000, 7, 320, 240), [0, 0, 0, 0], 'equidistant'),
    'fisheye corner pp': (640, 480, K(150, 150, -0.5, -0.5), [0.01, 0, 0, 0], 'equidistant'),
    'fisheye 1x1': (1, 1, K(150, 150, 0, 0), [0, 0, 0, 0], 'equidistant'),
    'fisheye tiny f': (640, 480, K(6.4, 6.4, 320, 240), [0, 0, 0, 0], 'equidistant'),
    'plumb_bob fx << fy': (640, 480, K(7, 6000, 320, 240), [0.1, 0, 0, 0, 0], 'plumb_bob'),
    'plumb_bob corner pp': (640, 480, K(600, 600, 639.5, -0.5), [-0.2, 0.05, 0, 0, 0],
                            'plumb_bob'),
    'plumb_bob 1x1': (1, 1, K(600, 600, 0, 0), [0, 0, 0, 0, 0], 'plumb_bob'),
}


@pytest.mark.parametrize('name', BOUNDS)
def test_a_camera_at_its_bounds_lifts_every_pixel_to_the_ray_its_closed_form_images(name):
    cam = camera_from_camera_info_fields(*BOUNDS[name])
    uv = image_grid(cam)
    lifted = cam.lift_where(uv)
    assert lifted.ok.any()
    back = pixels(cam, lifted.rays[lifted.ok])
    assert np.abs(back - uv[lifted.ok]).max() < 1e-6, name
    # a pixel declined is beyond every ray of the increasing branch
    limit, _ = reach(cam)
    md = np.column_stack([(uv[:, 0] - cam.u0) / cam.px, (uv[:, 1] - cam.v0) / cam.py])
    r = np.hypot(md[:, 0], md[:, 1])[~lifted.ok]
    assert (r >= limit * (1 - 1e-6)).all(), (name, r.min(), limit)


@pytest.mark.parametrize('xi, gamma', [(1e3, 300.0), (1e160, 300.0), (1e300, 300.0),
                                       (1.7e308, 3e6)])
def test_a_huge_xi_is_refused_with_a_reason_not_an_overflow(xi, gamma):
    """
    ξ ≫ γ: the limit circle ``γ/√(ξ² − 1)`` is a fraction of a pixel, or underflows.

    ``ξ ** 2`` raised OverflowError (not a ValueError) past ξ ≈ 1.3e154, which escaped
    ``camera_from_info`` and the camera_info callback.
    """
    fields = (640, 480, K(gamma, gamma, 320, 240), [xi, 0, 0, 0, 0], 'unified')
    with pytest.raises(CameraError, match='field'):
        camera_from_camera_info_fields(*fields)
    out = camera_from_info(*fields[:4], distortion_model='unified')
    assert isinstance(out, Refusal) and 'field' in out.reason, out


def test_a_field_imaged_into_less_than_a_pixel_is_refused_and_one_pixel_is_not():
    ok = UnifiedCamera(px=300.0, py=300.0, xi=math.hypot(1.0, 300.0 / 1.5))  # circle 1.5 px
    assert ok.lift_where([[320.0, 240.0], [321.0, 240.0]]).ok.all()
    with pytest.raises(CameraError, match='less than one pixel'):
        UnifiedCamera(px=300.0, py=300.0, xi=math.hypot(1.0, 300.0 / 0.5))


@pytest.mark.parametrize('size', [(640.5, 480), (640, 479.9), (1e-3, 480)])
def test_a_fractional_image_size_is_refused_not_truncated(size):
    """A width of 640.5 was truncated to 640 and the camera built for another image."""
    fields = (*size, K(600, 600, 320, 240), [0.0] * 5, 'plumb_bob')
    with pytest.raises(CameraError, match='whole number'):
        camera_from_camera_info_fields(*fields)
    assert isinstance(camera_from_info(*fields[:4]), Refusal)


# --- distortions about their fold ---------------------------------------------------------
def _draws(model: str, n: int, seed: int):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        fx = rng.uniform(100, 900)
        fy = fx * rng.uniform(0.5, 2.0)
        cx, cy = rng.uniform(-0.5, 639.5), rng.uniform(-0.5, 479.5)
        if model == 'equidistant':
            d = list(rng.normal(0, [0.1, 0.03, 0.01, 0.003]))
        elif model == 'unified':
            d = [rng.uniform(0, 2.5), *rng.normal(0, [0.3, 0.1]), 0.0, 0.0]
        else:
            d = [*rng.normal(0, [0.4, 0.2]), 0.0, 0.0, rng.normal(0, 0.05)]
        yield 640, 480, K(fx, fy, cx, cy), d, model


@pytest.mark.parametrize('model', ['plumb_bob', 'equidistant', 'unified'])
def test_a_distortion_folding_inside_the_image_is_refused_and_an_accepted_one_is_right(model):
    """
    Radial coefficients drawn about their fold, the principal point anywhere in the image.

    By the closed form: a model whose radius stops increasing before the image's farthest
    corner must be refused; an accepted one lifts each pixel to the ray imaged there.
    """
    accepted = refused = 0
    for fields in _draws(model, 150, {'plumb_bob': 1, 'equidistant': 2, 'unified': 3}[model]):
        try:
            cam = camera_from_camera_info_fields(*fields)
        except CameraError:
            refused += 1
            continue
        accepted += 1
        limit, folds = reach(cam)
        assert not (folds and limit < far_corner(cam) * (1 - 1e-6)), fields
        uv = image_grid(cam, 61)
        lifted = cam.lift_where(uv)
        if lifted.ok.any():
            back = pixels(cam, lifted.rays[lifted.ok])
            assert np.abs(back - uv[lifted.ok]).max() < 1e-6, fields
    assert accepted >= 20 and refused >= 10, (accepted, refused)


def test_a_camera_with_fx_and_fy_far_apart_is_still_one_camera():
    """fx/fy = 10³ (anamorphic, within the focal bounds): lift and closed form agree."""
    cam = CameraIntrinsics(px=6400.0, py=6.4, dist=(0.0,) * 5)
    uv = image_grid(cam)
    q = cam.lift(uv)
    assert np.abs(pixels(cam, q) - uv).max() < 1e-6


# --- tangential terms that fold -----------------------------------------------------------
#: plumb_bob with p1 = 0.16: its fold curve (det ∂m_d/∂m = 0) is imaged inside the image
#: about (113–194, 70–112) px; a 65 × 49 grid of lifts missed it (the inner sheet's lift
#: succeeds on most pixels there) and the camera was accepted with pixels no ray reaches
#: next to pixels two rays reach
TANGENTIAL_FOLD = (640, 480, K(605.5590137743604, 703.8350434946567, 260.64667240945045,
                               378.0739806260527),
                   [-0.08117256991138871, 0.06495595577958606, 0.16438718890077628,
                    0.07166609173224753, 0.0], 'plumb_bob')


def test_a_tangential_fold_imaged_inside_the_image_is_refused():
    with pytest.raises(CameraError, match='tangential distortion folds inside the image'):
        camera_from_camera_info_fields(*TANGENTIAL_FOLD)
    assert isinstance(camera_from_info(*TANGENTIAL_FOLD[:4]), Refusal)


@pytest.mark.parametrize('model', ['plumb_bob', 'unified'])
def test_an_accepted_tangential_distortion_reaches_every_pixel_of_its_field_once(model):
    """
    Tangential terms up to 0.2, radial ones, the principal point anywhere: 100 draws.

    Accepted (ξ ≤ 1 or a pinhole: the natural field covers the whole image plane): every
    pixel of a 2 px grid lifts, to the ray the closed form images there.
    """
    rng = np.random.default_rng({'plumb_bob': 11, 'unified': 12}[model])
    accepted = 0
    for _ in range(100):
        fx = rng.uniform(150, 700)
        fy, cx, cy = fx * rng.uniform(0.7, 1.4), rng.uniform(-0.5, 639.5), rng.uniform(-0.5, 479.5)
        p1, p2 = rng.normal(0, 0.08, 2)
        d = ([rng.normal(0, 0.2), rng.normal(0, 0.05), p1, p2, 0.0] if model == 'plumb_bob'
             else [rng.uniform(0, 1.0), rng.normal(0, 0.2), rng.normal(0, 0.05), p1, p2])
        try:
            cam = camera_from_camera_info_fields(640, 480, K(fx, fy, cx, cy), d, model)
        except CameraError:
            continue
        accepted += 1
        uv = image_grid(cam, 321)
        lifted = cam.lift_where(uv)
        assert lifted.ok.all(), (d, uv[~lifted.ok][:3])
        assert np.abs(pixels(cam, lifted.rays) - uv).max() < 1e-6, d
    assert accepted >= 30, accepted
