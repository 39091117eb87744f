"""
Adversarial inputs to the arm simulator's core (``pipeline/arm_sim.py``) and the loop.

The watchdog and the one-driver rule at their boundary (exactly ⌊cmd_timeout/dt⌋ periods,
at rates whose periods do not sum exactly in floats), a publisher restarting (its sequence
numbers start again at 1) against a second one, hold/release/reset/jump races with the
servo enabled, poses with the camera inside the target, and the headless loop's own
arguments. Expected counts are computed in exact fractions, not with the code's floats.

Found here: the one-driver window ended a period before the watchdog's (6 × 1/30 s > 0.2 s
in floats: a restarted driver was refused 5 times, not 6); a start or desired pose with the
camera inside the sphere was accepted (and rendered); ``release`` said "commands are
executed again" with the arm in error; ``closed_loop`` ran 2000 iterations of nothing at
``dt = 0`` and reversed every twist at ``dt < 0`` ("target lost"); a twist the arm
refuses escaped the loop as an exception, which the study took for a start where the
target is not observable.
"""
from __future__ import annotations

from fractions import Fraction
import math

import numpy as np
import pytest
from sphere_servo.core.targets import make_target
from sphere_servo.experiments.arm_cell import run_arm
from sphere_servo.pipeline.arm_sim import ArmSimCore, HELD, SEQ_UNSUPPORTED, SERVO_ENABLED
from sphere_servo.pipeline.params import ArmSimParams, ParameterError
from sphere_servo.sim.arm import pose_from_xyz_rpy, Status
from sphere_servo.sim.loop import run_loop
from sphere_servo.sim.observers import exact_observer
from sphere_servo.sim.plants import LoopOutcome

SCENE = {'hand_eye': [0.0, -0.04, 0.02, 0.0, 0.0, 0.0], 'velocity_scale': 0.5,
         'markers_rate': 0.0,
         'camera': {'width': 64, 'height': 48, 'px': 60.0, 'py': 60.0, 'u0': 32.0, 'v0': 24.0}}
MOVE = [0.0, 0.0, 0.01, 0.0, 0.0, 0.02]
CMO_START = pose_from_xyz_rpy([0.07, 0.12, 0.56], [-0.46, 0.40, -0.72])
CMO_DESIRED = pose_from_xyz_rpy([0.0, 0.0, 0.45], [0.0, 0.0, 0.0])


def core(**over) -> ArmSimCore:
    return ArmSimCore(ArmSimParams.from_mapping({**SCENE, 'clock_mode': 'lockstep', **over}))


def periods_within(rate, timeout) -> int:
    """⌊cmd_timeout / dt⌋ in exact arithmetic (``timeout`` as written in decimal)."""
    return math.floor(Fraction(str(timeout)) * Fraction(str(rate)))


# rates and timeouts whose ratio is a whole number of periods: the boundary itself
BOUNDARY = [(30, 0.2), (30, 0.1), (30, 0.5), (50, 0.2), (25, 0.2), (60, 0.05), (40, 0.15),
            (7, 0.0), (30, 0.0), (10, 0.25), (3, 1.0)]


@pytest.mark.parametrize('rate,timeout', BOUNDARY)
def test_the_watchdog_runs_a_command_floor_timeout_over_dt_plus_one_ticks(rate, timeout):
    sim = ArmSimCore(ArmSimParams.from_mapping({**SCENE, 'camera_rate': rate,
                                                'cmd_timeout': timeout}))   # realtime
    sim.on_tick()
    assert sim.on_command(MOVE).valid
    moving = 0
    for _ in range(periods_within(rate, timeout) + 5):
        f = sim.on_tick()
        if not np.any(f.qdot):
            break
        moving += 1
    assert moving == periods_within(rate, timeout) + 1 == sim.arm.watchdog_steps(sim.dt)
    assert f.info.status is Status.TIMEOUT and f.level.name == 'WARN'


@pytest.mark.parametrize('rate,timeout', BOUNDARY)
def test_a_restarted_driver_is_refused_while_its_old_command_would_still_run(rate, timeout):
    """
    Numbers from 1 again after 40: refused for ⌊cmd_timeout/dt⌋ periods, then it drives.

    The refusal window is the watchdog's (the old command would still run), each refused
    command passes a period with the arm still; it used to end one period early where the
    periods' float sum passes the timeout (30 Hz, 0.2 s: 5 refusals, not 6).
    """
    sim = core(camera_rate=rate, cmd_timeout=timeout)
    for seq in range(1, 41):
        assert sim.on_command(MOVE, seq=seq).valid
    refused, seq = 0, 1
    q = sim.frame().q
    while True:
        out = sim.on_command(MOVE, seq=seq)
        if out.valid:
            break
        assert 'out of sequence (number' in out.reason and 'one driver at a time' in out.reason
        np.testing.assert_array_equal(out.frame.q, q)           # held still
        assert out.frame.level.name == 'WARN' and out.frame.command_error == out.reason
        refused, seq = refused + 1, seq + 1
        assert refused < 1000
    assert refused == periods_within(rate, timeout)
    assert np.any(out.frame.qdot)                            # the restarted driver drives
    assert sim.on_command(MOVE, seq=seq + 1).valid


def test_a_driver_restart_is_accepted_at_once_when_it_is_the_only_publisher():
    sim = core()
    for seq in range(1, 11):
        sim.on_command(MOVE, seq=seq)
    assert not sim.on_command(MOVE, seq=1).valid              # the old one may still be there
    sim.on_command_publishers(['/servo'])                      # the graph: one publisher left
    assert sim.on_command(MOVE, seq=2).valid
    sim.on_command_publishers(['/servo', '/teleop'])
    assert not sim.on_command(MOVE, seq=1).valid              # a second one, while it drives


def test_a_second_publisher_with_higher_numbers_takes_over_a_limit():
    """
    Limit (pinned): sequence numbers tell publishers apart only by their order.

    A second publisher whose count is ahead of the driver's is taken for the driver, and
    the first is then refused; the graph check (``command_publishers``, a warning) is what
    says there are two.
    """
    sim = core()
    for seq in range(1, 6):
        assert sim.on_command(MOVE, seq=seq).valid
    assert sim.on_command([0.0, 0.0, -0.01, 0.0, 0.0, 0.0], seq=500).valid
    assert not sim.on_command(MOVE, seq=6).valid
    sim.on_command_publishers(['/servo', '/teleop'])
    f = sim.on_command(MOVE, seq=7).frame
    assert f.status_values()['command_publishers'] == '/servo,/teleop'
    assert f.level.name == 'WARN'


@pytest.mark.parametrize('frame_id', ['/camera_optical_frame', 'camera_optical_frame ',
                                      'CAMERA_OPTICAL_FRAME', 'camera_optical_frame\x00',
                                      'arm/camera_optical_frame', 'camera_link', ' '])
def test_a_twist_in_a_frame_that_only_looks_like_the_camera_s_is_refused(frame_id):
    sim = core()
    q = sim.on_command(MOVE).frame.q
    out = sim.on_command(MOVE, frame_id)
    assert not out.valid and repr(frame_id) in out.reason
    np.testing.assert_array_equal(out.frame.q, q)
    assert not np.any(out.frame.qdot)


# --- hold, release, reset and jumps, with and without the servo ------------------------------
def test_hold_with_the_servo_enabled_latches_and_only_a_reset_without_it_clears():
    sim = core()
    sim.on_servo_enabled(True)
    sim.on_command(MOVE, seq=1)
    assert sim.hold().success                       # hold is never refused: it stops the arm
    out = sim.on_command(MOVE, seq=2)
    assert not out.valid and out.reason == HELD and not np.any(out.frame.qdot)
    assert out.frame.status_values()['hold'] == HELD
    t, q = sim.frame().t, sim.frame().q
    for jump in (sim.reset, lambda: sim.go('start'), lambda: sim.go('desired')):
        j = jump()
        assert not j.success and j.message == SERVO_ENABLED and j.frame is None
    assert sim.held and sim.frame().t == t                # nothing passed, nothing moved
    np.testing.assert_array_equal(sim.frame().q, q)
    sim.on_servo_enabled(False)
    assert sim.reset().success and not sim.held
    assert sim.on_command(MOVE, seq=1).valid              # the hold and the sequence cleared


def test_a_jump_while_held_keeps_the_hold():
    sim = core()
    sim.hold()
    j = sim.go('desired')
    assert j.success and sim.held
    assert j.message.startswith('at desired (held: commands are refused until ~/release): ')
    assert float(j.message.rsplit(' ', 1)[-1]) == pytest.approx(j.frame.t, abs=1e-9)
    assert not sim.on_command(MOVE).valid
    assert sim.release().message == 'released: commands are executed again'
    assert sim.release().message == 'not held: nothing to release'
    assert sim.on_command(MOVE).valid


def test_release_does_not_claim_commands_run_while_the_arm_is_in_error():
    sim = core()
    sim.on_command(MOVE)
    sim.hold()
    q = sim.arm.q.copy()
    q[2] = sim.arm.upper[2] + 1e-6                  # a state a bug could leave
    sim.arm.q = q
    assert sim.on_tick().info.status is Status.ERROR
    msg = sim.release().message
    assert msg.startswith('released, but the arm is in error') and '~/reset' in msg
    j = sim.go('desired')                  # a jump moves it, and says the error stays
    assert j.success and '(the arm is in error: commands are refused until ~/reset)' in j.message
    assert j.frame.level.name == 'ERROR' and j.frame.info.status is Status.ERROR
    out = sim.on_command(MOVE)
    assert not out.valid and 'reset' in out.reason and out.frame.level.name == 'ERROR'
    assert sim.reset().success
    assert sim.on_command(MOVE).valid


# --- poses no camera can have -------------------------------------------------------------
@pytest.mark.parametrize('which', ['start_cMo', 'desired_cMo'])
@pytest.mark.parametrize('xyz', [[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], [0.03, -0.02, 0.03],
                                 [0.0, 0.0, 0.0499]])
def test_a_pose_with_the_camera_inside_the_sphere_is_refused(which, xyz):
    pose = xyz + [0.0, 0.0, 0.0]
    with pytest.raises(ParameterError, match=f'{which}=.*inside the target'):
        core(**{which: pose})
    sim = core()
    before = sim.frame()
    sim.params = sim.params.replace({which: pose})          # a runtime change, then the jump
    j = sim.go('start' if which == 'start_cMo' else 'desired')
    assert not j.success and 'inside the target' in j.message and j.frame is None
    np.testing.assert_array_equal(sim.frame().q, before.q)


def test_the_balloon_s_own_shape_decides_not_its_equal_volume_sphere():
    # semi-axes 6 × 5.5 × 4.5 cm; the sphere of equal volume has r ≈ 5.2 cm: 5.7 cm along
    # the target's x is inside the balloon, outside that sphere
    balloon = {'target': {'kind': 'balloon', 'axes': [0.06, 0.055, 0.045]}}
    sim = core(**balloon)
    inside = pose_from_xyz_rpy([0.057, 0.0, 0.0], [0.0, 0.0, 0.0])       # oMc
    assert inside.translation[0] > sim.target.radius
    q, ok, _ = sim.arm.solve_ik(sim.arm.wMo * inside, sim.arm.q)
    assert ok
    with pytest.raises(ParameterError, match='start_joints=.*inside the target'):
        core(**balloon, start_mode='joints', start_joints=q.tolist())
    outside = pose_from_xyz_rpy([0.0, 0.0, 0.047], [0.0, 0.0, 0.0]).inverse()   # cMo
    sim.params = sim.params.replace({'start_cMo': list(outside.translation) + [0, 0, 0]})
    assert sim.go('start').success                  # 2 mm above its 4.5 cm semi-axis


@pytest.mark.parametrize('cMo', [[0.0, 0.0, -0.45, 0.0, 0.0, 0.0],     # behind the camera
                                 [0.3, 0.0, 0.4, 0.0, 0.0, 0.0]])      # out of the view
def test_a_start_where_the_camera_does_not_see_the_target_is_a_pose_not_an_error(cMo):
    sim = core(start_cMo=cMo)
    f = sim.frame()
    np.testing.assert_allclose(f.oMc.inverse().translation, cMo[:3], atol=1e-5)
    assert not f.render_error and f.level.name == 'OK'


def test_a_twist_into_the_target_is_executed_a_limit():
    """
    Limit (pinned): the simulator has no collision model.

    A jump into the target is refused (above), but a twist that drives the camera into
    the sphere is executed like any other: the status stays ``ok``.
    """
    sim = core()
    sim.go('desired')                           # 0.45 m above the sphere's centre
    toward = [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]      # +z: the optical axis, at the centre
    for _ in range(200):
        f = sim.on_command(toward).frame
        depth = np.linalg.norm(f.oMc.translation) / sim.target.radius
        if depth < 0.9:
            break
    assert depth < 0.9, (depth, f.info.status)
    assert f.info.status is Status.OK and not f.command_error


def test_a_start_configuration_past_the_urdf_limits_is_a_parameter_error():
    q = [0.0, -1.57, 3.5, -1.57, -1.57, 0.0]        # within the parameter's ±2π
    for mode in ('joints', 'pose'):                 # in 'pose' it is the IK's seed
        with pytest.raises(ParameterError, match=r'start_joints=.*elbow_joint = 3\.5 not in'):
            core(start_mode=mode, start_joints=q)


def test_a_jump_reports_the_new_configuration_s_status_not_the_last_step_s():
    """It reported 'wrist_3_joint at position limit' (WARN) at the desired pose, at rest."""
    q0 = [0.0, -1.57, 1.57, -1.57, -1.57, 2 * np.pi - 0.05]
    sim = core(start_mode='joints', start_joints=q0)
    v = 0.8 * sim.arm.camera_jacobian()[:, 5]            # turns wrist_3 onto its limit
    for _ in range(4):
        f = sim.on_command(v).frame
    assert f.info.status is Status.JOINT_LIMIT
    j = sim.go('desired').frame
    assert j.info.status is Status.OK and j.level.name == 'OK' and not j.info.joints
    sv = np.linalg.svd(sim.arm.camera_jacobian(j.q), compute_uv=False)[-1]
    assert j.status_values()['sigma_min'] == f'{sv:.5f}'
    assert not np.any(j.qdot) and not np.any(j.info.qdot)


@pytest.mark.parametrize('mode', ['joints', 'pose'])
def test_a_runtime_start_joints_past_the_urdf_limits_makes_the_jumps_refuse(mode):
    """It used to raise ValueError out of go_start and go_desired (the guard's last resort)."""
    sim = core()
    before = sim.frame()
    sim.params = sim.params.replace({'start_mode': mode,
                                     'start_joints': [0.0, -1.57, -4.0, -1.57, -1.57, 0.0]})
    for which in ('start', 'desired'):
        j = sim.go(which)
        assert not j.success and j.frame is None
        assert 'start_joints is outside the joint position limits: elbow_joint = -4' in j.message
    np.testing.assert_array_equal(sim.frame().q, before.q)
    assert sim.frame().t == before.t
    assert sim.reset().success                      # the start taken at start-up


# --- the headless loop's arguments and the arm plant ---------------------------------------
@pytest.mark.parametrize('kw', [{'dt': 0.0}, {'dt': -0.1}, {'dt': float('nan')},
                                {'dt': float('inf')}, {'dt': '0.1'}, {'max_iter': 0},
                                {'max_iter': -5}, {'max_iter': 1.5}, {'max_iter': True},
                                {'max_lost': -1}])
def test_the_loop_refuses_a_period_or_a_budget_that_runs_nothing(kw):
    name = next(iter(kw))
    with pytest.raises(ValueError, match=name):
        run_loop(make_target('special', 0.05), CMO_START, CMO_DESIRED, **kw)


def test_a_twist_the_arm_refuses_ends_the_run_with_its_reason_not_an_exception():
    """A gain of 1e3 asks the UR5 for 353 m/s: the run ends, the records stay aligned."""
    res = run_arm(make_target('special', 0.05), CMO_START, CMO_DESIRED, gain=1e3,
                  max_iter=50)
    assert res.outcome is LoopOutcome.TARGET_LOST
    assert res.detail.startswith('the arm refused the twist: ‖v‖ of the camera twist')
    assert res.iterations == 1 and np.linalg.norm(res.v[-1][:3]) > 100
    assert len(res.joints) == len(res.oMc) == res.iterations + 1
    np.testing.assert_array_equal(res.joints[-1], res.joints[0])     # nothing integrated
    assert res.arm_status == [Status.OK]


@pytest.mark.parametrize('kw', [{'pixel_noise': float('nan')}, {'pixel_noise': -1.0},
                                {'pixel_noise': float('inf')}, {'pixel_noise': '1'},
                                {'pixel_noise': 1.0, 'contour_points': 4},
                                {'pixel_noise': 1.0, 'contour_points': 0},
                                {'contour_points': 64.0}])
def test_the_exact_observer_refuses_a_noise_it_would_not_apply(kw):
    with pytest.raises(ValueError, match=list(kw)[-1]):
        exact_observer(make_target('special', 0.05), **kw)


def test_the_exact_observer_at_its_smallest_fit_and_without_noise():
    target = make_target('special', 0.05)
    exact = exact_observer(target)(CMO_DESIRED)
    cO = CMO_DESIRED.translation             # ground truth: b = O/‖O‖, r_δ = r/‖O‖
    np.testing.assert_allclose(exact.sphere.b, cO / np.linalg.norm(cO), atol=1e-12)
    noisy = exact_observer(target, pixel_noise=1e-6, contour_points=5)(CMO_DESIRED)
    np.testing.assert_allclose(noisy.sphere.b, exact.sphere.b, atol=1e-6)


def test_an_rmw_without_sequence_numbers_does_not_stall_the_driver():
    """
    Every message numbered UINT64_MAX (rmw's "unsupported") tells no publishers apart.

    All were refused but the first while it was fresh (in lockstep: the arm held still 6
    periods in 7), and one a second after the graph check; now they are unknown numbers.
    """
    sim = core()
    unsupported = 2 ** 64 - 1
    assert SEQ_UNSUPPORTED == unsupported              # rmw/types.h: UINT64_MAX
    for _ in range(10):
        out = sim.on_command(MOVE, seq=unsupported)
        assert out.valid and np.any(out.frame.qdot), out.reason
    assert sim.on_command(MOVE, seq=3).valid           # a numbering RMW again: it drives
    assert not sim.on_command(MOVE, seq=2).valid
