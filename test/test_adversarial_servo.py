"""
Adversarial stamps for the servo's core: unset, negative, and absurd ones before the clock.

Features are built from exact observations (``observe``) of random-free fixed poses, so the
law's twist is non-zero: a case that is answered shows up as ``servoing``.
"""
from __future__ import annotations

import numpy as np
import pytest

from sphere_servo.core.features import make_feature_set
from sphere_servo.core.geometry import se3
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import special_sphere
from sphere_servo.pipeline.common import Level
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.servo import ServoCommand, ServoCore, ServoState

SEC = 10**9
TARGET = special_sphere()
FS = make_feature_set('s_n', observe(se3(np.eye(3), [0.0, 0.0, 0.45]), TARGET))
S = FS.features(observe(se3(np.eye(3), [0.03, -0.01, 0.5]), TARGET))


def servo() -> ServoCore:
    c = ServoCore(ServoParams.from_mapping({'start_enabled': True, 'max_image_age': 0.5,
                                            'future_tolerance': 0.1}))
    assert c.set_desired(FS.desired, 0) is None
    return c


def _refused(cmd, needle: str) -> None:
    assert isinstance(cmd, ServoCommand), cmd
    assert cmd.state is ServoState.BAD_STAMP, (cmd.state, cmd.reason)
    assert np.array_equal(cmd.twist, np.zeros(6)) and cmd.stamp_ns is None
    assert cmd.level is Level.WARN and needle in cmd.reason, cmd.reason


def test_the_features_answer_a_real_image():
    """The baseline the cases below differ from: a positive stamp is answered by the law."""
    out = servo().on_features(SEC, S, SEC, 0.0)
    assert out.state is ServoState.SERVOING and out.stamp_ns == SEC
    assert np.linalg.norm(out.twist) > 1e-3


@pytest.mark.parametrize('stamp, now', [
    (-1, 0),               # one nanosecond before the epoch, the clock not started
    (-SEC // 10, 0),       # sec = -1, nanosec = 9e8
    (-1, SEC // 10),       # within max_image_age of a clock just started
])
def test_a_negative_stamp_is_refused(stamp, now):
    """A stamp < 0 is no image's time (sim time starts at 0): a zero twist, and why."""
    c = servo()
    _refused(c.on_features(stamp, S, now, 0.0), 'stamp < 0')
    assert c.iteration == 0 and c.last_stamp_ns is None


@pytest.mark.parametrize('now', [SEC // 10, 0])
def test_a_zero_stamp_is_refused(now):
    """
    A zero stamp answers no image: the servo's own zero-stamped twists mean exactly that.

    Answering it with the law's twist publishes a command that claims to answer nothing.
    """
    _refused(servo().on_features(0, S, now, 0.0), 'stamp')


@pytest.mark.parametrize('ahead_ns', [3600 * SEC, 2**63 - 1, SEC // 10 + 1])
def test_a_stamp_taken_before_the_clock_started_does_not_block_the_run(ahead_ns):
    """
    Before the first /clock no stamp can be judged in the future; it is accepted then.

    Once the clock runs, a stamp far ahead of it (an hour, 2^63 − 1 ns) must not stay the
    source's last one: every real image after it would be refused as going backwards, and
    the servo would never move again. Each later image, on the running clock, is answered.
    """
    c = servo()
    first = c.on_features(SEC + ahead_ns, S, 0, 0.0)
    assert isinstance(first, ServoCommand)
    for k in range(1, 4):
        out = c.on_features(k * SEC, S, k * SEC, float(k))
        assert out.state is ServoState.SERVOING, (k, out.state, out.reason)
        assert out.stamp_ns == k * SEC


def test_a_stamp_within_tolerance_before_the_clock_keeps_the_order():
    """A stamp before the clock started that the running clock accepts still orders the rest."""
    c = servo()
    assert c.on_features(SEC, S, 0, 0.0).state is ServoState.SERVOING
    _refused(c.on_features(SEC - 1, S, SEC, 1.0), 'older than the last stamp')
    assert c.on_features(SEC + 1, S, SEC + 1, 1.0).state is ServoState.SERVOING
