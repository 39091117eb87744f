"""
rosbag2 ``metadata.yaml``: strict parsing on read, and writing it as ROS 2 Jazzy does.

Pure module (no rclpy). Parsing follows rosbag2's own decoder (``rosbag2_storage/yaml.hpp``):
the fields a version introduced are required from that version on (compression from 3,
QoS from 4, ``files`` from 5, ``custom_data`` from 6, type hashes from 7, ``ros_distro``
from 8), counts and times are integers, and a bad field is a :class:`BagError` naming it.
QoS profiles are read in both encodings (a YAML string of integer enums before version 9, a
list of names from 9) and their durations normalised as rosbag2 does
(``rosbag2_storage/qos.cpp``): the "infinite" spellings of older rmw implementations
({2147483647 s, 4294967295 ns} of Fast DDS in Foxy, {2147483647, 2147483647} of Connext, and
2^63-1 ns) and 0/0 ("unspecified", whose default is infinite for deadline, lifespan and
liveliness lease) are all the one infinite duration, so that profiles written by different
tools compare equal.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
import yaml

# rmw's RMW_DURATION_INFINITE, in ns and as metadata writes it (sec 9223372036, nsec 854775807)
INFINITE_NS = 2**63 - 1
INFINITE = QosTime(INFINITE_NS // 1_000_000_000, INFINITE_NS % 1_000_000_000)
# pre-Galactic spellings of infinity (rosbag2_storage/qos.cpp), and "unspecified"
_INFINITE_ALIASES = {(0x7FFFFFFF, 0xFFFFFFFF), (0x7FFFFFFF, 0x7FFFFFFF), (0, 0)}
VERSION = 9          # the metadata version Jazzy writes, and the newest one read
ROS_DISTRO = 'jazzy'
STORAGES = {'mcap': '.mcap', 'sqlite3': '.db3'}
_QOS_ENUMS = {'history': QosHistory, 'reliability': QosReliability,
              'durability': QosDurability, 'liveliness': QosLiveliness}
_DURATIONS = ('deadline', 'lifespan', 'liveliness_lease_duration')


class BagError(ValueError):
    """A bag cannot be created, opened or read; the message is one line."""


def qos_time(ns: int) -> QosTime:
    """Convert a duration (ns) to QoS metadata time (infinite → sec 9223372036, nsec 854775807)."""
    ns = min(max(int(ns), 0), INFINITE_NS)
    return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)


def normal_duration(t: QosTime) -> QosTime:
    """Return ``t``, or :data:`INFINITE` for every spelling of "infinite" and for 0/0."""
    if (t.sec, t.nsec) in _INFINITE_ALIASES or t.sec * 1_000_000_000 + t.nsec >= INFINITE_NS:
        return INFINITE
    return t


def normal_qos(q: Qos) -> Qos:
    """Return ``q`` with its three durations normalised (:func:`normal_duration`)."""
    return q._replace(**{k: normal_duration(getattr(q, k)) for k in _DURATIONS})


@dataclass(frozen=True)
class TopicMeta:
    """One entry of ``topics_with_message_count``."""

    name: str
    msgtype: str
    serialization_format: str = 'cdr'
    qos: tuple[Qos, ...] = ()
    type_hash: str = ''
    message_count: int = 0


@dataclass(frozen=True)
class FileMeta:
    """One entry of ``files``: a storage file's span and count."""

    path: str
    start_ns: int
    duration_ns: int
    message_count: int


@dataclass(frozen=True)
class BagMeta:
    """The content of ``rosbag2_bagfile_information``."""

    storage: str
    relative_file_paths: tuple[str, ...]
    start_ns: int
    duration_ns: int
    message_count: int
    topics: tuple[TopicMeta, ...]
    version: int = VERSION
    compression_format: str = ''
    compression_mode: str = ''
    files: tuple[FileMeta, ...] = ()
    custom_data: dict = field(default_factory=dict)
    ros_distro: str = ROS_DISTRO


class _Fields:
    """Typed access to a YAML mapping; each failure names the field (``where``)."""

    def __init__(self, node, where: str):
        if not isinstance(node, dict):
            raise BagError(f'{where} must be a mapping, got {_show(node)}')
        self.node, self.where = node, where

    def get(self, key: str, kind, default=None, required: bool = True):
        if key not in self.node or (self.node[key] is None and kind is not dict):
            if required:
                raise BagError(f'{self.where}.{key} is missing')
            return default
        value = self.node[key]
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise BagError(f'{self.where}.{key} must be a non-negative integer, '
                               f'got {_show(value)}')
        elif kind is dict:
            value = {} if value is None else value
            if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                      for k, v in value.items()):
                raise BagError(f'{self.where}.{key} must map strings to strings, '
                               f'got {_show(value)}')
        elif not isinstance(value, kind):
            raise BagError(f'{self.where}.{key} must be a {kind.__name__}, got {_show(value)}')
        return value

    def sub(self, key: str) -> _Fields:
        return _Fields(self.get(key, object), f'{self.where}.{key}')

    def ns(self, key: str, inner: str) -> int:
        return self.sub(key).get(inner, int)


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + '...'


def _enum(kind, value, where: str):
    """Parse a QoS policy given as a name (version 9) or an integer (before)."""
    try:
        if isinstance(value, bool):
            raise ValueError
        if isinstance(value, int):
            return kind(value)
        return kind.__members__[str(value).upper()]
    except (KeyError, ValueError):
        return kind.UNKNOWN  # as rmw's *_from_str: an unknown policy, not an error


def parse_qos(value, where: str) -> tuple[Qos, ...]:
    """Parse ``offered_qos_profiles`` (a YAML string before version 9, a list from 9)."""
    if value in (None, ''):
        return ()
    if isinstance(value, str):
        try:
            value = yaml.safe_load(value)
        except yaml.YAMLError as err:
            raise BagError(f'{where} is not valid YAML: {" ".join(str(err).split())}') \
                from None
        if value is None:
            return ()
    if not isinstance(value, list):
        raise BagError(f'{where} must be a list of QoS profiles, got {_show(value)}')
    out = []
    for i, item in enumerate(value):
        f = _Fields(item, f'{where}[{i}]')
        enums = {k: _enum(e, f.get(k, object), f'{f.where}.{k}') for k, e in _QOS_ENUMS.items()}
        times = {k: QosTime(f.ns(k, 'sec'), f.ns(k, 'nsec')) for k in _DURATIONS}
        avoid = f.get('avoid_ros_namespace_conventions', bool)
        out.append(normal_qos(Qos(enums['history'], f.get('depth', int), enums['reliability'],
                                  enums['durability'], times['deadline'], times['lifespan'],
                                  enums['liveliness'], times['liveliness_lease_duration'],
                                  avoid)))
    return tuple(out)


def qos_dict(q: Qos) -> dict:
    """Return a QoS profile as version-9 metadata writes it (policies by name)."""
    return {
        'history': q.history.name.lower(), 'depth': q.depth,
        'reliability': q.reliability.name.lower(), 'durability': q.durability.name.lower(),
        'deadline': q.deadline._asdict(), 'lifespan': q.lifespan._asdict(),
        'liveliness': q.liveliness.name.lower(),
        'liveliness_lease_duration': q.liveliness_lease_duration._asdict(),
        'avoid_ros_namespace_conventions': q.avoid_ros_namespace_conventions,
    }


def qos_yaml(qos) -> str:
    """Return QoS profiles as the YAML string of a storage file (MCAP channel, sqlite3)."""
    qos = list(qos)
    return yaml.safe_dump([qos_dict(q) for q in qos], sort_keys=False).strip() if qos else ''


def parse_metadata(text: str, where: str = 'metadata.yaml') -> BagMeta:
    """Parse the text of a ``metadata.yaml`` strictly; any bad field raises BagError."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise BagError(f'{where} is not valid YAML: {" ".join(str(err).split())}') from None
    info = _Fields(_Fields(doc, where).get('rosbag2_bagfile_information', object),
                   'rosbag2_bagfile_information')
    custom = info.node.get('custom_data')
    if isinstance(custom, dict) and not all(isinstance(x, str) for kv in custom.items()
                                            for x in kv):
        # rosbag2's emitter (yaml-cpp) writes a string value "42" or "true" unquoted: read
        # every scalar of custom_data as written, a string (as rosbag2 reads it back)
        info.node['custom_data'] = yaml.load(text, Loader=yaml.BaseLoader)[
            'rosbag2_bagfile_information']['custom_data']
    version = info.get('version', int)
    if not 1 <= version <= VERSION:
        raise BagError(f'metadata version {version} is not supported (1 to {VERSION}, Jazzy)')
    storage = info.get('storage_identifier', str)
    if storage not in STORAGES:
        raise BagError(f'storage {storage!r} is not supported (only {", ".join(STORAGES)})')
    paths = info.get('relative_file_paths', list)
    if not paths or not all(isinstance(p, str) and p.strip() for p in paths):
        raise BagError(f'relative_file_paths must list file names, got {_show(paths)}')
    topics = []
    for i, item in enumerate(info.get('topics_with_message_count', list)):
        t = _Fields(item, f'topics_with_message_count[{i}]')
        m = t.sub('topic_metadata')
        name = m.get('name', str)
        topics.append(TopicMeta(
            name=name, msgtype=m.get('type', str),
            serialization_format=m.get('serialization_format', str),
            qos=parse_qos(m.get('offered_qos_profiles', object, required=version >= 4),
                          f'{m.where}.offered_qos_profiles'),
            type_hash=m.get('type_description_hash', str, '', required=version >= 7),
            message_count=t.get('message_count', int)))
    files = []
    for i, item in enumerate(info.get('files', list, [], required=version >= 5)):
        f = _Fields(item, f'files[{i}]')
        files.append(FileMeta(f.get('path', str), f.ns('starting_time', 'nanoseconds_since_epoch'),
                              f.ns('duration', 'nanoseconds'), f.get('message_count', int)))
    mode = info.get('compression_mode', str, '', required=version >= 3).lower()
    fmt = info.get('compression_format', str, '', required=version >= 3).lower()
    if mode in ('', 'none'):
        mode = fmt = ''
    elif mode not in ('file', 'message'):
        raise BagError(f'compression_mode {mode!r} is not one of "", file, message')
    elif fmt != 'zstd':
        raise BagError(f'compression_format {fmt!r} is not supported (only zstd)')
    return BagMeta(
        storage=storage, relative_file_paths=tuple(paths),
        start_ns=info.ns('starting_time', 'nanoseconds_since_epoch'),
        duration_ns=info.ns('duration', 'nanoseconds'),
        message_count=info.get('message_count', int), topics=tuple(topics), version=version,
        compression_format=fmt, compression_mode=mode, files=tuple(files),
        custom_data=info.get('custom_data', dict, {}, required=version >= 6),
        ros_distro=info.get('ros_distro', str, '', required=version >= 8))


def read_metadata(bag_dir: Path) -> BagMeta:
    """Read and parse ``bag_dir/metadata.yaml``; errors name the file."""
    path = Path(bag_dir) / 'metadata.yaml'
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise BagError(f'cannot read {path}: {err}') from None
    try:
        return parse_metadata(text)
    except BagError as err:
        raise BagError(f'{path}: {err}') from None


def metadata_dict(meta: BagMeta) -> dict:
    """Return ``rosbag2_bagfile_information`` in Jazzy's field order (version 9)."""
    return {
        'version': VERSION, 'storage_identifier': meta.storage,
        'duration': {'nanoseconds': meta.duration_ns},
        'starting_time': {'nanoseconds_since_epoch': meta.start_ns},
        'message_count': meta.message_count,
        'topics_with_message_count': [
            {'topic_metadata': {'name': t.name, 'type': t.msgtype,
                                'serialization_format': t.serialization_format,
                                'offered_qos_profiles': [qos_dict(q) for q in t.qos],
                                'type_description_hash': t.type_hash},
             'message_count': t.message_count} for t in meta.topics],
        'compression_format': meta.compression_format,
        'compression_mode': meta.compression_mode,
        'relative_file_paths': list(meta.relative_file_paths),
        'files': [{'path': f.path, 'starting_time': {'nanoseconds_since_epoch': f.start_ns},
                   'duration': {'nanoseconds': f.duration_ns},
                   'message_count': f.message_count} for f in meta.files],
        'custom_data': dict(meta.custom_data) or None,
        'ros_distro': ROS_DISTRO,
    }


def metadata_text(meta: BagMeta, wrapped: bool = True) -> str:
    """Return the YAML of ``metadata.yaml`` (``wrapped=False``: the inner mapping only)."""
    inner = metadata_dict(meta)
    return yaml.safe_dump({'rosbag2_bagfile_information': inner} if wrapped else inner,
                          sort_keys=False)


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (a new or renamed file) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_metadata(bag_dir: Path, meta: BagMeta) -> Path:
    """Write ``bag_dir/metadata.yaml`` atomically and durably (temporary file, fsync, rename)."""
    bag_dir = Path(bag_dir)
    path, tmp = bag_dir / 'metadata.yaml', bag_dir / 'metadata.yaml.tmp'
    with open(tmp, 'w') as fh:
        fh.write(metadata_text(meta))
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)
    fsync_dir(bag_dir)
    return path
