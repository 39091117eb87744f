"""
``replay --answer TOPIC:=ANSWER``: every frame reaches a node that keeps only the newest.

The bag is written by ``rosbags`` (not this package's writer): 60 images 5 ms apart. The
node under the replay is this test's: it keeps one image (keep-last 1, as a camera node's
reader), takes 30 ms per image and answers each with a JointState of its header. Played at
the bag's pace it misses most images; with ``--answer`` it gets every one, in order, and the
replay exits 0. The header stamps are read from the serialized bytes
(:func:`~sphere_servo.bag.answers.header_stamp`), checked here against rclpy's and rosbags'
serializations.
"""
from __future__ import annotations

import time

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import get_typestore, Stores

from sphere_servo.bag.answers import header_stamp, parse_answer
from sphere_servo.bag.bagio import BagError

TS = get_typestore(Stores.ROS2_JAZZY)
IMAGE = 'sensor_msgs/msg/Image'
N, STEP_NS, T0 = 60, 5_000_000, 1_700_000_000 * 10**9


def _image_cdr(stamp_ns: int, big_endian: bool = False) -> bytes:
    T = TS.types
    sec, nsec = divmod(stamp_ns, 10**9)
    msg = T[IMAGE](header=T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id='cam'),
        height=2, width=2, encoding='mono8', is_bigendian=0, step=2,
        data=np.arange(4, dtype=np.uint8))
    raw = bytes(TS.serialize_cdr(msg, IMAGE, little_endian=not big_endian))
    return raw


@pytest.mark.parametrize('big_endian', [False, True])
def test_header_stamp_reads_rosbags_serializations(big_endian):
    for stamp in (0, 1, T0 + 123_456_789, (2**31 - 1) * 10**9 + 999_999_999):
        assert header_stamp(_image_cdr(stamp, big_endian)) == stamp


def test_header_stamp_reads_rclpy_serializations():
    from geometry_msgs.msg import TwistStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    for cls in (JointState, TwistStamped):
        m = cls()
        m.header.stamp.sec, m.header.stamp.nanosec = -5, 999_999_999
        assert header_stamp(serialize_message(m)) == -5 * 10**9 + 999_999_999


def test_header_stamp_refuses_what_is_no_stamp():
    raw = _image_cdr(T0)
    assert header_stamp(raw[:11]) is None                       # too short
    assert header_stamp(b'\x00\x02' + raw[2:]) is None           # parameter-list CDR
    bad = bytearray(raw)
    bad[8:12] = (10**9).to_bytes(4, 'little')                    # nanosec out of range
    assert header_stamp(bytes(bad)) is None


@pytest.mark.parametrize('text', ['/a', ':=/b', '/a:=', '/a:=/a', 'a:=/a'])
def test_malformed_answer_options_are_refused(text):
    with pytest.raises(BagError):
        parse_answer(text)


def test_answer_option_names_topics_fully():
    assert parse_answer('camera/image_raw:=features/s_n') == ('/camera/image_raw',
                                                              '/features/s_n')


def _bag(path):
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness
    from rosbags.interfaces import QosReliability, QosTime
    inf = QosTime(0, 0)
    qos = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
              inf, inf, QosLiveliness.AUTOMATIC, inf, False)
    with Writer(path, version=9) as w:
        c = w.add_connection('/cam/image', IMAGE, typestore=TS, offered_qos_profiles=[qos])
        for i in range(N):
            w.write(c, T0 + i * STEP_NS, _image_cdr(T0 + i * STEP_NS))
    return path


def _slow_node(node):
    """Keep the newest image only, take 30 ms on each, answer it: return the stamps seen."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, JointState
    seen = []
    pub = node.create_publisher(JointState, '/answer', 10)

    def on_image(msg):
        time.sleep(0.03)
        seen.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
        pub.publish(JointState(header=msg.header))
    node.create_subscription(Image, '/cam/image', on_image,
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
    return seen


def _play(launch, spin, *args):
    proc = launch('replay', *args, '--wait-for-subscribers', '20')
    spin(60.0, until=lambda: proc.popen.poll() is not None)
    spin(0.5)
    return proc


def test_replay_waits_for_each_answer(launch, test_node, tmp_path):
    node, spin = test_node
    seen = _slow_node(node)
    bag = _bag(tmp_path / 'bag')
    rep = _play(launch, spin, str(bag), '--answer', '/cam/image:=/answer')
    assert rep.popen.wait(10) == 0, rep.log()
    assert seen == [T0 + i * STEP_NS for i in range(N)], rep.log()
    # the bag's pace: the same node misses images (the case --answer is for)
    seen.clear()
    rep = _play(launch, spin, str(bag))
    assert rep.popen.wait(10) == 0, rep.log()
    assert 0 < len(seen) < N


def test_replay_answer_errors_exit_non_zero(launch, test_node, tmp_path):
    node, spin = test_node
    _slow_node(node)
    bag = _bag(tmp_path / 'bag')
    # a trigger the bag does not play; an answer nobody publishes
    for answer in ('/other:=/answer', '/cam/image:=/nobody'):
        rep = _play(launch, spin, str(bag), '--answer', answer, '--answer-timeout', '1')
        assert rep.popen.wait(10) == 1, rep.log()
        assert 'Traceback' not in rep.log()
