"""
``replay --answer``: inputs and situations the lockstep replay must not get silently wrong.

The standard: a replay that exits 0 answered every message it played; one that cannot tell
exits non-zero, says why, in bounded time, without a traceback. Bags are written with
``rosbags``; the answering node is this test's (or, to be killed, a process of its own).
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

from conftest import executable_path
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import get_typestore, Stores  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)
IMAGE, JOINTS = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/JointState'
T0, STEP = 1_700_000_000 * 10**9, 5_000_000


def _header(stamp: int):
    T = TS.types
    sec, nsec = divmod(stamp, 10**9)
    return T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id='cam')


def _image(stamp: int, big_endian: bool = False) -> bytes:
    msg = TS.types[IMAGE](header=_header(stamp), height=2, width=2, encoding='mono8',
                          is_bigendian=0, step=2, data=np.arange(4, dtype=np.uint8))
    return bytes(TS.serialize_cdr(msg, IMAGE, little_endian=not big_endian))


def _joints(stamp: int) -> bytes:
    empty = np.zeros(0)
    msg = TS.types[JOINTS](header=_header(stamp), name=[], position=empty, velocity=empty,
                           effort=empty)
    return bytes(TS.serialize_cdr(msg, JOINTS))


def _bag(path, stamps, topic='/cam/image', step=STEP, image=_image, answers=None,
         other=None):
    """
    Images of ``stamps`` on ``topic`` ``step`` ns apart.

    ``answers``: a topic of recorded answers too; ``other``: a topic of 5 strings.
    """
    with Writer(path, version=9) as w:
        msgtype = IMAGE if image is not _string else 'std_msgs/msg/String'
        c = w.add_connection(topic, msgtype, typestore=TS)
        a = w.add_connection(answers, JOINTS, typestore=TS) if answers else None
        if other:
            o = w.add_connection(other, 'std_msgs/msg/String', typestore=TS)
            for i in range(5):
                w.write(o, T0 + i * step, _string(i))
        for i, s in enumerate(stamps):
            w.write(c, T0 + i * step, image(s))
            if a is not None:
                w.write(a, T0 + i * step + 1, _joints(s))
    return str(path)


def _string(stamp: int) -> bytes:
    return bytes(TS.serialize_cdr(TS.types['std_msgs/msg/String'](data=str(stamp)),
                                  'std_msgs/msg/String'))


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def _answerer(node, copies=1, shift=0, delay=0.03, best_effort=False, topic='/cam/image',
              answer='/answer'):
    """
    Keep the newest image only, take ``delay`` s on it, answer it on ``copies`` publishers.

    ``shift`` ns added to the answer's stamp (a node that restamps). Returns the stamps seen.
    """
    seen = []
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                     else ReliabilityPolicy.RELIABLE)
    pubs = [node.create_publisher(JointState, answer, qos) for _ in range(copies)]

    def on_image(msg):
        time.sleep(delay)
        seen.append(_stamp(msg))
        out = JointState(header=msg.header)
        out.header.stamp.nanosec += shift
        for p in pubs:
            p.publish(out)
    node.create_subscription(Image, topic, on_image,
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
    return seen


def _play(launch, spin, *args, until=None, limit=60.0):
    """Run replay to its end (or ``until``) while spinning; return (proc, seconds)."""
    proc = launch('replay', *args, '--wait-for-subscribers', '20')
    t = time.monotonic()
    spin(limit, until=lambda: proc.popen.poll() is not None or (until and until(proc)))
    spin(0.3)
    return proc, time.monotonic() - t


def _clean(proc) -> str:
    log = proc.log()
    assert 'Traceback' not in log, log
    return log


def test_extra_answers_do_not_answer_a_later_message_of_the_same_stamp(
        launch, test_node, tmp_path):
    """Two publishers answer each image; the bag repeats its stamps (as --loop does)."""
    node, spin = test_node
    seen = _answerer(node, copies=2)
    stamps = [T0 + (i % 10) * STEP for i in range(40)]
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', stamps), '--answer',
                   '/cam/image:=/answer')
    assert rep.popen.wait(10) == 0, rep.log()
    assert seen == stamps, _clean(rep)


def test_answers_published_before_the_trigger_are_no_answers(launch, test_node, tmp_path):
    """Another node publishes every stamp of the bag before replay plays them."""
    node, spin = test_node
    seen = _answerer(node)
    stamps = [T0 + i * STEP for i in range(40)]
    prophet = node.create_publisher(JointState, '/answer', 100)
    told = []

    def tell(proc):
        # once replay's answer subscription matched: every answer, ahead of its image
        if not told and prophet.get_subscription_count() > 0:
            for s in stamps:
                prophet.publish(JointState(header=_header_msg(s)))
            told.append(1)
        return False
    # --delay: the prophecies land before the first image, however loaded the machine
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', stamps), '--answer',
                   '/cam/image:=/answer', '--delay', '2', until=tell)
    assert told and rep.popen.wait(10) == 0, rep.log()
    assert seen == stamps, _clean(rep)


def _header_msg(stamp: int):
    from std_msgs.msg import Header
    h = Header(frame_id='cam')
    h.stamp.sec, h.stamp.nanosec = divmod(stamp, 10**9)
    return h


def test_loop_waits_for_each_pass(launch, test_node, tmp_path):
    """--loop replays the same stamps; the second answer to each must not serve pass 2."""
    node, spin = test_node
    seen = _answerer(node, copies=2)
    stamps = [T0 + i * STEP for i in range(10)]
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', stamps), '--loop', '--answer',
                   '/cam/image:=/answer', until=lambda p: len(seen) >= 30)
    rep.popen.send_signal(signal.SIGINT)
    rep.popen.wait(10)
    assert seen[:30] == stamps * 3, _clean(rep)


def test_answer_topic_also_played_from_the_bag_is_refused(launch, test_node, tmp_path):
    """The bag's recorded answers would be replay's own answers (or pass for a publisher)."""
    node, spin = test_node
    bag = _bag(tmp_path / 'b', [T0 + i * STEP for i in range(20)], answers='/answer')
    rep, took = _play(launch, spin, bag, '--answer', '/cam/image:=/answer',
                      '--answer-timeout', '1')
    assert rep.popen.wait(10) == 1, rep.log()
    assert 'played from the bag' in _clean(rep) and took < 10, rep.log()


@pytest.mark.parametrize('shift', [1, None])
def test_a_node_that_restamps_or_never_answers_ends_the_replay_soon(
        launch, test_node, tmp_path, shift):
    """60 images, 1 s each: not 60 s of waiting; the reason is said."""
    node, spin = test_node
    if shift is None:   # a publisher of the answer topic that never answers
        node.create_publisher(JointState, '/answer', 10)
        node.create_subscription(Image, '/cam/image', lambda m: None, 10)
    else:
        _answerer(node, shift=shift)
    rep, took = _play(launch, spin, _bag(tmp_path / 'b', [T0 + i * STEP for i in range(60)]),
                      '--answer', '/cam/image:=/answer', '--answer-timeout', '1')
    assert rep.popen.wait(10) == 1, rep.log()
    log = _clean(rep)
    assert took < 20, log
    assert 'stopped' in log, log
    if shift:
        assert 'other stamps' in log, log


ANSWERER = """
import rclpy
from sensor_msgs.msg import Image, JointState
rclpy.init()
node = rclpy.create_node('answerer')
pub = node.create_publisher(JointState, '/answer', 10)
def on_image(msg):
    pub.publish(JointState(header=msg.header))
    print('answered', flush=True)
node.create_subscription(Image, '/cam/image', on_image, 10)
rclpy.spin(node)
"""


def test_answering_node_killed_mid_replay(launch, ros_env, tmp_path):
    """SIGKILL: no goodbye, its publisher lingers in the graph for the 20 s lease."""
    log = open(tmp_path / 'answerer.log', 'w+')
    answerer = subprocess.Popen([sys.executable, '-c', ANSWERER], env=ros_env, stdout=log,
                                stderr=subprocess.STDOUT)
    try:
        bag = _bag(tmp_path / 'b', [T0 + i * STEP for i in range(60)], step=100_000_000)
        rep = launch('replay', bag, '--answer', '/cam/image:=/answer', '--answer-timeout',
                     '2', '--wait-for-subscribers', '20')
        deadline = time.monotonic() + 60
        while (tmp_path / 'answerer.log').read_text().count('answered') < 10:
            assert time.monotonic() < deadline and rep.popen.poll() is None, rep.log()
            time.sleep(0.05)
        answerer.kill()
        killed = time.monotonic()
        assert rep.popen.wait(40) == 1, rep.log()
        out = _clean(rep)
        assert time.monotonic() - killed < 25, out
        assert 'had no answer' in out, out
    finally:
        answerer.kill()
        answerer.wait()


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signal_while_waiting_ends_promptly(launch, test_node, tmp_path, sig):
    node, spin = test_node
    node.create_publisher(JointState, '/answer', 10)
    node.create_subscription(Image, '/cam/image', lambda m: None, 10)
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', [T0 + i * STEP for i in range(5)]),
                   '--answer', '/cam/image:=/answer', '--answer-timeout', '60',
                   until=lambda p: 'playing' in p.log(), limit=30)
    spin(1.0)
    rep.popen.send_signal(sig)
    t = time.monotonic()
    code = rep.popen.wait(10)
    log = _clean(rep)
    assert time.monotonic() - t < 5, log
    # interrupted: no claim that the message went unanswered for 60 s
    assert 'in 60 s' not in log, log
    # cut short: the bag was not played answered
    assert code == 1 and 'interrupted while waiting' in log, log


def test_malformed_options_fail_before_playing(ros_env, tmp_path):
    """Each exits non-zero at once, with one error line, no traceback, nothing played."""
    bag = _bag(tmp_path / 'b', [T0])
    twice = ['--answer', '/cam/image:=/answer', '--answer', '/cam/image:=/other']
    cases = {
        'twice': (twice, 2, 'given 2 times'),
        'timeout alone': (['--answer-timeout', '3'], 2, 'without --answer'),
        'empty answer': (['--answer', '/cam/image:='], 1, 'bad --answer'),
        'empty trigger': (['--answer', ':=/answer'], 1, 'bad --answer'),
        'itself': (['--answer', 'cam/image:=/cam/image'], 1, 'cannot answer itself'),
        'two :=': (['--answer', '/cam/image:=/a:=/b'], 1, 'must not contain'),
        'double slash': (['--answer', '/cam/image:=//a'], 1, 'repeated'),
        'trailing slash': (['--answer', '/cam/image:=/a/'], 1, "end with a '/'"),
        **{f'timeout {t}': (['--answer', '/cam/image:=/answer', '--answer-timeout', t], 2,
                            'finite number of seconds > 0')
           for t in ('0', '-1', 'nan', 'inf', '1e400', '-0')},
    }
    exe = executable_path(ros_env, 'replay')
    procs = {what: subprocess.Popen([exe, bag, *args], env=ros_env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
             for what, (args, _, _) in cases.items()}
    for what, p in procs.items():
        out, err = p.communicate(timeout=60)
        code, text = cases[what][1:]
        assert p.returncode == code, f'{what}: exit {p.returncode}\n{out}{err}'
        assert 'Traceback' not in out + err and text in err, f'{what}:\n{err}'
        assert 'published' not in out, f'{what}: {out}'


@pytest.mark.parametrize('answer,code', [('cam/image:=answer', 0),
                                         ('/cam/raw:=/answer', 1)])
def test_remapped_trigger_is_named_as_published(launch, test_node, tmp_path, answer, code):
    """After --remap the trigger is the new name; the old one is refused, naming the new."""
    node, spin = test_node
    seen = _answerer(node)
    stamps = [T0 + i * STEP for i in range(20)]
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', stamps, topic='/cam/raw'),
                   '--remap', '/cam/raw:=/cam/image', '--answer', answer)
    assert rep.popen.wait(10) == code, rep.log()
    log = _clean(rep)
    assert seen == (stamps if code == 0 else []), log
    if code:
        assert 'publishes it on /cam/image' in log, log


def _xcdr2(stamp: int) -> bytes:
    """PLAIN_CDR2 little endian: the same bytes for an Image (nothing 8-byte aligned)."""
    return b'\x00\x07' + _image(stamp)[2:]


def _delimited(stamp: int) -> bytes:
    """DELIMITED_CDR2: a 4-byte size before the Header, where no stamp can be read."""
    body = _image(stamp)[4:]
    return b'\x00\x09\x00\x00' + len(body).to_bytes(4, 'little') + body


@pytest.mark.parametrize('case', ['big_endian', 'zero_stamps', 'xcdr2', 'delimited',
                                  'best_effort', 'max_rate_clock', 'rate_huge_timeout'])
def test_odd_bags_and_options_are_answered_or_refused(launch, test_node, tmp_path, case):
    """Exit 0 exactly when the node got every image, in order."""
    node, spin = test_node
    seen = _answerer(node, best_effort=case == 'best_effort')
    stamps = [0] * 20 if case == 'zero_stamps' else [T0 + i * STEP for i in range(20)]
    image = {'big_endian': lambda s: _image(s, True), 'xcdr2': _xcdr2,
             'delimited': _delimited}.get(case, _image)
    args = {'max_rate_clock': ['--max-rate', '--clock', '100'],
            'rate_huge_timeout': ['--rate', '4', '--answer-timeout', '1e300']}.get(case, [])
    clock = []
    if case == 'max_rate_clock':
        from rosgraph_msgs.msg import Clock
        node.create_subscription(Clock, '/clock', lambda m: clock.append(
            m.clock.sec * 10**9 + m.clock.nanosec), 100)
    rep, took = _play(launch, spin, _bag(tmp_path / 'b', stamps, image=image), '--answer',
                      '/cam/image:=/answer', '--answer-timeout', '2', *args)
    code = rep.popen.wait(10)
    log = _clean(rep)
    assert (code == 0) == (seen == stamps), f'exit {code}, seen {len(seen)}\n{log}'
    assert took < 30, log
    if case == 'delimited':
        assert code == 1 and 'no header stamp' in log, log
    elif case != 'xcdr2':   # whether the node reads XCDR2 is the middleware's business
        assert code == 0, log
    assert clock == sorted(clock), 'the clock went back'


@pytest.mark.parametrize('trigger, answer, rules', [
    ('/cam/image', '/answer2', ['-r', '/cam/image:=/cam2']),        # the bag's name
    ('/cam2', '/answer', ['-r', '/cam/image:=/cam2', '-r', '/answer:=/answer2']),
])
def test_ros_args_remaps_are_followed(launch, test_node, tmp_path, trigger, answer, rules):
    """``--ros-args -r`` renames the image and the answer: --answer names them either way."""
    node, spin = test_node
    seen = _answerer(node, topic='/cam2', answer='/answer2')
    stamps = [T0 + i * STEP for i in range(12)]
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', stamps), '--answer',
                   f'{trigger}:={answer}', '--ros-args', *rules, '--')
    assert rep.popen.wait(10) == 0, rep.log()
    assert seen == stamps, _clean(rep)


def test_a_remap_onto_a_played_topic_is_refused(launch, test_node, tmp_path):
    """An answer that rcl's rules put on a topic replay plays would answer itself."""
    node, spin = test_node
    _answerer(node)
    rep, _ = _play(launch, spin, _bag(tmp_path / 'b', [T0], other='/other'), '--answer',
                   '/cam/image:=/answer', '--ros-args', '-r', '/answer:=/other', '--')
    assert rep.popen.wait(10) == 1 and 'played from the bag too' in _clean(rep), rep.log()


def test_answer_type_without_header_or_trigger_never_played(launch, test_node, tmp_path):
    """Refused: answers that cannot carry a stamp; a trigger with no message in the bag."""
    node, spin = test_node
    node.create_publisher(String, '/said', 10)
    _answerer(node)
    rep, took = _play(launch, spin, _bag(tmp_path / 'a', [T0]), '--answer',
                      '/cam/image:=/said')
    assert rep.popen.wait(10) == 1 and 'carries no header' in _clean(rep), rep.log()
    rep, took = _play(launch, spin, _bag(tmp_path / 'b', [], other='/other'), '--answer',
                      '/cam/image:=/answer')
    assert rep.popen.wait(10) == 1 and 'no message of /cam/image' in _clean(rep), rep.log()
    rep, took = _play(launch, spin, _bag(tmp_path / 'c', [T0], image=_string), '--answer',
                      '/cam/image:=/answer')
    assert rep.popen.wait(10) == 1 and 'carries no header' in _clean(rep), rep.log()
