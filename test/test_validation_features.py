"""
Validation of feature vectors and of the law (issue 14, item 2): bounds at and past.

θu = log(R) has θ ∈ [0, π]; ``s_n,t = O/r`` has norm 1/r_δ > 1. A θu of ±inf or so large
that θ overflows (1e154 … 1e300) used to raise ``ValueError: math domain error`` out of
``geometry.sinc``; now every refusal is typed, and the law never returns a NaN twist.
"""
from __future__ import annotations

import math

from core_poses import CMO_DESIRED, CMO_FAR_START
import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.core.control import ControlError, VectorController
from sphere_servo.core.features import (check_feature_vector, FeatureError, make_feature_set,
                                        S_NT_MAX, THETA_MAX)
from sphere_servo.core.geometry import GeometryError, L_omega, sinc
from sphere_servo.core.measurement import observe, R_DELTA_MIN
from sphere_servo.core.targets import cc_target, special_sphere
from sphere_servo.core.validation import Bound, UNIT_TOL

HUGE = [1e154, 1e155, 1e200, 1e300, 1.7e308]


@pytest.mark.parametrize('x', [math.inf, -math.inf, math.nan])
def test_sinc_refuses_a_non_finite_angle_with_a_typed_error(x):
    with pytest.raises(GeometryError) as info:
        sinc(x)
    assert info.value.violation.bound is Bound.FINITE


@pytest.mark.parametrize('sign', [1.0, -1.0])
@pytest.mark.parametrize('v', [math.inf, -math.inf, math.nan, *HUGE])
def test_L_omega_refuses_or_is_finite_never_a_domain_error(v, sign):
    thetau = np.array([v, 0.3, -0.2])
    theta = math.sqrt(sum(float(x) * float(x) for x in thetau))
    if math.isfinite(theta):      # 1e154: θ² = 1e308 still fits, and the matrix is finite
        assert np.all(np.isfinite(L_omega(thetau, sign)))
    else:
        with pytest.raises(GeometryError) as info:
            L_omega(thetau, sign)
        assert info.value.violation.bound is Bound.FINITE and 'θ' in str(info.value)


def _desired(name):
    target = cc_target() if name == 's_cc' else special_sphere()
    return make_feature_set(name, observe(CMO_DESIRED, target)), target


@pytest.mark.parametrize('name', ['s_n', 's', 's_cc'])
def test_real_feature_vectors_pass(name):
    fs, target = _desired(name)
    for cMo in (CMO_DESIRED, CMO_FAR_START):
        s = fs.features(observe(cMo, target))
        np.testing.assert_array_equal(check_feature_vector(name, s), s)
    np.testing.assert_array_equal(check_feature_vector(name, fs.desired, 's*'), fs.desired)


def _refused(name, s, bound, quantity, what='s'):
    with pytest.raises(FeatureError) as info:
        check_feature_vector(name, s, what)
    v = info.value.violation
    assert v.bound is bound and quantity in v.quantity, str(info.value)
    assert what in str(info.value)


@pytest.mark.parametrize('name, rot', [('s_n', slice(3, 6)), ('s', slice(3, 6)),
                                       ('s_cc', slice(4, 7))])
def test_theta_is_at_most_pi(name, rot):
    fs, _ = _desired(name)
    s = fs.desired.copy()
    u = np.array([2.0, -1.0, 2.0]) / 3.0
    for theta, ok in ((math.pi, True), (THETA_MAX - 1e-9, True), (THETA_MAX + 1e-9, False),
                      (4.0, False), (1e200, False)):
        s[rot] = theta * u
        if ok:
            check_feature_vector(name, s)
        else:
            _refused(name, s, Bound.RANGE, '‖θu' if name != 's_cc' else '‖ζ')
    for bad in (math.inf, -math.inf, math.nan):
        s[rot] = [bad, 0.0, 0.0]
        _refused(name, s, Bound.FINITE, 's')


def test_s_nt_norm_is_over_one_and_bounded():
    fs, _ = _desired('s_n')
    s = fs.desired.copy()
    u = s[:3] / np.linalg.norm(s[:3])
    for n, ok in ((1.0 + 1e-9, True), (S_NT_MAX, True), (1.0, False), (0.5, False),
                  (S_NT_MAX * (1 + 1e-9), False), (1e300, False)):
        s[:3] = n * u
        if ok:
            check_feature_vector('s_n', s)
        else:
            _refused('s_n', s, Bound.RANGE, '‖s_n,t‖')
    assert S_NT_MAX == 1.0 / R_DELTA_MIN


def test_s_t_is_finite_and_bounded():
    s = np.zeros(6)
    check_feature_vector('s', s)               # s = 0 at the desired pose: no lower bound
    s[:3] = [2 * S_NT_MAX, 0.0, 0.0]
    check_feature_vector('s', s)
    s[0] *= 1 + 1e-9
    _refused('s', s, Bound.RANGE, '‖s_t‖')
    s[0] = math.inf
    _refused('s', s, Bound.FINITE, 's')


def test_s_cc_r_delta_and_b():
    fs, _ = _desired('s_cc')
    s = fs.desired.copy()
    for rd, ok in ((R_DELTA_MIN, True), (1 - 1e-12, True), (0.0, False), (1.0, False),
                   (-0.1, False)):
        s[0] = rd
        if ok:
            check_feature_vector('s_cc', s)
        else:
            _refused('s_cc', s, Bound.RANGE, 'r_delta')
    s = fs.desired.copy()
    s[1:4] *= 1 + 1.1 * UNIT_TOL
    _refused('s_cc', s, Bound.UNIT, 'b')


@pytest.mark.parametrize('name', ['s_n', 's', 's_cc'])
@pytest.mark.parametrize('s', [np.zeros(5), np.zeros(8), np.zeros((2, 3)), 'abc', None])
def test_the_shape_is_that_of_the_set(name, s):
    _refused(name, s, Bound.SHAPE, 's')


# --- the vector law ----------------------------------------------------------------------
@pytest.mark.parametrize('name', ['s_n', 's'])
@pytest.mark.parametrize('interaction', ['current', 'desired', 'mean'])
def test_vector_law_refuses_bad_s_and_s_star_with_a_typed_error(name, interaction):
    fs, target = _desired(name)
    law = VectorController(name, target.radius, interaction=interaction)
    s = fs.features(observe(CMO_FAR_START, target))
    assert np.all(np.isfinite(law.compute(s, fs.desired).v_c))
    for which in ('s', 's*'):
        for v in (math.inf, -math.inf, math.nan, *HUGE):
            bad_s, bad_star = s.copy(), fs.desired.copy()
            (bad_s if which == 's' else bad_star)[4] = v
            with pytest.raises(FeatureError) as info:
                law.compute(bad_s, bad_star)
            assert info.value.violation.bound in (Bound.FINITE, Bound.RANGE)
            assert f'of {which}' in str(info.value) or which in str(info.value)
    with pytest.raises(FeatureError, match='shape'):
        law.compute(s[:5], fs.desired)


def test_vector_law_at_the_bounds_gives_a_finite_twist_or_a_control_error():
    # the largest vectors the checks let through: the law gives a finite twist, or refuses
    # with ControlError; never NaN
    _, target = _desired('s_n')
    u = np.array([0.0, 0.6, 0.8])
    cases = [('s_n', np.r_[S_NT_MAX * u, math.pi * u], np.r_[1.0001 * u, 0.0, 0.0, 0.0]),
             ('s_n', np.r_[1.0001 * u, -THETA_MAX * u], np.r_[S_NT_MAX * u, 0.0, 0.0, 0.0]),
             ('s', np.r_[2 * S_NT_MAX * u, THETA_MAX * u], np.zeros(6))]
    for name, s, s_star in cases:
        for interaction in ('current', 'desired', 'mean'):
            law = VectorController(name, target.radius, interaction=interaction)
            try:
                v = law.compute(s, s_star).v_c
            except ControlError as exc:
                assert exc.violation is not None
            else:
                assert np.all(np.isfinite(v))


def test_control_error_is_typed():
    _, target = _desired('s')
    law = VectorController('s', target.radius)
    law._L = lambda s, r_hat: np.zeros((6, 6))           # a singular L̂
    with pytest.raises(ControlError) as info:
        law.compute(np.r_[0.1, 0, 0, 0, 0, 0], np.zeros(6))
    assert info.value.violation.bound is Bound.GEOMETRY and 'L̂' in str(info.value)
    law._L = lambda s, r_hat: np.eye(6) * 1e-300          # a twist that overflows
    with pytest.raises(ControlError) as info:
        law.compute(np.r_[1.0, 0, 0, 0, 0, 0], np.zeros(6))
    assert info.value.violation.bound is Bound.FINITE and 'twist' in str(info.value)


def test_features_of_an_observation_pass_their_own_check():
    # a feature set's output from any exact observation is a valid vector of that set
    rng = np.random.default_rng(2)
    for name in ('s_n', 's', 's_cc'):
        fs, target = _desired(name)
        for _ in range(30):
            xi = np.r_[rng.normal(scale=0.03, size=3), rng.normal(scale=0.3, size=3)]
            cMo = pin.exp6(pin.Motion(xi)).inverse() * CMO_DESIRED
            try:
                obs = observe(cMo, target)
            except ValueError:
                continue
            check_feature_vector(name, fs.features(obs))
