"""
Interaction matrices against central finite differences, measurements against ground truth.

Issue 2; DESIGN.md §2–§3.
"""
from __future__ import annotations

from core_poses import CMO_DESIRED, moved, random_visible_poses
import numpy as np
import pinocchio as pin
import pytest
from sphere_servo.core.features import FEATURE_SETS, make_feature_set
from sphere_servo.core.geometry import exp3, L_omega, log3
from sphere_servo.core.measurement import (
    conic_from_ellipse, cRo_measured, model_cRo_offset, observe, sphere_from_conic,
    sphere_from_moments, unit_ray)
from sphere_servo.core.targets import cc_target, special_sphere

TARGETS = {'special': special_sphere(0.05), 'cc': cc_target(0.05)}
N_POSES = 200
H = 1e-5


def fd_interaction(fs, target, cMo) -> np.ndarray:
    """
    Differentiate the feature map numerically under each unit camera twist.

    Central finite differences, 4th-order stencil: marks near the limb make the depth's
    square root strongly curved.
    """
    cols = []
    for j in range(6):
        xi = np.zeros(6)
        xi[j] = H
        f = [fs.features(observe(moved(cMo, k * xi), target)) for k in (2, 1, -1, -2)]
        cols.append((-f[0] + 8 * f[1] - 8 * f[2] + f[3]) / (12 * H))
    return np.column_stack(cols)


@pytest.mark.parametrize('kind', TARGETS)
@pytest.mark.parametrize('name', FEATURE_SETS)
def test_interaction_matrix_matches_finite_differences(kind, name):
    target = TARGETS[kind]
    fs = make_feature_set(name, observe(CMO_DESIRED, target))
    worst = 0.0
    seed = 10 * FEATURE_SETS.index(name) + list(TARGETS).index(kind)
    for cMo in random_visible_poses(target, N_POSES, seed=seed):
        obs = observe(cMo, target)
        L = fs.interaction(obs, target.radius)
        L_fd = fd_interaction(fs, target, cMo)
        worst = max(worst, np.linalg.norm(L - L_fd) / np.linalg.norm(L_fd))
    print(f'{kind} {name}: worst relative error {worst:.2e} over {N_POSES} poses')
    assert worst < 1e-5


def test_paper_sign_of_L_omega_is_wrong_for_this_convention():
    """
    DESIGN.md §3: with θu = log(ᶜ*R_c) and ω in the current frame the [u]× term is '+'.

    The '−' of the paper's eq. (7) disagrees with finite differences; '+' equals
    Pinocchio's Jlog3 (an independent implementation).
    """
    target = TARGETS['special']
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    cMo = random_visible_poses(target, 1, seed=3)[0]
    L_fd = fd_interaction(fs, target, cMo)[3:, 3:]
    thetau = fs.features(observe(cMo, target))[3:]
    assert np.linalg.norm(thetau) > 0.3
    assert np.allclose(L_omega(thetau, +1), L_fd, atol=1e-6)
    assert not np.allclose(L_omega(thetau, -1), L_fd, atol=1e-2)
    R = exp3(thetau)
    assert np.allclose(L_omega(thetau, +1), pin.Jlog3(R), atol=1e-12)


def fitted_conic(cMo, target) -> np.ndarray:
    """
    Fit a conic (least squares, SVD) to projected points of the 3-D occluding contour.

    Independent of the closed form ``b bᵀ − cos²θ I``.
    """
    cO = cMo.translation
    d = np.linalg.norm(cO)
    b = cO / d
    # contour circle: centre b·(d − r²/d), radius r·sqrt(1 − r²/d²), in the plane ⟂ b
    centre = b * (d - target.radius ** 2 / d)
    rad = target.radius * np.sqrt(1 - (target.radius / d) ** 2)
    e1 = np.cross(b, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(b, e1)
    ang = np.linspace(0, 2 * np.pi, 37)[:-1]
    P = centre + rad * (np.outer(np.cos(ang), e1) + np.outer(np.sin(ang), e2))
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    M = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, bxy, c, dd, e, f = np.linalg.svd(M)[2][-1]
    return np.array([[a, bxy / 2, dd / 2], [bxy / 2, c, e / 2], [dd / 2, e / 2, f]])


@pytest.mark.parametrize('kind', TARGETS)
def test_measurements_recover_ground_truth(kind):
    target = TARGETS[kind]
    rng = np.random.default_rng(7)
    offset = model_cRo_offset(target)
    for cMo in random_visible_poses(target, 100, seed=11):
        C = fitted_conic(cMo, target)
        s_nt_true = cMo.translation / target.radius
        for scale in (1.0, -1.0, rng.uniform(1e-3, 1e3), -rng.uniform(1e-3, 1e3)):
            m = sphere_from_conic(scale * C)
            assert np.abs(m.s_nt - s_nt_true).max() < 1e-9 * np.linalg.norm(s_nt_true)
            assert m.quality < 1e-8
        # blob moments of the same ellipse: centre c, region covariance A⁻¹/4
        A = C[:2, :2] / (C[:2, 2] @ np.linalg.solve(C[:2, :2], C[:2, 2]) - C[2, 2])
        c = -np.linalg.solve(C[:2, :2], C[:2, 2])
        assert np.allclose(conic_from_ellipse(c, A) / conic_from_ellipse(c, A)[2, 2],
                           C / C[2, 2], atol=1e-9)
        m2 = sphere_from_moments(c, np.linalg.inv(A) / 4.0)
        assert np.abs(m2.s_nt - s_nt_true).max() < 1e-9 * np.linalg.norm(s_nt_true)
        # partial pose from exact mark projections
        obs = observe(cMo, target)
        obs_img = type(obs)(m, {k: unit_ray(q[:2] / q[2]) for k, q in obs.q.items()}, obs.kind)
        cRo = cRo_measured(obs_img)
        assert np.abs(cRo - cMo.rotation @ offset).max() < 1e-9


@pytest.mark.parametrize('kind', TARGETS)
def test_thetau_is_the_true_relative_rotation(kind):
    target = TARGETS[kind]
    fs = make_feature_set('s_n', observe(CMO_DESIRED, target))
    for cMo in random_visible_poses(target, 50, seed=5):
        cdRc_true = CMO_DESIRED.rotation @ cMo.rotation.T
        assert np.allclose(fs.features(observe(cMo, target))[3:], log3(cdRc_true), atol=1e-9)
