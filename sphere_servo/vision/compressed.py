"""
Compressed images (no ROS): ``sensor_msgs/CompressedImage`` → ndarray.

What image_transport's ``compressed`` plugin publishes and most recorded camera bags carry.
``format`` is image_transport's ``"<encoding>; <jpeg|png> compressed <encoding>"`` (the
original encoding, then the one the codec was given: colour images are compressed as bgr8
by OpenCV), or a bare codec name (``"jpeg"``, ``"png"``: Foxglove, older drivers). The bytes
are decoded by OpenCV (``cv2.imdecode``, as the plugin does); a colour image comes out in
the order the producer gave the codec: ``bgr8`` unless the format names ``rgb8`` as the
compressed encoding. Refused (``ValueError``, saying why): an empty buffer, bytes OpenCV
cannot decode, a format that is not a colour or grey image of 8 bits (image_transport's
``compressedDepth``, a 16-bit PNG, an unknown codec). A refused frame is never measured.
"""
from __future__ import annotations

from array import array

import cv2
import numpy as np

from sphere_servo.vision.image import without_alpha

CODECS = ('jpeg', 'jpg', 'png', 'webp')


def parse_format(fmt: str) -> tuple[str, str]:
    """
    Return ``(codec, compressed encoding)`` of a CompressedImage ``format`` ('' if unsaid).

    Raises ``ValueError`` for a format that is not an 8-bit image this module decodes.
    """
    text = ' '.join(str(fmt).split()).lower()
    head, sep, tail = text.partition(';')
    words = (tail if sep else head).split()
    if not words:
        raise ValueError(f'CompressedImage format {fmt!r} names no codec: expected e.g. '
                         "'bgr8; jpeg compressed bgr8' or 'png'")
    codec = words[0]
    if codec not in CODECS:
        raise ValueError(f'CompressedImage format {fmt!r}: codec {codec!r} is not an 8-bit '
                         f'image codec this detector decodes ({", ".join(CODECS)}; '
                         'compressedDepth is depth)')
    if sep and head.strip() and not head.strip().endswith('8'):
        raise ValueError(f'CompressedImage format {fmt!r}: the original encoding '
                         f'{head.strip()!r} is not 8-bit colour or grey')
    enc = words[2] if len(words) >= 3 and words[1] == 'compressed' else ''
    if enc not in ('', 'bgr8', 'rgb8', 'mono8', 'bgra8', 'rgba8'):
        raise ValueError(f'CompressedImage format {fmt!r}: compressed encoding {enc!r} is '
                         'not 8-bit colour or grey')
    return codec, enc


def decode_compressed(fmt: str, data) -> tuple[np.ndarray, str]:
    """
    Decode a CompressedImage's bytes; return the image and its encoding.

    ``(H, W, 3)`` ``bgr8``/``rgb8`` (alpha dropped), or ``(H, W)`` ``mono8``; C-contiguous.
    Raises ``ValueError`` (module docstring: what is refused).
    """
    _, enc = parse_format(fmt)
    if isinstance(data, np.ndarray):        # rosbags' uint8[]
        buf = np.ascontiguousarray(data, np.uint8).ravel()
    else:                                   # rclpy's array('B'), bytes; a list of ints
        buf = np.frombuffer(data if isinstance(data, (bytes, bytearray, memoryview, array))
                            else bytes(data), np.uint8)
    if buf.size == 0:
        raise ValueError('CompressedImage has no data')
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f'CompressedImage data ({buf.size} bytes, format {fmt!r}) is not an '
                         'image OpenCV can decode (corrupt or truncated?)')
    if img.dtype != np.uint8:
        raise ValueError(f'CompressedImage decodes to {img.dtype} pixels: an 8-bit image is '
                         'needed')
    if img.ndim == 2 or img.shape[2] == 1:
        return np.ascontiguousarray(img.reshape(img.shape[:2])), 'mono8'
    rgb_order = enc.startswith('rgb')
    if img.shape[2] == 4:
        return without_alpha(img, 'rgba8' if rgb_order else 'bgra8')
    if img.shape[2] != 3:
        raise ValueError(f'CompressedImage decodes to {img.shape[2]} channels')
    return np.ascontiguousarray(img), 'rgb8' if rgb_order else 'bgr8'
