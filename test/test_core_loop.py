"""Control law and the headless closed loop (issue 2; paper §III and §IV.A)."""
from __future__ import annotations

from core_poses import CMO_DESIRED, CMO_FAR_START
import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.core.control import AdaptiveGain, Controller, saturate
from sphere_servo.core.features import check_radius, make_feature_set
from sphere_servo.core.geometry import rotation_angle_deg
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.sim.loop import LoopOutcome, run_loop


def test_far_start_is_a_large_displacement_with_marks_visible():
    cdMc = CMO_DESIRED * CMO_FAR_START.inverse()
    assert np.linalg.norm(cdMc.translation) >= 0.20
    assert rotation_angle_deg(cdMc.rotation) >= 60.0
    for target in (special_sphere(), cc_target()):
        observe(CMO_FAR_START, target)  # raises if a mark is hidden


def test_cc_target_all_three_sets_converge_and_s_is_straight():
    target = cc_target()
    results = {fs: run_loop(target, CMO_FAR_START, CMO_DESIRED, fs, dt=0.1, gain=0.5,
                            max_iter=3000) for fs in ('s_cc', 's_n', 's')}
    for name, res in results.items():
        print(f'{name}: path {res.path_length:.4f} m, straight {res.straight_distance:.4f} m, '
              f'ratio {res.path_length / res.straight_distance:.4f}, {res.iterations} it')
        assert res.converged, (name, res.reason)
        dt_err, dr_err = res.final_pose_error()
        assert dt_err < 1e-4 and dr_err < 0.05, (name, dt_err, dr_err)
    s_res = results['s']
    assert s_res.path_length / s_res.straight_distance < 1.01
    # the other two sets do not move in a straight line from this start
    assert results['s_n'].path_length / results['s_n'].straight_distance > 1.01


@pytest.mark.parametrize('name', ['s_n', 's'])
def test_special_sphere_converges_from_the_same_start(name):
    res = run_loop(special_sphere(), CMO_FAR_START, CMO_DESIRED, name, dt=0.1, gain=0.5,
                   max_iter=3000)
    assert res.converged, res.reason
    assert res.final_pose_error()[0] < 1e-4


@pytest.mark.parametrize('ratio', [0.05, 0.5, 1.0, 2.0, 20.0])
def test_sn_converges_for_any_positive_radius_estimate(ratio):
    """
    Paper §III: L_sn L̂_sn⁻¹ > 0 ⇔ r̂ > 0.

    λ·dt = 0.02 keeps the *discrete* loop within its stability margin up to r̂/r = 20 (the
    paper's proof is in continuous time).
    """
    target = special_sphere()
    res = run_loop(target, CMO_FAR_START, CMO_DESIRED, 's_n', r_hat=ratio * target.radius,
                   dt=0.04, gain=0.5, max_iter=30000, tol=1e-3)
    assert res.converged, (ratio, res.reason, res.iterations)
    assert res.final_pose_error()[0] < 1e-3 * target.radius * 5


@pytest.mark.parametrize('bad', [0.0, -0.05, np.nan, np.inf, -np.inf, 'abc', None])
def test_bad_radius_estimate_is_refused(bad):
    target = special_sphere()
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    with pytest.raises(ValueError, match='radius'):
        Controller(fs, bad)
    with pytest.raises(ValueError, match='radius'):
        check_radius(bad)
    with pytest.raises(ValueError, match='radius'):
        fs.interaction(observe(CMO_FAR_START, target), bad)


def test_negative_radius_would_diverge():
    """
    Necessity side of §III, shown on the loop itself.

    With r̂ < 0 forced past the check, the translation error grows.
    """
    target = special_sphere()
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    L_neg = fs.interaction_from(fs.desired, 1.0)
    L_neg[:3, :3] = +np.eye(3) / target.radius  # what r̂ = −r would give
    L_true = fs.interaction_from(fs.desired, target.radius)
    eig = np.linalg.eigvals(L_true @ np.linalg.inv(L_neg))
    assert np.min(eig.real) < 0


@pytest.mark.parametrize('interaction', ['current', 'desired', 'mean'])
def test_interaction_choices_and_adaptive_gain_converge(interaction):
    small = pin.SE3(pin.exp3(np.array([0.1, -0.15, 0.2])), np.array([0.03, -0.02, 0.40]))
    res = run_loop(special_sphere(), small, CMO_DESIRED, 's_n', interaction=interaction,
                   gain=AdaptiveGain(2.0, 0.3, 10.0), dt=0.1, max_iter=2000)
    assert res.converged, res.reason


def test_adaptive_gain_formula():
    g = AdaptiveGain(4.0, 0.4, 30.0)
    assert g(0.0) == pytest.approx(4.0)
    assert g(1e6) == pytest.approx(0.4)
    h = 1e-7
    assert (g(h) - g(0.0)) / h == pytest.approx(-30.0, rel=1e-4)
    with pytest.raises(ValueError):
        AdaptiveGain(0.4, 4.0, 30.0)


def test_saturation_keeps_direction():
    v = np.array([1.0, -2.0, 0.5, 0.3, 0.0, -0.4])
    out, sat = saturate(v, v_max=0.1, w_max=1.0)
    assert sat
    assert np.linalg.norm(out[:3]) == pytest.approx(0.1)
    assert np.allclose(np.cross(out[:3], v[:3]), 0) and np.allclose(np.cross(out[3:], v[3:]), 0)
    assert np.allclose(out / np.linalg.norm(out), v / np.linalg.norm(v))
    same, sat2 = saturate(v * 1e-3, 0.1, 1.0)
    assert not sat2 and np.array_equal(same, v * 1e-3)


def test_controller_reports_convergence_and_zero_error_at_goal():
    target = special_sphere()
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    out = Controller(fs, target.radius).compute(observe(CMO_DESIRED, target))
    assert out.converged and np.allclose(out.v_c, 0, atol=1e-12)


@pytest.mark.parametrize('name', ['s_n', 's'])
@pytest.mark.parametrize('interaction', ['current', 'desired', 'mean'])
def test_vector_law_equals_the_observation_law(name, interaction):
    """
    The servo node's law (feature vectors only) equals the law on observations.

    It gives the same twist for the sets whose L depends on s alone.
    """
    from sphere_servo.core.control import VectorController
    target = special_sphere()
    fs = make_feature_set(name, observe(CMO_DESIRED, target))
    kw = {'gain': 0.7, 'interaction': interaction, 'v_max': 0.05, 'w_max': 0.3}
    ctrl = Controller(fs, 0.5 * target.radius, **kw)
    vec = VectorController(name, 0.5 * target.radius, **kw)
    obs = observe(CMO_FAR_START, target)
    a = ctrl.compute(obs)
    b = vec.compute(fs.features(obs), fs.desired)
    assert np.allclose(a.v_c, b.v_c, atol=1e-12) and a.saturated == b.saturated
    with pytest.raises(ValueError, match='supports'):
        VectorController('s_cc', target.radius)


def test_loop_reports_a_target_lost_at_the_first_step():
    """A start from which the marks cannot be seen ends the run with a reason, not a crash."""
    from core_poses import camera_at
    res = run_loop(special_sphere(), camera_at([0.0, 0.0, 0.5]), CMO_DESIRED, 's_n')
    assert not res.converged and res.iterations == 0
    assert res.outcome is LoopOutcome.TARGET_LOST and 'hidden' in res.detail
    assert res.e.shape == (0, 6) and res.v.shape == (0, 6)


def test_loop_holds_still_through_a_few_lost_frames():
    """
    ``max_lost``: a dropped observation holds the camera instead of ending the run.

    It holds still (zero twist, like the servo node); more consecutive drops than allowed
    end the run.
    """
    from sphere_servo.core.measurement import MeasurementError
    target = special_sphere()
    calls = {'n': 0}

    def flaky(cMo):
        calls['n'] += 1
        if calls['n'] > 1 and calls['n'] % 4 == 0:  # every 4th frame after s* is lost
            raise MeasurementError('mark P1 is hidden (simulated dropout)')
        return observe(cMo, target)

    res = run_loop(target, CMO_FAR_START, CMO_DESIRED, 's_n', observer=flaky, max_lost=1)
    assert res.converged, res.reason
    assert len(res.oMc) == res.iterations  # no pose recorded for a dropped frame
    assert np.all(np.diff(res.t) > 0) and np.any(np.diff(res.t) > 0.15)  # gaps in time
    calls['n'] = 0
    res = run_loop(target, CMO_FAR_START, CMO_DESIRED, 's_n', observer=flaky, max_lost=0)
    assert not res.converged and res.outcome is LoopOutcome.TARGET_LOST
    assert 'simulated dropout' in res.detail and res.iterations == 2


def test_loop_ends_where_the_plant_stops_it():
    """
    A plant's stop ends the run after its step.

    Outcome, detail and joints come from the plant, the pose the step reached is recorded,
    and the histories up to it equal the free camera's (the same loop).
    """
    from sphere_servo.sim.loop import closed_loop
    from sphere_servo.sim.plants import FreeCamera, PlantStop

    class Stopping(FreeCamera):
        steps = 0

        def step(self, v_c, dt):
            super().step(v_c, dt)
            self.steps += 1
            if self.steps == 3:
                return PlantStop(LoopOutcome.JOINT_LIMIT, 'j2 at position limit', ('j2',))
            return None

    target = special_sphere()
    plant = Stopping(CMO_FAR_START, CMO_DESIRED)
    res = closed_loop(plant, target, 's_n')
    free = run_loop(target, CMO_FAR_START, CMO_DESIRED, 's_n')
    assert res.outcome is LoopOutcome.JOINT_LIMIT and not res.converged
    assert res.reason == 'joint_limit: j2 at position limit' and res.limit_joints == ('j2',)
    assert res.iterations == 3 and len(res.oMc) == 4 and plant.steps == 3
    np.testing.assert_array_equal(res.oMc[-1], plant.oMc())
    np.testing.assert_array_equal(res.oMc, free.oMc[:4])
    np.testing.assert_array_equal(res.v, free.v[:3])
    assert res.joints is None and res.arm_status is None and res.joint_limits is None
    assert free.outcome is LoopOutcome.CONVERGED and free.reason == 'converged'
