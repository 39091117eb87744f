"""
``replay`` of bags built as rosbag2 writes them, counted by a subscriber over DDS.

The bags (:mod:`bag_cases`): QoS durations 0/0 in ``metadata.yaml`` against 2147483647 /
4294967295 in the storage, a relative topic name, topics of a missing type (one a service
event), a service-event topic of an installed type, an empty topic; with its
``metadata.yaml``, without it, as a bare storage file; and split bags.
"""
from __future__ import annotations

import subprocess

import bag_cases as bc
from conftest import executable_path
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402

RELIABLE = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


class Counter:
    """Subscribers of the test node: what each topic received, in order."""

    def __init__(self, node, topics: dict):
        self.got = {t: [] for t in topics}
        for t, kind in topics.items():
            node.create_subscription(kind, t, self.got[t].append, RELIABLE)

    def counts(self) -> dict:
        return {t: len(v) for t, v in self.got.items()}


def _replay(launch, spin, counter, expected: dict, *args):
    proc = launch('replay', *args, '--wait-for-subscribers', '20')
    spin(60.0, until=lambda: proc.popen.poll() is not None and
         all(counter.counts()[t] >= n for t, n in expected.items()))
    spin(0.3)  # anything more that would come
    assert proc.popen.wait(10) == 0, proc.log()
    return proc.log()


@pytest.mark.parametrize('variant', ['metadata', 'no_metadata', 'bare_file'])
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_replay_plays_what_a_rosbag2_bag_holds(launch, test_node, tmp_path, storage, variant):
    node, spin = test_node
    bag = tmp_path / 'rosbag2'
    bc.rosbag2_case(bag, storage)
    target = bag
    if variant != 'metadata':
        (bag / 'metadata.yaml').unlink()
    if variant == 'bare_file':
        (target,) = bag.iterdir()
    counter = Counter(node, {'/chatter': String, '/AAA': String, '/empty': String,
                             '/svc/_service_event': SetBool.Event})
    log = _replay(launch, spin, counter, bc.PLAYED, str(target))
    assert counter.counts() == dict(bc.PLAYED, **{'/empty': 0}), log
    assert [m.data for m in counter.got['/chatter']] == [str(i) for i in range(20)]
    assert [m.data for m in counter.got['/AAA']] == [str(i) for i in range(12)]
    ev = counter.got['/svc/_service_event']
    assert [e.info.sequence_number for e in ev] == list(range(6))
    assert [e.request[0].data for e in ev] == [bool(i % 2) for i in range(6)]
    # the topics of missing types are named, and what is played is announced
    for topic, kind in (('/arrays', bc.ARRAYS), ('/basic/_service_event', bc.BASIC_EVENT)):
        assert f'warning: skipping {topic} [{kind}]' in log, log
    assert f'playing {target}: {sum(bc.PLAYED.values())} messages on 4 topics' in log, log
    assert f'published {sum(bc.PLAYED.values())} messages' in log, log


@pytest.mark.parametrize('asked', ['AAA', '/AAA'])
def test_relative_topic_selected_either_way(launch, test_node, tmp_path, asked):
    node, spin = test_node
    bag = tmp_path / 'rosbag2'
    bc.rosbag2_case(bag, 'mcap')
    counter = Counter(node, {'/AAA': String, '/chatter': String})
    log = _replay(launch, spin, counter, {'/AAA': 12}, str(bag), '--topics', asked,
                  '--max-rate')
    assert counter.counts() == {'/AAA': 12, '/chatter': 0}, log
    assert 'skipping' not in log  # unknown types that were not asked for are not mentioned


@pytest.mark.parametrize('storage, without_metadata', [('sqlite3', False), ('mcap', True)])
def test_replay_split_bag(launch, test_node, tmp_path, storage, without_metadata):
    node, spin = test_node
    bag = tmp_path / 'wbag'
    bc.split_bag(bag, storage)
    if without_metadata:
        (bag / 'metadata.yaml').unlink()
    counter = Counter(node, {f'/{n}': String for n in ('AAA', 'BBB', 'CCC')})
    _replay(launch, spin, counter, {'/AAA': 15, '/BBB': 15, '/CCC': 15}, str(bag))
    for n in ('AAA', 'BBB', 'CCC'):
        assert [m.data for m in counter.got[f'/{n}']] == [
            f'{p}.{i}.{n}' for p in range(3) for i in range(5)]


def test_selections_that_play_nothing_fail(ros_env, tmp_path):
    """A topic of a missing type asked for, an empty topic, a bag of missing types only."""
    bag = tmp_path / 'rosbag2'
    bc.rosbag2_case(bag, 'sqlite3')
    only_unknown = tmp_path / 'unknown'
    bc.rosbag2_case(only_unknown, 'mcap', topics=[('/arrays', bc.ARRAYS, 3)])
    cases = {
        'asked for a missing type': ([str(bag), '--topics', '/arrays'],
                                     'cannot play /arrays [test_msgs/msg/Arrays]: its message '
                                     'type is not installed'),
        'asked for a service event of a missing type': (
            [str(bag), '--topics', 'basic/_service_event'],
            'cannot play /basic/_service_event [test_msgs/srv/BasicTypes_Event]'),
        'empty topic': ([str(bag), '--topics', '/empty'], 'nothing to play'),
        'only missing types': ([str(only_unknown)], 'nothing to play'),
    }
    exe = executable_path(ros_env, 'replay')
    procs = {what: subprocess.Popen([exe, *args], env=ros_env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
             for what, (args, _) in cases.items()}
    for what, p in procs.items():
        out, err = p.communicate(timeout=60)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert p.returncode == 1, f'{what}: exit {p.returncode}\n{out}{err}'
        assert 'Traceback' not in out + err, f'{what}:\n{err}'
        assert len(lines) == 1 and 'replay: error:' in lines[0], f'{what}: {err!r}'
        assert cases[what][1] in lines[0], f'{what}: {lines[0]}'
        assert 'published' not in out, f'{what}: {out}'
