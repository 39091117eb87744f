"""
Pure tests of the UR5 + eye-in-hand camera model (no ROS).

Jacobian against finite differences of Pinocchio's forward kinematics, DLS tracking,
uniform velocity scaling, position limits, watchdog, IK.
"""
import numpy as np
import pinocchio as pin
import pytest

from sphere_servo.core.geometry import integrate_camera
from sphere_servo.sim.arm import ArmModel, find_ur5_urdf, pose_from_xyz_rpy, Status

Q_NOMINAL = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
HAND_EYE = pose_from_xyz_rpy([0.02, -0.04, 0.03], [0.05, -0.03, 0.4])


@pytest.fixture(scope='module')
def arm():
    return ArmModel(tool0Mc=HAND_EYE, q0=Q_NOMINAL)


def test_urdf_found_and_override_checked(tmp_path):
    assert find_ur5_urdf().endswith('ur5_robot.urdf')
    with pytest.raises(FileNotFoundError, match='given path'):
        find_ur5_urdf(tmp_path / 'nope.urdf')


def test_default_camera_looks_out_of_the_flange():
    a = ArmModel(q0=Q_NOMINAL)
    pin.framesForwardKinematics(a.model, a.data, a.q)
    wrist3 = a.data.oMi[a.model.getJointId('wrist_3_joint')].translation
    wMc = a.wMc()
    outward = wMc.translation - wrist3
    assert np.allclose(wMc.rotation[:, 2], outward / np.linalg.norm(outward), atol=1e-9)


@pytest.mark.parametrize('seed', range(5))
def test_camera_jacobian_matches_finite_differences(arm, seed):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, arm.model.nq)
    J = arm.camera_jacobian(q)
    eps = 1e-6
    J_fd = np.zeros_like(J)
    for i in range(arm.model.nv):
        dq = np.zeros(arm.model.nv)
        dq[i] = eps
        Mp = arm.wMc(pin.integrate(arm.model, q, dq))
        Mm = arm.wMc(pin.integrate(arm.model, q, -dq))
        # twist in the current camera frame: wMc(q+) = wMc(q−)·exp6(2ε v)
        J_fd[:, i] = pin.log6(Mm.inverse() * Mp).vector / (2 * eps)
    assert np.allclose(J, J_fd, atol=1e-6), np.abs(J - J_fd).max()
    # and a point fixed in the world moves in the camera as Ẋ = −v − ω × X
    wX = np.array([0.4, 0.1, 0.2])
    qdot = rng.normal(size=arm.model.nv)
    v = J @ qdot
    X = lambda qq: arm.wMc(qq).actInv(wX)  # noqa: E731
    Xdot = (X(pin.integrate(arm.model, q, qdot * eps))
            - X(pin.integrate(arm.model, q, -qdot * eps))) / (2 * eps)
    assert np.allclose(Xdot, -v[:3] - np.cross(v[3:], X(q)), atol=1e-6)


def test_dls_tracks_a_twist():
    a = ArmModel(tool0Mc=HAND_EYE, q0=Q_NOMINAL)
    v_c = np.array([0.03, -0.02, 0.05, 0.1, -0.05, 0.2])
    dt, n = 1 / 30, 15
    expected = a.wMc()
    for _ in range(n):
        expected = integrate_camera(expected, v_c, dt)  # re-integrated in the moving frame
        a.command(v_c)
        info = a.step(dt)
        assert info.status == Status.OK and info.scale == 1.0
    err = pin.log6(expected.inverse() * a.wMc()).vector
    # first-order integration of q: error O(dt²) per step, well under a millimetre here
    assert np.linalg.norm(err[:3]) < 1e-3 and np.linalg.norm(err[3:]) < 2e-3


def test_twist_beyond_limits_is_scaled_as_a_whole(arm):
    arm.reset()
    v_c = np.array([2.0, -1.0, 3.0, 4.0, -2.0, 5.0])  # far beyond joint velocity limits
    info = arm.twist_to_qdot(v_c)
    J = arm.camera_jacobian()
    assert info.scale < 1.0
    assert np.all(np.abs(info.qdot) <= arm.vmax + 1e-12)
    assert np.isclose(np.max(np.abs(info.qdot) / arm.vmax), 1.0)
    realised = J @ info.qdot
    # same direction as commanded (per-axis clipping would bend it)
    assert np.allclose(realised / np.linalg.norm(realised), v_c / np.linalg.norm(v_c),
                       atol=1e-6)
    assert np.allclose(realised, info.scale * v_c, atol=1e-6)


def test_non_finite_twist_is_refused_and_stops_the_arm(arm):
    for bad in ([np.nan, 0, 0, 0, 0, 0], [0, 0, np.inf, 0, 0, 0], [1, 2, 3]):
        arm.reset()
        arm.command([0, 0, 0.1, 0, 0, 0])
        assert np.any(arm.step(1 / 30).qdot)
        with pytest.raises(ValueError):
            arm.command(bad)
        # the refused twist drops the previous one: at rest from the next step (issue 14)
        assert np.allclose(arm._cmd, 0.0)
        assert not np.any(arm.step(1 / 30).qdot)


def _wrist3_twist(a):
    """Camera twist that turns wrist_3 positively: the column of wrist_3 in J_c."""
    return a.camera_jacobian()[:, 5].copy()


def test_joint_stops_at_its_limit_and_can_move_away():
    q0 = Q_NOMINAL.copy()
    a = ArmModel(tool0Mc=HAND_EYE, q0=q0)
    hi = a.upper[5]
    q0[5] = hi - 0.05
    a.reset(q0)
    v_c = 1.0 * _wrist3_twist(a)  # ≈1 rad/s on wrist_3: reaches the limit in ~2 steps
    statuses = []
    for _ in range(6):
        a.command(v_c)
        info = a.step(1 / 30)
        statuses.append(info.status)
        assert a.q[5] <= hi + 1e-12
    assert a.q[5] == pytest.approx(hi, abs=1e-9)
    assert statuses[-1] == Status.JOINT_LIMIT and info.joints == ['wrist_3_joint']
    assert 'wrist_3_joint' in info.message
    # other joints keep their limits-free motion but wrist_3 no longer moves further
    q_before = a.q.copy()
    a.command(v_c)
    a.step(1 / 30)
    assert a.q[5] == pytest.approx(q_before[5], abs=1e-12)
    # moving away is allowed
    a.command(-v_c)
    info = a.step(1 / 30)
    assert info.status == Status.OK and a.q[5] < hi - 1e-3


def test_watchdog_stops_the_arm():
    a = ArmModel(q0=Q_NOMINAL, cmd_timeout=0.1)
    a.command([0, 0, 0.05, 0, 0, 0])
    for _ in range(3):
        assert a.step(1 / 30).status == Status.OK
    q = a.q.copy()
    for _ in range(3):
        info = a.step(1 / 30)
    assert info.status == Status.TIMEOUT and np.all(info.qdot == 0)
    q2 = a.q.copy()
    a.step(1 / 30)
    assert np.array_equal(a.q, q2) and not np.array_equal(q, q2)


def test_singularity_slows_down_and_is_reported():
    # wrist_2 = 0 aligns wrist_1 and wrist_3 axes: a wrist singularity
    q = Q_NOMINAL.copy()
    q[4] = 0.02
    a = ArmModel(q0=q)
    J = a.camera_jacobian()
    U, S, Vt = np.linalg.svd(J)
    assert S[-1] < a.singular_threshold
    # try both directions along the weakest twist: one drives deeper into the singularity
    infos = [a.twist_to_qdot(sign * 0.05 * U[:, -1]) for sign in (1, -1)]
    assert any(i.status == Status.SINGULARITY and i.scale < 1 for i in infos)
    assert np.all(np.abs(infos[0].qdot) <= a.vmax) and np.all(np.isfinite(infos[0].qdot))


def test_ik_reaches_a_camera_pose(arm):
    arm.reset()
    goal = arm.wMc() * pose_from_xyz_rpy([0.1, -0.08, 0.15], [0.3, -0.2, 0.5])
    q, ok, err = arm.solve_ik(goal)
    assert ok and err < 1e-6
    assert np.allclose(arm.wMc(q).homogeneous, goal.homogeneous, atol=1e-5)
    # through cMo, with a target placed in the world
    arm.wMo = arm.wMc() * pose_from_xyz_rpy([0, 0, 0.45], [0, 0, 0])
    cMo_des = pose_from_xyz_rpy([0.05, 0.02, 0.5], [0.2, 0.1, -0.3])
    q, ok, _ = arm.ik_for_cMo(cMo_des)
    assert ok and np.allclose(arm.cMo(q).homogeneous, cMo_des.homogeneous, atol=1e-5)
    arm.wMo = pin.SE3.Identity()


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match='6 joint values'):
        ArmModel(q0=[0, 0, 0])
    with pytest.raises(ValueError, match='NaN'):
        ArmModel(q0=[0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match='limits'):
        ArmModel(q0=[0, 0, 4.0, 0, 0, 0])
    with pytest.raises(ValueError, match='velocity_scale'):
        ArmModel(velocity_scale=0.0)
