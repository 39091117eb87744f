"""
Bags shaped as rosbag2 writes them (not as our writer does), written here without our writer.

- a split bag whose topic changes type between files: ``reindex`` must say so and count, in
  ``metadata.yaml``, only what a reader will read (not the other type's messages as the
  first type's);
- a split bag with a topic only in its second file and messages out of time order across the
  files: read, in time order;
- ``reindex`` given a file that is not storage, next to a bag: refused, the bag untouched;
- an MCAP file with no summary section and no chunks (libmcap's ``noSummary``,
  ``noChunking``), only a footer: read;
- sqlite3 files of older rosbag2 schemas (Dashing: no QoS column; Foxy; Humble: the
  ``schema`` and ``metadata`` tables), messages inserted out of time order: read in order.
"""
from __future__ import annotations

import os
from pathlib import Path
import shutil
import sqlite3
import struct
import subprocess
import sys

from bag_cases import foxy_qos, STRING, string_cdr, TS
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from sphere_servo.bag import mcap
from sphere_servo.bag.bagio import iter_raw, open_bag
import yaml

pytest.importorskip('rclpy')

REPO = Path(__file__).resolve().parents[1]
BOOL = 'std_msgs/msg/Bool'


def _reindex(path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, '-m', 'sphere_servo.bag.repair', str(path)],
                          env=env, capture_output=True, text=True, timeout=120, cwd=REPO)


def _payload(msgtype: str, t: int) -> bytes:
    if msgtype == STRING:
        return string_cdr(str(t))
    return TS.serialize_cdr(TS.types[msgtype](data=True), msgtype)


def _split(path: Path, ext: str, parts: list[list[tuple[str, str, int]]]) -> None:
    """Write ``parts`` (each a list of (topic, type, t)) as ``path/<name>_<i><ext>``."""
    plugin = StoragePlugin.MCAP if ext == '.mcap' else StoragePlugin.SQLITE3
    path.mkdir()
    for i, items in enumerate(parts):
        part = path.parent / f'{path.name}_{i}'
        with Writer(part, version=9, storage_plugin=plugin) as w:
            conns = {}
            for topic, msgtype, t in items:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=TS,
                                                    offered_qos_profiles=[foxy_qos()])
                w.write(conns[topic], t, _payload(msgtype, t))
        shutil.move(part / f'{part.name}{ext}', path / f'{part.name}{ext}')
        shutil.rmtree(part)


def _read(path: Path) -> tuple[list[tuple[str, int]], list[str], dict[str, int]]:
    reader = open_bag(path)
    try:
        got = [(c.topic, ts) for c, ts, _ in iter_raw(reader)]
        return got, list(reader.warnings), {c.topic: c.msgcount for c in reader.connections}
    finally:
        reader.close()


@pytest.mark.parametrize('ext', ['.mcap', '.db3'])
def test_reindex_of_a_topic_whose_type_changes_between_files_says_so(tmp_path, ext):
    bag = tmp_path / 'bag'
    _split(bag, ext, [[('/a', STRING, 100), ('/a', STRING, 300)],
                      [('/b', STRING, 50), ('/a', STRING, 200)],
                      [('/a', BOOL, 500), ('/a', BOOL, 600)]])
    res = _reindex(bag)
    assert res.returncode == 0, res.stderr
    assert f'/a has type {BOOL} in bag_2{ext}' in res.stderr, res.stderr
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: (t['topic_metadata']['type'], t['message_count'])
              for t in info['topics_with_message_count']}
    assert counts == {'/a': (STRING, 3), '/b': (STRING, 1)}
    assert info['message_count'] == 4
    assert [f['message_count'] for f in info['files']] == [2, 2, 2]  # what each file holds
    got, warnings, stored = _read(bag)
    assert stored == {'/a': 3, '/b': 1}
    assert got == [('/b', 50), ('/a', 100), ('/a', 200), ('/a', 300)]
    assert len(warnings) == 1 and BOOL in warnings[0], warnings  # the type, not a count lie


@pytest.mark.parametrize('ext', ['.mcap', '.db3'])
def test_split_bag_topic_in_a_later_file_out_of_order_across_files(tmp_path, ext):
    bag = tmp_path / 'bag'
    _split(bag, ext, [[('/a', STRING, 100), ('/a', STRING, 400)],
                      [('/b', STRING, 50), ('/a', STRING, 200), ('/b', STRING, 300)]])
    want = [('/b', 50), ('/a', 100), ('/a', 200), ('/b', 300), ('/a', 400)]
    assert _read(bag) == (want, [], {'/a': 3, '/b': 2})
    assert _reindex(bag).returncode == 0
    assert _read(bag) == (want, [], {'/a': 3, '/b': 2})


def test_reindex_refuses_a_file_that_is_not_storage(tmp_path):
    bag = tmp_path / 'bag'
    _split(bag, '.db3', [[('/a', STRING, 100)]])
    notes = bag / 'notes.txt'
    notes.write_text('not a bag\n')
    res = _reindex(notes)
    assert res.returncode == 1 and 'not a rosbag2 bag' in res.stderr, res.stderr
    assert not (bag / 'metadata.yaml').exists()


def _mcap_without_summary(path: Path, stamps: list[int]) -> None:
    """Write an MCAP file of unchunked messages, a data end and a footer, no summary."""
    with open(path, 'wb') as fh:
        fh.write(mcap.MAGIC + mcap.record(mcap.OP_HEADER, mcap._str('ros2') +
                                          mcap._str('libmcap 1.4.0')))
        fh.write(mcap.Schema(1, STRING, 'ros2msg', b'string data\n').record())
        fh.write(mcap.Channel(1, 1, '/chatter', 'cdr', {}).record())
        for seq, t in enumerate(stamps):
            fh.write(mcap.record(mcap.OP_MESSAGE, struct.pack('<HIQQ', 1, seq, t, t) +
                                 string_cdr(str(t))))
        fh.write(mcap.record(mcap.OP_DATA_END, struct.pack('<I', 0)))
        fh.write(mcap.record(mcap.OP_FOOTER, struct.pack('<QQI', 0, 0, 0)) + mcap.MAGIC)


def test_mcap_without_summary_or_chunks_is_read(tmp_path):
    bag = tmp_path / 'bag'
    bag.mkdir()
    _mcap_without_summary(bag / 'bag_0.mcap', [10, 20, 30, 40])
    want = [('/chatter', t) for t in (10, 20, 30, 40)]
    assert _read(bag) == (want, [], {'/chatter': 4})
    assert _read(bag / 'bag_0.mcap') == (want, [], {'/chatter': 4})
    assert _reindex(bag).returncode == 0
    assert _read(bag) == (want, [], {'/chatter': 4})


FOXY_QOS = yaml.safe_dump([{
    'history': 1, 'depth': 10, 'reliability': 2, 'durability': 2,
    'deadline': {'sec': 2147483647, 'nsec': 4294967295},
    'lifespan': {'sec': 2147483647, 'nsec': 4294967295}, 'liveliness': 1,
    'liveliness_lease_duration': {'sec': 2147483647, 'nsec': 4294967295},
    'avoid_ros_namespace_conventions': False}])


def _old_db3(path: Path, schema: str, stamps: list[int]) -> None:
    con = sqlite3.connect(path)
    if schema == 'humble':
        con.execute('CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, '
                    'ros_distro TEXT NOT NULL)')
        con.execute("INSERT INTO schema VALUES (3, 'humble')")
        con.execute('CREATE TABLE metadata(id INTEGER PRIMARY KEY, '
                    'metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL)')
    if schema == 'dashing':
        con.execute('CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, '
                    'type TEXT NOT NULL, serialization_format TEXT NOT NULL)')
        con.execute(f"INSERT INTO topics VALUES (1, '/chatter', '{STRING}', 'cdr')")
    else:
        con.execute('CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, '
                    'type TEXT NOT NULL, serialization_format TEXT NOT NULL, '
                    'offered_qos_profiles TEXT NOT NULL)')
        con.execute(f"INSERT INTO topics VALUES (1, '/chatter', '{STRING}', 'cdr', ?)",
                    (FOXY_QOS,))
    con.execute('CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, '
                'timestamp INTEGER NOT NULL, data BLOB NOT NULL)')
    for i, t in enumerate(stamps):
        con.execute('INSERT INTO messages VALUES (?, 1, ?, ?)', (i + 1, t, string_cdr(str(t))))
    con.commit()
    con.close()


@pytest.mark.parametrize('schema', ['dashing', 'foxy', 'humble'])
def test_db3_of_older_rosbag2_schemas_is_read(tmp_path, schema):
    bag = tmp_path / 'bag'
    bag.mkdir()
    _old_db3(bag / 'bag_0.db3', schema, [30, 10, 20])
    want = [('/chatter', t) for t in (10, 20, 30)]
    assert _read(bag) == (want, [], {'/chatter': 3})
    res = _reindex(bag)
    assert res.returncode == 0, res.stderr
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert (info['starting_time']['nanoseconds_since_epoch'], info['duration']['nanoseconds'],
            info['message_count']) == (10, 20, 3)
    assert _read(bag) == (want, [], {'/chatter': 3})
