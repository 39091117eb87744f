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
- Disabled (``start_enabled: false`` until :meth:`ServoCore.enable`): a zero twist.
- No desired features yet (:meth:`ServoCore.set_desired` not called, or only refused):
  a zero twist, state ``no desired``. The servo pairs each features message with the
  latest desired it holds.
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
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.types import Twist
from sphere_servo.pipeline.common import Level, NodeStatus, Refusal, stamp_text
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.vectors import FEATURE_NAMES

LOST = 'the target or a mark is lost'
NO_DESIRED = 'no desired features yet'


class ServoState(str, Enum):
    """What the servo is doing (the value is the published status text)."""

    WAITING = 'waiting'          # no features yet
    DISABLED = 'disabled'        # features come, the servo is not enabled: zero twists
    NO_DESIRED = 'no desired'    # enabled, features come, but no desired yet: zero twists
    SERVOING = 'servoing'        # a twist from the law
    CONVERGED = 'converged'      # ‖s − s*‖ < tol: zero twist
    TARGET_LOST = 'target lost'  # the target or a mark lost, or no valid twist: zero twist
    STALE = 'stale'              # no usable features for longer than the timeout: zero twist


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
        self.enabled = params.start_enabled
        self.state = ServoState.WAITING
        self.iteration = 0      # images answered while enabled
        self.skipped = 0        # features skipped as older than max_image_age
        self.last_stamp_ns: int | None = None  # the image answered last
        self.last_rx: float | None = None      # wall time of the last usable features
        self.size = len(FEATURE_NAMES[self.feature_set])
        self.s_star: np.ndarray | None = None   # the desired features
        self.desired_stamp_ns: int | None = None

    def set_desired(self, s_star, stamp_ns: int) -> Refusal | None:
        """
        Hold ``s_star`` as the desired features, from the image stamped ``stamp_ns``.

        Refused (the desired held stays) unless it has the set's size and is finite.
        """
        s_star = np.asarray(s_star, dtype=float)
        if s_star.shape != (self.size,) or not np.all(np.isfinite(s_star)):
            return Refusal(f'desired {self.feature_set} needs {self.size} finite values, got '
                           f'{s_star.ravel().tolist()}')
        self.s_star, self.desired_stamp_ns = s_star, int(stamp_ns)
        return None

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
        age_ns = now_ns - stamp_ns
        if stamp_ns == self.last_stamp_ns:  # the same image again (a re-publication)
            return Unanswered(Ignored.REPEAT, age_ns, self.skipped)
        if age_ns > self.max_age_ns:  # superseded or late: not usable, not answered
            self.skipped += 1
            return Unanswered(Ignored.TOO_OLD, age_ns, self.skipped)
        self.last_rx = wall_now
        self.last_stamp_ns = stamp_ns
        if not self.enabled:
            return self._command(ServoState.DISABLED, Level.OK, stamp_ns=stamp_ns)
        self.iteration += 1
        if self.s_star is None:
            return self._command(ServoState.NO_DESIRED, Level.WARN, stamp_ns=stamp_ns,
                                 reason=NO_DESIRED)
        if invalid:
            return self._stop(ServoState.TARGET_LOST, invalid, stamp_ns, fault=invalid)
        if s is None:
            return self._stop(ServoState.TARGET_LOST, LOST, stamp_ns)
        try:
            out = self.law.compute(s, self.s_star)
        except GeometryError as exc:  # MeasurementError, ControlError
            return self._stop(ServoState.TARGET_LOST, str(exc), stamp_ns, fault=str(exc))
        return self._command(ServoState.CONVERGED if out.converged else ServoState.SERVOING,
                             Level.OK, twist=np.zeros(6) if out.converged else out.v_c,
                             stamp_ns=stamp_ns, converged=out.converged,
                             error_norm=out.error_norm, gain=out.gain,
                             saturated=out.saturated)

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
