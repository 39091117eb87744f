"""
Control law (no ROS). DESIGN.md §4, paper eq. (17).

``v_c = −λ L̂⁺ (s − s*)``: ``v_c = (v, ω)`` (6,) is the camera twist in the current camera
frame (m/s, rad/s); ``L̂`` is the interaction matrix with the estimated radius ``r̂``,
evaluated at the current features, the desired ones, or their mean (as ViSP offers).

Gain: constant, or adaptive as ViSP's ``vpAdaptiveGain``
``λ(x) = (λ₀ − λ∞) exp(−λ'₀ x / (λ₀ − λ∞)) + λ∞`` with ``x = ‖s − s*‖∞`` (infinity norm,
as ViSP), λ₀ the gain at 0, λ∞ the gain at infinity, λ'₀ the slope at 0.

Saturation scales the *whole* twist (direction kept) so ``‖v‖ ≤ v_max`` and ``‖ω‖ ≤ ω_max``.
Convergence: ``‖s − s*‖₂ < tol``.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from sphere_servo.core import linalg
from sphere_servo.core.features import check_radius, FeatureSet, SnFeatures, STFeatures
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation
from sphere_servo.core.validation import Bound, refuse

INTERACTION_CHOICES = ('current', 'desired', 'mean')
#: L(s, r̂) of the sets whose interaction matrix depends on the feature vector only
VECTOR_INTERACTIONS = {'s_n': SnFeatures.interaction_from, 's': STFeatures.interaction_from}
#: their feature sets, whose ``check_vector`` says what a feature vector from outside may be
VECTOR_SETS = {'s_n': SnFeatures, 's': STFeatures}


class ControlError(GeometryError):
    """The control law cannot produce a valid twist (non-finite error or matrix)."""


@dataclass(frozen=True)
class AdaptiveGain:
    """
    ViSP's adaptive gain.

    ``lambda_0`` at x = 0, ``lambda_inf`` as x → ∞, ``slope_0`` = dλ/dx at 0 (magnitude).
    Requires ``lambda_0 > lambda_inf > 0``, ``slope_0 > 0``.
    """

    lambda_0: float = 4.0
    lambda_inf: float = 0.4
    slope_0: float = 30.0

    def __post_init__(self):
        vals = (self.lambda_0, self.lambda_inf, self.slope_0)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f'adaptive gain parameters must be finite, got {vals}')
        if not (self.lambda_0 > self.lambda_inf > 0 and self.slope_0 > 0):
            raise ValueError('adaptive gain needs lambda_0 > lambda_inf > 0 and slope_0 > 0, '
                             f'got {vals}')

    def __call__(self, x: float) -> float:
        d = self.lambda_0 - self.lambda_inf
        return d * np.exp(-self.slope_0 * x / d) + self.lambda_inf


@dataclass(slots=True)
class ControlOutput:
    """One step of the law: twist (6,), error (n,), gain used, ‖e‖₂, converged flag."""

    v_c: np.ndarray
    error: np.ndarray
    gain: float
    error_norm: float
    converged: bool
    saturated: bool


def saturate(v_c: np.ndarray, v_max: float, w_max: float) -> tuple[np.ndarray, bool]:
    """Scale ``v_c`` uniformly so ``‖v‖ ≤ v_max`` and ``‖ω‖ ≤ w_max`` (direction kept)."""
    if v_max == math.inf and w_max == math.inf:
        return v_c, False
    nv, nw = math.sqrt(float(v_c[:3] @ v_c[:3])), math.sqrt(float(v_c[3:] @ v_c[3:]))
    k = min(1.0, v_max / nv if nv > 0 else np.inf, w_max / nw if nw > 0 else np.inf)
    return (v_c * k, True) if k < 1.0 else (v_c, False)


class _Law:
    """What every form of the law shares: gain, saturation, convergence, the solve."""

    def __init__(self, r_hat: float, gain: float | AdaptiveGain = 0.5,
                 interaction: str = 'current', v_max: float = np.inf, w_max: float = np.inf,
                 tol: float = 1e-4):
        self.r_hat = check_radius(r_hat)
        if not isinstance(gain, AdaptiveGain):
            gain = float(gain)
            if not np.isfinite(gain) or gain <= 0:
                raise ValueError(f'gain λ must be finite and > 0, got {gain}')
        self.gain = gain
        if interaction not in INTERACTION_CHOICES:
            raise ValueError(f'interaction must be one of {INTERACTION_CHOICES}, '
                             f'got {interaction!r}')
        self.interaction = interaction
        for nm, val in (('v_max', v_max), ('w_max', w_max), ('tol', tol)):
            if np.isnan(val) or val <= 0:
                raise ValueError(f'{nm} must be > 0, got {val}')
        self.v_max, self.w_max, self.tol = float(v_max), float(w_max), float(tol)

    def lam(self, error: np.ndarray) -> float:
        """Gain for this error (constant, or adaptive on ``‖e‖∞``)."""
        if isinstance(self.gain, AdaptiveGain):
            return self.gain(float(np.max(np.abs(error))))
        return self.gain

    def _combine(self, L_current, L_desired) -> np.ndarray:
        if self.interaction == 'desired':
            return L_desired
        return L_current if self.interaction == 'current' else 0.5 * (L_current + L_desired)

    def _twist(self, e: np.ndarray, L: np.ndarray) -> ControlOutput:
        """``−λ L⁺ e``, saturated; raises :class:`ControlError` rather than return NaN."""
        if not math.isfinite(float(e @ e)):
            refuse(ControlError, 'feature error s − s*', e, Bound.FINITE,
                   'finite entries with a finite norm')
        lam = self.lam(e)
        try:
            if L.shape[0] == L.shape[1]:
                v_c = -lam * linalg.solve(L, e)
            else:
                v_c = -lam * (np.linalg.pinv(L) @ e)
        except np.linalg.LinAlgError as exc:
            refuse(ControlError, 'interaction matrix L̂', f'singular ({exc})', Bound.GEOMETRY,
                   'an invertible L̂')
        if not math.isfinite(float(v_c @ v_c)):
            refuse(ControlError, 'twist −λ L̂⁺ (s − s*)', v_c, Bound.FINITE,
                   'finite entries with a finite norm')
        v_c, sat = saturate(v_c, self.v_max, self.w_max)
        norm = math.sqrt(float(e @ e))
        return ControlOutput(v_c, e, lam, norm, norm < self.tol, sat)


class Controller(_Law):
    """
    ``v_c = −λ L̂⁺ (s − s*)`` for a :class:`~sphere_servo.core.features.FeatureSet`.

    r_hat        estimated radius r̂ (m), finite and > 0 (``ValueError`` otherwise).
    gain         constant λ > 0, or an :class:`AdaptiveGain`.
    interaction  'current' | 'desired' | 'mean': where L̂ is evaluated.
    v_max, w_max twist saturation (m/s, rad/s); ``inf`` disables it.
    tol          convergence threshold on ‖s − s*‖₂.
    """

    def __init__(self, features: FeatureSet, r_hat: float, **kw):
        super().__init__(r_hat, **kw)
        self.features = features
        self._L_desired = features.interaction(features.desired_obs, self.r_hat)

    def L_hat(self, obs: Observation, s: np.ndarray | None = None) -> np.ndarray:
        """
        ``L̂`` (n×6) at current / desired / mean features.

        ``s``: the current features, if already computed.
        """
        if self.interaction == 'desired':
            return self._L_desired
        return self._combine(self.features.interaction(obs, self.r_hat, s), self._L_desired)

    def compute(self, obs: Observation) -> ControlOutput:
        """
        Twist for the current observation.

        Raises a ``ValueError`` subclass
        (:class:`~sphere_servo.core.measurement.MeasurementError` or :class:`ControlError`)
        instead of ever returning a non-finite twist: the caller then sends zero velocity.
        """
        s = self.features.features(obs)
        return self._twist(s - self.features.desired, self.L_hat(obs, s))


class VectorController(_Law):
    """
    The same law from feature *vectors* alone, as the servo node receives them.

    For ``s_n`` (eq. 6) and ``s`` (eq. 16) the interaction matrix is a function of the
    feature vector only, so ``compute(s, s_star)`` needs nothing else. (``s_cc``'s ζ rows need
    the marks' depths: use :class:`Controller` on observations for it.)
    """

    def __init__(self, feature_set: str, r_hat: float, **kw):
        super().__init__(r_hat, **kw)
        try:
            self._L = VECTOR_INTERACTIONS[feature_set]
            self._check = VECTOR_SETS[feature_set].check_vector
        except KeyError:
            raise ValueError(f'the vector law supports {tuple(VECTOR_INTERACTIONS)}, '
                             f'got {feature_set!r}') from None
        self.feature_set = feature_set

    def compute(self, s: np.ndarray, s_star: np.ndarray) -> ControlOutput:
        """
        Twist for the feature vectors ``s`` (current) and ``s_star`` (desired), each (6,).

        Both are checked first (the set's ``check_vector``): 6 finite numbers,
        ``‖θu‖ ≤ π + tol`` (θu = log R), for ``s_n`` ``1 < ‖s_n,t‖ ≤ S_NT_MAX`` (‖O‖ > r),
        for ``s`` a bounded ``s_t``; a refusal is a
        :class:`~sphere_servo.core.features.FeatureError` naming the bound. The law then
        raises :class:`ControlError` rather than return a non-finite twist.
        """
        s, s_star = self._check(s, 's'), self._check(s_star, 's*')
        L_star = self._L(s_star, self.r_hat) if self.interaction != 'current' else None
        L = self._L(s, self.r_hat) if self.interaction != 'desired' else None
        return self._twist(s - s_star, self._combine(L, L_star))
