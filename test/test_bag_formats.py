"""
Reading every rosbag2 (offline, no DDS): bags built as rosbag2 and older tools write them.

The bags come from :mod:`bag_cases` (written with ``rosbags``, then edited as rosbag2's own
bags differ), not from this package's writer; what a replay publishes over DDS is checked in
``test_bag_play.py``.
"""
from __future__ import annotations

from pathlib import Path
import sqlite3

import bag_cases as bc
import pytest
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from sphere_servo.bag import bagio
from sphere_servo.bag.metadata import (INFINITE, normal_duration, parse_metadata,
                                       read_metadata)
from sphere_servo.bag.replay import unplayable
import yaml

STORAGES = ['mcap', 'sqlite3']


def _strings(path: Path, topics=None) -> list[tuple[str, int, str]]:
    """(topic, stamp, data) of every String message read through bagio."""
    with bagio.bag(path) as r:
        conns = bagio.select_connections(r, topics)
        return [(c.topic, t, r.deserialize(raw, c.msgtype).data)
                for c, t, raw in bagio.iter_raw(r, [c for c in conns
                                                    if c.msgtype == bc.STRING])]


@pytest.mark.parametrize('storage', STORAGES)
def test_qos_mismatch_between_metadata_and_storage(tmp_path, storage):
    """
    0/0 durations in metadata.yaml, 2147483647/4294967295 in the storage: all is read.

    rosbags' own reader pairs connections by identical QoS and reads nothing from this
    bag (shown first, so the bag reproduces the failure); the summary counts what is read.
    """
    bag = tmp_path / 'talker'
    stamps = bc.rosbag2_case(bag, storage, topics=[('/chatter', bc.STRING, 20)])
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    q = meta['rosbag2_bagfile_information']['topics_with_message_count'][0][
        'topic_metadata']['offered_qos_profiles'][0]
    assert q['deadline'] == {'sec': 0, 'nsec': 0}
    with AnyReader([bag], default_typestore=bc.TS) as r:
        assert sum(c.msgcount for c in r.connections) == 20
        assert list(r.messages()) == []
    got = _strings(bag)
    assert [d for _, _, d in got] == [str(i) for i in range(20)]
    assert [t for _, t, _ in got] == stamps['/chatter']
    with bagio.bag(bag) as r:
        s = bagio.summary(r)
        (conn,) = r.connections
    assert s['message_count'] == s['stored_count'] == 20 and s['skipped'] == []
    assert s['topics'][0]['qos'][0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
    assert all(getattr(conn.ext.offered_qos_profiles[0], k) == INFINITE
               for k in ('deadline', 'lifespan', 'liveliness_lease_duration'))


def test_every_spelling_of_infinite_is_one_duration():
    for sec, nsec in [(0, 0), (2147483647, 4294967295), (2147483647, 2147483647),
                      (9223372036, 854775807), (10**12, 0)]:
        assert normal_duration(QosTime(sec, nsec)) == INFINITE, (sec, nsec)
    assert normal_duration(QosTime(1, 500)) == QosTime(1, 500)
    assert normal_duration(QosTime(2147483647, 0)) == QosTime(2147483647, 0)


@pytest.mark.parametrize('storage', STORAGES)
def test_relative_and_absolute_names_select_the_same_topic(tmp_path, storage):
    bag = tmp_path / 'b'
    bc.rosbag2_case(bag, storage)
    with bagio.bag(bag) as r:
        names = {c.topic for c in r.connections}
        assert 'AAA' in names and '/AAA' not in names  # kept as stored
        for asked in (['AAA'], ['/AAA'], [' /AAA ']):
            (c,) = bagio.select_connections(r, asked)
            assert c.topic == 'AAA' and c.msgcount == 12
        (c,) = bagio.select_connections(r, ['chatter'])
        assert c.topic == '/chatter'
        with pytest.raises(bagio.BagError, match='not in bag'):
            bagio.select_connections(r, ['/AAAA'])
    assert len(_strings(bag, ['/AAA'])) == 12


@pytest.mark.parametrize('storage', STORAGES)
def test_unknown_types_are_skipped_and_named(tmp_path, storage):
    bag = tmp_path / 'b'
    stamps = bc.rosbag2_case(bag, storage)
    with bagio.bag(bag) as r:
        sel = bagio.select(r, None, unplayable)
        s = bagio.summary(r, None, unplayable)
        assert {c.topic for c in sel.connections} == {'/chatter', 'AAA', '/svc/_service_event',
                                                      '/empty'}
        skipped = {x.topic: x.count for x in sel.skipped}
        assert skipped == {'/arrays': 4, '/basic/_service_event': 4}
        assert all('test_msgs' in x.reason for x in sel.skipped)
        assert sel.count == s['message_count'] == sum(bc.PLAYED.values())
        assert s['stored_count'] == sum(n for *_, n in bc.CASE_TOPICS)
        assert {t['name'] for t in s['skipped']} == bc.UNKNOWN
        text = bagio.format_summary(s)
        assert 'skipped' in text and 'test_msgs/msg/Arrays' in text
        # asked for by name, a topic that cannot be played is an error saying why
        for topic in ('/arrays', 'basic/_service_event'):
            with pytest.raises(bagio.BagError, match=r'cannot play .*not installed'):
                bagio.select(r, [topic], unplayable)
        # offline, the bag's own definition of the missing type still decodes it
        (arr,) = bagio.select_connections(r, ['/arrays'])
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in bagio.iter_raw(r, [arr])]
        assert [list(m.int32_values) for m in msgs] == [[i, -i, 7] for i in range(4)]
        assert [m.string_values[0] for m in msgs] == [f'a{i}' for i in range(4)]
        # every stored message is read, in time order
        all_ts = [t for _, t, _ in bagio.iter_raw(r)]
    assert all_ts == sorted(t for v in stamps.values() for t in v)


@pytest.mark.parametrize('storage', STORAGES)
def test_bag_without_metadata_and_bare_storage_file(tmp_path, storage):
    bag = tmp_path / 'b'
    bc.rosbag2_case(bag, storage)
    expected = _strings(bag)
    (bag / 'metadata.yaml').unlink()
    (data,) = list(bag.iterdir())
    for path in (bag, data):
        with bagio.bag(path) as r:
            s = bagio.summary(r, None, unplayable)
            assert s['source'] == 'storage' and '(no metadata.yaml)' in bagio.format_summary(s)
            assert s['message_count'] == sum(bc.PLAYED.values())
        assert _strings(path) == expected
    # a bare file moved out of its directory
    lone = tmp_path / data.name
    data.rename(lone)
    assert _strings(lone) == expected


def test_message_compressed_bag_without_metadata(tmp_path):
    """Per-message zstd (rosbag2_compression) is recognised without metadata.yaml too."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode
    bag = tmp_path / 'z'
    w = Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3)
    w.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with w:
        c = w.add_connection('/chatter', bc.STRING, typestore=bc.TS)
        for i in range(4):
            w.write(c, i + 1, bc.string_cdr(f'z{i}'))
    expected = [('/chatter', i + 1, f'z{i}') for i in range(4)]
    assert _strings(bag) == expected
    (bag / 'metadata.yaml').unlink()
    assert _strings(bag) == expected


@pytest.mark.parametrize('storage', STORAGES)
def test_split_bag(tmp_path, storage):
    bag = tmp_path / 'wbag'
    stamps = bc.split_bag(bag, storage)
    got = _strings(bag)
    assert [t for _, t, _ in got] == stamps
    assert [d for _, _, d in got][:4] == ['0.0.AAA', '0.0.BBB', '0.0.CCC', '0.1.AAA']
    assert got[-1][2] == '2.4.CCC'
    with bagio.bag(bag) as r:
        s = bagio.summary(r)
        assert len(s['files']) == 3 and s['message_count'] == 45
        assert {t['name']: t['count'] for t in s['topics']} == {'AAA': 15, 'BBB': 15,
                                                                'CCC': 15}
    (bag / 'metadata.yaml').unlink()  # the files alone, in split order
    assert _strings(bag) == got


def _meta_text(**changes) -> str:
    base = {
        'version': 9, 'storage_identifier': 'mcap', 'duration': {'nanoseconds': 5},
        'starting_time': {'nanoseconds_since_epoch': 10}, 'message_count': 2,
        'topics_with_message_count': [{'topic_metadata': {
            'name': '/a', 'type': bc.STRING, 'serialization_format': 'cdr',
            'offered_qos_profiles': [], 'type_description_hash': 'RIHS01_x'},
            'message_count': 2}],
        'compression_format': '', 'compression_mode': '', 'relative_file_paths': ['a.mcap'],
        'files': [{'path': 'a.mcap', 'starting_time': {'nanoseconds_since_epoch': 10},
                   'duration': {'nanoseconds': 5}, 'message_count': 2}],
        'custom_data': None, 'ros_distro': 'jazzy'}
    for key, value in changes.items():
        node = base
        *path, last = key.split('__')
        for p in path:
            node = node[int(p)] if p.isdigit() else node[p]
        if value is KeyError:
            del node[last]
        else:
            node[last] = value
    return yaml.safe_dump({'rosbag2_bagfile_information': base})


@pytest.mark.parametrize('change, match', [
    ({'message_count': '12a'}, r'message_count must be a non-negative integer'),
    ({'message_count': 2.5}, r'message_count must be a non-negative integer'),
    ({'message_count': True}, r'message_count must be a non-negative integer'),
    ({'message_count': -1}, r'message_count must be a non-negative integer'),
    ({'topics_with_message_count__0__message_count': 'x'},
     r'topics_with_message_count\[0\]\.message_count'),
    ({'version': 10}, r'version 10 is not supported'),
    ({'version': '9'}, r'version must be a non-negative integer'),
    ({'storage_identifier': 'rosbag_v2'}, r"storage 'rosbag_v2' is not supported"),
    ({'relative_file_paths': []}, r'relative_file_paths'),
    ({'duration__nanoseconds': 'soon'}, r'duration\.nanoseconds'),
    ({'ros_distro': KeyError}, r'ros_distro is missing'),
    ({'files': KeyError}, r'files is missing'),
    ({'compression_mode': 'gzip'}, r'compression_mode'),
    ({'compression_mode': 'message', 'compression_format': 'lz4'}, r'compression_format'),
    ({'topics_with_message_count__0__topic_metadata__name': KeyError},
     r'topic_metadata\.name is missing'),
    ({'topics_with_message_count__0__topic_metadata__offered_qos_profiles': [{'depth': 1}]},
     r'offered_qos_profiles\[0\]\.history is missing'),
])
def test_metadata_is_parsed_strictly(change, match):
    assert parse_metadata(_meta_text()).message_count == 2  # the base is valid
    with pytest.raises(bagio.BagError, match=match):
        parse_metadata(_meta_text(**change))


def test_metadata_fields_by_version():
    """Fields a version introduced are optional before it (rosbag2_storage/yaml.hpp)."""
    old = _meta_text(version=4, files=KeyError, custom_data=KeyError, ros_distro=KeyError,
                     topics_with_message_count__0__topic_metadata__type_description_hash=(
                         KeyError))
    m = parse_metadata(old)
    assert (m.version, m.files, m.custom_data, m.ros_distro) == (4, (), {}, '')
    # a version 8 QoS string with integer policies, as Humble writes it
    v8 = _meta_text(version=8, topics_with_message_count__0__topic_metadata__offered_qos_profiles=(
        '- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n  deadline:\n'
        '    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 0\n    nsec: 0\n'
        '  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n'
        '  avoid_ros_namespace_conventions: false'))
    (q,) = parse_metadata(v8).topics[0].qos
    assert (q.history.name, q.depth, q.reliability.name, q.durability.name) == (
        'KEEP_LAST', 5, 'BEST_EFFORT', 'TRANSIENT_LOCAL')
    assert q.deadline == q.lifespan == INFINITE


def test_bad_metadata_refuses_the_bag(tmp_path):
    bag = tmp_path / 'b'
    bc.rosbag2_case(bag, 'mcap', topics=[('/chatter', bc.STRING, 3)])
    path = bag / 'metadata.yaml'
    path.write_text(path.read_text().replace('message_count: 3', 'message_count: 3x', 1))
    with pytest.raises(bagio.BagError, match='message_count must be a non-negative integer'):
        bagio.open_bag(bag)


def test_written_metadata_is_jazzys(tmp_path):
    """Our writer: ros_distro jazzy, MCAP channel metadata as rosbag2_storage_mcap's."""
    from sphere_servo.bag import mcap
    from sphere_servo.bag.writer import BagWriter
    for storage in STORAGES:
        path = tmp_path / storage
        with BagWriter(path, storage) as w:
            t = w.add_topic('/chatter', bc.STRING, [bc.foxy_qos()], typestore=bc.TS)
            for i in range(5):
                w.write(t, 100 + i, bc.string_cdr(str(i)), publish_time=50 + i)
        meta = read_metadata(path)
        assert meta.ros_distro == 'jazzy' and meta.version == 9
        raw = yaml.safe_load((path / 'metadata.yaml').read_text())[
            'rosbag2_bagfile_information']
        assert list(raw) == ['version', 'storage_identifier', 'duration', 'starting_time',
                             'message_count', 'topics_with_message_count',
                             'compression_format', 'compression_mode', 'relative_file_paths',
                             'files', 'custom_data', 'ros_distro']
        ext = '.mcap' if storage == 'mcap' else '.db3'
        assert raw['relative_file_paths'] == [f'{storage}_0{ext}']
        (topic,) = meta.topics
        assert topic.type_hash == bc.TS.hash_rihs01(bc.STRING)
        f = path / raw['relative_file_paths'][0]
        if storage == 'mcap':
            sc = mcap.scan(f)  # reads the data section of the finished file
            (ch,) = sc.channels.values()
            assert ch.metadata['topic_type_hash'] == topic.type_hash
            assert yaml.safe_load(ch.metadata['offered_qos_profiles'])[0]['deadline'] == {
                'sec': 9223372036, 'nsec': 854775807}
            (schema,) = sc.schemas.values()
            assert (schema.name, schema.encoding) == (bc.STRING, 'ros2msg')
            assert sc.library and sc.stopped.startswith('summary') and sc.message_count == 5
            with AnyReader([path], default_typestore=bc.TS) as r:
                assert [t for _, t, _ in r.messages()] == [100, 101, 102, 103, 104]
            from rosbags.rosbag2.storage_mcap import McapReader
            mr = McapReader(f)
            mr.open()  # the summary: statistics, chunk indexes with their message indexes
            assert mr.statistics.message_count == 5 and mr.statistics.channel_count == 1
            assert sum(sum(c.channel_count.values()) for c in mr.chunks) == 5
            mr.close()
        else:
            con = sqlite3.connect(f)
            assert con.execute('SELECT schema_version, ros_distro FROM schema').fetchall() == [
                (4, 'jazzy')]
            assert con.execute('PRAGMA journal_mode').fetchone() == ('delete',)
            (stored,) = con.execute('SELECT metadata FROM metadata').fetchone()
            assert yaml.safe_load(stored)['ros_distro'] == 'jazzy'
            con.close()
            assert not Path(f'{f}-wal').exists()


def test_older_formats_read(tmp_path):
    """A version-8 sqlite3 bag, QoS as a YAML string of integer enums (Humble)."""
    with Writer(tmp_path / 'v8', version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        c = w.add_connection('/chatter', bc.STRING, typestore=bc.TS,
                             offered_qos_profiles=[bc.foxy_qos()])
        for i in range(3):
            w.write(c, i + 1, bc.string_cdr(str(i)))
    bc.zero_durations(tmp_path / 'v8')
    assert [d for _, _, d in _strings(tmp_path / 'v8')] == ['0', '1', '2']
