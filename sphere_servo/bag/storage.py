"""
The storage readers of ``rosbags``, made to read every storage file rosbag2 writes.

Pure module (no rclpy). ``rosbags``' readers go wrong on valid files in these ways:

- a message definition of an encoding they do not know makes the whole file unreadable (a
  ``KeyError`` on open). rosbag2 records a type whose definition it cannot find with the
  encoding ``unknown`` (or empty) and no text; an MCAP file may hold a ``jsonschema`` or
  ``protobuf`` channel beside the ROS ones. Such a definition is read here as none: the
  topic is still listed (its type then comes from the Jazzy typestore, or it is skipped
  as a type no one knows);
- MCAP chunks without message index records (libmcap's ``noMessageIndex``; the index is
  optional in the specification) are never read: ``rosbags`` picks the chunks to read by
  their message indexes, so the file reads as empty while its statistics count every
  message. Here such a chunk is indexed by reading it once on open;
- MCAP statistics without per-channel counts (optional too) give every topic 0 messages:
  counts and times are then taken from the chunks (whenever the statistics disagree);
- an MCAP file of unchunked messages (rosbag2's ``fastwrite`` preset) whose receive times
  go back somewhere (the recorder's callbacks run on several threads) stops with an error
  midway: here it is read by time, then in file order, as rosbag2 reads an indexed file;
- sqlite3 messages of one timestamp come in no defined order (grouped by topic, in
  practice): rosbag2 reads them as recorded (``ORDER BY timestamp, id``), and so does this
  reader. Ties are common in bags recorded on simulated time (``--use-sim-time``).
"""
from __future__ import annotations

from array import array
from collections import Counter
from contextlib import contextmanager
import struct

import numpy as np

from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2 import storage_mcap, storage_sqlite3
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

MCAP_FORMATS = {'ros2msg': MessageDefinitionFormat.MSG, 'ros2idl': MessageDefinitionFormat.IDL,
                'omgidl': MessageDefinitionFormat.IDL}
# rosbags' query of the sqlite3 definitions, and the same restricted to the known encodings
_DEFS_QUERY = ('SELECT topic_type, encoding, encoded_message_definition, '
               'type_description_hash FROM message_definitions ORDER BY id')
_KNOWN_DEFS_QUERY = _DEFS_QUERY.replace(
    ' ORDER BY', " WHERE encoding IN ('ros2msg', 'ros2idl') ORDER BY")


def mcap_msgdef(schema) -> MessageDefinition:
    """Return an MCAP schema's definition; none when its encoding is not a ROS one."""
    fmt = MCAP_FORMATS.get(schema.encoding) if schema is not None else None
    if fmt is None:
        return MessageDefinition(MessageDefinitionFormat.NONE, '')
    return MessageDefinition(fmt, schema.data)


@contextmanager
def _patched(module, name: str, value):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


class Mcap(McapReader):
    """``rosbags``' MCAP reader; see the module docstring."""

    def open(self) -> None:  # noqa: A003 (rosbags' name)
        with _patched(storage_mcap, 'get_msgdef', mcap_msgdef):
            super().open()
        unindexed = [c for c in self.chunks if not c.channel_count]
        every = {c.id: c for c in self.connections}
        for chunk in unindexed:
            src = storage_mcap.msgsrc(chunk, every, 0, 2**63 - 1, self.bio)
            chunk.channel_count.update(Counter(m.connection.id for m in src if m.offset))
        counts = Counter()
        for chunk in self.chunks:
            counts.update(chunk.channel_count)
        stats = self.statistics
        if self.chunks and counts != Counter(stats.channel_message_counts if stats else {}):
            # the chunks' own counts (message indexes) over statistics that lack or miscount
            self.connections = [c._replace(msgcount=counts.get(c.id, 0))
                                for c in self.connections]
            n = sum(counts.values())
            start = min(c.message_start_time for c in self.chunks)
            end = max(c.message_end_time for c in self.chunks)
            self.metadata = self.metadata._replace(
                duration=end - start + 1 if n else 0, start_time=start if n else 2**63 - 1,
                end_time=end + 1 if n else 0, message_count=n)
        self._order = ()  # unknown until read (:meth:`_unchunked_order`)

    def messages(self, connections, start: int | None = None, stop: int | None = None):
        """Yield (connection, log time, data) by time, then in file order."""
        if self._order == ():
            self._order = None if self.chunks else self._unchunked_order()
        if self._order is None:  # indexed, or unchunked in time order: rosbags reads it right
            yield from super().messages(connections, start, stop)
            return
        wanted = {c.id: c for c in connections}
        lo, hi = -1 if start is None else start, 2**64 if stop is None else stop
        for t, pos in zip(*self._order):
            t = int(t)
            if lo <= t < hi:
                self.bio.seek(int(pos))
                size, cid = _MSG.unpack(self.bio.read(_MSG.size))[:2]
                data = self.bio.read(size - 2)[20:]  # after sequence, log and publish time
                if cid in wanted:
                    yield wanted[cid], t, data

    def _unchunked_order(self):
        """(log time, message data offset) of an unchunked file out of time order, or None."""
        bio, times, offsets = self.bio, array('Q'), array('Q')
        bio.seek(self.data_start)
        while bio.tell() < self.data_end:
            at = bio.tell()
            op, size = _REC.unpack(bio.read(_REC.size))
            if op == 0x06:
                return None  # chunks without chunk index: rosbags reads them
            if op == 0x05:
                times.append(struct.unpack('<Q', bio.read(14)[6:])[0])
                offsets.append(at + 1)
                size -= 14
            bio.seek(size, 1)
        times = np.frombuffer(times, dtype=np.uint64)
        if not len(times) or np.all(times[1:] >= times[:-1]):
            return None
        keep = np.argsort(times, kind='stable')
        return times[keep], np.frombuffer(offsets, dtype=np.uint64)[keep]


_REC = struct.Struct('<BQ')
_MSG = struct.Struct('<QH')  # a message record after its opcode: length, channel id


class _Cursor:
    """A cursor that reads only the definitions of known encodings."""

    def __init__(self, cur):
        self.cur = cur

    def execute(self, query, *args):
        return self.cur.execute(_KNOWN_DEFS_QUERY if query == _DEFS_QUERY else query, *args)

    def __getattr__(self, name):
        return getattr(self.cur, name)


class _Connection:
    """An ``apsw`` connection whose cursors are :class:`_Cursor`."""

    def __init__(self, *args, **kwargs):
        self.con = _APSW.Connection(*args, **kwargs)

    def cursor(self):
        return _Cursor(self.con.cursor())

    def __getattr__(self, name):
        return getattr(self.con, name)


class _Apsw:
    """``apsw`` as ``rosbags``' sqlite3 reader sees it while it lists the definitions."""

    Connection = _Connection

    def __getattr__(self, name):
        return getattr(_APSW, name)


_APSW = storage_sqlite3.apsw


class Sqlite3(Sqlite3Reader):
    """``rosbags``' sqlite3 reader; see the module docstring."""

    def _open(self) -> None:
        with _patched(storage_sqlite3, 'apsw', _Apsw()):
            super()._open()

    def messages(self, connections, start: int | None = None, stop: int | None = None):
        """Yield (connection, timestamp, data) by time, then as recorded (rosbag2's order)."""
        ids = sorted({c.id for c in connections})
        where, args = [f'topic_id IN ({",".join("?" * len(ids))})'], list(ids)
        for clause, value in (('timestamp >= ?', start), ('timestamp < ?', stop)):
            if value is not None:
                where.append(clause)
                args.append(value)
        conns = {c.id: c for c in self.connections}
        for cid, ts, data in self.dbconn.execute(
                f'SELECT topic_id, timestamp, data FROM messages WHERE {" AND ".join(where)} '
                'ORDER BY timestamp, id', args):
            yield conns[cid], ts, data


def storage_reader(path):
    """Return the (unopened) reader of a storage file: ``.mcap`` or ``.db3``."""
    return (Mcap if str(path).endswith('.mcap') else Sqlite3)(path)
