"""
The arm refuses absurd twists before integrating, stops at once, and has an error state.

Issue 14, items 1 and 8: a finite twist of ~1e307 used to turn the joint state into NaN for
good (status still ``ok``); a NaN twist after a valid one left the old command running until
``cmd_timeout``.
"""
from __future__ import annotations

import numpy as np
import pytest
from sphere_servo.core.validation import Bound
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.sim.arm import ArmModel, LIMIT_TOL, Status, TwistError

Q_NOMINAL = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
DT = 1 / 30
MOVE = np.array([0.01, -0.02, 0.05, 0.1, 0.05, -0.1])


@pytest.fixture
def arm():
    return ArmModel(q0=Q_NOMINAL, cmd_timeout=0.5)


def _refused(arm, v_c, bound: Bound) -> TwistError:
    with pytest.raises(TwistError) as info:
        arm.command(v_c)
    assert info.value.violation.bound is bound, str(info.value)
    return info.value


@pytest.mark.parametrize('huge', [1e307, 1e308, -1.7e308])
@pytest.mark.parametrize('part', [slice(0, 3), slice(3, 6), slice(0, 6)])
def test_a_huge_twist_is_refused_and_the_arm_stays_usable(arm, huge, part):
    arm.command(MOVE)
    arm.step(DT)
    q = arm.q.copy()
    v = np.zeros(6)
    v[part] = huge
    err = _refused(arm, v, Bound.RANGE)
    assert 'camera twist' in str(err) and ('m/s' in str(err) or 'rad/s' in str(err))
    info = arm.step(DT)
    # nothing integrated: at rest from this step, joints finite and unchanged
    assert np.all(np.isfinite(arm.q)) and np.array_equal(arm.q, q)
    assert not np.any(info.qdot) and info.status is Status.OK
    # a valid twist afterwards moves the arm again, without a reset
    arm.command(MOVE)
    info = arm.step(DT)
    assert info.status is Status.OK and np.any(info.qdot) and np.all(np.isfinite(arm.q))
    assert not np.array_equal(arm.q, q)


def test_the_twist_bound_at_and_past(arm):
    lin, ang = arm.twist_limit
    u = np.array([0.6, 0.0, 0.8])
    for part, lim in ((slice(0, 3), lin), (slice(3, 6), ang)):
        v = np.zeros(6)
        v[part] = lim * u * (1 - 1e-12)
        arm.command(v)                       # at the bound: accepted, scaled by the joints
        info = arm.step(DT)
        assert np.all(np.isfinite(arm.q)) and np.all(np.abs(info.qdot) <= arm.vmax + 1e-12)
        arm.reset(Q_NOMINAL)
        v[part] = lim * u * (1 + 1e-9)
        _refused(arm, v, Bound.RANGE)


def test_the_bound_is_physical_and_above_the_servos_own_limits(arm):
    # ‖v‖ ≤ Σ q̇max_i L_i and ‖ω‖ ≤ Σ q̇max_i hold in every configuration: sample the
    # camera Jacobian (Pinocchio) at random q with joint speeds at their limits
    rng = np.random.default_rng(7)
    vmax = np.array(arm.model.velocityLimit)
    best = np.zeros(2)
    for _ in range(300):
        q = rng.uniform(arm.lower, arm.upper)
        J = arm.camera_jacobian(q)
        for _ in range(20):
            v = J @ (vmax * rng.choice([-1.0, 1.0], size=6))
            best = np.maximum(best, [np.linalg.norm(v[:3]), np.linalg.norm(v[3:])])
    assert np.all(best <= np.array(arm.reach_speed))
    assert np.all(best >= 0.4 * np.array(arm.reach_speed))   # a bound, but not a loose one
    table = ServoParams.table()
    assert table['v_max'].bounds[1] <= arm.twist_limit[0]
    assert table['w_max'].bounds[1] <= arm.twist_limit[1]


@pytest.mark.parametrize('bad', [[np.nan, 0, 0, 0, 0, 0], [0, 0, 0, 0, np.inf, 0], [1, 2, 3],
                                 'abc'])
def test_a_refused_twist_after_a_valid_one_stops_the_arm_at_once(arm, bad):
    arm.command(MOVE)
    assert np.any(arm.step(DT).qdot)
    with pytest.raises(TwistError):
        arm.command(bad)
    q = arm.q.copy()
    info = arm.step(DT)            # well within cmd_timeout, yet at rest
    assert not np.any(info.qdot) and np.array_equal(arm.q, q)
    assert info.status is Status.OK


@pytest.mark.parametrize('timeout', [0.1, 0.2, 0.5, 1.0])
def test_the_watchdog_stops_after_the_documented_steps(timeout):
    arm = ArmModel(q0=Q_NOMINAL, cmd_timeout=timeout)
    arm.command(MOVE)
    moving = 0
    for _ in range(100):
        if np.any(arm.step(DT).qdot):
            moving += 1
        else:
            break
    assert moving == arm.watchdog_steps(DT) == int(round(timeout * 30)) + 1
    assert arm.info.status is Status.TIMEOUT


def _corrupt(arm, q):
    arm.q = np.asarray(q, dtype=float)   # as a bug elsewhere might leave it


@pytest.mark.parametrize('how', ['nan q', 'past the limit', 'nan qdot'])
def test_an_invalid_state_is_an_error_until_reset(arm, how, monkeypatch):
    arm.command(MOVE)
    arm.step(DT)
    if how == 'nan q':
        q = arm.q.copy()
        q[2] = np.nan
        _corrupt(arm, q)
    elif how == 'past the limit':
        q = arm.q.copy()
        q[2] = arm.upper[2] + 1e-6
        _corrupt(arm, q)
    else:
        real = arm.twist_to_qdot

        def nan_qdot(v_c, dt=None):
            info = real(v_c, dt)
            info.qdot = np.full(arm.model.nv, np.nan)
            return info
        monkeypatch.setattr(arm, 'twist_to_qdot', nan_qdot)
    q_before = arm.q.copy()
    info = arm.step(DT)
    assert info.status is Status.ERROR and not np.any(info.qdot)
    assert info.error is not None and 'reset' in info.message
    np.testing.assert_array_equal(arm.q, q_before)          # nothing integrated
    err = _refused(arm, MOVE, Bound.STATE)
    assert 'reset' in str(err)
    for _ in range(3):                                      # it stays in error
        assert arm.step(DT).status is Status.ERROR
    monkeypatch.undo()
    arm.reset()
    arm.command(MOVE)
    info = arm.step(DT)
    assert info.status is Status.OK and np.any(info.qdot) and np.all(np.isfinite(arm.q))


def test_round_off_past_a_limit_is_not_an_error(arm):
    q = Q_NOMINAL.copy()
    q[2] = arm.upper[2] + 0.5 * LIMIT_TOL
    _corrupt(arm, q)
    arm.command(MOVE)
    assert arm.step(DT).status is not Status.ERROR
    assert arm.q[2] <= arm.upper[2]


def test_twist_to_qdot_applies_the_same_bound(arm):
    with pytest.raises(TwistError):
        arm.twist_to_qdot(np.r_[1e307, 0, 0, 0, 0, 0])
    assert np.all(np.isfinite(arm.twist_to_qdot(np.r_[arm.twist_limit[0], 0, 0, 0, 0, 0]).qdot))
