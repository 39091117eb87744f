"""
Write a rosbag2 (MCAP or sqlite3) as ROS 2 Jazzy writes it, losing at most one commit window.

Pure module (no rclpy). The layout is Jazzy's: a directory ``NAME`` holding ``NAME_0.mcap``
(or ``NAME_0.db3``) and, once closed, ``metadata.yaml`` (version 9, ``ros_distro: jazzy``).

- MCAP (:mod:`sphere_servo.bag.mcap`): profile ``ros2``; one ``ros2msg`` schema per type; one
  channel per topic with the metadata Jazzy's rosbag2_storage_mcap puts there
  (``offered_qos_profiles``, ``topic_type_hash``); chunks of 768 KiB (optionally zstd)
  with message indexes; at close the ``rosbag2`` metadata record, statistics and the
  summary. ``publish_time`` is the sender's stamp, ``log_time`` the reception time.
- sqlite3: Jazzy's schema version 4 (tables ``schema``, ``metadata``, ``topics``,
  ``message_definitions``, ``messages``, index ``timestamp_idx``), written in WAL mode as
  rosbag2's ``resilient`` preset does; at close the WAL is folded back into the file
  (rollback journal mode again, one self-contained ``.db3``). ``zstd`` compresses each message
  (``compression_mode: message``), as rosbag2_compression does.

Crash safety (:meth:`BagWriter.commit`, called at the latest ``commit_period`` after a
message was written): a commit writes the open MCAP chunk out (a full chunk is written at
once anyway) or commits the sqlite3 transaction, then fsyncs (sqlite3 ``synchronous=FULL``).
So after SIGKILL or a power loss the storage file holds every message written more than one
commit window (default 0.5 s) before, plus, for MCAP, every chunk already full; ``reindex``
(:mod:`sphere_servo.bag.repair`) makes it a complete bag again. While open, the storage
file carries an exclusive ``flock`` (``reindex`` refuses a bag still being written).
"""
from __future__ import annotations

from dataclasses import dataclass
import fcntl
from pathlib import Path
import sqlite3
import time

from sphere_servo.bag import mcap
from sphere_servo.bag.metadata import (BagError, BagMeta, FileMeta, fsync_dir, metadata_text,
                                       normal_qos, qos_yaml, ROS_DISTRO, STORAGES, TopicMeta,
                                       write_metadata)

COMMIT_PERIOD = 0.5  # s: the most a crash can lose (see the module docstring)
LIBRARY = 'sphere_servo rosbag2 writer'
SQLITE_SCHEMA = (
    'CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);',
    'CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, '
    'metadata TEXT NOT NULL);',
    'CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, '
    'serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL, '
    'type_description_hash TEXT NOT NULL);',
    'CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL, '
    'encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL, '
    'type_description_hash TEXT NOT NULL);',
    'CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, '
    'timestamp INTEGER NOT NULL, data BLOB NOT NULL);',
    'CREATE INDEX timestamp_idx ON messages (timestamp ASC);',
)
SQLITE_SCHEMA_VERSION = 4


@dataclass
class Topic:
    """A topic of the bag being written (the handle :meth:`BagWriter.write` takes)."""

    tid: int
    name: str
    msgtype: str
    msgdef: str
    encoding: str
    type_hash: str
    qos: tuple
    count: int = 0


def message_definition(msgtype: str, typestore) -> tuple[str, str, str]:
    """Return (definition text, ``ros2msg``/``ros2idl``, RIHS01 hash) of a typestore type."""
    text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
    encoding = 'ros2idl' if text.startswith('=' * 80 + '\nIDL: ') else 'ros2msg'
    return text, encoding, typestore.hash_rihs01(msgtype)


def _lock(fh) -> None:
    """Take the bag's writer lock (held until the file is closed or the process dies)."""
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        raise BagError(f'{fh.name} is being written by another process') from None


class _Mcap:

    def __init__(self, path: Path, compression: str, chunk_size: int):
        self.fh = open(path, 'xb')
        _lock(self.fh)
        self.w = mcap.McapWriter(self.fh, LIBRARY, 'zstd' if compression == 'zstd' else '',
                                 chunk_size)
        self.channel: dict[int, int] = {}

    def add(self, t: Topic) -> None:
        sid = self.w.add_schema(t.msgtype, t.encoding, t.msgdef.encode())
        self.channel[t.tid] = self.w.add_channel(
            t.name, sid, 'cdr', {'offered_qos_profiles': qos_yaml(t.qos),
                                 'topic_type_hash': t.type_hash})

    def write(self, t: Topic, log_time: int, publish_time: int, data: bytes) -> None:
        self.w.write(self.channel[t.tid], log_time, publish_time, data)

    def commit(self, sync: bool) -> None:
        self.w.flush(sync)

    def close(self, metadata_yaml: str) -> None:
        self.w.finish(metadata_yaml)
        self.fh.close()

    def abort(self) -> None:
        self.fh.close()


class _Sqlite3:

    def __init__(self, path: Path, compression: str, sync: bool):
        self.lock = open(path, 'xb')
        _lock(self.lock)
        self.con = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self.con.execute('PRAGMA journal_mode=WAL')
        self.con.execute(f'PRAGMA synchronous={"FULL" if sync else "NORMAL"}')
        self.con.execute('BEGIN')
        for stmt in SQLITE_SCHEMA:
            self.con.execute(stmt)
        self.con.execute('INSERT INTO schema (schema_version, ros_distro) VALUES (?, ?)',
                         (SQLITE_SCHEMA_VERSION, ROS_DISTRO))
        self.con.execute('COMMIT')
        self.types: set[str] = set()
        self.open_tx = False
        if compression == 'zstd':
            from backports import zstd
            self.compress = zstd.compress
        else:
            self.compress = None

    def add(self, t: Topic) -> None:
        self.commit(False)
        self.con.execute('BEGIN')
        self.con.execute('INSERT INTO topics (id, name, type, serialization_format, '
                         'offered_qos_profiles, type_description_hash) VALUES (?, ?, ?, ?, ?, ?)',
                         (t.tid, t.name, t.msgtype, 'cdr', qos_yaml(t.qos), t.type_hash))
        if t.msgtype not in self.types:
            self.types.add(t.msgtype)
            self.con.execute('INSERT INTO message_definitions (topic_type, encoding, '
                             'encoded_message_definition, type_description_hash) '
                             'VALUES (?, ?, ?, ?)', (t.msgtype, t.encoding, t.msgdef,
                                                     t.type_hash))
        self.con.execute('COMMIT')

    def write(self, t: Topic, log_time: int, publish_time: int, data: bytes) -> None:
        if not self.open_tx:
            self.con.execute('BEGIN')
            self.open_tx = True
        if self.compress is not None:
            data = self.compress(data)
        self.con.execute('INSERT INTO messages (timestamp, topic_id, data) VALUES (?, ?, ?)',
                         (log_time, t.tid, data))

    def commit(self, sync: bool) -> None:
        if self.open_tx:
            self.con.execute('COMMIT')  # synchronous=FULL: the WAL is on disk at return
            self.open_tx = False

    def close(self, metadata_yaml: str) -> None:
        self.commit(True)
        self.con.execute('INSERT INTO metadata (metadata_version, metadata) VALUES (?, ?)',
                         (9, metadata_yaml))
        self.con.execute('PRAGMA wal_checkpoint(TRUNCATE)')
        self.con.execute('PRAGMA journal_mode=DELETE')
        self.con.close()
        self.lock.close()

    def abort(self) -> None:
        self.con.close()
        self.lock.close()


class BagWriter:
    """
    A rosbag2 being written; see the module docstring.

    ``create()``, ``add_topic()`` per topic, ``write()`` per message, ``commit()`` when
    :meth:`commit_due` (the caller's writer loop), ``close()``. Not thread-safe: one thread
    owns it (sqlite3 connections stay in the thread that uses them).
    """

    def __init__(self, path: str | Path, storage: str = 'mcap', compression: str = 'none',
                 commit_period: float = COMMIT_PERIOD, chunk_size: int = mcap.CHUNK_SIZE,
                 sync: bool = True):
        if storage not in STORAGES:
            raise BagError(f'storage {storage!r} is not one of {", ".join(STORAGES)}')
        if compression not in ('none', 'zstd'):
            raise BagError(f'compression {compression!r} is not one of none, zstd')
        self.path, self.storage, self.compression = Path(path), storage, compression
        self.commit_period, self.chunk_size, self.sync = commit_period, chunk_size, sync
        self.file = self.path / f'{self.path.name}_0{STORAGES[storage]}'
        self.topics: list[Topic] = []
        self.start, self.end = None, None
        self._store = None
        self._dirty_since: float | None = None
        self._synced_dir = False

    def create(self) -> None:
        """Create the bag directory and its storage file (neither may exist)."""
        try:
            self.path.mkdir()
        except FileExistsError:
            raise BagError(f'output path {str(self.path)!r} exists already; '
                           'choose a new one') from None
        except OSError as err:
            raise BagError(f'cannot create {str(self.path)!r}: {err.strerror}') from None
        if self.storage == 'mcap':
            self._store = _Mcap(self.file, self.compression, self.chunk_size)
        else:
            self._store = _Sqlite3(self.file, self.compression, self.sync)
        self.commit()
        fsync_dir(self.path)
        fsync_dir(self.path.parent)

    def add_topic(self, name: str, msgtype: str, qos=(), typestore=None, msgdef: str = '',
                  encoding: str = 'ros2msg', type_hash: str = '') -> Topic:
        """
        Add a topic (its definition from ``typestore``, or ``msgdef``/``type_hash``).

        QoS durations are written normalised (every "infinite" as 2^63-1 ns).
        """
        if any(t.name == name for t in self.topics):
            raise BagError(f'topic {name} is in the bag already')
        if typestore is not None:
            msgdef, encoding, type_hash = message_definition(msgtype, typestore)
        t = Topic(len(self.topics) + 1, name, msgtype, msgdef, encoding, type_hash,
                  tuple(normal_qos(q) for q in qos))
        self._store.add(t)
        self.topics.append(t)
        return t

    def write(self, topic: Topic, log_time: int, data: bytes,
              publish_time: int | None = None) -> None:
        """Write one serialized message (``log_time``: its bag timestamp, ns)."""
        self._store.write(topic, log_time, log_time if publish_time is None else publish_time,
                          data)
        topic.count += 1
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)
        if self._dirty_since is None:
            self._dirty_since = time.monotonic()

    def seconds_to_commit(self) -> float | None:
        """Seconds until a commit is due (0: now; None: nothing to commit)."""
        if self._dirty_since is None:
            return None
        return max(0.0, self._dirty_since + self.commit_period - time.monotonic())

    def commit_due(self) -> bool:
        return self.seconds_to_commit() == 0.0

    def commit(self) -> None:
        """Make everything written so far survive a crash (see the module docstring)."""
        self._store.commit(self.sync)
        self._dirty_since = None
        if not self._synced_dir and self.start is not None:
            fsync_dir(self.path)  # the WAL file of sqlite3 is new
            self._synced_dir = True

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics)

    def metadata(self) -> BagMeta:
        """Return the bag's metadata as of now."""
        n = self.message_count
        start = self.start if n else 0
        duration = (self.end - self.start) if n else 0
        name = self.file.name
        return BagMeta(
            storage=self.storage, relative_file_paths=(name,), start_ns=start,
            duration_ns=duration, message_count=n,
            topics=tuple(TopicMeta(t.name, t.msgtype, 'cdr', t.qos, t.type_hash, t.count)
                         for t in self.topics),
            compression_format='zstd' if self.compression == 'zstd' and
            self.storage == 'sqlite3' else '',
            compression_mode='message' if self.compression == 'zstd' and
            self.storage == 'sqlite3' else '',
            files=(FileMeta(name, start, duration, n),))

    def close(self) -> BagMeta:
        """Finish the storage file and write ``metadata.yaml``; returns the metadata."""
        meta = self.metadata()
        self._store.close(metadata_text(meta, wrapped=False))
        self._store = None
        write_metadata(self.path, meta)
        return meta

    def abort(self) -> None:
        """Close the storage file as it is (``reindex`` can finish it)."""
        if self._store is not None:
            self._store.abort()
            self._store = None

    def __enter__(self) -> BagWriter:
        self.create()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
