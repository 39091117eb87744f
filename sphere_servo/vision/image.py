"""
Images as ndarrays (no ROS): raw ``sensor_msgs/Image`` buffers, checks, colour tests.

- :func:`image_from_buffer`  a raw buffer (height, width, step, encoding, data) → ndarray,
  without cv_bridge; the detector node and the bag tools decode with it.
- :func:`check_image`        an ndarray the detector can use, for its encoding.
- :func:`to_chroma`, :func:`chroma_test`  chromaticity ``rgb / (R + G + B)`` and a fast
  per-pixel "this colour within a tolerance" test.
- :func:`components`         the 8-connected components of a mask (one flood fill for one).
"""
from __future__ import annotations

from array import array

import cv2
import numpy as np

from sphere_servo.core.types import Image
from sphere_servo.core.validation import check_whole

# the encodings the detector works on (8-bit colour or grey)
ENCODINGS = ('rgb8', 'bgr8', 'mono8')
# 8-bit colour with an alpha channel (a ZED, Isaac Sim, a browser's canvas): the detector
# takes their colour channels (:func:`without_alpha`); alpha says nothing of the scene
ALPHA_ENCODINGS = {'rgba8': 'rgb8', 'bgra8': 'bgr8'}
# every encoding a buffer can be decoded from: channels, element type
LAYOUTS = {'rgb8': (3, np.uint8), 'bgr8': (3, np.uint8), 'rgba8': (4, np.uint8),
           'bgra8': (4, np.uint8), 'mono8': (1, np.uint8), '8UC1': (1, np.uint8),
           '8UC3': (3, np.uint8), 'mono16': (1, np.uint16), '16UC1': (1, np.uint16),
           '32FC1': (1, np.float32)}


# --- sensor_msgs/Image buffer → ndarray ---------------------------------------------------
def image_from_buffer(height: int, width: int, step: int, encoding: str, data, *,
                      is_bigendian: bool = False, encodings=ENCODINGS) -> np.ndarray:
    """
    Decode a ``sensor_msgs/Image``-like raw buffer into an ndarray.

    Returns (H, W, C) for a multi-channel encoding (channel order unchanged) or (H, W) for
    one channel, of the encoding's element type (native byte order): a view on ``data``
    for 8-bit encodings, a copy for a byte-swapped one. ``encodings`` are the accepted
    ones (default: the detector's :data:`ENCODINGS`; any of :data:`LAYOUTS`). Raises
    ``ValueError`` on an unsupported encoding, a size or step that is no whole number ≥ 0
    (:func:`~sphere_servo.core.validation.check_whole`: a bool or a fraction is none), a
    zero size, a ``step`` smaller than a row, data that are no bytes, or
    ``len(data) != step · height``.
    """
    if encoding not in encodings or encoding not in LAYOUTS:
        raise ValueError(f'unsupported image encoding {encoding!r}: use one of '
                         f'{tuple(encodings)}')
    height, width, step = (check_whole(ValueError, f'image {name}', value, 0) for name, value
                           in (('height', height), ('width', width), ('step', step)))
    if height <= 0 or width <= 0:
        raise ValueError(f'image has zero size: {width}x{height}')
    ch, dtype = LAYOUTS[encoding]
    dt = np.dtype(dtype).newbyteorder('>' if is_bigendian else '<')
    row = width * ch * dt.itemsize
    if step < row:
        raise ValueError(f'step {step} is smaller than a row of {width} {encoding} pixels '
                         f'({row} bytes)')
    if isinstance(data, (np.ndarray, memoryview, array)) and data.itemsize != 1:
        # its memory is not the message's bytes (an int32 array of byte values is 4× longer)
        raise ValueError(f'image data of {data.itemsize}-byte items: bytes (uint8) needed')
    if isinstance(data, array) and data.itemsize == 1:
        data = memoryview(data)    # rclpy's uint8[]: read in place (a copy costs ~0.3 ms)
    elif not isinstance(data, (bytes, bytearray, memoryview, np.ndarray)):
        try:                       # e.g. a list of ints; not a str, None, an object
            data = bytes(data) if not isinstance(data, str) else None
        except TypeError:
            data = None
        if data is None:
            raise ValueError('image data are no bytes')
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size != step * height:
        raise ValueError(f'image data has {buf.size} bytes, but step·height = '
                         f'{step}·{height} = {step * height}')
    rows = buf.reshape(height, step)[:, :row]
    if dt.itemsize > 1:
        rows = np.ascontiguousarray(rows).view(dt).astype(dtype, copy=False)
    return rows.reshape(height, width, ch) if ch > 1 else rows.reshape(height, width)


def without_alpha(img: np.ndarray, encoding: str) -> tuple[np.ndarray, str]:
    """
    Return an ``rgba8``/``bgra8`` image as ``rgb8``/``bgr8``, and its encoding.

    Alpha is dropped into a C-contiguous copy (``cv2.cvtColor``: 0.06 ms for 640×480, where
    numpy's strided copy takes 1.4 ms); any other encoding is returned as it is. As
    cv_bridge's ``rgba8`` → ``rgb8``: the colour channels are kept, not composited on a
    background (a camera's alpha is opaque, or meaningless). ``ValueError`` if an
    ``rgba8``/``bgra8`` image is not a non-empty (H, W, 4) uint8 array.
    """
    three = ALPHA_ENCODINGS.get(encoding)
    if three is None:
        return img, encoding
    # cvtColor takes an (H, W) or (H, W, 3) image too, and makes a colour image of it: an
    # image of another shape than its encoding's is refused, not turned into another one
    if not (isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
            and img.shape[2] == 4 and img.size):
        raise ValueError(f'{encoding} image must be a non-empty uint8 array of shape '
                         f'(H, W, 4), got {getattr(img, "shape", type(img).__name__)} '
                         f'{getattr(img, "dtype", "")}')
    return cv2.cvtColor(img, cv2.COLOR_RGBA2RGB), three


def check_image(image, encoding: str) -> Image:
    """
    Check an image for the detector; return it as a C-contiguous uint8 array.

    (H, W, 3) for rgb8 and bgr8, (H, W) for mono8 (an (H, W, 1) one is accepted). Raises
    ``ValueError`` on an unsupported encoding, another element type or shape, a zero size.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f'unsupported image encoding {encoding!r}: use one of '
                         f'{ENCODINGS}')
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f'image must be uint8, got {img.dtype}')
    if img.ndim == 3 and img.shape[2] == 1 and encoding == 'mono8':
        img = img[..., 0]
    want = 3 if LAYOUTS[encoding][0] == 3 else 2
    if img.ndim != want or (want == 3 and img.shape[2] != 3):
        raise ValueError(f'{encoding} image must have shape '
                         f'{"(H, W, 3)" if want == 3 else "(H, W)"}, got {img.shape}')
    if img.size == 0:
        raise ValueError(f'image has zero size: shape {img.shape}')
    return np.ascontiguousarray(img)


# --- colour ---------------------------------------------------------------------------------
def to_chroma(rgb: np.ndarray) -> np.ndarray:
    """Chromaticity ``rgb / (R + G + B)`` of (..., 3) colours."""
    tot = rgb[..., 0] + rgb[..., 1] + rgb[..., 2]     # (a last-axis .sum is slow)
    return rgb / np.maximum(tot, 1e-9)[..., None]


def chroma_test(c: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Build ``(Q, w)`` so that ``((p @ Q)² @ w) < 0`` tests an rgb row's chromaticity.

    The chromaticity ``p/Σp`` of the row ``p`` is within ``tol`` of ``c`` iff the test
    holds: ``p @ Q = (p − c·Σp, Σp)`` and ``w = (1, 1, 1, −tol²)``, i.e.
    ``|p − c·Σp|² < tol²·(Σp)²`` (one matrix product instead of a division per channel).
    """
    Q = np.empty((3, 4), np.float32)
    Q[:, :3] = np.eye(3) - np.asarray(c, float)[None, :]
    Q[:, 3] = 1.0
    return Q, np.array([1.0, 1.0, 1.0, -tol * tol], np.float32)


def components(m: np.ndarray, n: int) -> tuple[int, np.ndarray | None, np.ndarray | None]:
    """
    Label the 8-connected components of a 0/1 uint8 mask ``m`` with ``n`` pixels set.

    Returns ``cv2.connectedComponentsWithStats(m, connectivity=8)``'s count (background
    included), labels and stats; for one component (the usual mark) only its count 2, found
    by one flood fill from the first set pixel — sequential, where OpenCV's labelling hands
    a mask of a few rows to its thread pool, which waits for a free core on a loaded
    machine. ``m`` is overwritten.
    """
    x = int(m.reshape(-1).argmax())
    area = cv2.floodFill(m, None, (x % m.shape[1], x // m.shape[1]), 2, 0, 0, 8)[0]
    if area == n:
        return 2, None, None
    nlab, lab, st, _ = cv2.connectedComponentsWithStats((m > 0).view(np.uint8), connectivity=8)
    return nlab, lab, st


def row_ends(pts: np.ndarray) -> np.ndarray:
    """
    Return the first and the last of each row of the (N, 2) ``(x, y)`` pixels, row-major.

    Their convex hull is the pixels' (the same vertices), for a fraction of the points.
    """
    y = pts[:, 1]
    cut = np.flatnonzero(y[1:] != y[:-1])
    return pts[np.concatenate(((0,), cut + 1, cut, (len(y) - 1,)))]
