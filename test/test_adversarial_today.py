"""
Adversarial inputs to today's changes: whole numbers, camera_info caching, compressed formats.

Each case is an input the authors did not test, with the answer it must get: the value it
stands for, or a refusal (empty measurement, no exception); never a wrong value. Those that
failed before their fix: a Fraction of 10**400 (OverflowError out of check_whole, so out of
DetectorCore.on_image and on_camera_info), a long double of 1e4000 called not finite, a
refused camera_info (binning False, width Decimal(640)) whose cached refusal then refused the
equal, valid one (binning 0, width 640) and the reverse (binning True given binning 1's
camera), an roi given as a set or a dict (read in its iteration order), a format with words
after its compressed encoding, and colour data under ``compressed mono8``.
"""
from __future__ import annotations

from decimal import Decimal
from fractions import Fraction
import io
import math

import numpy as np
from PIL import Image as PILImage
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CameraError
from sphere_servo.core.targets import special_sphere
from sphere_servo.core.validation import Bound, check_whole
from sphere_servo.pipeline.common import Refusal
from sphere_servo.pipeline.detector import DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.vision.compressed import decode_compressed, parse_format
from sphere_servo.vision.detector import Detector
from sphere_servo.vision.poses import random_poses
from sphere_servo.vision.renderer import Renderer

CAM = CameraIntrinsics()
FIELDS = CAM.to_camera_info_fields()
HUGE = 10 ** 400


class Err(ValueError):
    """The caller's error class, carrying the violation."""

    def __init__(self, violation):
        super().__init__(str(violation))
        self.violation = violation


@pytest.mark.parametrize('value, lo, hi, want', [
    (np.uint64(2 ** 64 - 1), 0, math.inf, 2 ** 64 - 1),
    (np.uint64(2 ** 63 + 1), 0, math.inf, 2 ** 63 + 1),
    (np.uint64(2 ** 63 + 1), 1, 65536, Bound.RANGE),
    (np.int8(-1), 0, math.inf, Bound.RANGE), (np.uint8(255), 1, 65536, 255),
    (np.int16(480), 1, 65536, 480), (np.int32(480), 1, 65536, 480),
    (np.float16(480), 1, 65536, 480), (np.float32(480.5), 1, 65536, Bound.RANGE),
    (np.float64(480.0), 1, 65536, 480), (np.longdouble(480), 1, 65536, 480),
    (np.array(480), 1, 65536, 480), (np.array(480.0), 1, 65536, 480),
    (np.array([480]), 1, 65536, Bound.SHAPE),
    (np.array(np.uint64(2 ** 64 - 1)), 0, 9, Bound.RANGE),
    (Fraction(960, 2), 1, 65536, 480), (Fraction(961, 2), 1, 65536, Bound.RANGE),
    (Fraction(HUGE), 1, 65536, Bound.RANGE), (Fraction(HUGE), 0, math.inf, HUGE),
    (Fraction(HUGE + 1, 2), 0, math.inf, Bound.RANGE),
    (np.array(Fraction(HUGE), dtype=object), 1, 65536, Bound.RANGE),
    (np.longdouble('1e4000'), 1, 65536, Bound.RANGE),
    (np.longdouble('inf'), 0, math.inf, Bound.FINITE),
    (Decimal(480), 1, 65536, Bound.SHAPE), (Decimal('NaN'), 1, 65536, Bound.SHAPE),
    (HUGE, 1, 65536, Bound.RANGE), (-HUGE, 0, math.inf, Bound.RANGE), (HUGE, 0, math.inf, HUGE),
    (-0.0, 0, math.inf, 0), (-0.0, 1, 65536, Bound.RANGE), (1e300, 1, 65536, Bound.RANGE),
    (True, 0, math.inf, Bound.SHAPE), (np.bool_(False), 0, math.inf, Bound.SHAPE),
    (None, 0, math.inf, Bound.SHAPE), ('480', 0, math.inf, Bound.SHAPE),
    (480 + 0j, 0, math.inf, Bound.SHAPE), (float('nan'), 0, math.inf, Bound.FINITE),
    (np.timedelta64(480), 0, math.inf, Bound.SHAPE),
], ids=lambda v: repr(v)[:24])
def test_check_whole_of_every_number_type(value, lo, hi, want):
    if isinstance(want, Bound):
        with pytest.raises(Err) as info:
            check_whole(Err, 'n', value, lo, hi)
        assert info.value.violation.bound is want
        return
    got = check_whole(Err, 'n', value, lo, hi)
    assert type(got) is int and got == want


def _core() -> DetectorCore:
    return DetectorCore(DetectorParams.from_mapping({}))


def _info(core, width=640, height=480, **kw):
    return core.on_camera_info(width, height, FIELDS['k'], FIELDS['d'],
                               FIELDS['distortion_model'], **kw)


@pytest.mark.parametrize('h, w, step', [
    (Fraction(HUGE), 8, 24), (6, 8, Fraction(HUGE)), (6, Fraction(HUGE), 24),
    (np.uint64(2 ** 64 - 1), 8, 24), (6, np.uint64(2 ** 63), 24), (6, 8, np.float64(1e300)),
    (np.longdouble('1e4000'), 8, 24), (Decimal(6), 8, 24), (True, 8, 24), (-0.0, 8, 24),
    (np.array([6]), 8, 24), (None, 8, 24), (6, 8, Fraction(49, 2)),
], ids=lambda v: repr(v)[:24])
def test_on_image_with_sizes_of_any_type_rejects_without_raising(h, w, step):
    core = _core()
    cam = CameraIntrinsics(px=8.0, py=8.0, u0=4.0, v0=3.0, width=8, height=6)
    f = cam.to_camera_info_fields()
    assert not isinstance(core.on_camera_info(8, 6, f['k'], f['d']), Refusal)
    out = core.on_image(h, w, step, 'rgb8', bytes(6 * 24))
    assert out.status is DetectStatus.REJECTED and out.reason
    assert out.measurement == Measurement() and out.image is None
    ok = core.on_image(np.uint32(6), np.float64(8.0), np.array(24), 'rgb8', bytes(6 * 24))
    assert ok.status is DetectStatus.NOT_FOUND        # the same sizes, whole: read


@pytest.mark.parametrize('kw', [
    {'width': Fraction(HUGE)}, {'height': Fraction(HUGE)}, {'binning_x': Fraction(HUGE)},
    {'roi': (Fraction(HUGE), 0, 10, 10)}, {'roi': (0, 0, Fraction(HUGE), 10)},
    {'width': np.longdouble('1e4000')}, {'roi': {0, 5, 10, 20}},
    {'roi': {0: 0, 5: 5, 10: 10, 20: 20}}, {'roi': frozenset((0, 5, 10, 20))},
], ids=lambda v: repr(v)[:40])
def test_on_camera_info_refuses_without_raising(kw):
    core = _core()
    assert not isinstance(_info(core), Refusal)
    assert isinstance(_info(core, **kw), Refusal) and core.camera is None and core.refused


def test_a_camera_info_whose_reading_fails_leaves_no_camera(monkeypatch, scene):
    # an error no one foresaw: the node's guard catches it; the images must then not be
    # measured with the camera of the camera_info before
    import sphere_servo.pipeline.detector as pd
    core = _core()
    assert not isinstance(_info(core), Refusal)
    frame = scene[0]

    def broken(*args, **kw):
        raise RuntimeError('unforeseen')
    monkeypatch.setattr(pd, 'camera_from_info', broken)
    with pytest.raises(RuntimeError):
        _info(core, width=1280, height=720)
    assert core.camera is None and core.refused
    out = core.on_image(480, 640, 1920, 'rgb8', frame.tobytes())
    assert out.status is DetectStatus.REJECTED and out.measurement == Measurement()


@pytest.mark.parametrize('bad, good', [
    ({'binning_x': False}, {'binning_x': 0}), ({'binning_y': np.False_}, {'binning_y': 0}),
    ({'binning_x': True}, {'binning_x': 1}), ({'binning_x': np.True_}, {'binning_x': 1}),
    ({'width': Decimal(640)}, {'width': 640}), ({'width': Decimal(640)}, {'width': 640.0}),
    ({'roi': (False, 0, 0, 0)}, {'roi': (0, 0, 0, 0)}),
    ({'roi': (0, 0, True, True)}, {'roi': (0, 0, 1, 1)}),
])
@pytest.mark.parametrize('bad_first', [True, False])
def test_a_refused_camera_info_and_its_equal_valid_one_in_either_order(bad, good, bad_first):
    """Equal values of another type: the cache must not give one the other's answer."""
    core = _core()
    for kw in ((bad, good) if bad_first else (good, bad)):
        cam = _info(core, **kw)
        if kw is bad:
            assert isinstance(cam, Refusal) and core.camera is None
        else:
            assert not isinstance(cam, Refusal) and core.camera is cam


# --- compressed formats --------------------------------------------------------------------
@pytest.mark.parametrize('fmt', [
    'rgb8; png compressed rgb8 compressed bgr8', 'rgb8; jpeg rgb8 compressed bgr8',
    'rgb8; jpeg compressed bgr8 ; png', 'rgb8; jpeg compressed bgr8 rgb8', 'png rgb8',
    'rgb8; jpeg bgr8', 'rgb8; jpeg compressed bgr8\x00', 'bytes', None, b'jpeg', 123,
    'rgb8; jpeg compressed bgr8' * 500, 'rgb8; ｊｐｅｇ', '8UC3; jpeg', '16UC1; compressedDepth',
    'bayer_rggb8; jpeg compressed bgr8', 'rgb8;; jpeg',
])
def test_formats_whose_colour_order_is_no_one_thing_are_refused(fmt):
    with pytest.raises(ValueError, match='CompressedImage format'):
        parse_format(fmt)


@pytest.fixture(scope='module')
def scene():
    """Return (rgb8 frame, its camera, the pose): a special sphere with both marks in view."""
    target = special_sphere()
    M = random_poses(target, CAM, 1, 5)[0]
    return Renderer(CAM, target, background='gradient').render(M), M


def _pil(img, fmt, mode='RGB', **kw) -> bytes:
    out = io.BytesIO()
    PILImage.fromarray(img).convert(mode).save(out, fmt, **kw)
    return out.getvalue()


def _animated(img) -> bytes:
    out = io.BytesIO()
    first, second = PILImage.fromarray(img), PILImage.fromarray(np.ascontiguousarray(img[::-1]))
    first.save(out, 'WEBP', save_all=True, append_images=[second], lossless=True, duration=50)
    return out.getvalue()


LOSSLESS = {   # a standard file (its colours true): read as bgr by a bare format
    'rgba png': lambda img: _pil(img, 'PNG', 'RGBA'),
    'webp lossless': lambda img: _pil(img, 'WEBP', lossless=True),
    'webp rgba': lambda img: _pil(img, 'WEBP', 'RGBA', lossless=True),
    'animated webp': _animated,
    'png labelled jpeg': lambda img: _pil(img, 'PNG'),
}
LOSSY = {
    'cmyk jpeg': lambda img: _pil(img, 'JPEG', 'CMYK', quality=95),
    'progressive jpeg': lambda img: _pil(img, 'JPEG', quality=95, progressive=True),
    'palette png': lambda img: _pil(img, 'PNG', 'P'),
    'jpeg labelled png': lambda img: _pil(img, 'JPEG', quality=95),
}


@pytest.mark.parametrize('fmt', ['png', 'jpeg', 'rgb8; png compressed bgr8',
                                 'bgra8; png compressed bgra8', 'RGBA8 ;  PNG  Compressed BGRA8'])
@pytest.mark.parametrize('kind', sorted(LOSSLESS) + sorted(LOSSY))
def test_odd_files_decode_red_as_red(scene, kind, fmt):
    img, _ = scene
    data = {**LOSSLESS, **LOSSY}[kind](img)
    out, enc = decode_compressed(fmt, data)
    assert enc in ('rgb8', 'bgr8') and out.shape == img.shape
    rgb = (out if enc == 'rgb8' else out[..., ::-1]).astype(int)
    if kind in LOSSLESS:
        assert np.array_equal(rgb, img)
        return
    truth = img.astype(int)
    rb = truth[..., 0] - truth[..., 2]
    marks = np.abs(rb) > 60
    assert marks.sum() > 100
    agree = np.sign(rgb[..., 0] - rgb[..., 2])[marks] == np.sign(rb[marks])
    assert agree.mean() > 0.97, (kind, agree.mean())


@pytest.mark.parametrize('fmt', ['rgb8; jpeg compressed mono8', 'bgr8; png compressed mono8',
                                 'mono8; png compressed bgr8', 'mono8; png'])
def test_colour_data_said_to_be_grey_are_refused_grey_data_read(scene, fmt):
    img, _ = scene
    core = _core()
    _info(core)
    out = core.on_compressed(fmt, _pil(img, 'PNG'))
    assert out.status is DetectStatus.REJECTED and out.measurement == Measurement()
    grey, enc = decode_compressed(fmt, _pil(img, 'PNG', 'L'))
    assert enc == 'mono8'
    assert np.array_equal(grey, np.asarray(PILImage.fromarray(img).convert('L')))


def test_grey_jpeg_under_a_colour_format_is_grey(scene):
    img, _ = scene
    out, enc = decode_compressed('rgb8; jpeg compressed bgr8', _pil(img, 'JPEG', 'L'))
    assert enc == 'mono8' and out.shape == img.shape[:2]


# --- marks: a mark cut by a crop is refused, never measured off its true centre ---------------
def _angle(a, b) -> float:
    return math.degrees(math.acos(min(1.0, float(np.dot(a, b)))))


def _truth(M, target) -> dict:
    return {name: (M.act(p) / np.linalg.norm(M.act(p))) for name, p in target.marks().items()}


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8'])
@pytest.mark.parametrize('side', ['left', 'right', 'top', 'bottom'])
def test_a_mark_cut_by_the_image_border_is_not_measured_wrong(encoding, side):
    """
    Crop a rendered frame through a mark's centre: that mark is not measured.

    The cropped camera's K is shifted; the crop's other marks are the true ones (< 0.3°),
    as the full frame's are.
    """
    target = special_sphere()
    det = Detector.for_target(target)
    truth_seen = cut = 0
    for M in random_poses(target, CAM, 6, 11):
        img = Renderer(CAM, target, background='gradient').render(M)
        full = det.detect(img, 'rgb8', CAM)
        truth = _truth(M, target)
        for name, mark in full.marks.items():
            if mark.visible:
                truth_seen += 1
                assert _angle(mark.ray, truth[name]) < 0.3, name
        for name, mark in full.marks.items():
            if not mark.visible:
                continue
            u, v = (int(round(c)) for c in mark.uv_px)
            x0, y0, x1, y1 = {'left': (u, 0, 640, 480), 'right': (0, 0, u, 480),
                              'top': (0, v, 640, 480), 'bottom': (0, 0, 640, v)}[side]
            crop = np.ascontiguousarray(img[y0:y1, x0:x1])
            try:
                cam = CameraIntrinsics(px=CAM.px, py=CAM.py, u0=CAM.u0 - x0, v0=CAM.v0 - y0,
                                       width=x1 - x0, height=y1 - y0)
            except CameraError:     # a principal point far off a narrow crop: no camera
                continue
            if encoding == 'bgr8':
                crop = np.ascontiguousarray(crop[..., ::-1])
            got = det.detect(crop, encoding, cam)
            cut += 1
            m = got.marks[name]
            assert not m.visible, (name, side, m.uv_px)
            for other, om in got.marks.items():
                if om.visible:
                    assert _angle(om.ray, truth[other]) < 0.3, (other, side)
    assert truth_seen >= 6 and cut >= 6


@pytest.mark.parametrize('fmt', ['x' * 13000, 'rgb8; ' + 'j' * 5000, 'rgb8; jpeg compressed '
                                 + 'b' * 5000, 'bayer' * 3000 + '; jpeg'])
def test_a_huge_format_is_refused_in_a_short_message(fmt):
    with pytest.raises(ValueError) as info:
        parse_format(fmt)
    assert len(str(info.value)) < 400
    with pytest.raises(ValueError) as info:
        decode_compressed(fmt, b'\xff\xd8')
    assert len(str(info.value)) < 400


@pytest.mark.parametrize('fmt, colour', [
    ('rgb8; jpeg compressed bgr8', 'bgr8'), ('rgb8; jpeg', 'rgb8'), ('PNG', 'bgr8'),
    ('RGB8 ;  JPEG   compressed   BGR8', 'bgr8'),  # no colour image upstream: read as meant
    ('rgb8; jpeg compressed  bgr8', None), ('rgb8; JPEG compressed BGR8', None),
    ('bgr8; jpeg Compressed bgr8', None), ('rgba8; png compressed\tbgra8', None)])
def test_a_format_image_transport_reads_in_the_other_order_is_refused(fmt, colour):
    # image_transport finds 'compressed bgr' verbatim; where spacing or case hide it from
    # it, the two readings differ: neither can be trusted
    if colour is None:
        with pytest.raises(ValueError, match='image_transport'):
            parse_format(fmt)
    else:
        assert parse_format(fmt).colour == colour
