"""
Malformed inputs over DDS against the running servo and arm_sim nodes (issue 14).

One servo (wall clock) and one arm_sim (lockstep) serve every case of their group; a test
publisher feeds them. Each case asserts: the node is alive, the output is the safe one (a
zero twist answering the bad features; the command not executed: the joints did not move,
their velocity is zero), nothing non-finite was published, and the log names the problem.
"""
from __future__ import annotations

import math

from conftest import REPO
from malformed import (alive, all_finite, at, Group, in_log, stamp, twist_norm, values,
                       WAIT)
import numpy as np
import pytest

pytest.importorskip('rclpy')
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402, I100
from geometry_msgs.msg import TwistStamped  # noqa: E402
from sensor_msgs.msg import Image, JointState  # noqa: E402
from sphere_servo.pipeline.common import stamp_text  # noqa: E402
from sphere_servo.ros.conversions import header, twist_from_array  # noqa: E402
from sphere_servo.ros.vectors import DESIRED_QOS, ENABLED_QOS, features_msg  # noqa: E402
from std_msgs.msg import Bool, Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

S_STAR = np.array([0.0, 0.0, 9.0, 0.0, 0.0, 0.0])
S = S_STAR + np.array([0.3, -0.2, 0.5, 0.05, 0.0, -0.1])
ARM_SIM = str(REPO / 'config' / 'params' / 'arm_sim.yaml')


class Servo:
    """The servo (wall clock), publishers of features and desired, what it answers."""

    def __init__(self, g: Group):
        self.g = g
        self.twists, self.states = [], []
        g.node.create_subscription(TwistStamped, 'camera/cmd_vel', self.twists.append, 1000)
        g.node.create_subscription(DiagnosticArray, 'servo/state',
                                   lambda m: self.states.append(m), 1000)
        self.pub = g.node.create_publisher(JointState, 'features/s_n', 10)
        self.pub_desired = g.node.create_publisher(JointState, 'features/s_n/desired',
                                                   DESIRED_QOS)
        self.proc = g.start('servo', '--ros-args', '-p', 'max_image_age:=2.0',
                            '-p', 'timeout:=30.0', '-p', 'future_tolerance:=0.2')
        assert g.spin(WAIT, until=lambda: self.pub.get_subscription_count() > 0
                      and self.pub_desired.get_subscription_count() > 0), self.proc.log()
        self.pub_desired.publish(features_msg('s_n', header(1.0, 'cam'), S_STAR))
        assert g.spin(WAIT, until=lambda: in_log(self.proc, 'desired features of the image')), \
            self.proc.log()
        self.last = 0.0

    def now(self) -> float:
        """Return a fresh stamp on the servo's clock, after every stamp sent so far."""
        self.last = max(round(self.g.node.get_clock().now().nanoseconds * 1e-9, 4),
                        self.last + 0.001)
        return self.last

    def answer(self, msg: JointState):
        """Publish features; return the twist and the state that answer their stamp."""
        t = stamp(msg)
        self.pub.publish(msg)
        assert self.g.spin(WAIT, until=lambda: any(at(m, t) for m in self.twists)
                           and any(at(s, t) for s in self.states)), self.proc.log()[-2000:]
        return ([m for m in self.twists if at(m, t)][0],
                [s for s in self.states if at(s, t)][0].status[0])

    def good(self) -> None:
        tw, st = self.answer(features_msg('s_n', header(self.now(), 'cam'), S))
        assert twist_norm(tw.twist) > 0 and st.message == 'servoing', values(st)

    def state(self, pred):
        """Wait for a state that satisfies ``pred``; return it."""
        assert self.g.spin(WAIT, until=lambda: any(pred(s.status[0]) for s in self.states)), \
            [s.status[0].message for s in self.states[-5:]]
        return [s.status[0] for s in self.states if pred(s.status[0])][-1]


@pytest.fixture(scope='module')
def servo(install_space, tmp_path_factory):
    g = Group(install_space, tmp_path_factory.mktemp('servo'))
    s = Servo(g)
    yield s
    codes = g.close()
    assert all(c == 0 for c in codes.values()), codes


def _theta(*tu):
    return np.r_[S[:3], tu]


SERVO_VALUES = {  # kind: (features, what the log and the state name)
    'theta_u +inf': (_theta(math.inf, 0.0, 0.0), 'inf, 0.0, 0.0] is not finite'),
    'theta_u -inf': (_theta(0.0, -math.inf, 0.0), '-inf, 0.0] is not finite'),
    'theta_u 1e154': (_theta(1e154, 1e154, 0.0), '‖θu of s‖'),
    'theta_u 1e300': (_theta(0.0, 0.0, 1e300), '‖θu of s‖'),
    'theta_u beyond pi': (_theta(0.0, 0.0, 3.2), '‖θu of s‖'),
    's_nt inside the sphere': (np.r_[0.2, 0.1, 0.5, 0.0, 0.0, 0.0], '‖s_n,t‖ of s'),
    's_nt 1e300': (np.r_[0.0, 0.0, 1e300, 0.0, 0.0, 0.0], '‖s_n,t‖ of s'),
    'NaN features': (S * math.nan, 'not finite'),
}


@pytest.mark.parametrize('kind', SERVO_VALUES)
def test_servo_answers_impossible_features_with_a_zero_twist(kind, servo):
    s, needle = SERVO_VALUES[kind]
    servo.good()
    tw, st = servo.answer(features_msg('s_n', header(servo.now(), 'cam'), s))
    assert twist_norm(tw.twist) == 0 and st.message == 'target lost'
    assert needle in values(st)['reason'], values(st)
    _servo_ok(servo, 'no valid twist', needle)


@pytest.mark.parametrize('kind, make, needle', [
    ('wrong feature names', lambda t: JointState(header=header(t, 'cam'), name=['x'],
                                                 position=[1.0]), 'expected features'),
    ('names and values that do not pair', lambda t: JointState(
        header=header(t, 'cam'), name=list(features_msg('s_n', Header(), S).name),
        position=[1.0] * 5), '6 names but 5 values'),
])
def test_servo_answers_malformed_features_with_a_zero_twist(kind, make, needle, servo):
    servo.good()
    tw, st = servo.answer(make(servo.now()))
    assert twist_norm(tw.twist) == 0 and st.message == 'target lost'
    _servo_ok(servo, 'no valid twist', needle)


@pytest.mark.parametrize('kind, offset, needle', [
    ('features stamped in the future', +10.0, 'in the future'),
    ('stamps going backwards', -0.5, 'older than the last stamp'),
])
def test_servo_refuses_bad_stamps_with_a_zero_twist(kind, offset, needle, servo):
    servo.good()
    t = servo.now() + offset
    text = stamp_text(int(round(t * 1e9)))  # as the header carries it
    servo.pub.publish(features_msg('s_n', header(t, 'cam'), S))
    st = servo.state(lambda st: st.message == 'bad stamp' and text in values(st)['reason'])
    assert needle in values(st)['reason']
    assert not [m for m in servo.twists if at(m, t)]  # no twist answers that image
    servo.g.spin(0.3)
    assert twist_norm(servo.twists[-1].twist) == 0 and stamp(servo.twists[-1]) == 0.0
    _servo_ok(servo, 'no valid twist', needle)


@pytest.mark.parametrize('kind, s_star, needle', [
    ('desired theta_u inf', np.r_[S_STAR[:3], 0.0, math.inf, 0.0], 'needs 6 finite values'),
    ('desired theta_u 1e300', np.r_[S_STAR[:3], 0.0, 0.0, 1e300], '‖θu of s*‖'),
    ('desired of the wrong length', S_STAR[:5], 'desired'),
])
def test_servo_keeps_its_desired_when_a_bad_one_comes(kind, s_star, needle, servo):
    servo.good()
    before = values(servo.states[-1].status[0])['desired_stamp']
    msg = JointState(header=header(99.0, 'cam'), name=list(features_msg(
        's_n', Header(), S).name)[:len(s_star)], position=[float(v) for v in s_star])
    servo.pub_desired.publish(msg)
    assert servo.g.spin(WAIT, until=lambda: in_log(servo.proc, 'desired features refused',
                                                   needle)), servo.proc.log()[-2000:]
    servo.good()  # still servoing on the one it had
    assert values(servo.states[-1].status[0])['desired_stamp'] == before
    _servo_ok(servo, 'desired features refused', needle)


def test_servo_survives_a_flood(servo):
    """300 features at once, a third of them impossible: every twist finite, alive."""
    base = servo.now()  # after the last answered, 3 ms at most ahead (future tolerance)
    for k in range(300):
        s = _theta(0.0, 0.0, 1e300) if k % 3 == 0 else S
        servo.last = base + 1e-5 * k
        servo.pub.publish(features_msg('s_n', header(servo.last, 'cam'), s))
        if k % 50 == 0:
            servo.g.spin(0.01)
    servo.g.spin(WAIT, until=lambda: any(at(m, servo.last) for m in servo.twists))
    _servo_ok(servo, 'no valid twist', 'θu of s')


def _servo_ok(servo, *needles):
    assert alive(servo.proc), servo.proc.log()[-2000:]
    assert all(math.isfinite(v) for m in servo.twists for v in (
        m.twist.linear.x, m.twist.linear.y, m.twist.linear.z, m.twist.angular.x,
        m.twist.angular.y, m.twist.angular.z))
    assert in_log(servo.proc, *needles), servo.proc.log()[-2000:]
    servo.good()  # and it servos again


# --- arm_sim ---------------------------------------------------------------------------------
class Arm:
    """arm_sim in lockstep, a command publisher, what it publishes per frame."""

    def __init__(self, g: Group):
        self.g = g
        self.images, self.joints, self.status = [], [], []
        g.node.create_subscription(Image, 'camera/image_raw', self.images.append, 50)
        g.node.create_subscription(JointState, 'joint_states', self.joints.append, 500)
        g.node.create_subscription(DiagnosticArray, 'arm_sim/state',
                                   lambda m: self.status.append(m), 500)
        self.pub = g.node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)
        self.pub_enabled = g.node.create_publisher(Bool, 'servo/enabled', ENABLED_QOS)
        self.proc = g.start('arm_sim', '--ros-args', '--params-file', ARM_SIM,
                            '-p', 'clock_mode:=lockstep')
        assert g.spin(60.0, until=lambda: self.images and self.joints and self.status
                      and self.pub.get_subscription_count() > 0), self.proc.log()
        self.clients = {}

    def step(self, v, frame_id: str = 'camera_optical_frame', pub=None):
        """Send a twist; return the joint state and status of the frame it produced."""
        t0 = stamp(self.images[-1])
        (pub or self.pub).publish(TwistStamped(header=Header(frame_id=frame_id),
                                               twist=twist_from_array(v)))

        def frame():
            t = stamp(self.images[-1])
            return t > t0 and any(at(j, t) for j in self.joints) and any(
                at(s, t) for s in self.status)
        assert self.g.spin(WAIT, until=frame), self.proc.log()[-2000:]
        t = stamp(self.images[-1])
        return ([j for j in self.joints if at(j, t)][0],
                [s for s in self.status if at(s, t)][0].status[0])

    def call(self, service: str):
        if service not in self.clients:
            self.clients[service] = self.g.node.create_client(Trigger, f'/arm_sim/{service}')
        cli = self.clients[service]
        assert self.g.spin(WAIT, until=cli.service_is_ready)
        fut = cli.call_async(Trigger.Request())
        assert self.g.spin(WAIT, until=fut.done)
        res = fut.result()
        if res.success and 'first image stamped' in res.message:  # a jump: wait for its frame
            t = float(res.message.rsplit(' ', 1)[-1])
            assert self.g.spin(WAIT, until=lambda: any(at(i, t) for i in self.images))
        return res


@pytest.fixture(scope='module')
def arm(install_space, tmp_path_factory):
    g = Group(install_space, tmp_path_factory.mktemp('arm'))
    a = Arm(g)
    yield a
    codes = g.close()
    assert all(c == 0 for c in codes.values()), codes


V = [0.01, -0.01, 0.02, 0.02, 0.0, 0.05]


def _refused(arm, v, needle, frame_id='camera_optical_frame', pub=None):
    """Send a command the arm must refuse: it does not move, and says why."""
    moved, _ = arm.step(V)
    assert np.any(np.abs(moved.velocity) > 1e-6)  # a valid one moves the arm
    j, st = arm.step(v, frame_id, pub)
    assert np.all(np.array(j.velocity) == 0.0)  # refused: at rest at once
    np.testing.assert_array_equal(j.position, moved.position)
    assert needle in values(st).get('command_error', ''), values(st)
    assert st.message != 'error' and st.level == b'\x01'  # WARN, the state valid
    _arm_ok(arm, needle)


def _arm_ok(arm, needle):
    assert alive(arm.proc), arm.proc.log()[-2000:]
    assert all_finite(arm.joints, 'position', 'velocity')
    assert in_log(arm.proc, 'refusing', needle), arm.proc.log()[-2000:]
    j, st = arm.step(V)  # usable without a reset
    assert np.any(np.abs(j.velocity) > 1e-6) and 'command_error' not in values(st)


@pytest.mark.parametrize('kind, v, needle', [
    ('twist 1e307', [1e307, 0.0, 0.0, 0.0, 0.0, 0.0], '‖v‖ of the camera twist'),
    ('twist 1e308 then a valid one', [0.0, 1e308, 0.0, 0.0, 0.0, 1e308],
     '‖v‖ of the camera twist'),
    ('angular 1e5 rad/s', [0.0, 0.0, 0.0, 0.0, 1e5, 0.0], '‖ω‖ of the camera twist'),
    ('NaN twist', [math.nan, 0.0, 0.0, 0.0, 0.0, 0.0], 'is not finite'),
    ('inf twist', [0.0, 0.0, math.inf, 0.0, 0.0, 0.0], 'is not finite'),
    ('-inf twist', [0.0, 0.0, 0.0, -math.inf, 0.0, 0.0], 'is not finite'),
])
def test_arm_refuses_an_absurd_twist(kind, v, needle, arm):
    _refused(arm, v, needle)


@pytest.mark.parametrize('frame_id', ['tool0', ''])
def test_arm_refuses_a_twist_in_another_frame(frame_id, arm):
    _refused(arm, V, f'a camera twist in frame {frame_id!r}', frame_id)


def test_arm_hold_latches_until_release(arm):
    arm.step(V)
    assert arm.call('hold').success
    for _ in range(3):  # the next twists do not move the arm
        j, st = arm.step(V)
        assert np.all(np.array(j.velocity) == 0.0) and 'held' in values(st)['hold']
    assert in_log(arm.proc, 'refusing held')
    res = arm.call('release')
    assert res.success and 'released' in res.message
    j, st = arm.step(V)
    assert np.any(np.abs(j.velocity) > 1e-6) and 'hold' not in values(st)


@pytest.mark.parametrize('jump', ['go_start', 'go_desired', 'reset'])
def test_arm_refuses_a_jump_while_the_servo_is_enabled(jump, arm):
    before, _ = arm.step(V)
    arm.pub_enabled.publish(Bool(data=True))  # latched, as the servo's ~/enabled
    arm.g.spin(0.5)
    res = arm.call(jump)
    assert not res.success and 'the servo is enabled' in res.message, res.message
    j, _ = arm.step(np.zeros(6))
    np.testing.assert_allclose(j.position, before.position, atol=1e-3)  # no jump
    assert in_log(arm.proc, 'refused: the servo is enabled') and alive(arm.proc)
    arm.pub_enabled.publish(Bool(data=False))  # the teach sequence disables it first
    arm.g.spin(0.5)
    assert arm.call(jump).success


def test_arm_reports_and_refuses_a_second_command_publisher(arm):
    rogue = arm.g.node.create_publisher(TwistStamped, 'camera/cmd_vel', 10)
    assert arm.g.spin(WAIT, until=lambda: rogue.get_subscription_count() > 0)
    arm.g.spin(1.2)  # arm_sim looks at the publishers once a second
    _refused(arm, V, 'out of sequence', pub=rogue)
    assert in_log(arm.proc, 'from 2 publishers')
    _, st = arm.step(V)
    assert values(st)['command_publishers'].count('/') == 2, values(st)
    arm.g.node.destroy_publisher(rogue)


def test_arm_survives_a_flood(arm):
    """200 NaN twists at once: each steps the clock with the arm at rest; alive, finite."""
    n, t0 = len(arm.images), stamp(arm.images[-1])
    for k in range(200):
        arm.pub.publish(TwistStamped(header=Header(frame_id='camera_optical_frame'),
                                     twist=twist_from_array([math.nan] * 6)))
        if k % 20 == 0:
            arm.g.spin(0.01)
    arm.g.spin(5.0, until=lambda: len(arm.images) >= n + 200)  # some may be dropped (depth)
    flood = [j for j in arm.joints if stamp(j) > t0]
    assert flood and all(np.all(np.array(j.velocity) == 0.0) for j in flood)
    _arm_ok(arm, 'is not finite')
