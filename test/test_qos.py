"""
The QoS of every topic (issue 17): one table that the README and the nodes follow.

The table is ``sphere_servo.ros.qos.TOPICS``; the launcher's supervisor and the tests
subscribe with ``qos.observer`` of it.

- ``test_the_readme_table_gives_each_topic_its_qos``: the README's topic table names, for
  each topic, the kind and depth of :data:`TOPICS` (and transient-local where it is).
- ``test_every_topic_is_reliable_and_only_the_desired_is_latched``: the choices the README
  justifies (reliable everywhere; small sensor and command depths; monitors deep).
- ``test_a_streams_writer_is_transient_local_and_keeps_at_least_its_readers_depth``: what a
  recorder matched late needs (README, "Transient-local writers").
- ``test_each_node_creates_its_topics_with_the_tables_profile``: the four node classes,
  constructed in this process, publish and subscribe every topic of theirs that the table
  names with exactly its profile (depth included).
- ``test_the_running_nodes_offer_and_request_the_table``: over ROS, in both launcher modes,
  each topic's publishers and subscriptions in the graph have the table's reliability and
  durability (the writers :func:`qos.writer`'s; discovery does not carry the depth), and the
  pipeline's subscriptions exist (rclpy's time source subscribes ``/clock`` best effort,
  which a reliable writer serves).
"""
from __future__ import annotations

import re
import time

from conftest import REPO, wait_for
import pytest
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from sphere_servo.bringup.processes import Launcher
from sphere_servo.bringup.single import NODE_CLASSES, node_classes
from sphere_servo.pipeline.config import scenario
from sphere_servo.ros import qos

KINDS = {'sensor': qos.SENSOR, 'command': qos.COMMAND, 'pipeline': qos.PIPELINE,
         'monitor': qos.MONITOR, 'diagnostics': qos.DIAGNOSTICS, 'clock': qos.CLOCK,
         'latched': qos.LATCHED}


def _table_key(cell: str) -> str:
    """Map the topic cell of the README's table to a key of :data:`qos.TOPICS`."""
    names = re.findall(r'`([^`]+)`', cell)
    if names[0] == '~/state':
        return '<node>/state'
    name = names[1].lstrip('/') if names[0].startswith('~/') else names[0]
    return re.sub(r'^features/(s_n|s|s_cc)(?=/|$)', 'features/<set>', name)


def _readme_rows() -> dict[str, str]:
    text = (REPO / 'README.md').read_text()
    table = text[text.index('| topic | type | QoS |'):]
    rows = {}
    for line in table.splitlines()[2:]:
        if not line.startswith('|'):
            break
        cells = [c.strip() for c in line.strip('|').split('|')]
        rows[_table_key(cells[0])] = cells[2]
    return rows


def test_the_readme_table_gives_each_topic_its_qos():
    rows = _readme_rows()
    assert set(rows) == set(qos.TOPICS), set(rows) ^ set(qos.TOPICS)
    for topic, cell in rows.items():
        kind = re.match(r'(\w+)', cell).group(1)
        profile = qos.TOPICS[topic]
        assert KINDS[kind] is profile, (topic, cell)
        assert re.search(rf'depth {profile.depth}\b', cell), (topic, cell)
        latched = profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert ('transient-local' in cell) == latched, (topic, cell)


def test_every_topic_is_reliable_and_only_the_desired_is_latched():
    for topic, profile in qos.TOPICS.items():
        assert profile.reliability == ReliabilityPolicy.RELIABLE, topic
        latched = profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert latched == (topic in ('features/<set>/desired', '/servo/enabled',
                                     'arm_sim/markers')), topic
    assert qos.SENSOR.depth <= 5 and qos.COMMAND.depth <= 10 and qos.LATCHED.depth == 1
    assert qos.MONITOR.depth >= 100
    deep = qos.observer(qos.LATCHED, 50)
    assert (deep.depth, deep.durability, deep.reliability) == (
        50, DurabilityPolicy.TRANSIENT_LOCAL, ReliabilityPolicy.RELIABLE)


def _graph_names(relative: str, fset: str = 's_n') -> list[str]:
    if relative == '<node>/state':
        return [f'/{n}/state' for n in ('arm_sim', 'detector', 'features', 'servo')]
    name = relative.replace('<set>', fset)
    return [name if name.startswith('/') else f'/{name}']


def test_each_node_creates_its_topics_with_the_tables_profile(ros_env):
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    table = {name: profile for rel, profile in qos.TOPICS.items() for name in _graph_names(rel)}
    writers = {name: profile for rel, profile in qos.WRITERS.items()
               for name in _graph_names(rel)}
    nodes = []
    try:
        nodes = [cls(context=ctx) for cls in node_classes(NODE_CLASSES)]
        seen = set()
        for n in nodes:
            for kind, endpoints in (('publisher', n.publishers), ('subscription',
                                                                  n.subscriptions)):
                for e in endpoints:
                    if e.topic_name in table:
                        want = table[e.topic_name]
                        if kind == 'publisher':  # the same policies, a deeper history
                            want = writers.get(e.topic_name, want)
                        assert e.qos_profile == want, (n.get_name(), kind, e.topic_name)
                        seen.add((kind, e.topic_name))
        # every topic of the table is published by one of them, the inputs subscribed
        assert {t for k, t in seen if k == 'publisher'} == set(table)
        assert {t for k, t in seen if k == 'subscription'} >= {
            '/camera/image_raw', '/camera/camera_info', '/detector/measurement',
            '/features/s_n', '/features/s_n/desired', '/camera/cmd_vel'}
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize('single_process', [False, True], ids=['processes', 'single'])
def test_the_running_nodes_offer_and_request_the_table(single_process, ros_env, test_node,
                                                       tmp_path):
    node, spin = test_node
    sc = scenario('special_sphere')
    log = open(tmp_path / 'launch.log', 'w')
    run = Launcher(sc, out=log, env=ros_env, single_process=single_process)
    run.start()
    try:
        expected = {name: (profile, rel) for rel, profile in qos.TOPICS.items()
                    for name in _graph_names(rel)}
        ours = {'/arm_sim', '/detector', '/features', '/servo'}

        def endpoints():
            found = {}
            for name in expected:
                pubs = [i for i in node.get_publishers_info_by_topic(name)
                        if f'/{i.node_name}' in ours]
                subs = [i for i in node.get_subscriptions_info_by_topic(name)
                        if f'/{i.node_name}' in ours]
                found[name] = (pubs, subs)
            return found

        def all_published():
            spin(0.2)
            return all(pubs for pubs, _ in endpoints().values())
        wait_for(all_published, 60.0, what='every topic of the table published by a node')
        time.sleep(0.5)
        spin(0.5)
        checked = 0
        for name, (pubs, subs) in endpoints().items():
            profile = expected[name][0]
            # rclpy's time source subscribes /clock best effort (not ours)
            writer = qos.writer(expected[name][1])
            for want, info in ([(writer, i) for i in pubs]
                               + [(profile, i) for i in (subs if name != '/clock' else [])]):
                got = (info.qos_profile.reliability, info.qos_profile.durability)
                assert got == (want.reliability, want.durability), (name, info)
                checked += 1
        # the pipeline's own subscriptions are there: images, measurements, features, twists
        subscribed = {n for n, (_, subs) in endpoints().items() if subs}
        assert {'/camera/image_raw', '/camera/camera_info', '/detector/measurement',
                '/features/s_n', '/features/s_n/desired', '/camera/cmd_vel'} <= subscribed
        print(f'{checked} endpoints checked')
    finally:
        codes = run.stop()
        log.close()
    assert all(c == 0 for c in codes.values()), (codes, (tmp_path / 'launch.log').read_text())


def test_a_streams_writer_is_transient_local_and_keeps_at_least_its_readers_depth():
    """The writers a late recorder needs: transient-local, reliable, as deep as the readers."""
    assert set(qos.WRITERS) == set(qos.TOPICS) - {
        '/clock', '/diagnostics', 'features/<set>/desired', '/servo/enabled', 'arm_sim/markers'}
    for topic, table in qos.TOPICS.items():
        profile = qos.writer(topic)
        assert profile.reliability == table.reliability == ReliabilityPolicy.RELIABLE, topic
        assert profile.depth >= table.depth, topic
        if topic in qos.WRITERS:
            assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL, topic
            assert table.durability == DurabilityPolicy.VOLATILE, topic
        else:
            assert profile is table, topic
    assert qos.writer('camera/image_raw').depth == 30
