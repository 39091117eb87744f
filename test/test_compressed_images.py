"""
Compressed images (``sensor_msgs/CompressedImage``, image_transport's ``compressed``).

The frames are the detector corpus's colour frames (both renderers, textures, distractors,
far and grazing targets, five camera models, the CC target and the balloon), compressed by
OpenCV as image_transport's plugin does (rgb8 given to the codec as bgr8). Lossless PNG
gives the raw frame's detection field for field; JPEG at image_transport's default quality
(80) and at 95 moves no whole mark more than 1.5 px from where the raw frame has it, nor
the sphere's direction more than 0.05°, and finds the sphere in nearly every frame the raw
one does. What cannot be an 8-bit image (depth, 16 bits, another codec, corrupt or
truncated bytes) is refused, with an empty measurement. Every shape of ``format`` (the
plugin's, older plugins' ``rgb8; jpeg``, a bare ``jpeg``) is decoded in the colour order
compressed_image_transport's subscriber reads in it: red is the frame's red.
"""
from __future__ import annotations

from dataclasses import astuple

import cv2
from detector_corpus import cases, differences, record
import numpy as np
import pytest

from sphere_servo.pipeline.detector import DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.vision.compressed import decode_compressed, parse_format

IT_RGB = 'rgb8; {} compressed bgr8'     # image_transport's format of an rgb8 camera


@pytest.fixture(scope='module')
def frames():
    return [(name, make, img, cam) for name, make, img, enc, cam in cases() if enc == 'rgb8']


def core_of(make) -> DetectorCore:
    core = DetectorCore(DetectorParams.from_mapping({}))
    core.detector = make()
    return core


def encode(bgr: np.ndarray, ext: str, *params) -> bytes:
    ok, buf = cv2.imencode(ext, bgr, list(params))
    assert ok
    return buf.tobytes()


def raw(core, img, cam, encoding='rgb8'):
    h, w = img.shape[:2]
    return core.detect(h, w, img[0].size, encoding, img.tobytes(), cam)


@pytest.mark.parametrize('fmt, want', [
    ('rgb8; jpeg compressed bgr8', ('jpeg', 'rgb8', 'bgr8', 'bgr8')),
    ('bgr8; png compressed bgr8', ('png', 'bgr8', 'bgr8', 'bgr8')),
    ('mono8; jpeg compressed mono8', ('jpeg', 'mono8', 'mono8', 'bgr8')),
    ('rgb8; jpeg compressed rgb8', ('jpeg', 'rgb8', 'rgb8', 'rgb8')),
    ('rgb8; jpeg', ('jpeg', 'rgb8', '', 'rgb8')),
    ('jpeg', ('jpeg', '', '', 'bgr8')), ('PNG', ('png', '', '', 'bgr8')),
    ('  jpg ', ('jpg', '', '', 'bgr8')),
    ('bgra8; png compressed bgra8', ('png', 'bgra8', 'bgra8', 'bgr8')),
])
def test_formats_image_transport_and_others_write(fmt, want):
    """(codec, original encoding, compressed encoding, decoded colour order)."""
    assert astuple(parse_format(fmt)) == want


@pytest.mark.parametrize('fmt', ['16UC1; compressedDepth png', '32FC1; compressedDepth',
                                 'zstd', '', ';', 'bgr8; tiff compressed bgr8',
                                 'mono16; png compressed mono16', 'bgr8; jpeg compressed 16UC1',
                                 'rgb16; png compressed bgr8', 'bayer_rggb8; jpeg compressed ',
                                 '; jpeg'])
def test_formats_that_are_no_8_bit_image_are_refused(fmt):
    with pytest.raises(ValueError, match='CompressedImage format'):
        parse_format(fmt)


def test_png_gives_the_raw_frames_detection(frames):
    failures = []
    for name, make, img, cam in frames:
        core = core_of(make)
        want = raw(core, img, cam)
        out = core.detect_compressed(IT_RGB.format('png'), encode(img[..., ::-1], '.png'), cam)
        assert out.encoding == 'bgr8' and np.array_equal(out.image, img[..., ::-1])
        diff = differences(record(want.detection), record(out.detection), rel=0.0)
        if diff or out.measurement != want.measurement:
            failures.append((name, diff[:3]))
    assert not failures, failures


def test_an_rgb_ordered_codec_and_a_mislabelled_one(frames):
    """
    Read a producer that gave the codec rgb and says so right; judge one that does not.

    The second is a raw rgb8 frame labelled bgr8: the swap check's business.
    """
    refused = 0
    for name, make, img, cam in frames[::3]:
        core = core_of(make)
        png = encode(img, '.png')               # the codec was given rgb, not bgr
        said = core.detect_compressed('rgb8; png compressed rgb8', png, cam)
        assert said.encoding == 'rgb8'
        assert not differences(record(raw(core, img, cam).detection), record(said.detection),
                               rel=0.0), name
        unsaid = core.detect_compressed(IT_RGB.format('png'), png, cam)
        mislabelled = raw(core, img, cam, encoding='bgr8')
        assert not differences(record(mislabelled.detection), record(unsaid.detection),
                               rel=0.0), name
        refused += 'swapped' in unsaid.reason
    assert refused > 3


# Each format's shape, with what its producer gave OpenCV's encoder: 'bgr' a standard
# JPEG/PNG (its colours true in any viewer), 'rgb' one whose red and blue are stored swapped.
# compressed_image_transport's subscriber reads them so (CompressedSubscriber::
# internalCallback, cited in sphere_servo.vision.compressed); the detector must see red there
SHAPES = [
    ('rgb8; jpeg compressed bgr8', 'bgr'),    # the plugin, an rgb8 camera (cv_bridge to bgr8)
    ('bgr8; jpeg compressed bgr8', 'bgr'),    # the plugin, a bgr8 camera
    ('rgb8; jpeg compressed rgb8', 'rgb'),    # a producer that gave the codec rgb, and says so
    ('mono8; jpeg compressed mono8', 'mono'),  # the plugin, a mono8 camera
    ('rgb8; jpeg', 'rgb'),                    # the plugin before 1.8.5 converted colour to rgb8
    ('rgb8; jpeg compressed', 'rgb'),         # ... and wrote exactly this
    ('bgr8; jpeg compressed', 'rgb'),         # ... from a bgr8 camera too
    ('jpeg', 'bgr'),                          # the first plugin, cv_bridge's compressed_imgmsg,
    ('png', 'bgr'),                           # Foxglove: a standard file, no original encoding
]


@pytest.fixture(scope='module')
def red_and_blue(frames):
    """Return a corpus frame (rgb8) with many pixels whose red and blue differ by > 60."""
    for name, make, img, cam in frames:
        rb = img[..., 0].astype(int) - img[..., 2]
        if (np.abs(rb) > 60).sum() > 500:
            return img
    raise AssertionError('no corpus frame has red and blue marks')


@pytest.mark.parametrize('fmt, given', SHAPES)
def test_each_format_shape_decodes_red_as_red(red_and_blue, fmt, given):
    """
    The red the detector sees is the frame's red, for every format shape.

    The detector's red is channel 0 of its rgb view: the image if the decoder calls it
    rgb8, else the image reversed (vision.detector). PNG: exactly the frame; JPEG (95):
    the sign of red − blue is the frame's on every pixel where they differ by more than 60
    levels, and red is nearer the frame's red than its blue (a swap fails both).
    """
    img = red_and_blue
    ext = '.png' if 'png' in fmt else '.jpg'
    source = {'bgr': img[..., ::-1], 'rgb': img,
              'mono': cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)}[given]
    out, enc = decode_compressed(fmt, encode(np.ascontiguousarray(source), ext,
                                             cv2.IMWRITE_JPEG_QUALITY, 95))
    if given == 'mono':
        assert enc == 'mono8' and out.ndim == 2
        return
    assert enc in ('rgb8', 'bgr8') and out.shape == img.shape
    rgb = (out if enc == 'rgb8' else out[..., ::-1]).astype(int)
    if ext == '.png':
        assert np.array_equal(rgb, img)
    truth = img.astype(int)
    rb = truth[..., 0] - truth[..., 2]
    marks = np.abs(rb) > 60
    assert np.array_equal(np.sign(rgb[..., 0] - rgb[..., 2])[marks], np.sign(rb[marks])), fmt
    near, far = (np.abs(rgb[..., 0] - truth[..., c])[marks].mean() for c in (0, 2))
    assert near < 0.25 * far, (fmt, near, far)


def test_a_grey_png_gives_the_raw_grey_frames_detection(frames):
    for name, make, img, cam in frames[::4]:
        grey = np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
        core = core_of(make)
        want = raw(core, grey, cam, encoding='mono8')
        out = core.detect_compressed('mono8; png compressed mono8', encode(grey, '.png'), cam)
        assert out.encoding == 'mono8'
        assert not differences(record(want.detection), record(out.detection), rel=0.0), name


@pytest.mark.parametrize('quality', [95, 80])
def test_jpeg_moves_no_whole_mark(frames, quality):
    found = both = 0
    worst_mark, worst_b = 0.0, 0.0
    for name, make, img, cam in frames:
        core = core_of(make)
        want = raw(core, img, cam).detection
        jpg = encode(img[..., ::-1], '.jpg', cv2.IMWRITE_JPEG_QUALITY, quality)
        out = core.detect_compressed(IT_RGB.format('jpeg'), jpg, cam)
        assert out.status is not DetectStatus.REJECTED, (name, out.reason)
        got = out.detection
        found += want.found
        if not (want.found and got.found):
            # the raw frame's distractor may be no longer sphere-like: a sphere without marks
            assert want.found or not got.found or not any(
                m.visible for m in got.marks.values()), name
            continue
        both += 1
        cos = float(np.clip(want.sphere.b @ got.sphere.b, -1.0, 1.0))
        worst_b = max(worst_b, float(np.degrees(np.arccos(cos))))
        for k, m in got.marks.items():
            ref = want.marks[k]
            if m.visible and not m.partial:
                assert ref.visible, (name, k, 'a mark the raw frame does not have')
                worst_mark = max(worst_mark, float(np.hypot(*(m.uv_px - ref.uv_px))))
    assert both >= 0.95 * found
    assert worst_b < 0.05 and worst_mark < 1.5, (worst_b, worst_mark)


@pytest.mark.parametrize('case', ['corrupt', 'truncated jpeg', 'truncated png', 'empty',
                                  '16-bit png', 'depth', 'a list of ints', 'mono8 in colour'])
def test_what_is_no_image_is_refused_and_measures_nothing(frames, case):
    name, make, img, cam = frames[0]
    jpg = encode(img[..., ::-1], '.jpg')
    png = encode(img[..., ::-1], '.png')
    fmt, data = {
        'corrupt': (IT_RGB.format('jpeg'), bytes(range(256)) * 40),
        'truncated jpeg': (IT_RGB.format('jpeg'), jpg[:len(jpg) * 2 // 3]),
        'truncated png': (IT_RGB.format('png'), png[:-20]),
        'empty': ('jpeg', b''),
        '16-bit png': ('png', encode(img.astype(np.uint16) * 257, '.png')),
        'depth': ('16UC1; compressedDepth png', png),
        'a list of ints': ('png', [0, 1, 2, 3]),
        'mono8 in colour': ('mono8; png compressed mono8', png),
    }[case]
    core = core_of(make)
    core.on_camera_info(cam.width, cam.height, cam.to_camera_info_fields()['k'],
                        cam.to_camera_info_fields()['d'],
                        cam.to_camera_info_fields()['distortion_model'])
    out = core.on_compressed(fmt, data)
    assert out.status is DetectStatus.REJECTED and out.reason, case
    assert out.measurement == Measurement() and out.image is None
    with pytest.raises(ValueError):
        decode_compressed(fmt, data)
