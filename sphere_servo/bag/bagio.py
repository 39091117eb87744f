"""
rosbag2 files without ROS.

Open and validate a bag, list its topics, select what to play, iterate raw messages,
summarise it, and decode its images for offline processing: ``sensor_msgs/msg/Image`` or
``sensor_msgs/msg/CompressedImage`` (what ``ros2 bag record`` of image_transport's
``compressed`` topic holds: JPEG or PNG, :mod:`sphere_servo.vision.compressed`).

Pure module (no rclpy); shared by the ``record``, ``replay`` and ``reindex`` executables and
by offline pipelines (``iter_images``). Bags are read by :class:`~sphere_servo.bag.reader.
BagReader` (every rosbag2 of Jazzy or older: MCAP or sqlite3, split, with or without
``metadata.yaml``, topics matched by name as rosbag2 does). Every failure to read a bag is
raised as :class:`BagError` with a one-line message fit for a command line.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.interfaces import Connection
from sphere_servo.bag.metadata import BagError, INFINITE_NS, qos_dict, qos_time
from sphere_servo.bag.reader import BagReader, one_line, typestore
from sphere_servo.vision.compressed import decode_compressed
from sphere_servo.vision.image import image_from_buffer, LAYOUTS

__all__ = [
    'BagError', 'check_new_output', 'open_bag', 'bag', 'topic_name', 'on_topics',
    'select_connections',
    'Skipped', 'Selection', 'other_definition', 'select', 'summary', 'format_summary',
    'iter_raw',
    'IMAGE_TYPE', 'COMPRESSED_TYPE', 'IMAGE_TYPES', 'is_compressed', 'image_connections',
    'missing_image_topic',
    'image_to_array', 'decode_image', 'iter_images', 'typestore', 'INFINITE_NS', 'qos_time',
]

IMAGE_TYPE = 'sensor_msgs/msg/Image'
COMPRESSED_TYPE = 'sensor_msgs/msg/CompressedImage'
#: the types of an image topic the offline tools read
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)


def topic_name(name: str) -> str:
    """Fully qualified topic name, as the ROS graph and ``ros2 bag`` spell it."""
    name = name.strip()
    return name if name.startswith('/') else '/' + name


def check_new_output(path: str | Path) -> Path:
    """Return the output path for a new bag; it must not exist (rosbag2 never overwrites)."""
    path = Path(path)
    if path.exists():
        raise BagError(f'output path {str(path)!r} exists already; choose a new one')
    if not path.parent.is_dir():
        raise BagError(f'parent directory of output path {str(path)!r} does not exist')
    return path


def open_bag(path: str | Path) -> BagReader:
    """
    Open a rosbag2 (directory, or bare ``.mcap`` / ``.db3``) for reading, or raise BagError.

    The caller closes the returned reader (or use :func:`bag`).
    """
    return BagReader(path).open_files()


@contextmanager
def bag(path: str | Path) -> Iterator[BagReader]:
    """
    Open a bag as a context manager (:func:`open_bag`, then close the reader).

    ``with bag(path) as reader:``
    """
    reader = open_bag(path)
    try:
        yield reader
    finally:
        reader.close()


def on_topics(reader: BagReader, topics: Iterable[str]) -> list[Connection]:
    """
    Return the connections on any of ``topics``, by fully qualified name ([] if none).

    A bag may store a topic relative (``camera/image_raw``, as rosbag2 may write it): it is
    the topic ``/camera/image_raw`` all the same.
    """
    wanted = {topic_name(t) for t in topics}
    return [c for c in reader.connections if topic_name(c.topic) in wanted]


def _match(conns: list[Connection], wanted: str) -> list[Connection]:
    """Return the connections on ``wanted``: as stored, else by fully qualified name."""
    exact = [c for c in conns if c.topic == wanted]
    return exact or [c for c in conns if topic_name(c.topic) == topic_name(wanted)]


def select_connections(reader: BagReader, topics: Iterable[str] | None = None,
                       ) -> list[Connection]:
    """
    Select the connections on ``topics`` (all when None/empty); unknown topic → BagError.

    A topic is found by its name as stored or by its fully qualified name: ``AAA`` and
    ``/AAA`` both select a topic the bag stores as ``AAA`` (relative, as rosbag2 may write
    it) or as ``/AAA``.
    """
    conns = list(reader.connections)
    if not topics:
        return conns
    chosen: dict[int, Connection] = {}
    missing = []
    for t in topics:
        found = _match(conns, t.strip())
        if not found:
            missing.append(t)
        chosen.update((c.id, c) for c in found)
    if missing:
        raise BagError(f'topic {", ".join(missing)} not in bag; it has: '
                       f'{", ".join(sorted(c.topic for c in conns)) or "(no topics)"}')
    return [c for c in conns if c.id in chosen]


@dataclass(frozen=True)
class Skipped:
    """A topic of the bag that will not be played, and why."""

    topic: str
    msgtype: str
    count: int
    reason: str


@dataclass(frozen=True)
class Selection:
    """What a replay of a bag plays: its connections, and the topics left out."""

    connections: list
    skipped: list

    @property
    def count(self) -> int:
        """Messages that will be played (one pass)."""
        return sum(c.msgcount for c in self.connections)


def other_definition(conn: Connection) -> str | None:
    """
    Return why a topic's bytes are not of the Jazzy type of its name, or None.

    The bag records each type's hash (RIHS01, from Iron on): one that differs from Jazzy's
    for a Jazzy type means another definition (fields added, removed or retyped), whose
    bytes a subscriber of the Jazzy type would misread.
    """
    ts = typestore()
    if not conn.digest.startswith('RIHS01_') or conn.msgtype not in ts.fielddefs:
        return None
    jazzy = ts.hash_rihs01(conn.msgtype)
    if conn.digest == jazzy:
        return None
    return (f'it was recorded with another definition of {conn.msgtype} (type hash '
            f'{conn.digest[:15]}..., in Jazzy {jazzy[:15]}...): its bytes would be misread')


def select(reader: BagReader, topics: Iterable[str] | None = None, unplayable=None,
           ) -> Selection:
    """
    Select what to play: ``topics`` (all when None/empty) minus what cannot be played.

    ``unplayable(connection)`` returns why a topic cannot be played, or None (default: only
    CDR serialization is played; never a Jazzy type recorded with another definition, see
    :func:`other_definition`). As ``ros2 bag play``, a topic that cannot be played is
    skipped, with its reason in :attr:`Selection.skipped`, unless it was asked for by name:
    then :class:`BagError` says why.
    """
    asked = bool(topics)
    conns = select_connections(reader, topics)

    def why(c):
        if c.ext.serialization_format != 'cdr':
            return f'serialization format {c.ext.serialization_format!r} is not cdr'
        return other_definition(c) or (unplayable(c) if unplayable is not None else None)

    keep, skipped = [], []
    for c in conns:
        reason = why(c)
        if reason is None:
            keep.append(c)
        elif asked:
            raise BagError(f'cannot play {c.topic} [{c.msgtype}]: {reason}')
        else:
            skipped.append(Skipped(c.topic, c.msgtype, c.msgcount, reason))
    return Selection(keep, skipped)


def summary(reader: BagReader, topics: Iterable[str] | None = None, unplayable=None) -> dict:
    """
    Summarise what a replay plays (:func:`select`): storage, times, counts, topics.

    ``message_count`` and ``topics`` (name, type, count, QoS) count what will be played, as
    read from the storage; ``skipped`` lists the other topics (name, type, count, reason),
    ``stored_count`` every message the storage holds.
    """
    sel = select(reader, topics, unplayable)
    tops = [{'name': c.topic, 'type': c.msgtype, 'count': c.msgcount,
             'qos': [qos_dict(q) for q in c.ext.offered_qos_profiles]}
            for c in sel.connections]
    meta = reader.meta
    count = sel.count
    start, end = (reader.start_time, reader.end_time) if count else (0, 0)
    return {
        'paths': [str(p) for p in reader.paths], 'files': [str(f) for f in reader.files],
        'source': reader.source, 'storage': reader.storage,
        'version': meta.version if meta else None,
        'ros_distro': meta.ros_distro if meta else None,
        'compression': (meta.compression_mode or None, meta.compression_format or None)
        if meta else (None, None),
        'start_ns': start, 'end_ns': end, 'duration_s': max(0, end - start) / 1e9,
        'message_count': count, 'stored_count': reader.stored_count,
        'topics': sorted(tops, key=lambda t: t['name']),
        'skipped': [{'name': s.topic, 'type': s.msgtype, 'count': s.count, 'reason': s.reason}
                    for s in sel.skipped],
        'warnings': list(reader.warnings),
    }


def format_summary(s: dict) -> str:
    """``ros2 bag info``-like text of :func:`summary`."""
    lines = [f'Files:    {", ".join(Path(f).name for f in s["files"])}',
             f'Storage:  {s["storage"]}' + ('' if s.get('source', 'metadata.yaml') ==
                                            'metadata.yaml' else ' (no metadata.yaml)'),
             f'Duration: {s["duration_s"]:.3f} s',
             f'Messages: {s["message_count"]}' + (
                 f' of {s["stored_count"]} stored' if s.get('skipped') else ''),
             'Topics:']
    for t in s['topics']:
        lines.append(f'  {t["name"]} | {t["type"]} | {t["count"]} msgs')
    for t in s.get('skipped', []):
        lines.append(f'  {t["name"]} | {t["type"]} | {t["count"]} msgs | skipped: '
                     f'{t["reason"]}')
    return '\n'.join(lines)


def iter_raw(reader: BagReader, connections: list[Connection] | None = None,
             ) -> Iterator[tuple[Connection, int, bytes]]:
    """
    Yield (connection, bag timestamp ns, serialized CDR bytes) in time order.

    ``connections`` None reads every connection, an empty list none. Read errors (a
    corrupt chunk, a truncated file) are raised as BagError.
    """
    if connections is not None and not connections:
        return
    it = reader.messages(connections=connections or ())
    while True:
        try:
            conn, ts, raw = next(it)
        except StopIteration:
            return
        except BagError:
            raise
        except Exception as err:
            raise BagError(f'cannot read bag {", ".join(map(str, reader.paths))!r}: '
                           f'{one_line(err)}') from None
        yield conn, ts, bytes(raw)


def image_connections(reader: BagReader, topic: str) -> list[Connection]:
    """
    Return the connections of the image topic ``topic``; BagError if it has none to read.

    Refused: a topic not in the bag (the message names ``TOPIC/compressed`` when the bag has
    that instead: image_transport's compressed topic, to give as the image topic; it is never
    taken silently), a topic of another type than :data:`IMAGE_TYPES`.
    """
    conns = _match(list(reader.connections), topic.strip())
    if not conns:
        raise BagError(missing_image_topic(reader, topic))
    for c in conns:
        if c.msgtype not in IMAGE_TYPES:
            raise BagError(f'topic {c.topic} has type {c.msgtype}, not an image '
                           f'({" or ".join(IMAGE_TYPES)})')
    return conns


def missing_image_topic(reader: BagReader, topic: str) -> str:
    """Say that the image topic ``topic`` is not in the bag, and what to give instead."""
    have = sorted({topic_name(c.topic) for c in reader.connections})
    text = f'topic {topic_name(topic)} is not in the bag (it has {", ".join(have) or "no topics"})'
    compressed = topic_name(topic).rstrip('/') + '/compressed'
    if compressed in have:
        text += f'; its compressed images: give --image-topic {compressed}'
    return text


def is_compressed(msg) -> bool:
    """Tell a deserialized ``sensor_msgs/CompressedImage`` (rosbags, rclpy) from an Image."""
    # rosbags' classes name their type; rclpy's do not, and only CompressedImage has a format
    kind = getattr(msg, '__msgtype__', None)
    return kind == COMPRESSED_TYPE if kind else hasattr(msg, 'format')


def image_to_array(msg) -> np.ndarray:
    """
    Decode a deserialized sensor_msgs/Image (rosbags' dataclass) into a numpy array.

    HxWxC (HxW for one channel), C-contiguous; honours ``step`` padding and
    ``is_bigendian``. Raises :class:`BagError` on an encoding it cannot decode or a buffer
    whose size disagrees with ``step`` and ``height``.
    """
    try:
        return np.ascontiguousarray(image_from_buffer(
            msg.height, msg.width, msg.step, msg.encoding, msg.data,
            is_bigendian=bool(msg.is_bigendian), encodings=LAYOUTS))
    except ValueError as exc:
        raise BagError(str(exc)) from None


def decode_image(msg) -> tuple[np.ndarray, str]:
    """
    Return ``(array, encoding)`` of a deserialized Image or CompressedImage.

    An Image: :func:`image_to_array` and its own encoding (an alpha channel kept). A
    CompressedImage: :func:`~sphere_servo.vision.compressed.decode_compressed` (``bgr8`` or
    ``rgb8``, as compressed_image_transport reads its format, or ``mono8``). BagError on
    what neither reads (a compressedDepth or 16-bit image, corrupt or truncated bytes),
    saying why.
    """
    if not is_compressed(msg):
        return image_to_array(msg), str(msg.encoding)
    try:
        return decode_compressed(msg.format, msg.data)
    except ValueError as exc:
        raise BagError(str(exc)) from None


def iter_images(path: str | Path, topic: str = '/camera/image_raw',
                ) -> Iterator[tuple[int, object, np.ndarray]]:
    """
    Offline processing: (bag timestamp ns, header, image array) for each image on ``topic``.

    An Image or a CompressedImage (:func:`decode_image`: a compressed colour image comes in
    the order compressed_image_transport reads its format in, bgr8 for the plugin's own
    ``rgb8; jpeg compressed bgr8``). The header (``stamp.sec``,
    ``stamp.nanosec``, ``frame_id``) is kept so that whatever is computed from the image can
    carry the image's own stamp, as the live nodes do.
    """
    with bag(path) as reader:
        conns = image_connections(reader, topic)
        for conn, ts, raw in iter_raw(reader, conns):
            msg = reader.deserialize(raw, conn.msgtype)
            yield ts, msg.header, decode_image(msg)[0]
