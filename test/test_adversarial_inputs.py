"""
Adversarial inputs of the detector's ROS-free cores: compressed images, alpha, binning/roi.

One frame of the independent renderer (test/independent_render.py: not this package's
renderer), encoded here with OpenCV and Pillow as producers other than image_transport do;
every answer is compared with the raw frame's detection or with the pose. Each test pins a
class of input: it is measured as the raw frame is, or refused with an empty measurement
(status REJECTED), never measured wrong, and no exception escapes. Found by this file and
fixed: a decompression bomb was decoded in full before its size could be refused (seconds,
gigabytes), data that are no bytes raised TypeError, an ndarray of another dtype was wrapped
modulo 256, ``without_alpha`` turned a 2-D or 3-channel image into a colour one.
"""
from __future__ import annotations

from array import array
from dataclasses import astuple
import io
import struct
import time
import zlib

import cv2
from independent_scenes import CAMERAS, scenes
import numpy as np
from PIL import Image as PILImage, TiffImagePlugin
import pytest

from sphere_servo.core.camera_models import camera_info_reduction
from sphere_servo.core.central import CameraError
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.detector import (camera_from_info, camera_from_msg, DetectorCore,
                                            DetectStatus, Refusal)
from sphere_servo.pipeline.params import DetectorParams, ParameterError
from sphere_servo.pipeline.vectors import Measurement
from sphere_servo.vision.compressed import decode_compressed, MAX_PIXELS, parse_format
from sphere_servo.vision.image import without_alpha

K = [600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0]
IT = 'rgb8; {} compressed bgr8'


@pytest.fixture(scope='module')
def scene():
    """(rgb image, t (m), camera, core, raw detection) of one seeded independent frame."""
    img, _, t, _ = next(scenes(CAMERAS['vga_f600'], special_sphere(), 1, 3))
    cam = camera_from_info(640, 480, K, [0.0] * 5)
    core = DetectorCore(DetectorParams.from_mapping({}))
    raw = core.detect(480, 640, 640 * 3, 'rgb8', img.tobytes(), cam)
    assert raw.status is DetectStatus.FOUND
    assert all(m.visible for m in raw.detection.marks.values())
    return img, t, cam, core, raw


def pil(image: PILImage.Image, fmt: str, **kw) -> bytes:
    out = io.BytesIO()
    image.save(out, fmt, **kw)
    return out.getvalue()


def refused(out) -> bool:
    return (out.status is DetectStatus.REJECTED and bool(out.reason)
            and out.measurement == Measurement() and out.image is None)


def close_to_raw(out, raw, px: float = 1.5) -> None:
    """Found; the sphere's direction within 0.05° and every visible mark within ``px``."""
    assert out.status is DetectStatus.FOUND, out.reason
    cos = float(np.clip(out.detection.sphere.b @ raw.detection.sphere.b, -1.0, 1.0))
    assert np.degrees(np.arccos(cos)) < 0.05
    for k, m in out.detection.marks.items():
        if m.visible:
            assert np.hypot(*(m.uv_px - raw.detection.marks[k].uv_px)) < px, k


# --- format ----------------------------------------------------------------------------------
@pytest.mark.parametrize('fmt, want', [
    ('RGB8 ;  JPEG   compressed   BGR8', ('jpeg', 'rgb8', 'bgr8', 'bgr8')),
    ('rgb8;\tjpeg\ncompressed bgr8', ('jpeg', 'rgb8', 'bgr8', 'bgr8')),
    # no ';': compressed_image_transport reads the decoded channels as bgr8, whatever follows
    ('png compressed rgb8', ('png', '', 'rgb8', 'bgr8')),
    # a colour original without 'compressed bgr…': it reads them as rgb (older plugins')
    ('rgb8; jpeg compressed', ('jpeg', 'rgb8', '', 'rgb8')),
    ('bgr8; jpeg', ('jpeg', 'bgr8', '', 'rgb8')),
])
def test_format_spacing_and_case_are_read(fmt, want):
    """(codec, original encoding, compressed encoding, decoded colour order)."""
    assert astuple(parse_format(fmt)) == want


@pytest.mark.parametrize('fmt', ['rgb8; jpeg compressed bgr8; q=80', 'rgb8; compressedDepth png',
                                 'rgb8 jpeg', 'jpeg; rgb8', 'bgr8; jpeg compressed bgr16',
                                 None, b'png', 'avif', 'rgb8;png compressed rgb8;'])
def test_format_with_extra_fields_depth_or_no_codec_is_refused(fmt):
    with pytest.raises(ValueError, match='CompressedImage format'):
        parse_format(fmt)


# --- what the bytes are ----------------------------------------------------------------------
@pytest.mark.parametrize('kind', ['webp lossless', 'png rgba', 'png with exif', 'png'])
def test_lossless_bytes_of_the_three_codecs_give_the_raw_detection(scene, kind):
    """The bytes decide the codec (as cv2.imdecode and image_transport): lossless is exact."""
    img, _, cam, core, raw = scene
    P = PILImage.fromarray(img)
    exif = P.getexif()
    exif[0x0112] = 6
    data = {'webp lossless': lambda: pil(P, 'WEBP', lossless=True), 'png': lambda: pil(P, 'PNG'),
            'png rgba': lambda: pil(P.convert('RGBA'), 'PNG'),
            'png with exif': lambda: pil(P, 'PNG', exif=exif)}[kind]()
    out = core.detect_compressed(IT.format('jpeg'), data, cam)
    assert out.status is DetectStatus.FOUND and out.measurement == raw.measurement


@pytest.mark.parametrize('kind', ['bmp', 'tiff', 'gif', 'ppm'])
def test_bytes_of_other_codecs_are_refused(scene, kind):
    """Was: decoded as OpenCV reads them (no producer of CompressedImage sends them)."""
    img, _, cam, core, _ = scene
    data = pil(PILImage.fromarray(img), kind.upper())
    assert refused(core.detect_compressed('jpeg', data, cam))


def test_tiff_turned_by_its_orientation_tag_is_not_measured(scene):
    """Was: OpenCV turns a TIFF by its tag even IMREAD_UNCHANGED; a square one was measured."""
    img, _, _, core, _ = scene
    square = np.ascontiguousarray(img[:, :480])
    cam = camera_from_info(480, 480, [600.0, 0.0, 240.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0],
                           [0.0] * 5)
    want = core.detect(480, 480, 480 * 3, 'rgb8', square.tobytes(), cam)
    assert want.status is DetectStatus.FOUND
    tags = TiffImagePlugin.ImageFileDirectory_v2()
    tags[274] = 6                                     # orientation: rotate 90° to view
    out = core.detect_compressed('png', pil(PILImage.fromarray(square), 'TIFF', tiffinfo=tags),
                                 cam)
    assert refused(out)


def test_exif_orientation_is_not_applied(scene):
    """A rotated decode would no longer be the camera_info's image: the stored pixels are."""
    img, _, cam, core, raw = scene
    P = PILImage.fromarray(img)
    exif = P.getexif()
    exif[0x0112] = 6                                  # 'rotate 90° clockwise to view'
    plain, turned = pil(P, 'JPEG', quality=95), pil(P, 'JPEG', quality=95, exif=exif)
    a, _ = decode_compressed('jpeg', plain)
    b, _ = decode_compressed('jpeg', turned)
    assert b.shape == (480, 640, 3) and np.array_equal(a, b)
    close_to_raw(core.detect_compressed('jpeg', turned, cam), raw)


def test_cmyk_jpeg_is_converted_to_colour(scene):
    img, _, cam, core, raw = scene
    data = pil(PILImage.fromarray(img).convert('CMYK'), 'JPEG', quality=95)
    out = core.detect_compressed(IT.format('jpeg'), data, cam)
    assert out.image.shape == (480, 640, 3)
    close_to_raw(out, raw)


def test_palette_png_loses_marks_but_misplaces_none(scene):
    img, _, cam, core, raw = scene
    data = pil(PILImage.fromarray(img).convert('P'), 'PNG')
    close_to_raw(core.detect_compressed('png', data, cam), raw)


@pytest.mark.parametrize('kind', ['grey jpeg', 'grey+alpha png'])
def test_grey_bytes_labelled_colour_find_no_coloured_mark(scene, kind):
    img, _, cam, core, raw = scene
    P = PILImage.fromarray(img)
    data = pil(P.convert('L'), 'JPEG') if kind == 'grey jpeg' else pil(P.convert('LA'), 'PNG')
    out = core.detect_compressed(IT.format('png'), data, cam)
    close_to_raw(out, raw)
    assert not any(m.visible for m in out.detection.marks.values())


@pytest.mark.parametrize('kind', ['16-bit png', 'pfm', 'hdr', '1x1 png', 'half size png'])
def test_no_8_bit_image_of_the_cameras_size_is_refused(scene, kind):
    img, _, cam, core, _ = scene
    bgr = img[..., ::-1]
    data = {'16-bit png': lambda: cv2.imencode('.png', bgr.astype(np.uint16) * 257)[1],
            'pfm': lambda: cv2.imencode('.pfm', bgr.astype(np.float32))[1],
            'hdr': lambda: cv2.imencode('.hdr', bgr.astype(np.float32))[1],
            '1x1 png': lambda: cv2.imencode('.png', bgr[:1, :1])[1],
            'half size png': lambda: cv2.imencode('.png', bgr[::2, ::2])[1]}[kind]()
    assert refused(core.detect_compressed('png', data, cam))


# --- decompression bombs ---------------------------------------------------------------------
def zero_png(w: int, h: int) -> bytes:
    """Return a PNG of w×h black rgb pixels (1 MB of it declares 20000×20000)."""
    def chunk(tag, body):
        return struct.pack('>I', len(body)) + tag + body + struct.pack(
            '>I', zlib.crc32(tag + body) & 0xffffffff)
    z = zlib.compressobj(9)
    row = bytes(1 + 3 * w)
    idat = b''.join(z.compress(row) for _ in range(h)) + z.flush()
    return (b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', struct.pack('>IIBBBBB', w, h, 8, 2, 0, 0, 0))
            + chunk(b'IDAT', idat) + chunk(b'IEND', b''))


def big_jpeg(scene) -> bytes:
    """Return the frame's JPEG, its SOF header saying 60000×60000 (10 GB decoded)."""
    data = bytearray(cv2.imencode('.jpg', scene[0])[1].tobytes())
    sof = data.index(b'\xff\xc0')
    data[sof + 5:sof + 9] = struct.pack('>HH', 60000, 60000)
    return bytes(data)


@pytest.mark.parametrize('kind', ['png', 'jpeg'])
@pytest.mark.parametrize('with_camera', [True, False])
def test_decompression_bomb_is_refused_before_decoding(scene, kind, with_camera):
    """Was: decoded in full (a 1 MB PNG: 1.2 GB, seconds), then refused for its size."""
    cam, core = scene[2], scene[3]
    data = zero_png(10_000, 8_000) if kind == 'png' else big_jpeg(scene)
    t0 = time.perf_counter()
    out = core.detect_compressed(IT.format(kind), data, cam if with_camera else None)
    assert refused(out) and time.perf_counter() - t0 < 0.2
    assert 'not decoded' in out.reason
    assert 10_000 * 8_000 > MAX_PIXELS


def test_an_image_smaller_than_the_camera_is_decoded_to_say_why(scene):
    img, _, cam, core, _ = scene
    out = core.detect_compressed('png', cv2.imencode('.png', img[:240])[1], cam)
    assert refused(out) and 'does not match' in out.reason


# --- what the data are -----------------------------------------------------------------------
@pytest.mark.parametrize('kind', ['bytes', 'bytearray', 'array B', 'list', 'uint8 2-D',
                                  'memoryview', 'int32 ndarray of bytes', 'int16 memoryview',
                                  'strided memoryview'])
def test_byte_values_in_any_container_are_read(scene, kind):
    img, _, cam, core, raw = scene
    enc = cv2.imencode('.png', img[..., ::-1])[1].ravel()
    data = {'bytes': lambda: enc.tobytes(), 'bytearray': lambda: bytearray(enc.tobytes()),
            'array B': lambda: array('B', enc.tobytes()), 'list': lambda: enc.tolist(),
            'uint8 2-D': lambda: enc.reshape(1, -1), 'memoryview': lambda: memoryview(enc),
            'int32 ndarray of bytes': lambda: enc.astype(np.int32),
            'int16 memoryview': lambda: memoryview(enc.astype(np.int16)),
            'strided memoryview': lambda: memoryview(np.repeat(enc, 2))[::2]}[kind]()
    out = core.detect_compressed(IT.format('png'), data, cam)
    assert out.status is DetectStatus.FOUND and out.measurement == raw.measurement


@pytest.mark.parametrize('kind', ['str', 'None', 'int', 'float', 'float ndarray', 'wrapping int16',
                                  'negative list', 'object'])
def test_data_that_are_no_bytes_are_refused_not_raised(scene, kind):
    """Was: TypeError escaped for str/None, bytes(5) decoded 5 zeros, int16 wrapped mod 256."""
    img, _, cam, core, _ = scene
    enc = cv2.imencode('.png', img[..., ::-1])[1].ravel()
    data = {'str': 'abc', 'None': None, 'int': 5, 'float': 1.5,
            'float ndarray': enc.astype(float), 'wrapping int16': enc.astype(np.int16) + 256,
            'negative list': [-1, 300], 'object': object()}[kind]
    assert refused(core.detect_compressed(IT.format('png'), data, cam))
    assert refused(core.on_compressed('png', data))
    with pytest.raises(ValueError):
        decode_compressed('png', data)


# --- alpha -----------------------------------------------------------------------------------
@pytest.mark.parametrize('pad', [0, 1, 2, 3, 4, 13])
@pytest.mark.parametrize('encoding', ['rgba8', 'bgra8'])
def test_alpha_rows_with_any_padding_give_the_raw_detection(scene, encoding, pad):
    img, _, cam, core, raw = scene
    four = np.dstack([img, np.full(img.shape[:2], 7, np.uint8)])
    if encoding == 'bgra8':
        four = four[..., [2, 1, 0, 3]]
    rows = np.full((480, 640 * 4 + pad), 255, np.uint8)
    rows[:, :640 * 4] = four.reshape(480, -1)
    out = core.detect(480, 640, 640 * 4 + pad, encoding, rows.tobytes(), cam)
    assert out.encoding == encoding[:3] + '8' and out.measurement == raw.measurement


@pytest.mark.parametrize('step, extra', [(640 * 4 - 1, 0), (640 * 4, 1), (640 * 3, 0)])
def test_alpha_buffer_of_another_size_is_refused(scene, step, extra):
    img, _, cam, core, _ = scene
    data = bytes(step * 480 + extra)
    assert refused(core.detect(480, 640, step, 'rgba8', data, cam))


@pytest.mark.parametrize('height, step, data', [
    (None, 1920, bytes(921600)), (float('inf'), 1920, bytes(921600)), (480.5, 1920, bytes(921600)),
    (480, '1920', bytes(921600)), (480, 1920, None), (480, 1920, 'x' * 921600),
    (480, 1920, object()), (480, 1920, np.zeros(921600 // 4, np.int32)),
    (480, 1920, memoryview(np.zeros(921600 // 2, np.uint16))),
])
def test_raw_fields_that_are_no_image_are_refused_not_raised(scene, height, step, data):
    """Was: TypeError or OverflowError escaped; 480.5 rows were read as 480."""
    cam, core = scene[2], scene[3]
    assert refused(core.detect(height, 640, step, 'rgb8', data, cam))


def test_raw_fields_of_numpy_and_whole_float_types_are_read(scene):
    img, _, cam, core, raw = scene
    out = core.detect(480.0, np.int64(640), np.uint32(1920), 'rgb8', img.tobytes(), cam)
    assert out.measurement == raw.measurement


@pytest.mark.parametrize('shape, dtype', [((480, 2560), np.uint8), ((48, 64, 3), np.uint8),
                                          ((0, 64, 4), np.uint8), ((48, 64, 4), np.uint16),
                                          ((48, 64, 2), np.uint8)])
def test_without_alpha_refuses_what_is_no_four_channel_image(shape, dtype):
    """Was: cv2 made a colour image of an (H, W) or (H, W, 3) one, or raised cv2.error."""
    with pytest.raises(ValueError, match=r'\(H, W, 4\)'):
        without_alpha(np.zeros(shape, dtype), 'rgba8')


# --- camera_info binning and roi -------------------------------------------------------------
def reduced(**kw):
    return camera_from_info(640, 480, K, [0.0] * 5, **kw)


@pytest.mark.parametrize('kw', [
    {'binning_x': 2.5}, {'binning_x': -1}, {'binning_y': float('nan')}, {'binning_y': 1e30},
    {'binning_x': float('inf')}, {'binning_x': None}, {'binning_x': 641}, {'binning_x': 'two'},
    {'roi': (640, 0, 1, 1)}, {'roi': (0, 480, 1, 1)}, {'roi': (0, 0, 641, 480)},
    {'roi': (-1, 0, 10, 10)}, {'roi': (0, 0, 0, 10)}, {'roi': (0.5, 0, 10, 10)},
    {'roi': (0, 0, 10)}, {'roi': 'abcd'}, {'roi': (2 ** 63, 0, 1, 1)},
    {'binning_x': 640},                       # 1×480 px: fx 0.94 px for a 480 px side
    {'roi': (100, 100, 200, 200), 'intrinsics_error': (0.1, 0.1, 5.0, 5.0)},
])
def test_binning_or_roi_no_image_has_is_refused(kw):
    assert isinstance(reduced(**kw), Refusal)


@pytest.mark.parametrize('roi, u0, v0', [((0, 0, 1, 1), 320, 240), ((639, 0, 1, 1), -319, 240),
                                         ((0, 479, 1, 1), 320, -239),
                                         ((639, 479, 1, 1), -319, -239)])
def test_one_pixel_roi_at_each_corner_keeps_the_calibrated_principal_point(roi, u0, v0):
    cam = reduced(roi=roi)
    assert (cam.width, cam.height, cam.u0, cam.v0, cam.px) == (1, 1, u0, v0, 600.0)
    assert cam.reduction.to_full(cam.u0, cam.v0) == (320.0, 240.0)


def test_one_axis_binning_and_numbers_of_other_types():
    cam = reduced(binning_y=np.uint8(2), roi=[np.int64(0), 0, 640, 480])
    want = (640, 240, 600, 300, 320, 120)
    assert (cam.width, cam.height, cam.px, cam.py, cam.u0, cam.v0) == want
    assert camera_info_reduction(640, 480, 1, 1, (0, 0, 640, 480)) is None
    with pytest.raises(CameraError, match='binning_x'):
        camera_info_reduction(640, 480, 0.5)


@pytest.mark.parametrize('model, d', [('equidistant', [0.1, -0.02, 0.0, 0.0]),
                                      ('unified', [0.8, 0.01, 0.0, 0.0, 0.0])])
def test_binning_keeps_the_model_and_its_distortion(model, d):
    full = camera_from_info(640, 480, K, d, distortion_model=model)
    half = camera_from_info(640, 480, K, d, distortion_model=model, binning_x=2, binning_y=2)
    assert type(half) is type(full) and half.dist == full.dist
    assert (half.width, half.height, half.px, half.u0) == (320, 240, 300.0, 160.0)
    P = np.array([[0.3, -0.2, 1.0], [-0.5, 0.4, 1.0]])
    assert np.allclose(half.project(P) * 2.0, full.project(P), atol=1e-9)


def test_roi_message_with_do_rectify_reads_the_raw_roi():
    class Roi:
        x_offset, y_offset, width, height, do_rectify = 100, 50, 320, 240, True

    class Info:
        width, height, k, d, distortion_model = 640, 480, K, [0.0] * 5, 'plumb_bob'
        binning_x, binning_y, roi = 0, 0, Roi()

    cam = camera_from_msg(Info())
    assert (cam.width, cam.height, cam.u0, cam.v0) == (320, 240, 220.0, 190.0)


def test_crop_whose_principal_point_is_outside_it_measures_the_full_frames_sphere(scene):
    """A crop of the rendered frame, (u0, v0) = (320, 180) right of its 240 px: same sphere."""
    img, t, _, core, raw = scene
    x, y, w, h = 0, 60, 240, 300
    cam = reduced(roi=(x, y, w, h))
    assert cam.u0 > cam.width
    crop = np.ascontiguousarray(img[y:y + h, x:x + w])
    out = core.detect(h, w, w * 3, 'rgb8', crop.tobytes(), cam)
    b = out.detection.sphere.b
    assert out.status is DetectStatus.FOUND
    assert np.degrees(np.arccos(min(1.0, b @ raw.detection.sphere.b))) < 0.01
    assert np.degrees(np.arccos(min(1.0, b @ t / np.linalg.norm(t)))) < 0.1
    for k, m in out.detection.marks.items():
        assert np.allclose(m.uv_px + (x, y), raw.detection.marks[k].uv_px, atol=0.01)


def test_crop_given_without_its_roi_is_refused(scene):
    img, _, cam, core, _ = scene
    crop = np.ascontiguousarray(img[60:360, :240])
    assert refused(core.detect(300, 240, 240 * 3, 'rgb8', crop.tobytes(), cam))


# --- parameters ------------------------------------------------------------------------------
@pytest.mark.parametrize('values', [
    {'image_reliability': 'BEST_EFFORT'}, {'image_reliability': ''},
    {'image_reliability': 1}, {'image_reliability': True}, {'image_reliability': 'best effort'},
    {'image_transport': 'theora'}, {'image_transport': 'Compressed'},
    {'image_transport': 'compressed '}, {'image_transport': 'compressedDepth'},
    {'image_transport': None}, {'image_transport': ['raw']},
])
def test_transport_and_reliability_outside_their_choices_refuse_start_up(values):
    with pytest.raises(ParameterError):
        DetectorParams.from_mapping(values)
