"""
Camera validation (issue 14, items 6 and 10).

K sane, size matching the image, distortion applied or refused, intrinsics errors that
make the camera impossible refused by name.
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import (camera_from_camera_info_fields,
                                             check_camera_for_image, FisheyeCamera,
                                             UnifiedCamera)
from sphere_servo.core.central import (CameraError, FOCAL_RATIO_MAX, FOCAL_RATIO_MIN,
                                       MAX_IMAGE_SIDE, PRINCIPAL_POINT_MARGIN)
from sphere_servo.core.validation import Bound

MODELS = [('plumb_bob', [0.0] * 5), ('equidistant', [0.0] * 4), ('unified', [0.9, 0, 0, 0, 0])]


def _k(fx, fy=None, cx=320.0, cy=240.0):
    return [fx, 0.0, cx, 0.0, fx if fy is None else fy, cy, 0.0, 0.0, 1.0]


def _refused(fn, bound: Bound, quantity: str) -> CameraError:
    with warnings.catch_warnings():
        warnings.simplefilter('error')            # a refusal, not a numpy warning
        with pytest.raises(CameraError) as info:
            fn()
    v = info.value.violation
    assert v is not None and v.bound is bound and quantity in v.quantity, str(info.value)
    return info.value


@pytest.mark.parametrize('model, d', MODELS)
def test_focal_lengths_within_their_physical_range(model, d):
    side = 640
    lo, hi = FOCAL_RATIO_MIN * side, FOCAL_RATIO_MAX * side
    for fx, ok in ((hi, True), (hi * (1 + 1e-9), False), (1e300, False),
                   (lo * (1 - 1e-9), False), (0.0, False), (-600.0, False)):
        if ok:
            assert camera_from_camera_info_fields(640, 480, _k(fx), d, model).px == fx
        else:
            err = _refused(lambda: camera_from_camera_info_fields(640, 480, _k(fx), d, model),
                           Bound.RANGE, 'px')
            assert 'focal lengths must be' in str(err)
    _refused(lambda: camera_from_camera_info_fields(640, 480, _k(600.0, 1e300), d, model),
             Bound.RANGE, 'py')


def test_the_smallest_focal_length_is_accepted_for_a_wide_camera():
    # lo = 6.4 px: a fisheye whose 180° fits in 20 px is odd but physical; a pinhole that
    # short sees ±88.9°
    assert CameraIntrinsics(px=6.4, py=6.4).px == 6.4
    assert FisheyeCamera(px=6.4, py=6.4).px == 6.4


@pytest.mark.parametrize('model, d', MODELS)
def test_principal_point_within_one_image_of_the_image(model, d):
    m = PRINCIPAL_POINT_MARGIN
    for cx, cy, ok in ((-m * 640, 240.0, True), ((1 + m) * 640, 240.0, True),
                       (320.0, -m * 480, True), (320.0, (1 + m) * 480, True),
                       (-m * 640 - 1.0, 240.0, False), ((1 + m) * 640 + 1.0, 240.0, False),
                       (320.0, -m * 480 - 1.0, False), (320.0, (1 + m) * 480 + 1.0, False)):
        make = (lambda: camera_from_camera_info_fields(640, 480, _k(600.0, cx=cx, cy=cy), d,
                                                       model))
        if ok:
            assert (make().u0, make().v0) == (cx, cy)
        else:
            _refused(make, Bound.RANGE, 'u0' if cy == 240.0 else 'v0')


def test_a_wide_camera_whose_pixels_see_nothing_says_so_first():
    with pytest.raises(CameraError, match='no pixel') as info:
        FisheyeCamera(px=60.0, py=60.0, u0=-600.0)
    assert info.value.violation.bound is Bound.FIELD


@pytest.mark.parametrize('size, ok', [((1, 1), True), ((MAX_IMAGE_SIDE, 480), True),
                                      ((0, 480), False), ((640, MAX_IMAGE_SIDE + 1), False),
                                      ((640.5, 480), False), ((np.nan, 480), False)])
def test_the_image_size_is_a_whole_number_in_range(size, ok):
    w, h = size
    if ok:
        cam = CameraIntrinsics(px=max(w, h), py=max(w, h), u0=0.0, v0=0.0, width=w, height=h)
        assert (cam.width, cam.height) == (w, h)
    else:
        err = _refused(lambda: CameraIntrinsics(u0=0.0, v0=0.0, width=w, height=h),
                       Bound.FINITE if np.isnan(w) else Bound.RANGE,
                       'width' if w != 640 else 'height')
        assert np.isnan(w) or 'image size' in str(err)


def test_non_finite_distortion_is_refused_by_name():
    _refused(lambda: CameraIntrinsics(dist=(0.0, np.nan, 0.0, 0.0, 0.0)), Bound.FINITE, 'k2')
    _refused(lambda: FisheyeCamera(dist=(0.0, 0.0, np.inf, 0.0)), Bound.FINITE, 'k3')
    _refused(lambda: UnifiedCamera(xi=np.nan), Bound.FINITE, 'xi')
    _refused(lambda: UnifiedCamera(xi=-0.1), Bound.RANGE, 'xi')


# --- intrinsics errors ---------------------------------------------------------------------
@pytest.mark.parametrize('cam', [CameraIntrinsics(), FisheyeCamera(), UnifiedCamera()],
                         ids=lambda c: type(c).__name__)
def test_an_intrinsics_error_that_makes_the_camera_impossible_is_refused_by_name(cam):
    assert cam.with_error(px=-0.9).px == pytest.approx(cam.px * 0.1)
    for name in ('px', 'py'):
        for e in (-1.0, -1.5, -np.inf):
            err = _refused(lambda: cam.with_error(**{name: e}),
                           Bound.RANGE if np.isfinite(e) else Bound.FINITE,
                           f'intrinsics error {name}')
            assert f'intrinsics error {name}' in str(err)
    for name in ('u0', 'v0'):
        _refused(lambda: cam.with_error(**{name: np.nan}), Bound.FINITE,
                 f'intrinsics error {name}')
        with pytest.raises(CameraError) as info:   # the principal point, or no pixel sees
            cam.with_error(**{name: 5.0})
        assert f'intrinsics error {name} = 5.0' in str(info.value)
        assert info.value.violation.bound in (Bound.RANGE, Bound.FIELD)
    err = _refused(lambda: cam.with_error(px=1e300), Bound.RANGE, 'px')
    assert 'intrinsics error px = 1e+300' in str(err)


# --- the camera of an image ----------------------------------------------------------------
def test_a_camera_must_match_the_image_size():
    cam = CameraIntrinsics()
    assert check_camera_for_image(cam, 640, 480, applies_distortion=False) is cam
    for w, h in ((320, 240), (640, 481), (480, 640)):
        err = _refused(lambda: check_camera_for_image(cam, w, h, applies_distortion=True),
                       Bound.MISMATCH, 'camera size')
        assert '640x480' in str(err) and f'{w}x{h}' in str(err)


def test_distortion_is_applied_or_refused_never_ignored():
    plumb = CameraIntrinsics(dist=(-0.25, 0.08, 0.001, -0.0015, -0.01))
    fish = FisheyeCamera()
    for cam in (plumb, fish, UnifiedCamera()):
        assert check_camera_for_image(cam, 640, 480, applies_distortion=True) is cam
    err = _refused(lambda: check_camera_for_image(plumb, 640, 480, applies_distortion=False),
                   Bound.UNSUPPORTED, 'distortion')
    assert '-0.25' in str(err)
    _refused(lambda: check_camera_for_image(fish, 640, 480, applies_distortion=False),
             Bound.UNSUPPORTED, 'camera model')
    # the consumer that applies it: lift() moves a corner pixel's ray by the distortion
    corner = np.array([[0.0, 0.0]])
    assert not np.allclose(plumb.lift(corner), CameraIntrinsics().lift(corner), atol=1e-3)


@pytest.mark.parametrize('k, match', [(_k(600.0)[:8], '9 finite'), (_k(np.nan), '9 finite'),
                                      ([600.0, 1.0, 320, 0, 600, 240, 0, 0, 1], 'no skew')])
def test_factory_refusals_are_typed(k, match):
    with pytest.raises(CameraError, match=match) as info:
        camera_from_camera_info_fields(640, 480, k, [], 'plumb_bob')
    assert info.value.violation is not None
    with pytest.raises(CameraError) as info:
        camera_from_camera_info_fields(640, 480, _k(600.0), [0.1] * 8, 'rational_polynomial')
    assert info.value.violation.bound is Bound.UNSUPPORTED
