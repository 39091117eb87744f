"""
The arm simulator core without ROS: lockstep and realtime stepping, jumps, re-publishing.

Poses are checked against the parameters that define them (the IK of ``desired_cMo``) and
against the arm model's own forward kinematics; times against the camera period.
"""
from __future__ import annotations

import numpy as np
import pytest

from sphere_servo.pipeline.arm_sim import ArmSimCore, START_TIME
from sphere_servo.pipeline.common import Level
from sphere_servo.pipeline.params import ArmSimParams, ParameterError
from sphere_servo.sim.arm import pose_from_xyz_rpy, Status

DT = 1.0 / 30.0
SCENE = {'hand_eye': [0.0, -0.04, 0.02, 0.0, 0.0, 0.0], 'velocity_scale': 0.5,
         'camera': {'width': 160, 'height': 120, 'px': 150.0, 'py': 150.0, 'u0': 80.0,
                    'v0': 60.0}}


@pytest.fixture(scope='module')
def lockstep():
    return ArmSimParams.from_mapping({**SCENE, 'clock_mode': 'lockstep'})


def test_lockstep_one_frame_per_command(lockstep):
    sim = ArmSimCore(lockstep)
    first = sim.frame()
    assert first.t == START_TIME and first.stamp_ns == 1_000_000_000
    assert first.image.shape == (120, 160, 3) and sim.republish_due
    q0 = first.q
    out = sim.on_command([0.02, 0.0, 0.03, 0.0, 0.0, 0.1])
    assert out.valid and not sim.republish_due
    sim.on_servo_enabled(True)  # a servo drives: a frame it may have lost is sent again
    assert sim.republish_due
    sim.on_servo_enabled(False)
    assert out.frame.t == pytest.approx(START_TIME + DT, abs=1e-12)
    assert np.any(out.frame.q != q0) and np.any(out.frame.qdot)
    # the frame shows the arm's state: its pose is the forward kinematics of its q
    np.testing.assert_allclose(out.frame.oMc.homogeneous,
                               sim.arm.oMc(out.frame.q).homogeneous, atol=1e-12)
    held = sim.on_command([np.nan, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert not held.valid and held.frame.t == pytest.approx(START_TIME + 2 * DT, abs=1e-12)
    np.testing.assert_array_equal(held.frame.q, out.frame.q)  # held still, time goes on
    assert not np.any(held.frame.qdot) and held.frame.info.status is Status.OK
    stamps = [sim.on_command(np.zeros(6)).frame.stamp_ns for _ in range(3)]
    assert np.diff(stamps).tolist() == [33_333_333, 33_333_334]  # rounded, never drifting


def test_realtime_commands_do_not_step(lockstep):
    sim = ArmSimCore(lockstep.replace({'clock_mode': 'realtime'}))
    assert not sim.republish_due
    t0 = sim.frame().t
    out = sim.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    assert out.valid and out.frame is None and sim.frame().t == t0
    assert np.any(sim.on_tick().qdot)  # the valid command runs on the ticks
    refused = sim.on_command([np.inf] * 6)
    assert not refused.valid and 'finite' in refused.reason
    stopped = sim.on_tick()  # a refused command stops the arm at once (issue 14, item 8)
    assert stopped.t == pytest.approx(t0 + 2 * DT) and not np.any(stopped.qdot)


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_an_absurd_twist_is_refused_and_the_arm_stays_usable(lockstep, mode):
    sim = ArmSimCore(lockstep.replace({'clock_mode': mode}))
    q0 = sim.frame().q
    out = sim.on_command([1e308, 0.0, 0.0, 0.0, 0.0, 1e307])
    assert not out.valid and out.reason
    frame = out.frame if mode == 'lockstep' else sim.on_tick()
    assert np.all(np.isfinite(frame.q)) and not np.any(frame.qdot)
    np.testing.assert_array_equal(frame.q, q0)
    assert frame.info.status is not Status.ERROR
    ok = sim.on_command([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])  # usable without a reset
    moved = ok.frame if mode == 'lockstep' else sim.on_tick()
    assert ok.valid and np.all(np.isfinite(moved.q)) and np.any(moved.q != q0)


def test_jumps_and_their_replies(lockstep):
    sim = ArmSimCore(lockstep)
    sim.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    t = sim.frame().t
    jump = sim.go('desired')
    assert jump.success and jump.frame.t == pytest.approx(t + DT)
    oMc_d = pose_from_xyz_rpy([0, 0, 0.45], [0, 0, 0]).inverse()  # desired_cMo default
    np.testing.assert_allclose(jump.frame.oMc.homogeneous, oMc_d.homogeneous, atol=1e-5)
    assert jump.message.endswith(f'first image stamped {jump.frame.t:.9f}')
    assert float(jump.message.rsplit(' ', 1)[-1]) == pytest.approx(jump.frame.t, abs=1e-9)
    assert not np.any(jump.frame.qdot) and sim.republish_due  # re-published until a command
    start = sim.go('start')
    cMo_s = pose_from_xyz_rpy(lockstep.start_cMo[:3], lockstep.start_cMo[3:])
    np.testing.assert_allclose(start.frame.oMc.homogeneous, cMo_s.inverse().homogeneous,
                               atol=1e-5)
    sim.on_command([0.0, 0.02, 0.0, 0.0, 0.0, 0.0])
    reset = sim.reset()
    assert reset.success and reset.message.startswith('at start (reset):')
    np.testing.assert_array_equal(reset.frame.q, sim.arm.q_start)
    assert reset.frame.t == pytest.approx(start.frame.t + 2 * DT)  # time is kept


def test_hold_drops_the_command(lockstep):
    sim = ArmSimCore(lockstep.replace({'clock_mode': 'realtime'}))
    sim.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    assert np.any(sim.on_tick().qdot)
    assert sim.hold().message == 'command dropped'
    assert not np.any(sim.on_tick().qdot)


def test_unreachable_poses_are_refused(lockstep):
    far = [0.0, 0.0, 5.0, 0.0, 0.0, 0.0]  # 5 m away: beyond the UR5's reach
    with pytest.raises(ParameterError, match='no UR5 configuration reaches start_cMo'):
        ArmSimCore(lockstep.replace({'start_cMo': far}))
    sim = ArmSimCore(lockstep)
    before = sim.frame()
    sim.params = sim.params.replace({'desired_cMo': far})  # a runtime change
    jump = sim.go('desired')
    assert not jump.success and jump.frame is None
    assert 'no UR5 configuration reaches desired_cMo' in jump.message
    np.testing.assert_array_equal(sim.frame().q, before.q)


def test_joint_limit_status_and_values(lockstep):
    q0 = [0.0, -1.57, 1.57, -1.57, -1.57, 2 * np.pi - 0.05]
    sim = ArmSimCore(lockstep.replace({'start_mode': 'joints', 'start_joints': q0}))
    v = 0.8 * sim.arm.camera_jacobian()[:, 5]  # turns wrist_3 positively
    for _ in range(4):
        f = sim.on_command(v).frame
    assert f.q[5] == pytest.approx(2 * np.pi, abs=1e-9)
    assert f.info.status is Status.JOINT_LIMIT and f.level is Level.WARN
    vals = f.status_values()
    assert list(vals) == ['joints', 'sigma_min', 'scale', 'sim_time', 'detail']
    assert vals['joints'] == 'wrist_3_joint' and vals['sim_time'] == f'{f.t:.6f}'
    assert vals['detail'] == 'wrist_3_joint at position limit'


def test_a_twist_in_another_frame_is_refused(lockstep):
    """
    A twist whose frame is not camera_optical_frame is not executed.

    In lockstep the period passes with the arm held still (the loop goes on), and the
    frame's status says why (WARN); in realtime the arm stops at once (issue 14, item 8).
    """
    sim = ArmSimCore(lockstep)
    moved = sim.on_command([0.02, 0.0, 0.03, 0.0, 0.0, 0.1]).frame
    out = sim.on_command([0.02, 0.0, 0.03, 0.0, 0.0, 0.1], 'tool0')
    assert not out.valid and "frame 'tool0'" in out.reason
    assert "takes twists in 'camera_optical_frame' only" in out.reason
    assert out.frame.t == pytest.approx(moved.t + DT, abs=1e-12)
    np.testing.assert_array_equal(out.frame.q, moved.q)
    assert not np.any(out.frame.qdot)
    st = out.frame.status()
    assert st.state is Status.OK and st.level is Level.WARN
    assert st.values['command_error'] == out.reason
    fine = sim.on_command(np.zeros(6), 'camera_optical_frame').frame
    assert fine.level is Level.OK and 'command_error' not in fine.status_values()
    rt = ArmSimCore(lockstep.replace({'clock_mode': 'realtime'}))
    rt.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
    assert rt.on_tick().qdot @ rt.arm.camera_jacobian()[2] > 0  # the valid +z command runs
    assert not rt.on_command([0.0, 0.0, -0.05, 0.0, 0.0, 0.0], '').valid
    first = rt.on_tick()
    assert not np.any(first.qdot)  # the refused command stopped the arm


def test_a_lockstep_answer_to_a_frame_before_a_jump_steps_nothing(lockstep):
    """
    The race a taught run meets: the servo answers the frame shown before a jump.

    The answer arrives after the jump's frame; executed, it would move the arm from the
    new pose with a twist computed at the old one and put a second frame in flight, so
    the run would depend on when it arrived. Refused, the jump's frame still waits for its
    own answer, which steps one period from the new pose.
    """
    sim = ArmSimCore(lockstep)
    before = sim.on_command(np.zeros(6)).frame     # the image the late answer is for
    jump = sim.go('start').frame
    late = sim.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], stamp_ns=before.stamp_ns)
    assert not late.valid and late.frame is None
    assert f'{before.stamp_ns * 1e-9:.9f}' in late.reason
    assert f'{jump.stamp_ns * 1e-9:.9f}' in late.reason
    now = sim.frame()
    assert now.stamp_ns == jump.stamp_ns and np.array_equal(now.q, jump.q)
    assert not np.any(now.qdot) and sim.republish_due  # the jump's frame is sent again
    for stamp in (-1, jump.stamp_ns + 1, 2 ** 62):  # no frame shown has these stamps
        assert not sim.on_command(np.ones(6) * 0.01, stamp_ns=stamp).valid
        assert sim.frame().stamp_ns == jump.stamp_ns
    answer = sim.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], stamp_ns=jump.stamp_ns)
    assert answer.valid and answer.frame.t == pytest.approx(jump.t + DT, abs=1e-12)
    assert np.any(answer.frame.q != jump.q)
    unstamped = sim.on_command(np.zeros(6))  # answers no image (a teleoperator): steps
    assert unstamped.valid and unstamped.frame.t == pytest.approx(jump.t + 2 * DT, abs=1e-12)


def test_realtime_commands_are_taken_whatever_their_stamp(lockstep):
    rt = ArmSimCore(lockstep.replace({'clock_mode': 'realtime'}))
    q0 = rt.frame().q
    old = rt.on_command([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], stamp_ns=1)  # latency is normal
    assert old.valid and np.any(rt.on_tick().q != q0)
