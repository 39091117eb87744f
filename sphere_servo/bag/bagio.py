"""
rosbag2 files without ROS.

Open and validate a bag, list its topics, iterate raw messages, summarise its metadata, and
decode its images for offline processing.

Pure module (no rclpy), built on the ``rosbags`` library; shared by the ``record`` and
``replay`` executables and by offline pipelines (``iter_images``). Every failure to read a
bag is raised as :class:`BagError` with a one-line message fit for a command line.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
import sqlite3

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, Qos, QosTime
from rosbags.typesys import get_typestore, Stores
from sphere_servo.vision.image import image_from_buffer, LAYOUTS
import yaml

__all__ = [
    'BagError', 'check_new_output', 'open_bag', 'bag', 'topic_name', 'select_connections',
    'summary', 'format_summary', 'iter_raw', 'image_to_array', 'iter_images', 'typestore',
    'INFINITE_NS', 'qos_time',
]

# rmw's "infinite" duration (RMW_DURATION_INFINITE), as `ros2 bag` writes it in QoS metadata
INFINITE_NS = 2**63 - 1
_TYPESTORE = None


class BagError(ValueError):
    """A bag cannot be created, opened or read; the message is one line."""


def typestore():
    """Return the Jazzy typestore, built on the first call."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def _one_line(err: BaseException) -> str:
    text = ' '.join(str(err).split()) or type(err).__name__
    return text if len(text) <= 300 else text[:297] + '...'


def qos_time(ns: int) -> QosTime:
    """Convert a duration (ns) to QoS metadata time (infinite → sec 9223372036, nsec 854775807)."""
    ns = min(max(int(ns), 0), INFINITE_NS)
    return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)


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


def _bag_dir(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise BagError(f'no such bag: {str(path)!r} does not exist')
    if path.is_file():
        if path.suffix in ('.mcap', '.db3') and (path.parent / 'metadata.yaml').is_file():
            return path.parent
        raise BagError(f'{str(path)!r} is not a rosbag2 bag: give the bag directory '
                       '(with metadata.yaml)')
    if not (path / 'metadata.yaml').is_file():
        raise BagError(f'{str(path)!r} is not a rosbag2 bag: no metadata.yaml in it')
    return path


def _metadata(bag_dir: Path) -> dict:
    try:
        meta = yaml.safe_load((bag_dir / 'metadata.yaml').read_text())
    except (OSError, yaml.YAMLError):
        return {}
    info = meta.get('rosbag2_bagfile_information') if isinstance(meta, dict) else None
    return info if isinstance(info, dict) else {}


def _check_storage(bag_dir: Path) -> None:
    """
    Check the integrity of sqlite3 files, which rosbags only notices midway through a bag.

    MCAP's summary section, read at open, already catches a truncated MCAP.
    """
    info = _metadata(bag_dir)
    db3 = [bag_dir / Path(x).name for x in info.get('relative_file_paths') or []
           if str(x).endswith('.db3')]
    total = 0
    for f in db3:
        try:
            con = sqlite3.connect(f'file:{f}?mode=ro', uri=True)
            try:
                res = con.execute('PRAGMA quick_check').fetchone()
                total += con.execute('SELECT count(*) FROM messages').fetchone()[0]
            finally:
                con.close()
        except sqlite3.Error as err:
            raise BagError(f'cannot read bag {str(bag_dir)!r}: {f.name}: {_one_line(err)}') \
                from None
        if not res or res[0] != 'ok':
            raise BagError(f'cannot read bag {str(bag_dir)!r}: {f.name} is corrupt')
    expected = info.get('message_count')
    if db3 and len(db3) == len(info.get('relative_file_paths') or []) and \
            isinstance(expected, int) and total != expected:
        raise BagError(f'cannot read bag {str(bag_dir)!r}: its db3 holds {total} messages, '
                       f'metadata.yaml says {expected} (truncated?)')


def open_bag(path: str | Path) -> AnyReader:
    """
    Open a rosbag2 directory (MCAP or sqlite3) for reading, or raise :class:`BagError`.

    The caller closes the returned reader (or use :func:`bag`).
    """
    bag_dir = _bag_dir(path)
    reader = AnyReader([bag_dir], default_typestore=typestore())
    try:
        reader.open()
    except Exception as err:  # rosbags raises several types; all mean "unreadable"
        raise BagError(f'cannot read bag {str(bag_dir)!r}: {_one_line(err)}') from None
    try:
        _check_storage(bag_dir)
    except BagError:
        reader.close()
        raise
    return reader


@contextmanager
def bag(path: str | Path) -> Iterator[AnyReader]:
    """
    Open a bag as a context manager (:func:`open_bag`, then close the reader).

    ``with bag(path) as reader:``
    """
    reader = open_bag(path)
    try:
        yield reader
    finally:
        reader.close()


def select_connections(reader: AnyReader, topics: Iterable[str] | None = None) -> list[Connection]:
    """Select the connections on ``topics`` (all when None/empty); unknown topic → BagError."""
    conns = list(reader.connections)
    if not topics:
        return conns
    wanted = [topic_name(t) for t in topics]
    have = {c.topic for c in conns}
    missing = [t for t in wanted if t not in have]
    if missing:
        raise BagError(f'topic {", ".join(missing)} not in bag; it has: '
                       f'{", ".join(sorted(have)) or "(no topics)"}')
    return [c for c in conns if c.topic in wanted]


def _qos_dict(q: Qos) -> dict:
    return {
        'history': q.history.name.lower(), 'depth': q.depth,
        'reliability': q.reliability.name.lower(), 'durability': q.durability.name.lower(),
        'liveliness': q.liveliness.name.lower(),
        'deadline': q.deadline._asdict(), 'lifespan': q.lifespan._asdict(),
        'liveliness_lease_duration': q.liveliness_lease_duration._asdict(),
        'avoid_ros_namespace_conventions': q.avoid_ros_namespace_conventions,
    }


def summary(reader: AnyReader) -> dict:
    """Metadata summary: storage, version, times, counts, and per topic type/count/QoS."""
    topics: dict[str, dict] = {}
    for c in reader.connections:
        t = topics.setdefault(c.topic, {'name': c.topic, 'type': c.msgtype, 'count': 0,
                                        'qos': []})
        t['count'] += c.msgcount
        t['qos'].extend(_qos_dict(q) for q in getattr(c.ext, 'offered_qos_profiles', []))
    files = []
    for rd in reader.readers:
        files.extend(str(Path(rd.path) / Path(x).name)
                     for x in _metadata(Path(rd.path)).get('relative_file_paths') or [])
    info = _metadata(Path(reader.paths[0])) if reader.paths else {}
    start, end = reader.start_time, reader.end_time
    count = sum(t['count'] for t in topics.values())
    if count == 0:
        start = end = 0
    return {
        'paths': [str(p) for p in reader.paths], 'files': files,
        'storage': info.get('storage_identifier'), 'version': info.get('version'),
        'compression': (info.get('compression_mode') or None,
                        info.get('compression_format') or None),
        'start_ns': start, 'end_ns': end, 'duration_s': max(0, end - start) / 1e9,
        'message_count': count, 'topics': sorted(topics.values(), key=lambda t: t['name']),
    }


def format_summary(s: dict) -> str:
    """``ros2 bag info``-like text of :func:`summary`."""
    lines = [f'Files:    {", ".join(Path(f).name for f in s["files"])}',
             f'Storage:  {s["storage"]}',
             f'Duration: {s["duration_s"]:.3f} s',
             f'Messages: {s["message_count"]}',
             'Topics:']
    for t in s['topics']:
        lines.append(f'  {t["name"]} | {t["type"]} | {t["count"]} msgs')
    return '\n'.join(lines)


def iter_raw(reader: AnyReader, connections: list[Connection] | None = None,
             ) -> Iterator[tuple[Connection, int, bytes]]:
    """
    Yield (connection, bag timestamp ns, serialized CDR bytes) in time order.

    Read errors (a corrupt chunk, a truncated file) are raised as BagError.
    """
    it = reader.messages(connections=connections) if connections is not None \
        else reader.messages()
    while True:
        try:
            conn, ts, raw = next(it)
        except StopIteration:
            return
        except Exception as err:
            raise BagError(f'cannot read bag {", ".join(map(str, reader.paths))!r}: '
                           f'{_one_line(err)}') from None
        yield conn, ts, bytes(raw)


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


def iter_images(path: str | Path, topic: str = '/camera/image_raw',
                ) -> Iterator[tuple[int, object, np.ndarray]]:
    """
    Offline processing: (bag timestamp ns, header, image array) for each Image on ``topic``.

    The header (``stamp.sec``, ``stamp.nanosec``, ``frame_id``) is kept so that whatever is
    computed from the image can carry the image's own stamp, as the live nodes do.
    """
    with bag(path) as reader:
        conns = select_connections(reader, [topic])
        for conn, ts, raw in iter_raw(reader, conns):
            if conn.msgtype != 'sensor_msgs/msg/Image':
                raise BagError(f'topic {conn.topic} has type {conn.msgtype}, not an Image')
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:
                raise BagError(f'cannot decode message on {conn.topic}: {_one_line(err)}') \
                    from None
            yield ts, msg.header, image_to_array(msg)
