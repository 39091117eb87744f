"""
rosbag2 bags built the way rosbag2 and older tools write them, for the bag tests.

Written with the ``rosbags`` library (not this package's writer) and then edited as
rosbag2's own bags differ from what ``rosbags`` expects; modelled on rosbag2's test
resources (``rosbag2_tests/resources``: ``cdr_test`` with ``test_msgs/msg/Arrays``, the
service-event bags, the split ``wbag`` of relative topics ``AAA``, ``BBB``, …):

- storage QoS durations {2147483647 s, 4294967295 ns} (Fast DDS's "infinite" before
  Galactic) while ``metadata.yaml`` says 0/0, both meaning infinite;
- a topic stored with a relative name (``AAA``);
- a topic of a type no installed package provides (``test_msgs/msg/Arrays``), with its
  definition in the bag (MCAP schema, sqlite3 ``message_definitions``), and a service-event
  topic of a missing type (``test_msgs/srv/BasicTypes_Event``);
- a service-event topic of an installed type (``std_srvs/srv/SetBool_Event``);
- a topic listed with no message;
- split bags (several storage files, one ``metadata.yaml``).
"""
from __future__ import annotations

import hashlib
from pathlib import Path
import shutil

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
import yaml

TS = get_typestore(Stores.ROS2_JAZZY)
FOXY_INF = QosTime(2147483647, 4294967295)
STRING = 'std_msgs/msg/String'
ARRAYS = 'test_msgs/msg/Arrays'
ARRAYS_DEF = ('bool[3] bool_values\nint32[3] int32_values\nfloat64[3] float64_values\n'
              'string[3] string_values\n')
BASIC_EVENT = 'test_msgs/srv/BasicTypes_Event'
BASIC_EVENT_DEF = ('service_msgs/ServiceEventInfo info\n'
                   'test_msgs/BasicTypes_Request[<=1] request\n'
                   'test_msgs/BasicTypes_Response[<=1] response\n')
SETBOOL_EVENT = 'std_srvs/srv/SetBool_Event'
SETBOOL_EVENT_DEF = ('service_msgs/ServiceEventInfo info\n'
                     'std_srvs/SetBool_Request[<=1] request\n'
                     'std_srvs/SetBool_Response[<=1] response\n')
# (topic, type, messages) of the rosbag2-like bag; played = what replay must publish
CASE_TOPICS = [('/chatter', STRING, 20), ('AAA', STRING, 12), ('/arrays', ARRAYS, 4),
               ('/svc/_service_event', SETBOOL_EVENT, 6),
               ('/basic/_service_event', BASIC_EVENT, 4), ('/empty', STRING, 0)]
PLAYED = {'/chatter': 20, '/AAA': 12, '/svc/_service_event': 6}
UNKNOWN = {'/arrays', '/basic/_service_event'}


def foxy_qos(reliability=QosReliability.RELIABLE, durability=QosDurability.VOLATILE) -> Qos:
    return Qos(QosHistory.KEEP_LAST, 10, reliability, durability, FOXY_INF, FOXY_INF,
               QosLiveliness.AUTOMATIC, FOXY_INF, False)


def string_cdr(text: str) -> bytes:
    return TS.serialize_cdr(TS.types[STRING](data=text), STRING)


def arrays_cdr(i: int) -> bytes:
    ts = get_typestore(Stores.EMPTY)
    ts.register(get_types_from_msg(ARRAYS_DEF, ARRAYS))
    import numpy as np
    msg = ts.types[ARRAYS](bool_values=np.array([True, False, i % 2 == 0]),
                           int32_values=np.array([i, -i, 7], dtype=np.int32),
                           float64_values=np.array([i / 2, 0.0, -1.5]),
                           string_values=[f'a{i}', 'b', 'c'])
    return ts.serialize_cdr(msg, ARRAYS)


def setbool_event_cdr(i: int) -> bytes:
    from rclpy.serialization import serialize_message
    from std_srvs.srv import SetBool
    ev = SetBool.Event()
    ev.info.event_type = ev.info.REQUEST_RECEIVED
    ev.info.sequence_number = i
    ev.request = [SetBool.Request(data=bool(i % 2))]
    return serialize_message(ev)


def _hash(text: str) -> str:
    return 'RIHS01_' + hashlib.sha256(text.encode()).hexdigest()


def _payload(msgtype: str, i: int) -> bytes:
    if msgtype == STRING:
        return string_cdr(f'{i}')
    if msgtype == ARRAYS:
        return arrays_cdr(i)
    if msgtype == SETBOOL_EVENT:
        return setbool_event_cdr(i)
    return bytes([0, 1, 0, 0]) + bytes(range(16))  # never decoded: its type is missing


def _add(w: Writer, topic: str, msgtype: str, qos: Qos):
    if msgtype == STRING:
        return w.add_connection(topic, msgtype, typestore=TS, offered_qos_profiles=[qos])
    text = {ARRAYS: ARRAYS_DEF, BASIC_EVENT: BASIC_EVENT_DEF,
            SETBOOL_EVENT: SETBOOL_EVENT_DEF}[msgtype]
    return w.add_connection(topic, msgtype, msgdef=text, rihs01=_hash(text),
                            offered_qos_profiles=[qos])


def zero_durations(bag: Path) -> None:
    """Give every QoS of ``metadata.yaml`` 0/0 durations (the storage keeps its own)."""
    path = bag / 'metadata.yaml'
    meta = yaml.safe_load(path.read_text())
    for t in meta['rosbag2_bagfile_information']['topics_with_message_count']:
        qos = t['topic_metadata']['offered_qos_profiles']
        as_text = isinstance(qos, str)  # before version 9: a YAML string
        qos = yaml.safe_load(qos) if as_text else qos
        for q in qos:
            for k in ('deadline', 'lifespan', 'liveliness_lease_duration'):
                q[k] = {'sec': 0, 'nsec': 0}
        t['topic_metadata']['offered_qos_profiles'] = yaml.safe_dump(qos) if as_text else qos
    path.write_text(yaml.safe_dump(meta, sort_keys=False))


def rosbag2_case(path: Path, storage: str, topics=CASE_TOPICS, t0: int = 1_700_000_000 * 10**9,
                 ) -> dict[str, list[int]]:
    """
    Write the rosbag2-like bag (module docstring) at ``path``; return its stamps per topic.

    Messages 10 ms apart, topics interleaved; ``metadata.yaml`` then gets 0/0 durations.
    """
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    stamps: dict[str, list[int]] = {}
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = [(_add(w, name, msgtype, foxy_qos()), name, msgtype, n)
                 for name, msgtype, n in topics]
        k = 0
        for i in range(max(n for *_, n in topics)):
            for conn, name, msgtype, n in conns:
                if i < n:
                    t = t0 + k * 10_000_000
                    w.write(conn, t, _payload(msgtype, i))
                    stamps.setdefault(name, []).append(t)
                    k += 1
    zero_durations(path)
    return stamps


def split_bag(path: Path, storage: str = 'sqlite3', parts: int = 3,
              names=('AAA', 'BBB', 'CCC'), per_part: int = 5) -> list[int]:
    """
    Write a split bag like rosbag2's ``wbag``: relative topics, ``parts`` storage files.

    Each file is written by its own ``rosbags`` writer; ``metadata.yaml`` lists them all,
    as rosbag2 writes it after splitting. Returns the stamps in time order.
    """
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    ext = '.mcap' if storage == 'mcap' else '.db3'
    path.mkdir()
    stamps, metas = [], []
    t = 1_000_000
    for p in range(parts):
        part = path.parent / f'{path.name}_{p}'
        with Writer(part, version=9, storage_plugin=plugin) as w:
            conns = [w.add_connection(n, STRING, typestore=TS, offered_qos_profiles=[foxy_qos()])
                     for n in names]
            for i in range(per_part):
                for c in conns:
                    w.write(c, t, string_cdr(f'{p}.{i}.{c.topic}'))
                    stamps.append(t)
                    t += 1000
        metas.append(yaml.safe_load((part / 'metadata.yaml').read_text())[
            'rosbag2_bagfile_information'])
        shutil.move(part / f'{part.name}{ext}', path / f'{part.name}{ext}')
        shutil.rmtree(part)
    info = dict(metas[0])
    info['relative_file_paths'] = [m['relative_file_paths'][0] for m in metas]
    info['files'] = [m['files'][0] for m in metas]
    info['message_count'] = sum(m['message_count'] for m in metas)
    info['starting_time'] = metas[0]['starting_time']
    info['duration'] = {'nanoseconds': stamps[-1] - stamps[0]}
    info['topics_with_message_count'] = [
        dict(t, message_count=sum(m['topics_with_message_count'][k]['message_count']
                                  for m in metas))
        for k, t in enumerate(metas[0]['topics_with_message_count'])]
    (path / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': info},
                                                       sort_keys=False))
    zero_durations(path)
    return stamps
