"""
What the demo's (and the paper report's) ROS figures show.

The servo run from the start pose on, in the taught camera frame — not the teach sequence
before it.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pinocchio as pin

from sphere_servo.experiments.demo import ros_figures, run_window


def _histories():
    """
    Make a supervisor's histories of a taught run.

    Frames every 0.1 s; 1.0–1.9 s the arm at the desired pose under an earlier, wrong teach
    (its error is −e0); 2.0–2.4 s at the start pose while the servo is still disabled (zero
    twists); from 2.5 s the enabled servo brings the camera to 1 mm short of the taught
    pose, converging at 4.0 s after 16 iterations.
    """
    oMc_taught = pin.SE3(pin.exp3(np.array([0.0, 0.1, 0.0])), np.array([0.0, 0.0, -0.45]))
    oMc_start = oMc_taught * pin.SE3(pin.exp3(np.array([0.3, 0.0, 0.2])),
                                     np.array([0.2, 0.1, -0.05]))
    e0 = np.array([1.0, 2.0, -1.0, 0.3, -0.2, 0.1])
    s_star = np.array([0.0, 0.0, 9.0, 0.0, 0.0, 0.0])
    off = pin.SE3(np.eye(3), np.array([0.001, 0.0, 0.0]))  # 1 mm along the camera's x
    feats, poses, meas, twists = [], [], [], []

    def frame(t, oMc, e, v, b_x):
        feats.append((t, s_star + e, s_star))
        poses.append((t, oMc.homogeneous.copy()))
        meas.append((t, {'b_x': b_x, 'b_y': 0.0, 'b_z': 1.0, 'P1_qx': 0.0, 'P1_qy': 0.1,
                         'P1_qz': 1.0}))
        twists.append((t, v))
    for k in range(10):                       # the teach sequence, at the desired pose
        frame(1.0 + 0.1 * k, oMc_taught, -e0, np.zeros(6), 0.0)
    for k in range(5):                        # at the start, the servo still disabled
        frame(2.0 + 0.1 * k, oMc_start * off, e0, np.zeros(6), 0.1)
    for k in range(21):                       # the run: start pose → 1 mm short of taught
        t, a = 2.5 + 0.1 * k, 1.0 - k / 20
        oMc = oMc_taught * pin.exp6(pin.Motion(a * pin.log6(oMc_taught.inverse() * oMc_start)
                                               .vector)) * off
        frame(t, oMc, a * e0, -a * e0, 0.1 * a)
    return SimpleNamespace(features=feats, poses=poses, measurements=meas, twists=twists,
                           t_start=2.0, t_enabled=2.5, t_converged=4.0,
                           iterations_converged=16, oMc_taught=oMc_taught), oMc_start, e0


def test_run_window_starts_at_the_start_pose_in_the_taught_frame():
    sup, oMc_start, e0 = _histories()
    w = run_window(sup)
    # from the first enabled frame: neither the pre-teach −e0 nor the disabled zero twists
    assert len(w['t']) == 21 and w['t'][0] == 0.0 and np.isclose(w['t'][-1], 2.0)
    np.testing.assert_allclose(w['e'][0], e0, atol=1e-12)
    np.testing.assert_allclose(w['v'][0], -e0, atol=1e-12)
    off = pin.SE3(np.eye(3), np.array([0.001, 0.0, 0.0]))
    start_in_taught = (sup.oMc_taught.inverse() * oMc_start * off).translation
    np.testing.assert_allclose(w['cd_p'][0], start_in_taught, atol=1e-9)
    # the last point shows where the servo stopped (1 mm off), not the origin
    np.testing.assert_allclose(w['cd_p'][-1], [0.001, 0.0, 0.0], atol=1e-9)
    assert len(w['b']) == 21 and set(w['marks']) == {'P1'} and len(w['marks']['P1']) == 21
    assert w['iterations'] == 16  # the servo's own count, not the window's length


def test_run_window_orders_late_deliveries_by_stamp():
    """Under load some messages arrive late: the window is the same in any arrival order."""
    sup, _, _ = _histories()
    w = run_window(sup)
    rng = np.random.default_rng(2)
    for name in ('features', 'poses', 'measurements'):
        hist = getattr(sup, name)
        setattr(sup, name, [hist[i] for i in rng.permutation(len(hist))])
    w2 = run_window(sup)
    for k in ('t', 'e', 'v', 'cd_p', 'b'):
        np.testing.assert_array_equal(w2[k], w[k])
    np.testing.assert_array_equal(w2['marks']['P1'], w['marks']['P1'])


def test_ros_figures_are_written(tmp_path):
    sup, _, _ = _histories()
    files = ros_figures(sup, tmp_path, 'synthetic run')
    assert [f.name for f in files] == ['fig3.png', 'fig4.png']
    assert all(f.stat().st_size > 10_000 for f in files)
