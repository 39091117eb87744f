"""
Images with an alpha channel (``rgba8``, ``bgra8``) are measured as the frame without it.

A ZED or Isaac Sim publishes them. Over every colour frame of the detector corpus (both
renderers, textures, distractors, far and grazing targets, five camera models, the CC target
and the balloon), the detector core given the frame as ``rgba8`` or ``bgra8`` — random
alpha, rows padded or not — gives the detection it gives the ``rgb8`` frame, field for
field; a ``bgra8`` buffer labelled ``rgba8`` gives what a ``bgr8`` one labelled ``rgb8``
gives (the swap check's answer), so the alpha path opens no way around it. Encodings the
detector cannot read stay refused.
"""
from __future__ import annotations

from detector_corpus import cases, differences, record
import numpy as np
import pytest

from sphere_servo.pipeline.detector import DetectorCore, DetectStatus
from sphere_servo.pipeline.params import DetectorParams


@pytest.fixture(scope='module')
def frames():
    return [(name, make, img, cam) for name, make, img, enc, cam in cases() if enc == 'rgb8']


def buffer(img: np.ndarray, order: str, alpha: np.ndarray | None, pad: int) -> dict:
    """``img`` (rgb) as a raw buffer: channels in ``order`` ('rgb'/'bgr'), alpha, padding."""
    ch = img if order == 'rgb' else img[..., ::-1]
    if alpha is not None:
        ch = np.dstack([ch, alpha])
    h, w, c = ch.shape
    rows = np.zeros((h, w * c + pad), np.uint8)
    rows[:, :w * c] = ch.reshape(h, -1)
    enc = order + ('a8' if alpha is not None else '8')
    return {'height': h, 'width': w, 'step': w * c + pad, 'encoding': enc,
            'data': rows.tobytes()}


def detect(make, cam, buf: dict, label: str | None = None):
    core = DetectorCore(DetectorParams.from_mapping({}))
    core.detector = make()
    return core.detect(**{**buf, 'encoding': buf['encoding'] if label is None else label},
                       camera=cam)


def test_alpha_is_dropped_and_the_detection_is_the_same(frames):
    rng = np.random.default_rng(7)
    failures, found = [], 0
    for k, (name, make, img, cam) in enumerate(frames):
        want = detect(make, cam, buffer(img, 'rgb', None, 0))
        assert want.status is not DetectStatus.REJECTED, (name, want.reason)
        found += want.detection.found
        alpha = rng.integers(0, 256, img.shape[:2], dtype=np.uint8)
        for order in ('rgb', 'bgr'):
            out = detect(make, cam, buffer(img, order, alpha, 8 * (k % 2)))
            assert out.status is want.status, (name, order, out.reason)
            assert out.encoding == order + '8' and out.image.shape == img.shape
            assert out.image.flags.c_contiguous
            diff = differences(record(want.detection), record(out.detection), rel=0.0)
            if diff or out.measurement != want.measurement:
                failures.append((name, order, diff[:3]))
    assert not failures, failures
    assert found > 0.6 * len(frames)       # not a corpus of misses


def test_a_mislabelled_alpha_frame_is_judged_as_a_mislabelled_one_without(frames):
    refused = 0
    for name, make, img, cam in frames:
        plain = detect(make, cam, buffer(img, 'bgr', None, 0), label='rgb8')
        alpha = detect(make, cam, buffer(img, 'bgr', np.full(img.shape[:2], 255, np.uint8),
                                         4), label='rgba8')
        assert alpha.encoding == 'rgb8'
        diff = differences(record(plain.detection), record(alpha.detection), rel=0.0)
        assert not diff, (name, diff[:3])
        refused += 'swapped' in plain.reason
    assert refused > 10        # the swap check does speak on this corpus


@pytest.mark.parametrize('encoding', ['yuv422', '8UC3', '8UC4', 'mono16', '16UC1', 'rgb16',
                                      'bayer_rggb8', 'RGBA8', ''])
def test_other_encodings_stay_refused(frames, encoding):
    name, make, img, cam = frames[0]
    buf = buffer(img, 'rgb', np.zeros(img.shape[:2], np.uint8), 0)
    out = detect(make, cam, buf, label=encoding)
    assert out.status is DetectStatus.REJECTED and out.image is None
    assert f'unsupported image encoding {encoding!r}' in out.reason
    assert 'rgba8' in out.reason and 'bgra8' in out.reason    # what it does take


def test_a_short_alpha_buffer_is_refused(frames):
    name, make, img, cam = frames[0]
    buf = buffer(img, 'rgb', np.zeros(img.shape[:2], np.uint8), 0)
    out = detect(make, cam, {**buf, 'step': img.shape[1] * 3})   # rows of rgb8, label rgba8
    assert out.status is DetectStatus.REJECTED and 'smaller than a row' in out.reason
