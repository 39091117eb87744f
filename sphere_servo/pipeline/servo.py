"""
The servo's logic without ROS: features → camera twist, ``v_c = −λ L̂⁺ (s − s*)`` (eq. 17).

:class:`ServoCore` owns what the ``servo`` node decides; the node only turns messages into
numbers and commands into messages. Stamps are int nanoseconds; ``now_ns`` is the node's
clock (sim time with ``use_sim_time``), ``wall_now`` a monotonic wall clock in seconds.

- Each image is answered once: features with the stamp of the last answered image are a
  repeat (not answered), and so are features whose image is older than ``max_image_age``
  on the node's clock (``now_ns − stamp_ns > max_image_age``). In lockstep
  ``max_image_age: 0`` answers only the current frame: each command steps the simulator,
  so answering a superseded frame (a backlog that Fast DDS delivers late, in a burst,
  under load) would leave several frames in flight and the run would depend on the load.
- Stamps (:class:`~sphere_servo.core.stamps.StampRule`, after the two rules above): features
  stamped more than ``future_tolerance`` ahead of the node's clock, or older than the last
  image answered (stamps going backwards: another source, a replay), are refused: a zero
  twist that answers no image (a zero stamp), state ``bad stamp``, and the log says why.
  A clock that has not started (sim time before the first ``/clock``: 0) judges no stamp
  in the future, and once it runs a stamp so taken that is in its future is forgotten (it
  would refuse every later image as going backwards); a clock that jumps back (a
  restarted simulator) restarts the rule. A zero stamp (unset: the servo's own zero
  stamp answers no image) or a negative one is no image's time: refused the same way.
- Values: s and s* are checked against their set's physical bounds
  (:func:`~sphere_servo.core.features.check_feature_vector`): a refused desired leaves the
  one held; refused features give a zero twist (``target lost``, the error names the bound).
- Disabled (``start_enabled: false`` until :meth:`ServoCore.enable`): a zero twist.
- No desired features yet (:meth:`ServoCore.set_desired` not called, or only refused):
  a zero twist, state ``no desired``. The servo pairs each features message with the
  latest desired it holds, while that desired's publisher lives
  (:meth:`ServoCore.on_desired_publishers`): when none of the publishers of the desired
  topic it came from is left (the features node died), the desired is dropped, and the
  state ``no desired`` says ``teach again`` (a restarted features node holds none, unless
  it keeps it in its ``desired_file``, which it then publishes again).
- Target or a mark lost, unreadable features, or a law that cannot give a finite twist:
  a zero twist, state ``target lost``.
- Watchdog (:meth:`ServoCore.on_tick`, on the wall clock, since in lockstep sim time
  freezes exactly when the pipeline dies): a zero twist while no features have come
  (``waiting``) and when none usable came for ``timeout`` wall seconds (``stale``).

:class:`ServoState` values are the strings published in the servo's status message, so a
supervisor compares with ``ServoState.CONVERGED.value`` and never with a literal.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from sphere_servo.core.control import AdaptiveGain, VectorController
from sphere_servo.core.features import check_feature_vector
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.stamps import StampCheck, StampRule, StampVerdict
from sphere_servo.core.types import Twist
from sphere_servo.pipeline.common import Level, NodeStatus, Refusal, stamp_text
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.vectors import FEATURE_NAMES

LOST = 'the target or a mark is lost'
NO_DESIRED = 'no desired features yet'
TEACH_AGAIN = ('no desired features: teach again (the features node that published them '
               'is gone)')
FEATURES = 'features'  # the one source of the stamp rule: the features topic


class ServoState(str, Enum):
    """What the servo is doing (the value is the published status text)."""

    WAITING = 'waiting'          # no features yet
    DISABLED = 'disabled'        # features come, the servo is not enabled: zero twists
    NO_DESIRED = 'no desired'    # enabled, features come, but no desired yet: zero twists
    SERVOING = 'servoing'        # a twist from the law
    CONVERGED = 'converged'      # ‖s − s*‖ < tol: zero twist
    TARGET_LOST = 'target lost'  # the target or a mark lost, or no valid twist: zero twist
    STALE = 'stale'              # no usable features for longer than the timeout: zero twist
    BAD_STAMP = 'bad stamp'      # features stamped in the future or going backwards: zero


class Ignored(Enum):
    """Why features were not answered."""

    REPEAT = 'repeat'    # the image answered last
    TOO_OLD = 'too old'  # older than max_image_age on the node's clock


@dataclass(slots=True)
class Unanswered:
    """Features that get no answer: why, the image's age, and how many were too old."""

    why: Ignored
    age_ns: int
    skipped: int


@dataclass(slots=True)
class ServoCommand:
    """
    What the servo sends: a twist and the status that goes with it.

    twist       (6,) ``(v, ω)`` in the current camera frame, m/s and rad/s.
    stamp_ns    the answered image's stamp; None for the watchdog's commands.
    desired_stamp_ns  the stamp of the image the desired features held came from (0: not
                from an image of the run; None: no desired yet).
    reason      why the twist is zero ('' when the law gave it).
    fault       the error that left no valid twist ('' if none): worth an error log.
    error_norm, gain, saturated   the law's output (None unless it ran).
    changed     the state differs from the previous command's.
    """

    twist: Twist
    state: ServoState
    level: Level
    iteration: int
    stamp_ns: int | None = None
    reason: str = ''
    fault: str = ''
    converged: bool = False
    target_lost: bool = False
    error_norm: float | None = None
    gain: float | None = None
    saturated: bool | None = None
    changed: bool = False
    send_twist: bool = True  # False: a state only (the lockstep watchdog)
    desired_stamp_ns: int | None = None

    def values(self, image_age_ns: int | None = None) -> dict[str, str]:
        """
        Return the status values, key → text, in the published order.

        ``image_age_ns``: the node's clock at the twist's publication − the image stamp,
        published with the law's output.
        """
        v = {}
        if self.reason:
            v['reason'] = self.reason
        if self.error_norm is not None:
            v['error_norm'] = f'{self.error_norm:.6g}'
        v['converged'] = str(self.converged)
        v['target_lost'] = str(self.target_lost)
        if self.gain is not None:
            v['gain'] = f'{self.gain:.4g}'
            v['saturated'] = str(self.saturated)
            if image_age_ns is not None:
                v['image_age'] = f'{image_age_ns * 1e-9:.6f}'
        v['iteration'] = str(self.iteration)
        if self.stamp_ns is not None:
            v['stamp'] = stamp_text(self.stamp_ns)
        if self.desired_stamp_ns is not None:
            v['desired_stamp'] = stamp_text(self.desired_stamp_ns)
        return v

    def status(self, image_age_ns: int | None = None) -> NodeStatus:
        """Return the servo's status with this command (see :meth:`values`)."""
        return NodeStatus(self.state, self.level, self.values(image_age_ns))


def law_options(p: ServoParams) -> dict:
    """Return the law's options of the servo's parameters: r̂, gain (constant or adaptive)."""
    gain = AdaptiveGain(p.lambda_0, p.lambda_inf, p.slope_0) if p.adaptive else p.gain
    return {'r_hat': p.r_hat, 'gain': gain, 'interaction': p.interaction, 'v_max': p.v_max,
            'w_max': p.w_max, 'tol': p.tol}


def make_law(p: ServoParams) -> VectorController:
    """Build the servo's law, on feature vectors of ``feature_set``."""
    return VectorController(p.feature_set, **law_options(p))


class ServoCore:
    """The servo's state machine (see the module docstring)."""

    def __init__(self, params: ServoParams):
        self.params = params
        self.law = make_law(params)
        self.feature_set = params.feature_set
        self.timeout = params.timeout
        self.max_age_ns = int(round(params.max_image_age * 1e9))
        self.stamps = StampRule(int(round(params.future_tolerance * 1e9)))
        self.enabled = params.start_enabled
        self.state = ServoState.WAITING
        self.iteration = 0      # images answered while enabled
        self.skipped = 0        # features skipped as older than max_image_age
        self.last_stamp_ns: int | None = None  # the image answered last
        self.last_now_ns = 0                   # the node's clock at the last features
        self.last_rx: float | None = None      # wall time of the last usable features
        self.size = len(FEATURE_NAMES[self.feature_set])
        self.s_star: np.ndarray | None = None   # the desired features
        self.desired_stamp_ns: int | None = None
        self.desired_publishers: frozenset = frozenset()  # of the desired topic, then
        self.desired_lost = False  # the desired held was dropped: its publisher is gone

    def set_desired(self, s_star, stamp_ns: int,
                    publishers: frozenset = frozenset()) -> Refusal | None:
        """
        Hold ``s_star`` as the desired features, from the image stamped ``stamp_ns``.

        Refused (the desired held stays) unless it has the set's size, is finite and
        within the set's physical bounds. ``publishers``: ids of the desired topic's
        publishers when it came (see :meth:`on_desired_publishers`).
        """
        s_star = np.asarray(s_star, dtype=float)
        if s_star.shape != (self.size,) or not np.all(np.isfinite(s_star)):
            return Refusal(f'desired {self.feature_set} needs {self.size} finite values, got '
                           f'{s_star.ravel().tolist()}')
        try:
            s_star = check_feature_vector(self.feature_set, s_star, 's*')
        except GeometryError as exc:  # FeatureError
            return Refusal(f'desired {self.feature_set} refused: {exc}')
        self.s_star, self.desired_stamp_ns = s_star, int(stamp_ns)
        self.desired_publishers = frozenset(publishers)
        self.desired_lost = False
        return None

    def on_desired_publishers(self, publishers: frozenset) -> bool:
        """
        Drop the desired held when none of its topic's publishers of then is left.

        ``publishers``: ids of the desired topic's publishers now. Returns True when the
        desired was dropped by this call (the servo then says ``teach again``). A desired
        that came with no publisher ids (a test, a bag) is never dropped.
        """
        if self.s_star is None or not self.desired_publishers \
                or self.desired_publishers & publishers:
            return False
        self.s_star, self.desired_stamp_ns, self.desired_lost = None, None, True
        self.desired_publishers = frozenset()
        return True

    def enable(self, on: bool) -> None:
        """Start (True) or stop (False) servoing; disabled, every answer is a zero twist."""
        self.enabled = bool(on)

    def on_features(self, stamp_ns: int, s, now_ns: int, wall_now: float,
                    invalid: str = '') -> ServoCommand | Unanswered:
        """
        Answer the features ``s`` of the image stamped ``stamp_ns``, against the desired held.

        ``s`` (6,), or None when the target or a mark is lost; ``invalid``: why the features
        could not be read (they are then unusable: target lost).
        """
        if stamp_ns <= 0:  # unset (0: what answers no image), or before the epoch
            what = 'an unset stamp (0)' if stamp_ns == 0 else 'a stamp < 0'
            reason = f"features stamped {stamp_ns} ns refused: {what} is no image's time"
            return self._command(ServoState.BAD_STAMP, Level.WARN, reason=reason, fault=reason)
        age_ns = now_ns - stamp_ns
        if stamp_ns == self.last_stamp_ns:  # the same image again (a re-publication)
            return Unanswered(Ignored.REPEAT, age_ns, self.skipped)
        if age_ns > self.max_age_ns:  # superseded or late: not usable, not answered
            self.skipped += 1
            return Unanswered(Ignored.TOO_OLD, age_ns, self.skipped)
        last = self.stamps.last(FEATURES)
        if now_ns < self.last_now_ns or (  # the clock jumped back: a restarted simulator
                now_ns > 0 and last is not None
                and last - now_ns > self.stamps.future_tolerance_ns):
            # or it has started, and the last stamp, taken unjudged before, is in its future
            self.stamps.forget()
        self.last_now_ns = now_ns
        # a clock that has not started (sim time before the first /clock) judges no future
        verdict = self.stamps.check(FEATURES, stamp_ns, now_ns if now_ns > 0 else stamp_ns)
        if not verdict.accepted:
            return self._bad_stamp(verdict)
        self.last_rx = wall_now
        self.last_stamp_ns = stamp_ns
        if not self.enabled:
            return self._command(ServoState.DISABLED, Level.OK, stamp_ns=stamp_ns)
        self.iteration += 1
        if self.s_star is None:
            return self._command(ServoState.NO_DESIRED, Level.WARN, stamp_ns=stamp_ns,
                                 reason=TEACH_AGAIN if self.desired_lost else NO_DESIRED)
        if invalid:
            return self._stop(ServoState.TARGET_LOST, invalid, stamp_ns, fault=invalid)
        if s is None:
            return self._stop(ServoState.TARGET_LOST, LOST, stamp_ns)
        try:
            out = self.law.compute(s, self.s_star)
        except GeometryError as exc:  # FeatureError, MeasurementError, ControlError
            return self._stop(ServoState.TARGET_LOST, str(exc), stamp_ns, fault=str(exc))
        return self._command(ServoState.CONVERGED if out.converged else ServoState.SERVOING,
                             Level.OK, twist=np.zeros(6) if out.converged else out.v_c,
                             stamp_ns=stamp_ns, converged=out.converged,
                             error_norm=out.error_norm, gain=out.gain,
                             saturated=out.saturated)

    def _bad_stamp(self, check: StampCheck) -> ServoCommand:
        """Return the zero twist of a refused stamp (it answers no image: no stamp)."""
        what = 'the clock' if check.verdict is StampVerdict.FUTURE else 'the image answered last'
        reason = (f'features stamped {stamp_text(check.stamp_ns)} refused: '
                  f'{check.verdict.value} ({check.delta_ns * 1e-9:+.6f} s from {what}, '
                  f'{stamp_text(max(check.reference_ns, 0))}; future tolerance '
                  f'{self.params.future_tolerance:g} s)')
        return self._command(ServoState.BAD_STAMP, Level.WARN, reason=reason, fault=reason)

    def on_tick(self, wall_now: float) -> ServoCommand | None:
        """
        Return the watchdog's zero twist when waiting or stale, else None.

        With ``lockstep`` the command carries the state only: a twist would step the
        simulator (an extra period under a zero twist, so a run would depend on how long
        the machine's load delays the features), and a lockstep arm does not move between
        twists anyway.
        """
        if self.last_rx is None:
            cmd = self._command(ServoState.WAITING, Level.OK, reason='no features yet')
        elif wall_now - self.last_rx > self.timeout:
            if self.desired_lost and self.s_star is None:  # why nothing comes: say it
                cmd = self._command(ServoState.NO_DESIRED, Level.WARN, reason=TEACH_AGAIN)
            else:
                cmd = self._stop(ServoState.STALE,
                                 f'no usable features for more than {self.timeout} s')
        else:
            return None
        cmd.send_twist = not self.params.lockstep
        return cmd

    def _stop(self, state: ServoState, reason: str, stamp_ns: int | None = None,
              fault: str = '') -> ServoCommand:
        return self._command(state, Level.WARN, stamp_ns=stamp_ns, reason=reason,
                             fault=fault, target_lost=True)

    def _command(self, state: ServoState, level: Level, twist: Twist | None = None,
                 **kw) -> ServoCommand:
        changed, self.state = state != self.state, state
        return ServoCommand(np.zeros(6) if twist is None else twist, state, level,
                            self.iteration, changed=changed,
                            desired_stamp_ns=self.desired_stamp_ns, **kw)
