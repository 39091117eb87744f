"""
Adversarial inputs to the simulated UR5 (``sim/arm.py``), checked against Pinocchio.

Twists at and one ulp past the physical bound, subnormal and -0.0 components, twists at and
near the wrist, elbow and shoulder singularities, commands that drive a joint past its
position limit, and what the camera really does: its velocity by finite differences of the
camera pose, computed by a Pinocchio model of the URDF built here (not the arm's own).

Found here: near a singularity the damped solution left the camera moving elsewhere than
commanded (wrist: 47 % of a +z twist, at 62° from it; elbow: 11 % of a +x twist) with
status ``ok`` whenever the motion did not decrease σ_min; it is now ``singularity``.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.core.validation import Bound
from sphere_servo.sim.arm import ArmModel, find_ur5_urdf, pose_from_xyz_rpy, Status, TwistError

DT = 1.0 / 30.0
Q_NOMINAL = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
HAND_EYE = pose_from_xyz_rpy([0.0, -0.04, 0.02], [0.0, 0.0, 0.0])


class Truth:
    """The camera pose from a Pinocchio model of the URDF of our own: tool0 · tool0Mc."""

    def __init__(self, tool0Mc: pin.SE3):
        self.model = pin.buildModelFromUrdf(find_ur5_urdf())
        self.data = self.model.createData()
        self.tool0 = self.model.getFrameId('tool0')
        self.tool0Mc = tool0Mc
        self.vlim = np.array(self.model.velocityLimit)

    def wMc(self, q) -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, float))
        return self.data.oMf[self.tool0] * self.tool0Mc

    def twist(self, q0, q1, dt: float) -> np.ndarray:
        """Return the camera's velocity from q0 to q1 in ``dt``, in the camera frame at q0."""
        return np.array(pin.log6(self.wMc(q0).inverse() * self.wMc(q1)).vector) / dt


@pytest.fixture(scope='module')
def truth():
    return Truth(HAND_EYE)


@pytest.fixture
def arm():
    return ArmModel(q0=Q_NOMINAL, tool0Mc=HAND_EYE, velocity_scale=0.5, cmd_timeout=0.2)


def _step(arm, truth, v, dt=DT):
    """Command ``v``, step ``dt``; return (what the camera did, the step's info)."""
    q0 = arm.q.copy()
    arm.command(v)
    info = arm.step(dt)
    return truth.twist(q0, arm.q, dt), info


# --- the physical bound, exactly and one ulp past -----------------------------------------
def test_the_bound_is_the_documented_one(arm, truth):
    # README: ‖v‖ ≤ 100 m/s (the absolute bound), ‖ω‖ ≤ 10 × Σ q̇max_i = 190.5 rad/s
    assert arm.twist_limit == (100.0, pytest.approx(10 * truth.vlim.sum(), rel=1e-12))
    assert arm.twist_limit[1] == pytest.approx(190.5)


@pytest.mark.parametrize('direction', [(1, 0, 0), (0, -1, 0), (0, 0, 1), (0.6, -0.8, 0),
                                       (0, 0.6, -0.8)])
@pytest.mark.parametrize('part', ['v', 'w'])
def test_a_twist_exactly_at_the_bound_runs_and_one_ulp_past_is_refused(arm, truth, direction,
                                                                       part):
    lim = arm.twist_limit[0 if part == 'v' else 1]
    at = np.zeros(6)
    sl = slice(0, 3) if part == 'v' else slice(3, 6)
    at[sl] = lim * np.asarray(direction, float)
    if math.hypot(*at[sl]) != lim:
        pytest.skip('this direction has no exact float norm at the bound')
    achieved, info = _step(arm, truth, at)
    # accepted: scaled as a whole by the joint speed limits, so along the command
    assert info.status in (Status.OK, Status.SINGULARITY) and np.any(info.qdot)
    assert np.max(np.abs(info.qdot) / arm.vmax) == pytest.approx(1.0, abs=1e-12)
    cos = achieved @ at / np.linalg.norm(achieved) / np.linalg.norm(at)
    assert cos > 0.99, cos     # one period at the joints' full speed: first order only
    past = at.copy()
    i = int(np.argmax(np.abs(past)))
    past[i] = np.nextafter(past[i], math.copysign(np.inf, past[i]))
    assert math.hypot(*past[sl]) > lim
    q = arm.q.copy()
    with pytest.raises(TwistError) as err:
        arm.command(past)
    assert err.value.violation.bound is Bound.RANGE
    assert ('m/s' if part == 'v' else 'rad/s') in str(err.value)
    info = arm.step(DT)        # stopped at once, nothing integrated
    assert not np.any(info.qdot) and np.array_equal(arm.q, q)


@pytest.mark.parametrize('v', [
    [-0.0] * 6,
    [5e-324, 0.0, 0.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, -5e-324, 5e-324, 2.2250738585072014e-308],
    [1e-300] * 6,
], ids=['minus-zero', 'one-subnormal', 'subnormal-rotation', 'tiny'])
def test_zero_and_subnormal_twists_do_not_move_the_arm_or_break_it(arm, v):
    arm.command(v)
    q = arm.q.copy()
    for _ in range(3):
        info = arm.step(DT)
        assert info.status is Status.OK and np.all(np.isfinite(info.qdot))
        assert np.all(np.abs(info.qdot) < 1e-290)
    np.testing.assert_allclose(arm.q, q, rtol=0, atol=1e-280)
    arm.command([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])    # still usable
    assert np.any(arm.step(DT).qdot)


@pytest.mark.parametrize('v', [[1e308, 1e308, 0, 0, 0, 0], [0, 0, 0, -1e308, 1e308, 1e308],
                               [1.7976931348623157e308, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, -1e200]])
def test_components_near_the_float_maximum_are_refused_not_overflowed(arm, v):
    with pytest.raises(TwistError) as err:
        arm.command(v)
    assert err.value.violation.bound is Bound.RANGE
    assert math.isinf(err.value.violation.value) or err.value.violation.value > 100


# --- what the camera does: finite differences of the camera pose ----------------------------
@pytest.mark.parametrize('seed', range(6))
def test_the_camera_moves_as_commanded_where_no_limit_binds(arm, truth, seed):
    rng = np.random.default_rng(seed)
    q = Q_NOMINAL + rng.uniform(-0.4, 0.4, 6)
    arm.reset(q)
    assert arm.sigma_min() > arm.singular_threshold
    v = np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.05, 3)]
    # a short step: the tangent (J q̇ = v); a period: q is integrated to first order
    for dt, tol in ((1e-5, 1e-6), (DT, 1e-2)):
        arm.reset(q)
        achieved, info = _step(arm, truth, v, dt)
        assert info.status is Status.OK and info.scale == 1.0
        np.testing.assert_allclose(achieved, v, atol=tol * np.linalg.norm(v))


@pytest.mark.parametrize('speed', [2.0, 30.0, 100.0])
def test_a_twist_too_fast_for_the_joints_is_slowed_as_a_whole(arm, truth, speed):
    """Step 3: one factor for the whole q̇; the camera keeps the commanded direction."""
    v = speed * np.array([0.3, -0.5, 0.81, 0.0, 0.0, 0.0]) / np.linalg.norm([0.3, -0.5, 0.81])
    arm.command(v)
    info = arm.twist_to_qdot(v)       # no dt: no limit landing, to compare at the tangent
    assert info.scale < 1 and np.max(np.abs(info.qdot) / arm.vmax) == pytest.approx(1.0)
    J = arm.camera_jacobian()
    np.testing.assert_allclose(J @ info.qdot, info.scale * v, atol=1e-9 * speed)
    # and the speed limits are the URDF's × velocity_scale, per joint
    assert np.all(np.abs(info.qdot) <= 0.5 * truth.vlim + 1e-12)


def _near(q_index: int, value: float) -> np.ndarray:
    q = Q_NOMINAL.copy()
    q[q_index] = value
    return q


#: a shoulder singularity (neither the elbow's q3 = 0 nor the wrist's q5 = 0), found by a grid
#: search of σ_min over (q2, q3, q4): σ_min ≈ 4e-6
SHOULDER = np.array([0.0, -2.55, 2.2, 0.51666667, -1.57, 0.0])


SINGULAR = {
    'wrist exact': _near(4, 0.0), 'wrist 0.003': _near(4, 0.003), 'wrist -0.02': _near(4, -0.02),
    'elbow exact': _near(2, 0.0), 'elbow 0.003': _near(2, 0.003), 'elbow -0.03': _near(2, -0.03),
    'shoulder': SHOULDER,
}


@pytest.mark.parametrize('where', list(SINGULAR))
def test_near_a_singularity_a_departure_from_the_command_is_never_silent(truth, where):
    """
    Where the arm cannot follow the twist, its status says so.

    Every twist (axes, random, and along the weakest and strongest singular directions,
    both ways): either the camera moves as commanded (× the uniform ``scale``), or the
    status is ``singularity``. The wrist and elbow cases used to give ``ok`` with the
    camera moving elsewhere, whenever the motion did not decrease σ_min.
    """
    arm = ArmModel(q0=SINGULAR[where], tool0Mc=HAND_EYE, velocity_scale=0.5)
    J = arm.camera_jacobian()
    U, S, _ = np.linalg.svd(J)
    assert S[-1] < arm.singular_threshold, S[-1]
    rng = np.random.default_rng(3)
    twists = [0.05 * e for e in np.eye(6)] + [0.05 * rng.normal(size=6) for _ in range(6)]
    twists += [s * 0.05 * U[:, k] for k in (0, 5) for s in (1, -1)]
    departed = 0
    for v in twists:
        arm.reset(SINGULAR[where])
        achieved, info = _step(arm, truth, v)
        assert np.all(np.isfinite(arm.q)) and np.all(np.abs(info.qdot) <= arm.vmax + 1e-12)
        follows = np.linalg.norm(achieved - info.scale * v) <= 0.02 * np.linalg.norm(v)
        departed += not follows
        assert follows or info.status is Status.SINGULARITY, (where, v, achieved)
        assert info.sigma_min == pytest.approx(S[-1], abs=1e-12)
        assert f'sigma_min={S[-1]:.4f}' in info.message or info.status is Status.OK
    assert departed, 'a singular configuration where every twist is followed?'


def test_just_above_the_threshold_there_is_no_damping_and_no_status(truth):
    arm = ArmModel(q0=_near(4, 0.3), tool0Mc=HAND_EYE, velocity_scale=0.5)
    assert arm.singular_threshold < arm.sigma_min() < 2 * arm.singular_threshold
    U = np.linalg.svd(arm.camera_jacobian())[0]
    v = 0.01 * U[:, 5]                 # the weakest direction: a large q̇, not damped
    achieved, info = _step(arm, truth, v)
    assert info.status is Status.OK
    np.testing.assert_allclose(achieved, info.scale * v, atol=0.02 * np.linalg.norm(v))


# --- joint position limits -----------------------------------------------------------------
CELL = {2: (-2.5, 2.5), 4: (-2.2, -1.0)}


@pytest.mark.parametrize('joint', range(6))
@pytest.mark.parametrize('side', [1, -1])
def test_a_command_driving_a_joint_past_its_limit_lands_it_exactly_there(truth, joint, side):
    """
    Step 4 lands the joint on its limit, never past it, not even by round-off.

    Step 1 then locks it, and the others realise the least-squares part of the twist
    (numpy's lstsq on the remaining columns of the Jacobian).
    """
    arm = ArmModel(q0=Q_NOMINAL, tool0Mc=HAND_EYE, velocity_scale=0.5)
    # near their own limits the elbow (±π: folded) and wrist_2 (±2π ≡ 0) are singular:
    # cell limits there, as experiments.arm_cell sets them
    if joint in CELL:
        arm.lower[joint], arm.upper[joint] = CELL[joint]
    limit = (arm.upper if side > 0 else arm.lower)[joint]
    q = Q_NOMINAL.copy()
    q[joint] = limit - side * 0.03
    arm.reset(q)
    assert arm.sigma_min() > arm.singular_threshold
    for _ in range(3):                  # command the joint's own column: it turns that way
        v = side * 0.5 * arm.camera_jacobian()[:, joint]
        arm.command(v)
        info = arm.step(DT)
        assert side * (arm.q[joint] - limit) <= 0.0       # never past
    assert arm.q[joint] == limit
    assert info.status is Status.JOINT_LIMIT and arm.joint_names[joint] in info.joints
    # at the limit: locked, and the rest is the least-squares solution without it
    v = side * 0.05 * arm.camera_jacobian()[:, joint] + np.r_[0.01, 0.0, 0.0, 0.0, 0.0, 0.02]
    info = arm.twist_to_qdot(v)
    assert info.qdot[joint] == 0.0 and info.status is Status.JOINT_LIMIT
    J = arm.camera_jacobian()
    rest = np.arange(6) != joint
    x = np.linalg.lstsq(J[:, rest], v, rcond=None)[0]
    if info.sigma_min >= arm.singular_threshold and info.scale == 1.0:
        np.testing.assert_allclose(info.qdot[rest], x, atol=1e-9 * np.linalg.norm(x))
    # and away from the limit it moves again, along the command
    away = -v
    achieved, info = _step(arm, truth, away)
    assert side * (arm.q[joint] - limit) < 0
    assert achieved @ away > 0.9 * np.linalg.norm(achieved) * np.linalg.norm(away)


@pytest.mark.parametrize('rate', [0.1, 0.2])
def test_a_slow_camera_rate_lands_a_joint_on_its_limit_within_one_long_period(truth, rate):
    """camera_rate 0.1 Hz (its bound): one 10 s period would turn a joint 16 rad."""
    arm = ArmModel(q0=Q_NOMINAL, tool0Mc=HAND_EYE, velocity_scale=0.5)
    v = 10.0 * arm.camera_jacobian()[:, 5]           # wrist_3 at full speed, 1.6 rad/s
    arm.command(v)
    info = arm.step(1.0 / rate)
    assert np.all(arm.q <= arm.upper) and np.all(arm.q >= arm.lower)
    assert info.status is Status.JOINT_LIMIT, info.status
    assert np.any(arm.q == arm.upper) or np.any(arm.q == arm.lower)
    assert np.all(np.isfinite(truth.wMc(arm.q).homogeneous))


def test_a_start_configuration_outside_the_limits_is_refused_naming_the_joint():
    q = Q_NOMINAL.copy()
    upper = float(pin.buildModelFromUrdf(find_ur5_urdf()).upperPositionLimit[2])
    assert upper == pytest.approx(np.pi, abs=1e-9)   # the elbow's limit: ±π (the URDF's)
    q[2] = np.nextafter(upper, 4.0)                  # one ulp past it
    with pytest.raises(ValueError, match=r'elbow_joint = 3\.14159 not in \[-3\.14159, '):
        ArmModel(q0=q)
    q[2] = upper                                     # exactly at it: a configuration
    assert ArmModel(q0=q).q[2] == upper
