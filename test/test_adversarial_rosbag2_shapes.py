"""
Storage files as rosbag2 and other MCAP writers make them, written here byte by byte.

Each must read exactly what was written (topics, counts, times, order), or be refused:

- MCAP schemas of encodings ``rosbags`` does not know: rosbag2's ``unknown`` (or empty)
  for a type whose definition it could not find, a ``jsonschema`` channel beside the ROS
  ones; the same ``unknown`` in a Jazzy sqlite3 ``message_definitions`` table;
- a definition recorded as ``ros2msg`` (``ros2idl``) with an empty text: the type is
  decoded as Jazzy defines it, not as a message without fields;
- a Jazzy type recorded with another definition (an extra field; its RIHS01 hash differs
  from Jazzy's): not played as the Jazzy type (a subscriber would misread its bytes),
  refused when asked for by name, still decoded by its recorded definition; beside a topic
  of the same type recorded with Jazzy's definition, neither is decoded as the other;
- MCAP chunks without message index records, statistics without per-channel counts
  (both optional in the MCAP specification); unchunked messages (rosbag2's ``fastwrite``)
  whose receive times go back: read by time, then in file order;
- messages of equal timestamps on several topics (a bag recorded on simulated time): read
  as recorded, as rosbag2 reads them (by time, then by record order), also from a db3
  without rosbag2's timestamp index (one another tool wrote);
- a split bag compressed per file (``compression_mode: FILE``, ``.db3.zstd`` /
  ``.mcap.zstd``), its files listed out of order under the directory they were recorded in:
  every message, in time order;
- one storage file of a split bag, given alone: that file's messages only (as rosbag2
  reads a file), not the whole bag's;
- ``custom_data`` as rosbag2's emitter (yaml-cpp) writes it: the strings ``42``, ``true``,
  ``010`` unquoted; the bag is read, its custom data as recorded;
- a servo run whose topics are stored relative (``servo/state``, as rosbag2 may store a
  name) beside an absolute image topic: the run read from it is the recorded one;
- a split run whose ``servo/state`` changes type in its second file: the watch tools read
  the rest and say what they left out;
- a run whose ``servo/state`` (``camera/cmd_vel``) is of another type than the nodes
  publish: refused in one line, not a traceback.
"""
from __future__ import annotations

from contextlib import redirect_stderr
import io
from pathlib import Path
import shutil
import sqlite3
import struct
import zlib

from bag_cases import foxy_qos, split_bag, STRING, string_cdr, TS
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from run_bag import run_bag
from sphere_servo.bag.bagio import bag, BagError, iter_raw, open_bag, select, typestore
from sphere_servo.bag.run import read_run
from sphere_servo.experiments import video
import yaml

MAGIC = b'\x89MCAP0\r\n'
BOOL = 'std_msgs/msg/Bool'
STRING_DEF = b'string data\n'


def _s(x) -> bytes:
    b = x.encode() if isinstance(x, str) else x
    return struct.pack('<I', len(b)) + b


def _rec(op: int, body: bytes) -> bytes:
    return struct.pack('<BQ', op, len(body)) + body


def write_mcap(path: Path, schemas, channels, messages, index: bool = True,
               channel_counts: bool = True, chunked: bool = True, zero_stats: bool = False,
               ) -> None:
    """
    Write a finished MCAP file of one uncompressed chunk, as libmcap lays it out.

    ``schemas``: (id, name, encoding, data); ``channels``: (id, schema id, topic, message
    encoding); ``messages``: (channel id, log time, data), in file order. ``index``: message
    index records after the chunk; ``channel_counts``: the statistics' per-channel counts;
    ``chunked`` False: the messages straight in the data section (rosbag2's ``fastwrite``);
    ``zero_stats``: statistics of 0 messages.
    """
    out = bytearray(MAGIC + _rec(0x01, _s('ros2') + _s('libmcap 1.4.0')))
    head = b''.join(_rec(0x03, struct.pack('<H', i) + _s(n) + _s(e) + _s(d))
                    for i, n, e, d in schemas)
    head += b''.join(_rec(0x04, struct.pack('<HH', i, sid) + _s(t) + _s(enc) +
                          _s(_s('offered_qos_profiles') + _s('')))
                     for i, sid, t, enc in channels)
    out += head
    chunk, idx = bytearray(head), {}
    for seq, (cid, t, data) in enumerate(messages):
        idx.setdefault(cid, []).append((t, len(chunk)))
        chunk += _rec(0x05, struct.pack('<HIQQ', cid, seq, t, t) + data)
    t0, t1 = min(m[1] for m in messages), max(m[1] for m in messages)
    chunk_at, offsets = len(out), {}
    if chunked:
        out += _rec(0x06, struct.pack('<QQQI', t0, t1, len(chunk), zlib.crc32(chunk)) +
                    _s('') + struct.pack('<Q', len(chunk)) + bytes(chunk))
    else:
        out += chunk[len(head):]
    chunk_len = len(out) - chunk_at
    for cid, pairs in sorted(idx.items()) if index and chunked else ():
        offsets[cid] = len(out)
        body = b''.join(struct.pack('<QQ', t, o) for t, o in pairs)
        out += _rec(0x07, struct.pack('<HI', cid, len(body)) + body)
    mi_len = len(out) - chunk_at - chunk_len
    out += _rec(0x0F, struct.pack('<I', 0))
    summary_at = len(out)
    out += head
    counts = b''.join(struct.pack('<HQ', c, len(p)) for c, p in sorted(idx.items())) \
        if channel_counts else b''
    out += _rec(0x0B, struct.pack('<QHIIIIQQ', 0 if zero_stats else len(messages),
                                  len(schemas), len(channels), 0, 0, int(chunked),
                                  *((0, 0) if zero_stats else (t0, t1))) + _s(counts))
    if chunked:
        out += _rec(0x08, struct.pack('<QQQQ', t0, t1, chunk_at, chunk_len) + _s(b''.join(
            struct.pack('<HQ', c, o) for c, o in sorted(offsets.items()))) +
            struct.pack('<Q', mi_len) + _s('') + struct.pack('<QQ', len(chunk), len(chunk)))
    out += _rec(0x02, struct.pack('<QQI', summary_at, 0, 0)) + MAGIC
    path.write_bytes(bytes(out))


def read(path: Path):
    """Return (topic, time) in read order, {topic: count}, {topic: type}, played count."""
    reader = open_bag(path)
    try:
        got = [(c.topic, ts) for c, ts, _ in iter_raw(reader)]
        return (got, {c.topic: c.msgcount for c in reader.connections},
                {c.topic: c.msgtype for c in reader.connections}, select(reader).count)
    finally:
        reader.close()


# (channel, log time) in file order: out of time order inside the chunk
ORDER = [(1, 30), (2, 15), (1, 10), (1, 20)]
READ = [('/chatter', 10), ('/other', 15), ('/chatter', 20), ('/chatter', 30)]


def _two_channel_mcap(path: Path, other_schema, other_encoding='cdr', **kw) -> None:
    path.mkdir()
    write_mcap(path / 'bag_0.mcap', [(1, STRING, 'ros2msg', STRING_DEF), other_schema],
               [(1, 1, '/chatter', 'cdr'), (2, other_schema[0], '/other', other_encoding)],
               [(c, t, string_cdr(str(t)) if c == 1 else b'{"a": 1}') for c, t in ORDER],
               **kw)


@pytest.mark.parametrize('schema, encoding, played', [
    ((2, 'foo_msgs/msg/Bar', 'unknown', b''), 'cdr', 4),   # rosbag2: definition not found
    ((2, 'foo_msgs/msg/Bar', '', b''), 'cdr', 4),
    ((2, 'Foo', 'jsonschema', b'{"type": "object"}'), 'json', 3),  # json: not played
])
def test_mcap_schema_of_an_encoding_rosbags_does_not_know(tmp_path, schema, encoding, played):
    _two_channel_mcap(tmp_path / 'bag', schema, encoding)
    assert read(tmp_path / 'bag') == (READ, {'/chatter': 3, '/other': 1},
                                      {'/chatter': STRING, '/other': schema[1]}, played)


@pytest.mark.parametrize('encoding', ['ros2msg', 'ros2idl'])
def test_empty_definition_is_no_definition(tmp_path, encoding):
    (tmp_path / 'bag').mkdir()
    write_mcap(tmp_path / 'bag' / 'bag_0.mcap', [(1, STRING, encoding, b'')],
               [(1, 1, '/chatter', 'cdr')], [(1, 5, string_cdr('hello'))])
    with bag(tmp_path / 'bag') as reader:
        got = [reader.deserialize(raw, c.msgtype).data for c, _, raw in iter_raw(reader)]
    assert got == ['hello']


@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_type_of_another_definition_is_not_played(tmp_path, storage):
    other = get_typestore(Stores.EMPTY)
    other.register(get_types_from_msg('string data\nint32 extra\n', STRING))
    raw = bytes(other.serialize_cdr(other.types[STRING](data='a', extra=7), STRING))
    with Writer(tmp_path / 'bag', version=9, storage_plugin=storage) as w:
        conn = w.add_connection('/chatter', STRING, msgdef='string data\nint32 extra\n',
                                rihs01=other.hash_rihs01(STRING))
        same = w.add_connection('/same', BOOL, typestore=TS)
        w.write(conn, 5, raw)
        w.write(same, 6, bytes(TS.serialize_cdr(TS.types[BOOL](data=True), BOOL)))
    with bag(tmp_path / 'bag') as reader:
        sel = select(reader)
        assert ([c.topic for c in sel.connections], [s.topic for s in sel.skipped]) == \
            (['/same'], ['/chatter'])
        with pytest.raises(BagError, match='/chatter'):
            select(reader, ['/chatter'])
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in iter_raw(reader)]
    assert [(m.data, getattr(m, 'extra', None)) for m in msgs] == [('a', 7), (True, None)]
    # a split bag (one definition a file): file 0 has the other one, file 1 Jazzy's
    (tmp_path / 'two').mkdir()
    parts = [({'msgdef': 'string data\nint32 extra\n', 'rihs01': other.hash_rihs01(STRING)},
              raw), ({'typestore': TS}, string_cdr('b'))]
    for i, (msgdef, data) in enumerate(parts):
        with Writer(tmp_path / f'part{i}', version=9, storage_plugin=storage) as w:
            w.write(w.add_connection('/chatter', STRING, **msgdef), 5 + i, data)
        (f,) = [f for f in (tmp_path / f'part{i}').iterdir() if f.name != 'metadata.yaml']
        f.rename(tmp_path / 'two' / f'two_{i}{f.suffix}')
    with bag(tmp_path / 'two') as reader:
        assert reader.message_count == 2
        for c, _, raw in iter_raw(reader):
            with pytest.raises(BagError, match='two different definitions'):
                reader.deserialize(raw, c.msgtype)


@pytest.mark.parametrize('kw', [{'index': False}, {'channel_counts': False},
                                {'index': False, 'channel_counts': False},
                                {'chunked': False},
                                {'channel_counts': False, 'zero_stats': True}])
def test_mcap_without_indexes_counts_or_chunks(tmp_path, kw):
    _two_channel_mcap(tmp_path / 'bag', (2, STRING, 'ros2msg', STRING_DEF), **kw)
    with bag(tmp_path / 'bag') as reader:
        assert (reader.start_time, reader.end_time) == (10, 31)
    assert read(tmp_path / 'bag') == (READ, {'/chatter': 3, '/other': 1},
                                      {'/chatter': STRING, '/other': STRING}, 4)


@pytest.mark.parametrize('encoding', ['unknown', ''])
def test_db3_definition_rosbag2_did_not_find(tmp_path, encoding):
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        chatter = w.add_connection('/chatter', STRING, typestore=TS,
                                   offered_qos_profiles=[foxy_qos()])
        other = w.add_connection('/other', 'foo_msgs/msg/Bar', msgdef='int32 a\n',
                                 rihs01='RIHS01_' + '0' * 64,
                                 offered_qos_profiles=[foxy_qos()])
        for c, t in ORDER:
            w.write(chatter if c == 1 else other, t, string_cdr(str(t)))
    con = sqlite3.connect(tmp_path / 'bag' / 'bag.db3')
    con.execute('UPDATE message_definitions SET encoding = ?, encoded_message_definition = '
                "'' WHERE topic_type = 'foo_msgs/msg/Bar'", (encoding,))
    con.commit()
    con.close()
    got = read(tmp_path / 'bag')
    assert got == (READ, {'/chatter': 3, '/other': 1},
                   {'/chatter': STRING, '/other': 'foo_msgs/msg/Bar'}, 4)


@pytest.mark.parametrize('storage, index', [(StoragePlugin.SQLITE3, True),
                                            (StoragePlugin.SQLITE3, False),
                                            (StoragePlugin.MCAP, True)])
def test_messages_of_equal_times_are_read_as_recorded(tmp_path, storage, index):
    written = [(f'/t{k % 3}', 1000 + 10 * (k // 6) - 10 * (k % 2)) for k in range(60)]
    with Writer(tmp_path / 'bag', version=9, storage_plugin=storage) as w:
        conns = {t: w.add_connection(t, STRING, typestore=TS) for t in ('/t0', '/t1', '/t2')}
        for k, (topic, t) in enumerate(written):
            w.write(conns[topic], t, string_cdr(str(k)))
    if not index:
        con = sqlite3.connect(tmp_path / 'bag' / 'bag.db3')
        con.execute('DROP INDEX timestamp_idx')
        con.commit()
        con.close()
    with bag(tmp_path / 'bag') as reader:
        got = [(c.topic, t, raw) for c, t, raw in iter_raw(reader)]
    want = sorted(((topic, t, string_cdr(str(k))) for k, (topic, t) in enumerate(written)),
                  key=lambda m: m[1])  # stable: record order within a time
    assert got == want


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_split_bag_compressed_per_file_listed_out_of_order(tmp_path, storage):
    from backports import zstd
    path = tmp_path / 'wbag'
    stamps = split_bag(path, storage)
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    names = info['relative_file_paths']
    for name in names:
        (path / f'{name}.zstd').write_bytes(zstd.compress((path / name).read_bytes()))
        (path / name).unlink()
    info.update(compression_mode='FILE', compression_format='zstd',
                relative_file_paths=[f'recorded_as/{n}.zstd' for n in reversed(names)])
    (path / 'metadata.yaml').write_text(yaml.safe_dump(meta))
    with bag(path) as reader:
        got = [(c.topic, t, bytes(raw)) for c, t, raw in iter_raw(reader)]
        assert reader.message_count == len(stamps) == 45
    assert [t for _, t, _ in got] == stamps
    assert [raw for *_, raw in got] == [string_cdr(f'{p}.{i}.{n}') for p in range(3)
                                        for i in range(5) for n in ('AAA', 'BBB', 'CCC')]


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_one_file_of_a_split_bag_reads_that_file(tmp_path, storage):
    path = tmp_path / 'wbag'
    stamps = split_bag(path, storage)
    name = f'wbag_1.{"mcap" if storage == "mcap" else "db3"}'
    assert (path / name).is_file()
    with bag(path / name) as reader:
        got = [(t, bytes(raw)) for _, t, raw in iter_raw(reader)]
        assert (reader.message_count, reader.warnings) == (15, [])
    assert got == [(t, string_cdr(f'1.{i}.{n}'))
                   for t, (i, n) in zip(stamps[15:30], [(i, n) for i in range(5)
                                                        for n in ('AAA', 'BBB', 'CCC')])]


def test_custom_data_of_unquoted_strings(tmp_path):
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection('/chatter', STRING, typestore=TS)
        w.write(conn, 5, string_cdr('x'))
    path = tmp_path / 'bag' / 'metadata.yaml'
    text = path.read_text()
    assert text.count('custom_data: null') == 1
    path.write_text(text.replace('custom_data: null', 'custom_data:\n    run: 42\n'
                                 '    ok: true\n    trial: 010\n    who: ann'))
    with bag(tmp_path / 'bag') as reader:
        assert reader.meta.custom_data == {'run': '42', 'ok': 'true', 'trial': '010',
                                           'who': 'ann'}
        assert [(c.topic, t) for c, t, _ in iter_raw(reader)] == [('/chatter', 5)]


@pytest.fixture(scope='module')
def rec(tmp_path_factory):
    """Return the servo run of :func:`run_bag`, recorded once for this module."""
    return run_bag(tmp_path_factory.mktemp('run'))


def test_run_of_relative_topics_is_the_recorded_run(tmp_path, rec):
    rel = tmp_path / 'relative'
    with bag(rec.bag) as reader, Writer(rel, version=9,
                                        storage_plugin=StoragePlugin.SQLITE3) as w:
        conns = {c.topic: w.add_connection(c.topic if 'image' in c.topic else c.topic[1:],
                                           c.msgtype, typestore=typestore())
                 for c in reader.connections}
        for c, t, raw in iter_raw(reader):
            w.write(conns[c.topic], t, raw)
    run = read_run(rel)
    desired = run.desired and (run.desired.how, run.desired.stamp, run.desired.values)
    assert (len(run.frames), desired) == \
        (rec.iterations, ('taught', rec.taught_stamp, rec.desired_meas))
    assert (run.states, run.meas) == (read_run(rec.bag).states, read_run(rec.bag).meas)


def test_watch_tools_say_what_the_reader_left_out(tmp_path, rec):
    split = tmp_path / 'split'
    shutil.copytree(rec.bag, split)
    with Writer(tmp_path / 'extra', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/servo/state', STRING, typestore=TS)
        for t in (1, 2):
            w.write(conn, t, string_cdr('not a DiagnosticArray'))
    shutil.move(tmp_path / 'extra' / 'extra.mcap', split / 'extra.mcap')
    meta = yaml.safe_load((split / 'metadata.yaml').read_text())
    meta['rosbag2_bagfile_information']['relative_file_paths'].append('extra.mcap')
    (split / 'metadata.yaml').write_text(yaml.safe_dump(meta))
    run = read_run(split)
    assert len(run.frames) == rec.iterations
    assert [('/servo/state' in w, ' 2 ' in w) for w in run.warnings] == [(True, True)]
    err = io.StringIO()
    with redirect_stderr(err):  # stops at the output, a directory, after reading the bag
        assert video.main([str(split), '-o', str(tmp_path), '--quiet']) == 1
    lines = err.getvalue().splitlines()
    assert len(lines) == 2 and '/servo/state' in lines[0] and str(tmp_path) in lines[1]


@pytest.mark.parametrize('topic', ['/servo/state', '/camera/cmd_vel'])
def test_watch_tools_refuse_a_run_topic_of_another_type(tmp_path, rec, topic):
    other = tmp_path / 'other'
    ts = typestore()
    text = bytes(ts.serialize_cdr(ts.types[STRING](data='x'), STRING))
    with bag(rec.bag) as reader, Writer(other, version=9,
                                        storage_plugin=StoragePlugin.MCAP) as w:
        conns = {c.topic: w.add_connection(c.topic, STRING if c.topic == topic else c.msgtype,
                                           typestore=ts) for c in reader.connections}
        for c, t, raw in iter_raw(reader):
            w.write(conns[c.topic], t, text if c.topic == topic else raw)
    err = io.StringIO()
    with redirect_stderr(err):
        assert video.main([str(other), '-o', str(tmp_path / 'v.mp4'), '--quiet']) == 1
    lines = err.getvalue().splitlines()
    assert len(lines) == 1 and topic in lines[0] and STRING in lines[0], lines
    assert not (tmp_path / 'v.mp4').exists()
