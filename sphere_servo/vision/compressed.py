"""
Compressed images (no ROS): ``sensor_msgs/CompressedImage`` → ndarray.

What image_transport's ``compressed`` plugin publishes and most recorded camera bags carry.
``format`` is image_transport's ``"<encoding>; <jpeg|png> compressed <encoding>"`` (the
original encoding, then the one the codec was given: colour images are compressed as bgr8
by OpenCV), an older plugin's ``"rgb8; jpeg compressed"`` / ``"rgb8; jpeg"``, or a bare codec
name (``"jpeg"``, ``"png"``: Foxglove, cv_bridge, the first plugin). The bytes are decoded
by OpenCV (``cv2.imdecode``, as the plugin does), and a colour image's channels are in the
order compressed_image_transport's subscriber reads the format in (:func:`parse_format`):
the detector sees red where RViz, rqt and every image_transport subscriber do.
Refused (``ValueError``, saying why): an empty buffer, data that are no bytes, bytes OpenCV
cannot decode or whose image size cannot be read, a format that is not a colour or grey
image of 8 bits (image_transport's ``compressedDepth``, a 16-bit PNG, an unknown codec, an
original encoding the detector does not read, such as a Bayer mosaic, words after the
compressed encoding, which leave what the codec was given a guess), an image that the
format calls mono8 (original or compressed) but that decodes to colour, bytes of another
codec than JPEG, PNG or WebP (whichever the format names, as OpenCV reads what the bytes
are), and an image larger than the bound given (the camera's size; a decompression bomb is
refused before it is decoded). A refused frame is never measured.
"""
from __future__ import annotations

from array import array
from dataclasses import dataclass
import io
import warnings

import cv2
import numpy as np
from PIL import Image as PILImage

from sphere_servo.vision.image import without_alpha

CODECS = ('jpeg', 'jpg', 'png', 'webp')
# what the bytes may be (Pillow's names; MPO is a JPEG with more pictures after the first):
# any of the three under any codec's name, as OpenCV decodes them all. Not TIFF (OpenCV
# applies its orientation tag even with IMREAD_UNCHANGED: a square image would be measured
# rotated against its camera_info), nor BMP, GIF, PNM…, which no CompressedImage carries
CONTENTS = ('JPEG', 'MPO', 'PNG', 'WEBP')
# the most pixels decoded without a camera to bound them (8K is 33 Mpx): a 1 MB PNG of zeros
# declares 20000×20000 px, 1.2 GB and seconds of decoding, for an image no camera sends
MAX_PIXELS = 64_000_000


#: the original encodings (before the ``;``) of the images decoded here: the detector's own
COLOUR = ('rgb8', 'bgr8', 'rgba8', 'bgra8')
ORIGINALS = COLOUR + ('mono8',)


@dataclass(frozen=True)
class Format:
    """
    A CompressedImage ``format``, as compressed_image_transport's subscriber reads it.

    ``codec``: jpeg, jpg, png or webp. ``original``: the image's encoding before the codec
    ('' when the format has no ``;``). ``compressed``: the encoding named after
    ``compressed`` ('' if none). ``colour``: ``bgr8`` or ``rgb8``, the order of a decoded
    colour image's channels (OpenCV returns the file's channels reversed, so ``rgb8`` means
    the producer gave the codec rgb: its file has red and blue swapped).
    """

    codec: str
    original: str
    compressed: str
    colour: str


def _shown(fmt) -> str:
    """Return ``repr(fmt)`` for a message, at most 80 characters (a format can be any size)."""
    text = repr(fmt)
    return text if len(text) <= 80 else f'{text[:60]}… ({len(text)} characters)'


def parse_format(fmt: str) -> Format:
    """
    Read a CompressedImage ``format`` as compressed_image_transport's subscriber does.

    Upstream, ``CompressedSubscriber::internalCallback`` (ros-perception/
    image_transport_plugins, compressed_image_transport/src/compressed_subscriber.cpp: the
    rclcpp file with the ``mode`` parameter; ROS 1's, e.g. f0d9ffb, has the same logic)
    decodes with ``cv::imdecode`` (line 112; IMREAD_UNCHANGED by default: BGR for a colour
    file), then:

    - no ``;`` (lines 115-128): 1 channel is mono8, 3 are bgr8, as decoded: the file is a
      standard JPEG/PNG (``jpeg``, ``png``; the words after the codec are not read);
    - ``;`` and a colour original (rgb8, bgr8, rgba8, bgra8: ``enc::isColor``, lines
      130-137): the decoded channels are taken as bgr when the text after the ``;`` holds
      ``compressed bgr`` (lines 140-152: BGR2RGB for an rgb8 original), else as rgb (lines
      153-166: RGB2BGR for a bgr8 original, nothing for rgb8). So ``rgb8; jpeg compressed
      bgr8`` decodes to bgr8; ``rgb8; jpeg compressed rgb8``, ``rgb8; jpeg`` and ``rgb8;
      jpeg compressed`` (what older plugins wrote: they gave the codec rgb8) to rgb8;
    - ``;`` and another original (mono8): labelled so, the channels as decoded.

    Here the format's case and spacing are not significant (upstream compares verbatim),
    except where that changes the colour order upstream reads: then it is refused.
    Raises ``ValueError`` for a format that is not an 8-bit image this module decodes.
    """
    shown = _shown(fmt)
    text = ' '.join(str(fmt).split()).lower()
    head, sep, tail = text.partition(';')
    words = (tail if sep else head).split()
    if not words:
        raise ValueError(f'CompressedImage format {shown} names no codec: expected e.g. '
                         "'bgr8; jpeg compressed bgr8' or 'png'")
    codec = words[0]
    if codec not in CODECS:
        raise ValueError(f'CompressedImage format {shown}: codec {_shown(codec)} is not an 8-bit '
                         f'image codec this detector decodes ({", ".join(CODECS)}; '
                         'compressedDepth is depth)')
    original = head.strip() if sep else ''
    if sep and original not in ORIGINALS:
        raise ValueError(f'CompressedImage format {shown}: the original encoding '
                         f'{_shown(original)} is not 8-bit colour or grey that the detector reads '
                         f'({", ".join(ORIGINALS)})')
    if not (len(words) == 1 or words[1] == 'compressed' and len(words) <= 3):
        # e.g. 'rgb8; png compressed rgb8 compressed bgr8': upstream finds 'compressed bgr'
        # and reads bgr, yet the codec was said to be given rgb8. What the codec was given is
        # no longer one thing: the colour order would be a guess
        raise ValueError(f'CompressedImage format {shown}: after the codec, expected nothing, '
                         "'compressed' or 'compressed <encoding>'")
    enc = words[2] if len(words) == 3 else ''
    if enc not in ('', 'bgr8', 'rgb8', 'mono8', 'bgra8', 'rgba8'):
        raise ValueError(f'CompressedImage format {shown}: compressed encoding {_shown(enc)} is '
                         'not 8-bit colour or grey')
    colour = 'rgb8' if original in COLOUR and 'compressed bgr' not in tail else 'bgr8'
    theirs = _upstream_colour(str(fmt))
    if theirs is not None and theirs != colour:
        # e.g. 'rgb8; jpeg compressed  bgr8': read verbatim upstream finds no 'compressed bgr'
        raise ValueError(f'CompressedImage format {shown}: read here as {colour}, but as '
                         f'{theirs} by image_transport, which compares the format verbatim '
                         '(case and spaces): the colour order is not one thing')
    return Format(codec, original, enc, colour)


def _upstream_colour(fmt: str) -> str | None:
    """
    Return the channel order compressed_image_transport gives a colour image of ``fmt``.

    Verbatim, as its subscriber compares (:func:`parse_format`); None when it makes no colour
    image of it (an original that is not exactly a colour encoding's name).
    """
    original, sep, tail = fmt.partition(';')
    if not sep:
        return 'bgr8'
    if original not in COLOUR:
        return None
    return 'bgr8' if 'compressed bgr' in tail else 'rgb8'


def compressed_bytes(data) -> np.ndarray:
    """
    Return a CompressedImage's ``data`` as a 1-D uint8 array; ``ValueError`` if it is no bytes.

    rclpy's ``array('B')``, rosbags' uint8 ndarray, bytes, a list of ints in 0..255. Other
    arrays are read by value, never by their memory (an int32 array's raw bytes are no JPEG),
    and a value that is no byte is refused, not wrapped modulo 256 (a changed JPEG byte can
    still decode, to another image).
    """
    if isinstance(data, np.ndarray) and data.dtype == np.uint8:
        return np.ascontiguousarray(data).ravel()
    if isinstance(data, (bytes, bytearray)) or (isinstance(data, array) and data.itemsize == 1):
        return np.frombuffer(data, np.uint8)
    if isinstance(data, memoryview) and data.itemsize == 1:   # strided too: tobytes copies
        return np.frombuffer(data.tobytes(), np.uint8)
    if isinstance(data, (str, int, float)) or data is None:   # bytes(5) is 5 zeros
        raise ValueError(f'CompressedImage data is a {type(data).__name__}, not bytes')
    try:
        values = np.asarray(data).ravel().tolist()
        return np.frombuffer(bytes(values), np.uint8)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'CompressedImage data ({type(data).__name__}) are not bytes '
                         f'(integers in 0..255): {exc}') from None


def declared_size(buf: np.ndarray) -> tuple[str, tuple[int, int]]:
    """
    Return the codec (Pillow's name) and the (width, height) an image's header declares.

    Nothing is decoded. ``ValueError`` if no header is read (not an image Pillow identifies:
    corrupt, truncated).
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', PILImage.DecompressionBombWarning)
            with PILImage.open(io.BytesIO(buf.tobytes())) as im:
                return im.format, im.size
    except PILImage.DecompressionBombError as exc:   # > 179 Mpx: Pillow's own bound
        raise ValueError(f'CompressedImage declares too large an image: {exc}; not '
                         'decoded') from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise ValueError(f'CompressedImage data ({buf.size} bytes): no image size can be '
                         f'read from its header (corrupt or truncated?): {exc}') from None


def decode_compressed(fmt: str, data, max_size: tuple[int, int] | None = None
                      ) -> tuple[np.ndarray, str]:
    """
    Decode a CompressedImage's bytes; return the image and its encoding.

    ``(H, W, 3)`` ``bgr8``/``rgb8`` (alpha dropped; the order :func:`parse_format` reads in
    the format), or ``(H, W)`` ``mono8``; C-contiguous. ``max_size`` = (width, height): the
    largest image decoded (the camera's); without it, :data:`MAX_PIXELS`. Raises
    ``ValueError`` (module docstring: what is refused).
    """
    form, shown = parse_format(fmt), _shown(fmt)
    buf = compressed_bytes(data)
    if buf.size == 0:
        raise ValueError('CompressedImage has no data')
    # the header's size first: decoding a bomb allocates it all before anything can refuse it
    codec, (w, h) = declared_size(buf)
    if codec not in CONTENTS:
        raise ValueError(f'CompressedImage data are a {codec} image, not JPEG, PNG or WebP '
                         f'(format {shown})')
    if max_size is None:
        if w * h > MAX_PIXELS:
            raise ValueError(f'CompressedImage declares a {w}x{h} image: more than '
                             f'{MAX_PIXELS} pixels, not decoded')
    elif w > max_size[0] or h > max_size[1]:
        raise ValueError(f'CompressedImage declares a {w}x{h} image, larger than the '
                         f"camera's {max_size[0]}x{max_size[1]}: not decoded")
    # IMREAD_UNCHANGED ignores an EXIF orientation: the stored pixels are the sensor's, those
    # camera_info describes (IMREAD_COLOR would turn a 640x480 'orientation 6' JPEG 480x640)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:   # OpenCV's own checks (its pixel limit): an assertion, no None
        raise ValueError(f'CompressedImage data ({buf.size} bytes, format {shown}): OpenCV '
                         f'refuses to decode them: {exc}') from None
    if img is None:
        raise ValueError(f'CompressedImage data ({buf.size} bytes, format {shown}) is not an '
                         'image OpenCV can decode (corrupt or truncated?)')
    if img.shape[:2] != (h, w):   # Pillow and OpenCV read other images in these bytes
        raise ValueError(f'CompressedImage data decode to {img.shape[1]}x{img.shape[0]} '
                         f'pixels, but their header says {w}x{h}')
    if img.dtype != np.uint8:
        raise ValueError(f'CompressedImage decodes to {img.dtype} pixels: an 8-bit image is '
                         'needed')
    if img.ndim == 2 or img.shape[2] == 1:
        return np.ascontiguousarray(img.reshape(img.shape[:2])), 'mono8'
    if 'mono8' in (form.original, form.compressed):   # upstream labels it mono8 (an rgb8
        # original compressed as mono8: reads it as rgb) all the same: no order to trust
        raise ValueError(f'CompressedImage format {shown} says mono8, but its data decode '
                         f'to {img.shape[2]} channels')
    if img.shape[2] == 4:
        return without_alpha(img, 'rgba8' if form.colour == 'rgb8' else 'bgra8')
    if img.shape[2] != 3:
        raise ValueError(f'CompressedImage decodes to {img.shape[2]} channels')
    return np.ascontiguousarray(img), form.colour
