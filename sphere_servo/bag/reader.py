"""
Read any rosbag2 of ROS 2 Jazzy or older (MCAP, sqlite3), matching topics as rosbag2 does.

Pure module (no rclpy), on the storage readers of the ``rosbags`` library. ``rosbags``'
directory reader pairs a storage file's connections with ``metadata.yaml``'s topics only
when their QoS profiles are identical, so a bag whose ``metadata.yaml`` writes a duration as
0/0 while its storage says 2147483647/4294967295 (both "infinite"; rosbag2's own bags do this)
reads as empty. rosbag2 identifies a topic by its name (``SerializedBagMessage::topic_name``
against the topics of ``metadata.yaml``, in ``rosbag2_transport/player.cpp``); so does
:class:`BagReader`: it opens each storage file itself, takes its own connection list, and
merges connections by topic name across the files of a split bag, with the type, QoS and
hash of ``metadata.yaml`` where it has the topic (QoS normalised, see
:mod:`sphere_servo.bag.metadata`). Counts are the storage's own.

A bag is a directory with ``metadata.yaml`` (parsed strictly), a directory of storage files
without it, or a bare ``.mcap`` / ``.db3`` file (as ``ros2 bag info`` accepts them; one
file of a split bag is that file alone, with what ``metadata.yaml`` says of its topics).
The storage files are read by :mod:`sphere_servo.bag.storage` (``rosbags``' readers, made to
read what they misread). A storage
file that was never closed (an MCAP file without its footer, a sqlite3 file with a live WAL or
journal: the recorder was killed, or is still running) is refused with the command that
recovers it (``reindex``). The reader offers what ``rosbags``' ``AnyReader`` offers to the
code built on it: ``connections``, ``messages()``, ``deserialize()``, ``start_time``,
``end_time``, ``close()``.
"""
from __future__ import annotations

import heapq
from pathlib import Path
import re
import shutil
import sqlite3
import tempfile

from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                MessageDefinitionFormat)
from rosbags.typesys import get_types_from_idl, get_types_from_msg, get_typestore, Stores

from sphere_servo.bag import mcap
from sphere_servo.bag.metadata import BagError, BagMeta, normal_qos, read_metadata, STORAGES
from sphere_servo.bag.storage import storage_reader

_TYPESTORE = None
ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'
REINDEX_HINT = 'run `reindex {}` (ros2 run sphere_servo reindex) to recover its messages'


def typestore():
    """Return the Jazzy typestore, built on the first call."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def one_line(err: BaseException) -> str:
    """Return an exception's text on one line (at most 300 characters)."""
    text = ' '.join(str(err).split()) or type(err).__name__
    return text if len(text) <= 300 else text[:297] + '...'


def storage_files(bag_dir: Path) -> list[Path]:
    """Return the storage files of a directory, in split order (``NAME_<n>``, then by name)."""
    files = [p for p in bag_dir.iterdir() if p.is_file() and p.suffix in ('.mcap', '.db3')]

    def order(p: Path):
        m = re.search(r'_(\d+)$', p.stem)
        return (int(m[1]) if m else -1, p.name)
    return sorted(files, key=order)


def unclosed(path: Path) -> str | None:
    """Return why a storage file was not closed properly, or None when it was."""
    if path.suffix == '.mcap':
        return None if mcap.is_finished(path) else 'it has no MCAP footer (never closed)'
    for suffix in ('-wal', '-journal'):
        side = path.with_name(path.name + suffix)
        if side.is_file() and side.stat().st_size > 0:
            return f'its {side.name} holds data not yet in the database (never closed)'
    return None


def has_definition(msgdef: MessageDefinition) -> bool:
    """
    Whether a recorded message definition defines something.

    An empty text (a type whose definition the recorder did not find) is no definition: the
    type is then read as Jazzy defines it, not as a message without fields.
    """
    return msgdef.format != MessageDefinitionFormat.NONE and bool(msgdef.data.strip())


def message_compression(st) -> str:
    """
    Return ``message`` if an open storage holds zstd-compressed messages, else ''.

    For a bag without ``metadata.yaml``: its first message tells (CDR starts with an
    encapsulation header, never with the zstd frame magic).
    """
    if not st.metadata.message_count:
        return ''
    first = next(iter(st.messages(st.connections)), None)
    return 'message' if first is not None and bytes(first[2][:4]) == ZSTD_MAGIC else ''


def check_sqlite(path: Path, recover: bool = False) -> None:
    """
    Check a sqlite3 file's integrity (rosbags would notice damage only midway).

    ``recover``: first let SQLite recover what a killed writer left (replay the WAL, roll a
    journal back) and return the file to rollback-journal mode, self-contained.
    """
    try:
        con = sqlite3.connect(str(path), isolation_level=None) if recover else \
            sqlite3.connect(f'file:{path}?immutable=1', uri=True)
        try:
            if recover:
                con.execute('PRAGMA journal_mode=DELETE')
            res = con.execute('PRAGMA quick_check').fetchone()
            con.execute('SELECT count(*) FROM messages').fetchone()
        finally:
            con.close()
    except sqlite3.Error as err:
        raise BagError(f'{path.name}: {one_line(err)}') from None
    if not res or res[0] != 'ok':
        raise BagError(f'{path.name} is corrupt')


def _resolve(path: Path) -> tuple[Path, list[Path], BagMeta | None]:
    """Return (bag directory, storage files, metadata or None) for a path given by a user."""
    if not path.exists():
        raise BagError(f'no such bag: {str(path)!r} does not exist')
    if path.is_file():
        if path.suffix not in ('.mcap', '.db3'):
            raise BagError(f'{str(path)!r} is not a rosbag2 bag: give a bag directory, an '
                           '.mcap or a .db3 file')
        if (path.parent / 'metadata.yaml').is_file():
            meta = read_metadata(path.parent)
            if path.name in {Path(p).name for p in meta.relative_file_paths}:
                # that file alone (one part of a split bag, as rosbag2 reads a file), with
                # what metadata.yaml says of its topics
                bag_dir, files, meta = _resolve(path.parent)
                return bag_dir, [f for f in files if f.name == path.name], meta
        return path.parent, [path], None
    if (path / 'metadata.yaml').is_file():
        meta = read_metadata(path)
        files = [path / Path(p).name for p in meta.relative_file_paths]
        twice = sorted({f.name for f in files if files.count(f) > 1})
        if twice:  # its messages would all be read twice
            raise BagError(f'{str(path)!r}: metadata.yaml lists {", ".join(twice)} twice')
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise BagError(f'{str(path)!r}: metadata.yaml lists missing files: '
                           f'{", ".join(missing)}')
        suffix = STORAGES[meta.storage] + ('.zstd' if meta.compression_mode == 'file' else '')
        if any(not f.name.endswith(suffix) for f in files):
            raise BagError(f'{str(path)!r}: metadata.yaml says {meta.storage} storage but '
                           f'lists {", ".join(f.name for f in files)}')
        return path, files, meta
    files = storage_files(path)
    if not files:
        raise BagError(f'{str(path)!r} is not a rosbag2 bag: no metadata.yaml and no .mcap '
                       'or .db3 file in it')
    if len({f.suffix for f in files}) > 1:
        raise BagError(f'{str(path)!r} holds both .mcap and .db3 files and no metadata.yaml')
    return path, files, None


class BagReader:
    """A rosbag2 open for reading (see the module docstring); use as a context manager."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.bag_dir, self.files, self.meta = _resolve(self.path)
        self.paths = [self.path]
        self.storage = (self.meta.storage if self.meta else
                        'mcap' if self.files[0].suffix == '.mcap' else 'sqlite3')
        self.compression_mode = self.meta.compression_mode if self.meta else ''
        self.connections: list[Connection] = []
        self.storages: list = []
        self.warnings: list[str] = []
        self._tmp = None
        self._typestores: dict = {}
        self._msgdefs: dict = {}
        self._ambiguous: set = set()  # types the bag defines twice, differently
        self.stored_count = 0
        self.start_time, self.end_time = 2**63 - 1, 0
        self.is_open = False

    @property
    def source(self) -> str:
        return 'metadata.yaml' if self.meta else 'storage'

    @property
    def message_count(self) -> int:
        return sum(c.msgcount for c in self.connections)

    @property
    def duration(self) -> int:
        return max(0, self.end_time - self.start_time)

    def open_files(self) -> BagReader:
        """Open the storage files and pair their connections (raises BagError)."""
        try:
            for f in self._storage_paths():
                why = unclosed(f)
                if why is not None:
                    raise BagError(f'{f.name} was not closed ({why.split(" (")[0]}; its recorder '
                                   f'was killed, or is still writing): '
                                   + REINDEX_HINT.format(self.bag_dir))
                if f.suffix == '.db3':
                    check_sqlite(f)
                st = storage_reader(f)
                try:
                    st.open()
                except Exception as err:  # rosbags raises several types: all "unreadable"
                    raise BagError(f'{f.name}: {one_line(err)}') from None
                self.storages.append(st)
            if self.meta is None:  # rosbag2 compresses per message in either storage
                modes = {message_compression(st) for st in self.storages} - {''}
                self.compression_mode = modes.pop() if modes else ''
            self._merge()
        except BagError as err:
            self.close()
            raise BagError(f'cannot read bag {str(self.path)!r}: {err}') from None
        self.is_open = True
        return self

    def _storage_paths(self) -> list[Path]:
        if self.compression_mode != 'file':
            return list(self.files)
        from backports import zstd
        self._tmp = tempfile.TemporaryDirectory(prefix='bag_')
        out = []
        for f in self.files:
            dst = Path(self._tmp.name) / f.name[:-len('.zstd')]
            try:
                with open(f, 'rb') as src, zstd.open(src, 'rb') as z, open(dst, 'wb') as o:
                    shutil.copyfileobj(z, o)
            except Exception as err:
                raise BagError(f'{f.name}: cannot decompress: {one_line(err)}') from None
            out.append(dst)
        return out

    def _merge(self) -> None:
        """Build one connection per topic name over all storage files (see module docstring)."""
        meta_topics = {t.name: t for t in self.meta.topics} if self.meta else {}
        order = list(meta_topics)
        merged: dict[str, dict] = {}
        for st in self.storages:
            for sc in st.connections:
                m = merged.setdefault(sc.topic, {'type': sc.msgtype, 'count': 0, 'conns': [],
                                                 'ext': sc.ext, 'digest': sc.digest,
                                                 'msgdef': sc.msgdef})
                if sc.msgtype != m['type']:
                    self.warnings.append(
                        f'topic {sc.topic} has type {sc.msgtype} in {Path(st.path).name} and '
                        f'{m["type"]} elsewhere: its {sc.msgcount} {sc.msgtype} messages are '
                        'not read')
                    continue
                m['count'] += sc.msgcount
                m['conns'].append((st, sc))
                if not has_definition(m['msgdef']):
                    m['msgdef'] = sc.msgdef
                if sc.topic not in order:
                    order.append(sc.topic)
                self.start_time = min(self.start_time, st.metadata.start_time)
                self.end_time = max(self.end_time, st.metadata.end_time)
        self._storage_of: dict[int, list] = {}
        for name in order:
            m, t = merged.get(name), meta_topics.get(name)
            if t is not None and m is not None and t.msgtype != m['type']:
                self.warnings.append(f'metadata.yaml gives {name} type {t.msgtype}, the storage '
                                     f'{m["type"]}: read as {m["type"]}')
            msgtype = m['type'] if m else t.msgtype
            qos = t.qos if t is not None and t.qos else tuple(
                normal_qos(q) for q in m['ext'].offered_qos_profiles) if m else ()
            fmt = m['ext'].serialization_format if m else t.serialization_format
            digest = (t.type_hash if t is not None and t.type_hash else m['digest'] if m else '')
            conn = Connection(
                id=len(self.connections) + 1, topic=name, msgtype=msgtype,
                msgdef=m['msgdef'] if m else MessageDefinition(MessageDefinitionFormat.NONE, ''),
                digest=digest,
                msgcount=m['count'] if m else 0,
                ext=ConnectionExtRosbag2(serialization_format=fmt,
                                         offered_qos_profiles=list(qos)),
                owner=self)
            self.connections.append(conn)
            self._storage_of[conn.id] = m['conns'] if m else []
            for _, sc in m['conns'] if m else ():
                if has_definition(sc.msgdef):  # one type, one definition (the bytes' layout)
                    first = self._msgdefs.setdefault(msgtype, sc.msgdef)
                    if first.data.split() != sc.msgdef.data.split():
                        self._ambiguous.add(msgtype)
        self.stored_count = sum(c.msgcount for c in self.connections)
        whole = self.meta and len(self.files) == len(self.meta.relative_file_paths)
        if whole and self.meta.message_count != self.stored_count:
            self.warnings.append(f'metadata.yaml counts {self.meta.message_count} messages, the '
                                 f'storage holds {self.stored_count} (the storage is read)')
        if not self.stored_count:
            self.start_time, self.end_time = 0, 0

    def messages(self, connections=(), start: int | None = None, stop: int | None = None):
        """
        Yield (connection, timestamp ns, serialized bytes) in time order, over all files.

        As ``AnyReader.messages``: an empty ``connections`` means every connection.
        """
        if self.compression_mode == 'message':
            from backports import zstd
            unpack = zstd.decompress
        else:
            unpack = None
        conns = list(connections) or self.connections
        per_storage: dict[int, tuple] = {}
        for c in conns:
            for st, sc in self._storage_of.get(c.id, []):
                per_storage.setdefault(id(st), (st, {}))[1][sc.id] = c
        gens = [self._read(st, cmap, start, stop, unpack) for st, cmap in per_storage.values()]
        yield from heapq.merge(*gens, key=lambda m: m[1])

    @staticmethod
    def _read(st, cmap: dict, start, stop, unpack):
        wanted = [sc for sc in st.connections if sc.id in cmap]
        for sc, ts, data in st.messages(wanted, start, stop):
            yield cmap[sc.id], ts, unpack(data) if unpack else data

    def decodable(self, msgtype: str) -> str | None:
        """Return why messages of ``msgtype`` cannot be deserialized, or None if they can."""
        try:
            self._typestore_for(msgtype)
        except BagError as err:
            return str(err)
        return None

    def _typestore_for(self, msgtype: str):
        if msgtype in self._ambiguous:
            raise BagError(f'the bag holds two different definitions of {msgtype}: its '
                           'messages cannot all be decoded as one of them')
        if msgtype not in self._typestores:
            ts, why = None, None
            msgdef = self._msgdefs.get(msgtype)
            if msgdef is not None:  # the bag's own definition, as recorded
                try:
                    ts = get_typestore(Stores.EMPTY)
                    if msgdef.format == MessageDefinitionFormat.MSG:
                        ts.register(get_types_from_msg(msgdef.data, msgtype))
                    else:
                        ts.register(_idl_types(msgdef.data))
                    if msgtype not in ts.fielddefs:
                        raise ValueError(f'its definition does not define {msgtype}')
                except Exception as err:
                    ts, why = None, (f"the bag's definition of {msgtype} is unusable: "
                                     f'{one_line(err)}')
            if ts is None and msgtype in typestore().fielddefs:
                ts = typestore()
            if ts is None:
                why = why or (f'type {msgtype} is neither defined in the bag nor a Jazzy type '
                              'known offline')
            self._typestores[msgtype] = (ts, why)
        ts, why = self._typestores[msgtype]
        if ts is None:
            raise BagError(why)
        return ts

    def deserialize(self, raw: bytes, msgtype: str):
        """Deserialize a CDR message of ``msgtype`` (with the bag's definition when it has one)."""
        ts = self._typestore_for(msgtype)
        try:
            return ts.deserialize_cdr(raw, msgtype)
        except Exception as err:
            raise BagError(f'cannot decode a {msgtype} message: {one_line(err)}') from None

    def close(self) -> None:
        for st in self.storages:
            try:
                st.close()
            except Exception:  # closing a half-open storage: nothing left to release
                pass
        self.storages = []
        self.is_open = False
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> BagReader:
        return self if self.is_open else self.open_files()

    def __exit__(self, *exc) -> None:
        self.close()


def _idl_types(text: str) -> dict:
    sep = '=' * 80 + '\n'
    if not text.startswith(f'{sep}IDL: '):
        return get_types_from_idl(text)
    out = {}
    for part in text.split(sep)[1:]:
        out.update(get_types_from_idl(part.split('\n', 1)[1]))
    return out
