"""
The detector on a crop_decimate stream: the calibrated camera_info, binning and roi.

image_proc's crop_decimate (and a driver's binning) publishes a crop of the calibrated
image decimated by nearest pixel, with the camera_info of the calibrated camera plus
``binning_x``, ``binning_y`` and ``roi``. Here the independent renderer
(test/independent_render.py) draws the full image at a seeded pose; the test crops and
decimates it itself (slicing ``[y0:y1:b, x0:x1:b]``, which is what ``cv2.resize`` with
``INTER_NEAREST`` does), and :class:`~sphere_servo.pipeline.detector.DetectorCore` gets the
reduced image with the full camera_info. The truth is the pose.

What must hold: at 1280×720 decimated 2× to a 480×270 crop, the criteria of
test_detector_independent for a VGA image (no frame off by 1 % in s_n,t or 3° in θu, p99
1 % and 1.5°, at most 5 % not published), b within 0.1° and r_δ within 1 % in every frame,
each mark's ray within 0.05°; through the fisheye and catadioptric models of the configs
cropped to an roi, the criteria of test_detector_models. The same image with binning and
roi left unset is refused (size mismatch); an roi 4 px off the true crop moves b by what
4 px subtend (the roi is used, not only its size).
"""
from __future__ import annotations

import dataclasses
import math

import cv2
from independent_render import Light, render
from independent_scenes import (CAMERAS, random_light, random_poses, target_ball,
                                textured_background, wide_poses)
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import cRo_measured, model_cRo_offset
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.detector import DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from test_detector_independent import check_accuracy
from wide_cameras import twin, WIDE

TARGET = special_sphere()
HD = CAMERAS['hd_f900']
HD_INFO = CameraIntrinsics(HD.fx, HD.fy, HD.cx, HD.cy, HD.width, HD.height
                           ).to_camera_info_fields()
ROI, B = (160, 90, 960, 540), 2      # → 480×270
SHIFT = 4                            # px of the calibrated image


def crop_decimate(img: np.ndarray, roi, b: int) -> np.ndarray:
    """Crop ``roi`` = (x, y, w, h) and keep one pixel of each b × b block (nearest)."""
    x, y, w, h = roi
    return np.ascontiguousarray(img[y:y + h // b * b:b, x:x + w // b * b:b])


def buffer(img: np.ndarray) -> dict:
    h, w = img.shape[:2]
    return {'height': h, 'width': w, 'step': 3 * w, 'encoding': 'rgb8', 'data': img.tobytes()}


def core(info: dict, **reduction) -> DetectorCore:
    c = DetectorCore(DetectorParams.from_mapping({}))
    cam = c.on_camera_info(info['width'], info['height'], info['k'], info['d'],
                           info['distortion_model'], **reduction)
    assert c.camera is cam, cam
    return c


def crop_camera(cam, roi, b: int):
    """Return the independent renderer's camera of the reduced image (poses inside it)."""
    x, y, w, h = roi
    return dataclasses.replace(cam, fx=cam.fx / b, fy=cam.fy / b, cx=(cam.cx - x) / b,
                               cy=(cam.cy - y) / b, width=w // b, height=h // b)


def errors(det, R, t) -> tuple[float, float]:
    """Return the errors of a detection against the pose (R, t): s_n,t (%), θu (°)."""
    obs = det.to_observation('special')
    s = t / TARGET.radius
    e_s = 100 * np.linalg.norm(obs.sphere.s_nt - s) / np.linalg.norm(s)
    R_true = R @ model_cRo_offset(TARGET)
    return e_s, float(np.degrees(np.linalg.norm(pin.log3(cRo_measured(obs) @ R_true.T))))


def angle_deg(a, b) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def test_a_decimated_crop_with_the_full_camera_info():
    """12 HD frames, cropped and decimated 2×, against the pose; unset and shifted rois."""
    good = core(HD_INFO, binning_x=B, binning_y=B, roi=ROI)
    shifted = core(HD_INFO, binning_x=B, binning_y=B,
                   roi=(ROI[0] + SHIFT, *ROI[1:]))
    unset = core(HD_INFO)
    rng = np.random.default_rng(7919 + 11)
    e_s, e_r, missed, n = [], [], 0, 12
    for i, (R, t) in enumerate(random_poses(crop_camera(HD, ROI, B), TARGET, n, 11)):
        full = render(HD, [target_ball(TARGET, R, t)], textured_background(rng),
                      random_light(rng), rng=rng)
        img = crop_decimate(full, ROI, B)
        assert img.shape == (270, 480, 3)
        if i == 0:  # slicing is crop_decimate's nearest-pixel decimation
            x, y, w, h = ROI
            assert np.array_equal(img, cv2.resize(full[y:y + h, x:x + w], (w // B, h // B),
                                                  interpolation=cv2.INTER_NEAREST))
        out = good.on_image(**buffer(img))
        assert out.status is DetectStatus.FOUND, out.reason
        det = out.detection
        b_true = t / np.linalg.norm(t)
        assert angle_deg(det.sphere.b, b_true) < 0.1
        assert abs(det.sphere.r_delta * np.linalg.norm(t) / TARGET.radius - 1.0) < 0.01
        for name, oP in (('P1', TARGET.oP1), ('P2', TARGET.oP2)):
            mark = det.marks[name]
            if mark.visible:
                assert angle_deg(mark.ray, R @ oP + t) < 0.05, name
        try:
            es, er = errors(det, R, t)
        except ValueError:
            missed += 1
        else:
            e_s.append(es)
            e_r.append(er)
        # the roi is used: 4 px further right, every ray turns by what 4 px subtend
        moved = shifted.on_image(**buffer(img)).detection.sphere.b
        turn = angle_deg(moved, det.sphere.b)
        assert 0.75 < turn / math.degrees(SHIFT / HD.fx) < 1.05, turn
        assert moved[0] > det.sphere.b[0] and angle_deg(moved, b_true) > 0.15
        # binning and roi unset: the calibrated camera, refused by size
        refused = unset.on_image(**buffer(img))
        assert refused.status is DetectStatus.REJECTED and not refused.measurement.names
        assert 'camera size = 1280x720' in refused.reason and '480x270' in refused.reason
    print(check_accuracy(np.array(e_s), np.array(e_r), missed, n))


@pytest.mark.parametrize('name, roi', [('fisheye', (40, 20, 560, 440)),
                                       ('catadioptric', (60, 40, 520, 400))])
def test_a_crop_through_each_wide_model(name, roi):
    """8 frames of the config's camera cropped to ``roi``: its distortion about the crop."""
    cam = WIDE[name]
    ind = twin(cam)
    det = core(cam.to_camera_info_fields(), roi=roi)
    assert (det.camera.u0, det.camera.v0) == pytest.approx((cam.u0 - roi[0], cam.v0 - roi[1]))
    rng = np.random.default_rng(7919 + 5)
    e_s, e_r, missed, n = [], [], 0, 8
    for R, t in wide_poses(crop_camera(ind, roi, 1), TARGET, n, 5, off_deg=(0.0, 80.0)):
        b = t / np.linalg.norm(t)
        e1 = np.cross(b, [0.3, -0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        d = -b + rng.uniform(-0.6, 0.6) * e1 + rng.uniform(-0.6, 0.6) * np.cross(b, e1)
        full = render(ind, [target_ball(TARGET, R, t)], textured_background(rng, bank=16),
                      Light(direction=d / np.linalg.norm(d)), rng=rng)
        out = det.on_image(**buffer(crop_decimate(full, roi, 1)))
        try:
            es, er = errors(out.detection, R, t)
        except ValueError:
            missed += 1
            continue
        e_s.append(es)
        e_r.append(er)
    figures = (f'{name}: not published {missed}/{n}, s_n,t median/max {np.median(e_s):.3f}/'
               f'{np.max(e_s):.3f} %, θu median/max {np.median(e_r):.3f}/{np.max(e_r):.3f}°')
    print(figures)
    assert np.median(e_s) < 0.2 and np.max(e_s) < 1.0, figures
    assert np.median(e_r) < 0.3 and np.max(e_r) < 1.5, figures
    assert missed <= 1, figures
