"""
The servo core without ROS: state machine, repeat and age rules, watchdog, published values.

Stamps and clocks are int nanoseconds (node clock) and seconds (wall), given by the test, so
every case is deterministic.
"""
from __future__ import annotations

import numpy as np
import pytest

from sphere_servo.pipeline.common import Level
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.servo import (Ignored, LOST, ServoCommand, ServoCore, ServoState,
                                         Unanswered)

MS = 1_000_000
S_STAR = np.array([0.0, 0.0, 9.0, 0.0, 0.0, 0.0])  # s*_n: sphere 9 radii ahead, θu* = 0


def core(desired: bool = True, **over) -> ServoCore:
    """Return a servo core holding the desired S_STAR (of an image stamped 0) if ``desired``."""
    values = {'max_image_age': 0.5, 'timeout': 0.3, 'gain': 0.5, 'v_max': 10.0,
              'w_max': 100.0, 'tol': 1e-3, **over}
    c = ServoCore(ServoParams.from_mapping(values))
    if desired:
        assert c.set_desired(S_STAR, 0) is None
    return c


def answer(c: ServoCore, stamp_ns: int, s=None, now_ns=None, wall=0.0):
    s = S_STAR + np.array([0.02, -0.01, 0.03, 0.0, 0.0, 0.0]) if s is None else s
    return c.on_features(stamp_ns, s, stamp_ns if now_ns is None else now_ns, wall)


def test_translation_error_gives_the_closed_form_twist():
    """
    With θu = θu* = 0, eq. (6) is block triangular: ω = 0 and v = λ r̂ (s_n,t − s*_n,t).

    Checked against that closed form, and against its meaning: the point O moves as
    Ȯ = −v, so s_n,t = O/r decreases as ṡ = −λ (s − s*).
    """
    c = core(r_hat=0.05, gain=0.8)
    e_t = np.array([0.02, -0.01, 0.03])
    cmd = answer(c, 10 * MS, S_STAR + np.r_[e_t, 0.0, 0.0, 0.0])
    assert isinstance(cmd, ServoCommand) and cmd.state is ServoState.SERVOING
    np.testing.assert_allclose(cmd.twist[:3], 0.8 * 0.05 * e_t, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cmd.twist[3:], 0.0, atol=1e-15)
    s_dot = -cmd.twist[:3] / 0.05
    np.testing.assert_allclose(s_dot, -0.8 * e_t, rtol=1e-12)
    assert cmd.level is Level.OK and cmd.stamp_ns == 10 * MS and not cmd.target_lost
    assert cmd.error_norm == pytest.approx(np.linalg.norm(e_t)) and cmd.gain == 0.8


def test_state_machine_waiting_disabled_servoing_converged_lost():
    c = core(start_enabled=False)
    tick = c.on_tick(0.0)
    assert tick.state is ServoState.WAITING and tick.stamp_ns is None
    assert np.array_equal(tick.twist, np.zeros(6)) and not tick.changed  # starts waiting
    off = answer(c, 1 * MS)
    assert off.state is ServoState.DISABLED and off.changed and off.iteration == 0
    assert np.array_equal(off.twist, np.zeros(6)) and off.stamp_ns == 1 * MS
    c.enable(True)
    on = answer(c, 2 * MS)
    assert on.state is ServoState.SERVOING and on.iteration == 1 and np.any(on.twist)
    again = answer(c, 3 * MS)
    assert again.state is ServoState.SERVOING and not again.changed and again.iteration == 2
    done = answer(c, 4 * MS, S_STAR + 1e-4)  # ‖e‖₂ = 2.4e-4 < tol
    assert done.state is ServoState.CONVERGED and done.converged
    assert np.array_equal(done.twist, np.zeros(6))
    lost = c.on_features(5 * MS, None, 5 * MS, 0.0)
    assert lost.state is ServoState.TARGET_LOST and lost.level is Level.WARN
    assert lost.target_lost and lost.reason == LOST and not lost.fault
    assert np.array_equal(lost.twist, np.zeros(6)) and lost.iteration == 4
    c.enable(False)
    assert answer(c, 6 * MS).state is ServoState.DISABLED


def test_unusable_features_are_a_fault_and_a_zero_twist():
    c = core()
    bad = c.on_features(1 * MS, None, 1 * MS, 0.0, invalid='expected features …')
    assert bad.state is ServoState.TARGET_LOST and bad.fault == 'expected features …'
    nan = answer(c, 2 * MS, S_STAR * np.nan)
    assert nan.state is ServoState.TARGET_LOST and 'not finite' in nan.fault
    assert np.array_equal(nan.twist, np.zeros(6))
    short = answer(c, 3 * MS, np.ones(5))
    assert short.state is ServoState.TARGET_LOST and short.fault
    assert [bad.iteration, nan.iteration, short.iteration] == [1, 2, 3]


def test_each_image_is_answered_once():
    c = core()
    first = answer(c, 7 * MS, wall=1.0)
    assert isinstance(first, ServoCommand)
    repeat = answer(c, 7 * MS, wall=2.0)
    assert repeat == Unanswered(Ignored.REPEAT, 0, 0)
    assert c.iteration == 1 and c.last_rx == 1.0  # a repeat is not news for the watchdog
    assert isinstance(answer(c, 8 * MS), ServoCommand)
    # only the last answered image is a repeat: an image answered before it is not
    assert isinstance(answer(c, 7 * MS, now_ns=8 * MS), ServoCommand)


def test_age_rule_and_its_boundary():
    c = core(max_image_age=0.5)
    assert isinstance(answer(c, 1 * MS, now_ns=501 * MS), ServoCommand)  # exactly max: usable
    late = answer(c, 2 * MS, now_ns=502 * MS + 1)
    assert late == Unanswered(Ignored.TOO_OLD, 500 * MS + 1, 1)
    assert c.last_stamp_ns == 1 * MS and c.iteration == 1
    assert answer(c, 3 * MS, now_ns=900 * MS).skipped == 2
    ahead = answer(c, 10 * MS, now_ns=0)  # the node clock behind (no /clock yet): usable
    assert isinstance(ahead, ServoCommand)


def test_lockstep_age_zero_answers_only_the_current_frame():
    c = core(max_image_age=0.0)
    frame = 33_333_333
    assert isinstance(answer(c, 10 * frame, now_ns=10 * frame), ServoCommand)
    superseded = answer(c, 9 * frame, now_ns=11 * frame)
    assert superseded.why is Ignored.TOO_OLD and superseded.age_ns == 2 * frame
    assert answer(c, 11 * frame, now_ns=11 * frame + 1).why is Ignored.TOO_OLD
    assert isinstance(answer(c, 11 * frame, now_ns=11 * frame), ServoCommand)
    assert c.iteration == 2


def test_watchdog_on_the_wall_clock():
    c = core(timeout=0.3)
    assert answer(c, 1 * MS, wall=10.0).state is ServoState.SERVOING
    assert c.on_tick(10.29) is None  # not more than the timeout yet
    stale = c.on_tick(10.31)
    assert stale.state is ServoState.STALE and stale.level is Level.WARN and stale.changed
    assert stale.reason == 'no usable features for more than 0.3 s' and stale.target_lost
    assert np.array_equal(stale.twist, np.zeros(6)) and stale.stamp_ns is None
    # only late images come: they do not feed the watchdog, the arm stays stopped
    assert isinstance(answer(c, 2 * MS, now_ns=2 * MS + 600 * MS, wall=10.4), Unanswered)
    assert c.on_tick(10.45).state is ServoState.STALE
    fresh = answer(c, 3 * MS, wall=10.5)
    assert fresh.state is ServoState.SERVOING and fresh.changed
    assert c.on_tick(10.6) is None


def test_lockstep_watchdog_reports_but_sends_no_twist():
    """
    A lockstep arm steps once per twist: the watchdog's twists would add periods.

    So with ``lockstep`` the watchdog still reports waiting and stale (the states are the
    same), but its commands carry no twist to send; the answers to images still do.
    """
    for lockstep in (False, True):
        c = core(timeout=0.3, lockstep=lockstep)
        waiting = core(desired=False, lockstep=lockstep).on_tick(0.0)
        assert waiting.state is ServoState.WAITING and waiting.send_twist is not lockstep
        assert answer(c, 1 * MS, wall=10.0).send_twist
        stale = c.on_tick(10.31)
        assert stale.state is ServoState.STALE and stale.send_twist is not lockstep
        assert answer(c, 2 * MS, wall=10.4).send_twist


def test_published_values_in_order():
    c = core(desired=False, start_enabled=False)
    assert c.on_tick(0.0).values() == {'reason': 'no features yet', 'converged': 'False',
                                       'target_lost': 'False', 'iteration': '0'}
    assert answer(c, 1_500_000_007).values() == {
        'converged': 'False', 'target_lost': 'False', 'iteration': '0',
        'stamp': '1.500000007'}
    assert c.set_desired(S_STAR, 1_400_000_000) is None
    c.enable(True)
    cmd = answer(c, 2 * 10**9, S_STAR + np.r_[0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
    vals = cmd.values(image_age_ns=1_234_567)
    assert list(vals) == ['error_norm', 'converged', 'target_lost', 'gain', 'saturated',
                          'image_age', 'iteration', 'stamp', 'desired_stamp']
    assert vals['error_norm'] == '0.3' and vals['gain'] == '0.5' and vals['image_age'] == \
        '0.001235' and vals['stamp'] == '2.000000000' and vals['iteration'] == '1'
    assert vals['desired_stamp'] == '1.400000000'
    status = cmd.status(image_age_ns=1_234_567)
    assert (status.state, status.level, status.message) == (
        ServoState.SERVOING, Level.OK, 'servoing') and status.values == vals
    lost = c.on_features(3 * 10**9, None, 3 * 10**9, 0.0).values(image_age_ns=5)
    assert lost == {'reason': LOST, 'converged': 'False', 'target_lost': 'True',
                    'iteration': '2', 'stamp': '3.000000000', 'desired_stamp': '1.400000000'}


def test_no_twist_before_a_desired_and_it_says_so():
    """Features without a desired get a zero twist and the state ``no desired`` (WARN)."""
    c = core(desired=False)
    early = answer(c, 1 * MS)
    assert early.state is ServoState.NO_DESIRED and early.level is Level.WARN
    assert early.reason == 'no desired features yet' and early.changed
    assert np.array_equal(early.twist, np.zeros(6)) and early.desired_stamp_ns is None
    assert 'desired_stamp' not in early.values() and early.iteration == 1
    assert c.set_desired(S_STAR, 7) is None
    on = answer(c, 2 * MS)
    assert on.state is ServoState.SERVOING and np.any(on.twist) and on.desired_stamp_ns == 7


def test_a_desired_of_the_wrong_size_or_not_finite_is_refused():
    """A refused desired leaves the one held: the twist is still the law's on that one."""
    c = core()
    for bad in (np.ones(5), S_STAR * np.nan, np.r_[S_STAR[:5], np.inf]):
        refused = c.set_desired(bad, 9)
        assert refused is not None and 'desired s_n needs 6 finite values' in refused.reason
    assert c.desired_stamp_ns == 0 and np.array_equal(c.s_star, S_STAR)
    ref = core()
    e = S_STAR + np.r_[0.1, 0.0, -0.2, 0.0, 0.05, 0.0]
    np.testing.assert_array_equal(answer(c, 1 * MS, e).twist, answer(ref, 1 * MS, e).twist)


def test_saturation_keeps_the_direction():
    c = core(v_max=0.01, w_max=100.0, gain=1.0)
    e_t = np.array([0.3, -0.4, 0.0])
    cmd = answer(c, 1 * MS, S_STAR + np.r_[e_t, 0.0, 0.0, 0.0])
    assert cmd.saturated and np.linalg.norm(cmd.twist[:3]) == pytest.approx(0.01)
    np.testing.assert_allclose(cmd.twist[:3] / 0.01, e_t / 0.5, atol=1e-12)
