"""
MCAP files as rosbag2 (Jazzy) writes them: an incremental writer and a recovery scanner.

Pure module (no rclpy). Record layouts are those of the MCAP specification
(https://mcap.dev/spec): little-endian, records ``opcode u8 | length u64 | body``.

:class:`McapWriter` writes the ``ros2`` profile, schemas and channels straight into the data
section (so a killed file still names its topics), and messages in chunks (CRC-32 of the
uncompressed records; ``zstd`` optional) each followed by its message index records; a chunk
is written out (to the OS) as soon as it reaches ``chunk_size`` or :meth:`McapWriter.flush` is
called, so a killed file holds every message of every closed chunk.
:meth:`McapWriter.finish` adds the ``rosbag2`` metadata record, the data end, the summary
(schemas, channels, statistics, chunk indexes, metadata index, summary offsets, CRC-32) and
the footer.

:func:`scan` reads a file that was never finished (recorder killed, power loss) up to its first
incomplete or corrupt record; :func:`recover` truncates it there and finishes it with a
summary, regenerating the message index of the last chunk when the kill cut it.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
import os
import struct
from typing import BinaryIO
import zlib

MAGIC = b'\x89MCAP0\r\n'
PROFILE = 'ros2'
CHUNK_SIZE = 768 * 1024  # libmcap's default, which rosbag2 keeps
(OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX,
 OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX, OP_SUMMARY_OFFSET,
 OP_DATA_END) = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F
_SUMMARY_OPS = {OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA_INDEX, OP_SUMMARY_OFFSET,
                OP_FOOTER, OP_DATA_END, 0x0A}  # 0x0A: attachment index
_UNKNOWN_OPS = {0x00, *range(0x10, 0x80)}  # reserved: in a torn file, zeros or garbage
_REC = struct.Struct('<BQ')
_MSG = struct.Struct('<BQHIQQ')  # message record header: op, length, channel, seq, log, pub
FOOTER_SIZE = _REC.size + 20 + len(MAGIC)


def _compressors():
    from backports import zstd
    return {'': (lambda b: b, lambda b, n: b),
            'zstd': (zstd.compress, lambda b, n: zstd.decompress(b))}


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(data)
    if compression not in ('', 'zstd'):
        raise ValueError(f'unsupported chunk compression {compression!r}')
    return _compressors()[compression][1](data, size)


def _str(s: str) -> bytes:
    b = s.encode()
    return struct.pack('<I', len(b)) + b


def _map(d: dict) -> bytes:
    body = b''.join(_str(k) + _str(v) for k, v in sorted(d.items()))
    return struct.pack('<I', len(body)) + body


def record(op: int, body: bytes) -> bytes:
    """Frame one record."""
    return _REC.pack(op, len(body)) + body


class _Body:
    """Sequential reader of a record body; running off its end raises ValueError."""

    def __init__(self, data, pos: int = 0):
        self.data, self.pos = data, pos

    def take(self, n: int):
        if n < 0 or self.pos + n > len(self.data):
            raise ValueError('record shorter than its fields')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u(self, fmt: str) -> int:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def string(self) -> str:
        return bytes(self.take(self.u('<I'))).decode()

    def strmap(self) -> dict:
        return map_entries(self.take(self.u('<I')))


def map_entries(data) -> dict:
    """Decode the entries of an MCAP ``Map<string, string>`` (without its length prefix)."""
    sub, out = _Body(data), {}
    while sub.pos < len(sub.data):
        k = sub.string()
        out[k] = sub.string()
    return out


@dataclass
class Schema:
    sid: int
    name: str
    encoding: str
    data: bytes

    def record(self) -> bytes:
        return record(OP_SCHEMA, struct.pack('<H', self.sid) + _str(self.name) +
                      _str(self.encoding) + struct.pack('<I', len(self.data)) + self.data)

    @classmethod
    def parse(cls, body) -> Schema:
        b = _Body(body)
        sid, name, enc = b.u('<H'), b.string(), b.string()
        return cls(sid, name, enc, bytes(b.take(b.u('<I'))))


@dataclass
class Channel:
    cid: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict

    def record(self) -> bytes:
        return record(OP_CHANNEL, struct.pack('<HH', self.cid, self.schema_id) +
                      _str(self.topic) + _str(self.message_encoding) + _map(self.metadata))

    @classmethod
    def parse(cls, body) -> Channel:
        b = _Body(body)
        return cls(b.u('<H'), b.u('<H'), b.string(), b.string(), b.strmap())


@dataclass
class ChunkIndex:
    start: int
    end: int
    offset: int
    length: int
    mi_offsets: dict
    mi_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int

    def record(self) -> bytes:
        offsets = b''.join(struct.pack('<HQ', c, o) for c, o in sorted(self.mi_offsets.items()))
        return record(OP_CHUNK_INDEX, struct.pack('<QQQQI', self.start, self.end, self.offset,
                                                  self.length, len(offsets)) + offsets +
                      struct.pack('<Q', self.mi_length) + _str(self.compression) +
                      struct.pack('<QQ', self.compressed_size, self.uncompressed_size))


def message_indexes(entries: dict, at: int) -> tuple[bytes, dict]:
    """Message index records of a chunk written at file offset ``at``, and their offsets."""
    out, offsets = [], {}
    for cid in sorted(entries):
        pairs = sorted(entries[cid])
        offsets[cid] = at + sum(len(x) for x in out)
        body = b''.join(struct.pack('<QQ', t, o) for t, o in pairs)
        out.append(record(OP_MESSAGE_INDEX, struct.pack('<HI', cid, len(body)) + body))
    return b''.join(out), offsets


class McapWriter:
    """
    Write an MCAP file incrementally, as described in the module docstring.

    ``fh`` is a binary file open for writing at offset 0 (or, from :func:`recover`, at the end
    of a scanned file's intact part).
    """

    def __init__(self, fh: BinaryIO, library: str = 'sphere_servo', compression: str = '',
                 chunk_size: int = CHUNK_SIZE, header: bool = True):
        self.fh, self.chunk_size = fh, chunk_size
        self.compression = compression
        self._compress = _compressors()[compression][0]
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []
        self.chunk_indexes: list[ChunkIndex] = []
        self.counts: Counter = Counter()
        self.start, self.end = 2**64 - 1, 0
        self._reset_chunk()
        if header:
            fh.write(MAGIC + record(OP_HEADER, _str(PROFILE) + _str(library)))

    def _reset_chunk(self) -> None:
        self._parts: list[bytes] = []
        self._size = 0
        self._index: dict[int, list] = {}
        self._start, self._end = 2**64 - 1, 0

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Add (once per name) and write a schema; return its id."""
        for s in self.schemas:
            if s.name == name:
                return s.sid
        s = Schema(len(self.schemas) + 1, name, encoding, data)
        self.schemas.append(s)
        self.fh.write(s.record())
        self.fh.flush()
        return s.sid

    def add_channel(self, topic: str, schema_id: int, encoding: str, metadata: dict) -> int:
        """Add and write a channel; return its id."""
        c = Channel(len(self.channels) + 1, schema_id, topic, encoding, dict(metadata))
        self.channels.append(c)
        self.fh.write(c.record())
        self.fh.flush()
        return c.cid

    def write(self, channel_id: int, log_time: int, publish_time: int, data: bytes) -> None:
        """Add a message to the open chunk (written out once it reaches ``chunk_size``)."""
        seq = self.counts[channel_id] = self.counts[channel_id] + 1
        head = _MSG.pack(OP_MESSAGE, 22 + len(data), channel_id, seq & 0xFFFFFFFF,
                         log_time, publish_time)
        self._index.setdefault(channel_id, []).append((log_time, self._size))
        self._parts += (head, data)
        self._size += len(head) + len(data)
        self._start, self._end = min(self._start, log_time), max(self._end, log_time)
        self.start, self.end = min(self.start, log_time), max(self.end, log_time)
        if self._size >= self.chunk_size:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Write the open chunk and its message indexes (nothing when it is empty)."""
        if not self._parts:
            return
        raw = b''.join(self._parts)
        data = self._compress(raw) if self.compression else raw
        head = struct.pack('<QQQI', self._start, self._end, len(raw), zlib.crc32(raw)) + \
            _str(self.compression) + struct.pack('<Q', len(data))
        offset = self.fh.tell()
        self.fh.write(_REC.pack(OP_CHUNK, len(head) + len(data)) + head)
        self.fh.write(data)
        end = self.fh.tell()
        mi, mi_offsets = message_indexes(self._index, end)
        self.fh.write(mi)
        self.fh.flush()  # in the OS's hands: it survives the process being killed
        self.chunk_indexes.append(ChunkIndex(self._start, self._end, offset, end - offset,
                                             mi_offsets, len(mi), self.compression, len(data),
                                             len(raw)))
        self._reset_chunk()

    def flush(self, sync: bool = True) -> None:
        """Write the open chunk out and hand the file to the OS (``sync``: to the disk)."""
        self.close_chunk()
        self.fh.flush()
        if sync:
            os.fsync(self.fh.fileno())

    def finish(self, metadata_yaml: str | None) -> None:
        """Close the data section (``rosbag2`` metadata record) and write summary and footer."""
        self.close_chunk()
        fh = self.fh
        meta_index = []
        if metadata_yaml is not None:
            at = fh.tell()
            rec = record(OP_METADATA, _str('rosbag2') +
                         _map({'serialized_metadata': metadata_yaml}))
            fh.write(rec)
            meta_index.append(record(OP_METADATA_INDEX, struct.pack('<QQ', at, len(rec)) +
                                     _str('rosbag2')))
        fh.write(record(OP_DATA_END, struct.pack('<I', 0)))
        summary_start = fh.tell()
        counts = b''.join(struct.pack('<HQ', c, n) for c, n in sorted(self.counts.items()))
        any_msg = self.message_count > 0
        stats = record(OP_STATISTICS, struct.pack(
            '<QHIIIIQQI', self.message_count, len(self.schemas), len(self.channels), 0,
            len(meta_index), len(self.chunk_indexes), self.start if any_msg else 0,
            self.end if any_msg else 0, len(counts)) + counts)
        groups, parts, pos = [], [], summary_start
        for op, recs in ((OP_SCHEMA, [s.record() for s in self.schemas]),
                         (OP_CHANNEL, [c.record() for c in self.channels]),
                         (OP_STATISTICS, [stats]),
                         (OP_CHUNK_INDEX, [c.record() for c in self.chunk_indexes]),
                         (OP_METADATA_INDEX, meta_index)):
            if recs:
                length = sum(len(r) for r in recs)
                groups.append((op, pos, length))
                parts += recs
                pos += length
        offsets_start = pos
        parts += [record(OP_SUMMARY_OFFSET, struct.pack('<BQQ', *g)) for g in groups]
        footer = _REC.pack(OP_FOOTER, 20) + struct.pack('<QQ', summary_start, offsets_start)
        summary = b''.join(parts) + footer
        fh.write(summary + struct.pack('<I', zlib.crc32(summary)) + MAGIC)
        self.flush(sync=True)


def is_finished(path) -> bool:
    """Return whether an MCAP file ends with a footer and the closing magic."""
    try:
        with open(path, 'rb') as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() < len(MAGIC) * 2 + FOOTER_SIZE:
                return False
            fh.seek(-FOOTER_SIZE, os.SEEK_END)
            tail = fh.read()
    except OSError:
        return False
    return tail.endswith(MAGIC) and tail[0] == OP_FOOTER


@dataclass
class Scan:
    """What :func:`scan` found in an unfinished MCAP file."""

    library: str = ''
    schemas: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)
    chunk_indexes: list = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    start: int = 2**64 - 1
    end: int = 0
    good_end: int = 0         # the file is intact up to this offset
    regen: tuple | None = None  # (ChunkIndex, index entries): message indexes to rewrite
    size: int = 0
    stopped: str = 'end of file'  # why the scan stopped

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())


def _data_record(sc: Scan, op: int, body) -> tuple[int, int] | None:
    """Note a schema, channel or message record; a message's (channel, log time)."""
    if op == OP_SCHEMA:
        s = Schema.parse(body)
        sc.schemas.setdefault(s.sid, s)
    elif op == OP_CHANNEL:
        c = Channel.parse(body)
        sc.channels.setdefault(c.cid, c)
    elif op == OP_MESSAGE:
        cid, _, log_time = struct.unpack_from('<HIQ', body)
        sc.start, sc.end = min(sc.start, log_time), max(sc.end, log_time)
        return cid, log_time
    return None


def _chunk(body, offset: int, length: int, sc: Scan) -> tuple[ChunkIndex, dict]:
    """Check and decode one chunk record; return its index (without message indexes)."""
    b = _Body(body)
    start, end, usize, crc = b.u('<Q'), b.u('<Q'), b.u('<Q'), b.u('<I')
    compression = b.string()
    size = b.u('<Q')
    data = b.take(size)
    raw = _decompress(bytes(data), compression, usize)
    if len(raw) != usize or (crc and zlib.crc32(raw) != crc):
        raise ValueError('chunk checksum or size mismatch (torn write)')
    inner, entries, counts = _Body(memoryview(raw)), {}, Counter()
    while inner.pos < usize:
        at = inner.pos
        op, n = inner.u('<B'), inner.u('<Q')
        msg = _data_record(sc, op, inner.take(n))
        if msg is not None:
            entries.setdefault(msg[0], []).append((msg[1], at))
            counts[msg[0]] += 1
    sc.counts.update(counts)
    return ChunkIndex(start, end, offset, length, {}, 0, compression, size, usize), entries


def scan(path) -> Scan:
    """Read an MCAP file record by record up to its first incomplete or corrupt record."""
    sc = Scan()
    with open(path, 'rb') as fh:
        fh.seek(0, os.SEEK_END)
        sc.size = fh.tell()
        fh.seek(0)
        if fh.read(len(MAGIC)) != MAGIC:
            raise ValueError('not an MCAP file (bad magic)')
        pos, pending = len(MAGIC), None  # pending: (index, entries, covered channels)
        while True:
            head = fh.read(_REC.size)
            if len(head) < _REC.size:
                sc.stopped = 'end of file' if not head else 'incomplete record at the end'
                break
            op, n = _REC.unpack(head)
            body = fh.read(n) if n <= sc.size - pos - _REC.size else b''
            if len(body) != n:
                sc.stopped = 'incomplete record at the end'
                break
            end = pos + _REC.size + n
            if pending is not None and op != OP_MESSAGE_INDEX:
                sc.chunk_indexes.append(pending[0])  # its message indexes as the file has them
                pending = None
            try:
                if pos == len(MAGIC):
                    if op != OP_HEADER:
                        raise ValueError('no header record')
                    b = _Body(body)
                    if b.string() != PROFILE:
                        raise ValueError('profile is not ros2')
                    sc.library = b.string()
                elif op in _UNKNOWN_OPS:
                    raise ValueError(f'invalid opcode {op:#04x}')
                elif op in _SUMMARY_OPS:
                    sc.stopped = 'summary section (already indexed)'
                    break
                elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
                    msg = _data_record(sc, op, body)
                    if msg is not None:  # a message outside chunks (unchunked writers)
                        sc.counts[msg[0]] += 1
                elif op == OP_CHUNK:
                    index, entries = _chunk(body, pos, end - pos, sc)
                    pending = (index, entries, set())
                elif op == OP_MESSAGE_INDEX and pending is not None:
                    cid = struct.unpack_from('<H', body)[0]
                    pending[0].mi_offsets[cid] = pos
                    pending[0].mi_length = end - (pending[0].offset + pending[0].length)
                    pending[2].add(cid)
                elif op == OP_METADATA:
                    sc.good_end = pos  # a closing rosbag2 record: rewritten by finish()
                    pos = end
                    continue
            except (ValueError, struct.error, UnicodeDecodeError, zlib.error) as err:
                sc.stopped = f'corrupt record at offset {pos}: {err}'
                break
            except Exception as err:  # a decompressor's own error type: a torn chunk
                sc.stopped = f'corrupt record at offset {pos}: {type(err).__name__}: {err}'
                break
            pos = end
            if pending is None or pending[2] >= set(pending[1]):
                sc.good_end = pos
        if pending is not None:
            index, entries, covered = pending
            if covered >= set(entries):
                sc.chunk_indexes.append(index)
            else:  # killed while writing its message indexes: rewrite them
                index.mi_offsets, index.mi_length = {}, 0
                sc.good_end = index.offset + index.length
                sc.regen = (index, entries)
    return sc


def recover(path, metadata_yaml, library: str = 'sphere_servo') -> Scan:
    """
    Truncate an unfinished MCAP file after its last intact record and finish it.

    ``metadata_yaml(scan)`` gives the ``rosbag2`` metadata record's text. Returns the scan.
    """
    sc = scan(path)
    with open(path, 'r+b') as fh:
        fh.truncate(sc.good_end)
        fh.seek(sc.good_end)
        w = McapWriter(fh, library, header=False)
        w.schemas = [sc.schemas[k] for k in sorted(sc.schemas)]
        w.channels = [sc.channels[k] for k in sorted(sc.channels)]
        w.counts, w.start, w.end = Counter(sc.counts), sc.start, sc.end
        w.chunk_indexes = list(sc.chunk_indexes)
        if sc.regen is not None:
            index, entries = sc.regen
            mi, index.mi_offsets = message_indexes(entries, sc.good_end)
            index.mi_length = len(mi)
            fh.write(mi)
            w.chunk_indexes.append(index)
        w.chunk_indexes.sort(key=lambda c: c.offset)
        w.finish(metadata_yaml(sc))
    return sc
