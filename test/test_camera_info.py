"""
The CameraInfo encoding of each camera model and the factory's refusals (issue 18).

Every model round-trips through its ``sensor_msgs/CameraInfo`` fields; the factory refuses,
with a clear ``ValueError``, what it cannot honour instead of ignoring a distortion.
"""
from __future__ import annotations

import array
import math

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import (camera_from_camera_info_fields, FisheyeCamera,
                                             UnifiedCamera)

K = [600.0, 0.0, 320.0, 0.0, 610.0, 240.0, 0.0, 0.0, 1.0]
K_FISH = [150.0, 0.0, 320.0, 0.0, 150.0, 240.0, 0.0, 0.0, 1.0]
CAMERAS = [
    CameraIntrinsics(),
    CameraIntrinsics(px=610.0, py=605.0, u0=318.5, v0=241.0,
                     dist=(-0.25, 0.08, 0.001, -0.0015, -0.01)),
    FisheyeCamera(),
    FisheyeCamera(px=190.0, py=188.0, u0=321.0, v0=239.0, dist=(0.05, -0.01, 0.003, -0.0005)),
    UnifiedCamera(),
    UnifiedCamera(px=280.0, py=282.0, xi=1.6, dist=(-0.05, 0.01, 0.0005, -0.0003)),
]


@pytest.mark.parametrize('cam', CAMERAS, ids=lambda c: type(c).__name__)
def test_every_model_round_trips_through_its_camera_info_fields(cam):
    fields = cam.to_camera_info_fields()
    assert set(fields) == {'width', 'height', 'distortion_model', 'd', 'k', 'r', 'p'}
    assert fields['k'] == [cam.px, 0.0, cam.u0, 0.0, cam.py, cam.v0, 0.0, 0.0, 1.0]
    assert fields['r'] == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    assert fields['p'] == [cam.px, 0.0, cam.u0, 0.0, 0.0, cam.py, cam.v0, 0.0, 0.0, 0.0, 1.0,
                           0.0]
    back = camera_from_camera_info_fields(**fields)
    assert type(back) is type(cam) and back == cam
    # as a message gives them: array('d') for d, a tuple for k
    msg = camera_from_camera_info_fields(fields['width'], fields['height'], tuple(fields['k']),
                                         array.array('d', fields['d']),
                                         fields['distortion_model'])
    assert msg == cam


def test_the_encoding_of_each_model():
    assert CAMERAS[1].to_camera_info_fields()['distortion_model'] == 'plumb_bob'
    assert CAMERAS[1].to_camera_info_fields()['d'] == [-0.25, 0.08, 0.001, -0.0015, -0.01]
    fish = CAMERAS[3].to_camera_info_fields()
    assert fish['distortion_model'] == 'equidistant'
    assert fish['d'] == [0.05, -0.01, 0.003, -0.0005]                  # k1 k2 k3 k4
    uni = CAMERAS[5].to_camera_info_fields()
    assert uni['distortion_model'] == 'unified'
    assert uni['d'] == [1.6, -0.05, 0.01, 0.0005, -0.0003]             # ξ k1 k2 p1 p2
    assert uni['k'][0] == 280.0 and uni['k'][4] == 282.0               # γ1, γ2


def test_an_empty_d_means_no_distortion():
    assert camera_from_camera_info_fields(640, 480, K, [], 'plumb_bob') == \
        CameraIntrinsics(py=610.0)
    assert camera_from_camera_info_fields(640, 480, K, [], '') == CameraIntrinsics(py=610.0)
    assert camera_from_camera_info_fields(640, 480, K_FISH, None, 'equidistant') == \
        FisheyeCamera()


def test_the_factory_checks_the_distortion_actually_used():
    # the same K and d, three models: three different lifts of the same pixel
    d5, k = [0.05, -0.01, 0.003, -0.0005, 0.0], [400.0, 0, 320, 0, 400.0, 240, 0, 0, 1]
    pin = camera_from_camera_info_fields(640, 480, k, d5, 'plumb_bob')
    uni = camera_from_camera_info_fields(640, 480, k, [0.5, *d5[:4]], 'unified')
    fish = camera_from_camera_info_fields(640, 480, k, d5[:4], 'equidistant')
    rays = [c.lift([[600.0, 400.0]])[0] for c in (pin, uni, fish)]
    assert min(math.acos(min(1.0, a @ b)) for a, b in
               [(rays[0], rays[1]), (rays[1], rays[2]), (rays[0], rays[2])]) > 0.05


@pytest.mark.parametrize('model, d, match', [
    ('rational_polynomial', [0.1, 0.01, 0, 0, 0, 0, 0, 0], 'unsupported distortion_model'),
    ('fov', [0.9], 'unsupported distortion_model'),
    ('Plumb_Bob', [0.0] * 5, 'unsupported distortion_model'),
    ('', [0.1, 0, 0, 0, 0], 'unsupported distortion_model'),
    ('plumb_bob', [0.1, 0.01, 0, 0], 'needs 5 coefficients'),
    ('plumb_bob', [0.1, 0.01, 0, 0, 0, 0, 0, 0], 'needs 5 coefficients'),
    ('equidistant', [0.1, 0.01, 0, 0, 0], 'needs 4 coefficients'),
    ('unified', [0.9, 0, 0, 0], 'needs 5 coefficients'),
    ('unified', [], 'needs 5 coefficients'),
    ('plumb_bob', [math.nan, 0, 0, 0, 0], 'finite'),
    ('equidistant', [0, math.inf, 0, 0], 'finite'),
    ('unified', [-0.1, 0, 0, 0, 0], 'xi >= 0'),
    ('unified', [math.nan, 0, 0, 0, 0], 'finite'),
])
def test_the_factory_refuses_unknown_models_and_bad_coefficients(model, d, match):
    with pytest.raises(ValueError, match=match):
        camera_from_camera_info_fields(640, 480, K_FISH, d, model)


@pytest.mark.parametrize('k, match', [
    ([600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0], '9 finite'),
    ([math.nan, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0], '9 finite'),
    ([600.0, 0.5, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0], 'no skew'),
    ([600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 2.0], 'no skew'),
    ([0.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0], 'focal lengths must be > 0'),
    ([600.0, 0.0, 320.0, 0.0, -600.0, 240.0, 0.0, 0.0, 1.0], 'focal lengths must be > 0'),
])
@pytest.mark.parametrize('model, d', [('plumb_bob', [0.0] * 5), ('equidistant', [0.0] * 4),
                                      ('unified', [0.9, 0, 0, 0, 0])])
def test_the_factory_refuses_a_bad_K(k, match, model, d):
    with pytest.raises(ValueError, match=match):
        camera_from_camera_info_fields(640, 480, k, d, model)


@pytest.mark.parametrize('model, k, d', [
    ('plumb_bob', K, [-0.5, 0.0, 0.0, 0.0, 0.0]),                  # folds at 35° < corner 38°
    ('plumb_bob', K, [0.0, 0.0, 0.0, 0.0, -1.0]),
    ('plumb_bob', K, [0.0, 0.0, 0.3, 0.0, 0.0]),                   # tangential fold
    ('equidistant', K_FISH, [0.05, -0.01, 0.003, -0.0005]),        # folds at 132° < 153°
    ('equidistant', K_FISH, [-0.3, 0.0, 0.0, 0.0]),
    ('unified', K_FISH, [0.9, -0.3, 0.0, 0.0, 0.0]),
])
def test_the_factory_refuses_a_distortion_that_folds_inside_the_image(model, k, d):
    with pytest.raises(ValueError, match='folds inside the image'):
        camera_from_camera_info_fields(640, 480, k, d, model)


def test_a_natural_field_edge_inside_the_image_is_not_a_fold():
    # a circular fisheye image (180° at 94 px) and a unified fisheye (ξ > 1) whose limit
    # circle lies inside the image: pixels outside see nothing, and that is accepted
    fish = camera_from_camera_info_fields(640, 480, [60.0, 0, 320, 0, 60.0, 240, 0, 0, 1],
                                          [], 'equidistant')
    assert not fish.lift_where([[0.0, 0.0]]).ok[0]
    uni = camera_from_camera_info_fields(640, 480, K_FISH, [2.0, 0, 0, 0, 0], 'unified')
    assert not uni.lift_where([[0.0, 0.0]]).ok[0] and uni.lift_where([[320, 240]]).ok[0]
    with pytest.raises(ValueError, match='no pixel'):          # ...but some pixel must see
        camera_from_camera_info_fields(640, 480, [60.0, 0, 5000, 0, 60.0, 240, 0, 0, 1], [],
                                       'equidistant')
    with pytest.raises(ValueError, match='image size'):
        camera_from_camera_info_fields(0, 480, K_FISH, [], 'equidistant')


@pytest.mark.parametrize('cam', CAMERAS, ids=lambda c: type(c).__name__)
def test_with_error_works_for_every_model(cam):
    bad = cam.with_error(px=0.35, py=0.30, u0=-0.25, v0=0.27)
    assert type(bad) is type(cam)
    assert (bad.px, bad.py) == pytest.approx((cam.px * 1.35, cam.py * 1.30))
    assert (bad.u0, bad.v0) == pytest.approx((cam.u0 * 0.75, cam.v0 * 1.27))
    assert bad.dist == cam.dist and getattr(bad, 'xi', None) == getattr(cam, 'xi', None)
    assert (bad.width, bad.height) == (cam.width, cam.height)
    # the same pixel lifts to another ray, as the experiment needs
    uv = np.array([[400.0, 300.0]])
    assert np.linalg.norm(bad.lift(uv) - cam.lift(uv)) > 1e-3
    assert cam.with_error() == cam
