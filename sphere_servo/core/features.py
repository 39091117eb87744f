"""
The three feature sets of the paper's Table I and their interaction matrices (no ROS).

DESIGN.md §3. For each set, ``ṡ = L v_c`` with ``v_c = (v, ω)`` the camera twist in the
*current* camera frame. Every matrix takes the estimated radius ``r̂`` in place of r.

============  ====  =========================================================  ==========
set           size  features                                                   desired s*
============  ====  =========================================================  ==========
``s_n``       6     ``(s_n,t, θu)``, ``s_n,t = b/r_δ``, ``θu = log(ᶜ*R_c)``      (s*_n,t, 0)
``s``         6     ``(s_t, θu)``, ``s_t = s*_n,t − ᶜ*R_c s_n,t`` (eq. 15)       0
``s_cc``      7     ``(r_δ, b, ζ)``, ``ζ = log(V V*ᵀ)`` (eq. 3)                  (r*_δ, b*, 0)
============  ====  =========================================================  ==========

A feature set is built from the *desired* observation (the image taken at the taught
pose); it then maps any current :class:`~sphere_servo.core.measurement.Observation` to its
features and interaction matrix. ``ᶜ*R_c = ᶜ*R_o ᶜR_oᵀ`` uses the partial pose measured in
both images, so the choice of the target-attached frame cancels out.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
import math

import numpy as np

from sphere_servo.core.geometry import cross3, exp3, GeometryError, L_omega, log3, skew
from sphere_servo.core.measurement import (cRo_measured, MeasurementError, Observation,
                                           P3_over_r, P_over_r, R_DELTA_MIN)
from sphere_servo.core.targets import CC
from sphere_servo.core.validation import (Bound, check_array, check_range, check_unit,
                                          refuse)

FEATURE_SETS = ('s_n', 's', 's_cc')
#: θu = log(R) has θ ∈ [0, π]; a θu (or ζ) from outside may exceed π by round-off only
THETA_TOL = 1e-6
THETA_MAX = math.pi + THETA_TOL
#: ‖s_n,t‖ = ‖O‖/r = 1/r_δ ≤ 1/R_DELTA_MIN (core/measurement.py says why that bound)
S_NT_MAX = 1.0 / R_DELTA_MIN


class FeatureError(GeometryError):
    """A feature vector (s or s*) from outside breaks a physical bound of its set."""


def _norm(v: np.ndarray) -> float:
    return math.hypot(*v)  # no overflow for finite entries


def _within(s, lo: float, hi: float) -> np.ndarray | None:
    """
    Return ``s`` as a (6,) array if ``lo < ‖s[:3]‖ ≤ hi`` and ``‖s[3:]‖ ≤ THETA_MAX``, else None.

    The common case of a check, in floats (NaN and inf fail the comparisons); on None the
    full check says which bound failed.
    """
    try:
        a = np.asarray(s, dtype=float)
    except (TypeError, ValueError):
        return None
    if a.shape != (6,):
        return None
    x, y, z, tx, ty, tz = a.tolist()
    return a if lo < math.hypot(x, y, z) <= hi and math.hypot(tx, ty, tz) <= THETA_MAX else None


def check_thetau(v: np.ndarray, quantity: str) -> None:
    """Refuse a rotation vector ``θu`` (finite (3,)) with ``θ = ‖θu‖ > π + THETA_TOL``."""
    theta = _norm(v)
    if not theta <= THETA_MAX:
        refuse(FeatureError, f'‖{quantity}‖', theta, Bound.RANGE,
               f'≤ π + {THETA_TOL:g}: θu = log(R) has θ ∈ [0, π]')


def check_radius(r_hat: float) -> float:
    """
    Return ``r̂`` as a float; raise ``ValueError`` unless it is finite and > 0.

    Paper §III: the ``s_n`` law is stable for every ``r̂ > 0`` and diverges for ``r̂ ≤ 0``;
    never clamp.
    """
    try:
        r = float(r_hat)
    except (TypeError, ValueError):
        raise ValueError(f'estimated radius r̂ must be a number, got {r_hat!r}') from None
    if not np.isfinite(r) or r <= 0:
        raise ValueError(f'estimated radius r̂ must be finite and > 0, got {r_hat!r}')
    return r


class FeatureSet(ABC):
    """
    A feature set anchored on a desired observation.

    ``features(obs)`` → s (n,), ``desired`` → s* (n,), ``error(obs)`` → s − s* (n,),
    ``interaction(obs, r_hat)`` → L (n, 6).
    """

    name: str = ''
    size: int = 6
    labels: tuple = ()   # for plots (Unicode)
    names: tuple = ()    # for messages and files (ASCII: ros2 topic echo, CSV headers)

    def __init__(self, desired: Observation):
        self.desired_obs = desired
        self._setup(desired)
        self.desired = self.features(desired)

    @abstractmethod
    def _setup(self, desired: Observation) -> None: ...

    @abstractmethod
    def features(self, obs: Observation) -> np.ndarray: ...

    @abstractmethod
    def interaction(self, obs: Observation, r_hat: float,
                    s: np.ndarray | None = None) -> np.ndarray:
        """L (n×6) at ``obs``; ``s`` = ``features(obs)`` if the caller already has it."""

    def error(self, obs: Observation) -> np.ndarray:
        """``s − s*`` (n,)."""
        return self.features(obs) - self.desired

    @classmethod
    def check_vector(cls, s, what: str = 's') -> np.ndarray:
        """
        Return ``s`` as a float array if it can be a feature vector of this set, else refuse.

        Here: ``size`` finite numbers (:class:`FeatureError`); each set adds its physical
        bounds. ``what`` names the vector in the message ('s' or 's*').
        """
        return check_array(FeatureError, what, s, (cls.size,))


class SnFeatures(FeatureSet):
    """
    ``s_n = (s_n,t, θu)`` — the paper's minimal set, eqs. (5)–(7).

    ``L = [[−(1/r̂) I₃, [s_n,t]×], [0, L_ω(θu)]]`` with ``L_ω`` of DESIGN.md §3 (``+`` sign on
    ``[u]×``: θu = log(ᶜ*R_c), ω in the current frame; the paper's eq. (7) prints ``−``).
    """

    name = 's_n'
    labels = ('s_nt,x', 's_nt,y', 's_nt,z', 'θu_x', 'θu_y', 'θu_z')
    names = ('s_nt_x', 's_nt_y', 's_nt_z', 'thetau_x', 'thetau_y', 'thetau_z')

    def _setup(self, desired):
        self.cdRo = cRo_measured(desired)

    def cdRc(self, obs: Observation) -> np.ndarray:
        """``ᶜ*R_c = ᶜ*R_o ᶜR_oᵀ`` (3×3) from the desired and current images."""
        return self.cdRo @ cRo_measured(obs).T

    def features(self, obs):
        return np.concatenate([obs.sphere.s_nt, log3(self.cdRc(obs))])

    @classmethod
    def check_vector(cls, s, what='s'):
        """
        Refuse an ``s_n = (s_n,t, θu)`` that no camera can measure (:class:`FeatureError`).

        ``1 < ‖s_n,t‖ ≤ S_NT_MAX``: ``s_n,t = O/r`` and the camera is outside the sphere
        (``‖O‖ > r``), ``S_NT_MAX = 1/R_DELTA_MIN``; ``‖θu‖ ≤ π + THETA_TOL`` (θu = log R).
        """
        a = _within(s, 1.0, S_NT_MAX)
        if a is not None:
            return a
        s = check_array(FeatureError, what, s, (cls.size,))
        n = _norm(s[:3])
        if not 1.0 < n <= S_NT_MAX:
            refuse(FeatureError, f'‖s_n,t‖ of {what}', n, Bound.RANGE,
                   f'1 < ‖s_n,t‖ ≤ {S_NT_MAX:g}: s_n,t = O/r with ‖O‖ > r')
        check_thetau(s[3:], f'θu of {what}')
        return s

    @staticmethod
    def interaction_from(s: np.ndarray, r_hat: float) -> np.ndarray:
        """``L_sn`` (6×6) from a feature vector ``s = (s_n,t, θu)`` (eq. 6)."""
        k = -1.0 / check_radius(r_hat)
        x, y, z = (float(v) for v in s[:3])
        L = np.zeros((6, 6))
        L[:3] = [[k, 0.0, 0.0, 0.0, -z, y], [0.0, k, 0.0, z, 0.0, -x],
                 [0.0, 0.0, k, -y, x, 0.0]]
        L[3:, 3:] = L_omega(s[3:], +1.0)
        return L

    def interaction(self, obs, r_hat, s=None):
        return self.interaction_from(self.features(obs) if s is None else s, r_hat)


class STFeatures(SnFeatures):
    """
    ``s = (s_t, θu)`` with ``s_t = s*_n,t − ᶜ*R_c s_n,t`` (eq. 15), a 3-D servo.

    It servos the camera position ``ᶜ*t_c / r`` (no control of the target in the image).

    ``L = [[(1/r̂) ᶜ*R_c, 0], [0, L_ω(θu)]]`` (eq. 16).
    """

    name = 's'
    labels = ('s_t,x', 's_t,y', 's_t,z', 'θu_x', 'θu_y', 'θu_z')
    names = ('s_t_x', 's_t_y', 's_t_z', 'thetau_x', 'thetau_y', 'thetau_z')

    def _setup(self, desired):
        super()._setup(desired)
        self.s_nt_star = desired.sphere.s_nt.copy()

    def features(self, obs):
        cdRc = self.cdRc(obs)
        return np.concatenate([self.s_nt_star - cdRc @ obs.sphere.s_nt, log3(cdRc)])

    @classmethod
    def check_vector(cls, s, what='s'):
        """
        Refuse an ``s = (s_t, θu)`` that no camera can measure (:class:`FeatureError`).

        ``‖s_t‖ ≤ 2 S_NT_MAX``: ``s_t = s*_n,t − ᶜ*R_c s_n,t`` and each term is at most
        ``S_NT_MAX``; ``‖θu‖ ≤ π + THETA_TOL``.
        """
        a = _within(s, -1.0, 2.0 * S_NT_MAX)
        if a is not None:
            return a
        s = check_array(FeatureError, what, s, (cls.size,))
        n = _norm(s[:3])
        if not n <= 2.0 * S_NT_MAX:
            refuse(FeatureError, f'‖s_t‖ of {what}', n, Bound.RANGE,
                   f'≤ {2.0 * S_NT_MAX:g}: s_t = s*_n,t − R s_n,t, ‖s_n,t‖ ≤ {S_NT_MAX:g}')
        check_thetau(s[3:], f'θu of {what}')
        return s

    def interaction(self, obs, r_hat, s=None):
        return self.interaction_from(self.features(obs) if s is None else s, r_hat)

    @staticmethod
    def interaction_from(s: np.ndarray, r_hat: float) -> np.ndarray:
        """``L_s`` (6×6) from ``s = (s_t, θu)``: ᶜ*R_c = exp(θu) (eq. 16)."""
        r_hat = check_radius(r_hat)
        L = np.zeros((6, 6))
        L[:3, :3] = exp3(s[3:]) / r_hat
        L[3:, 3:] = L_omega(s[3:], +1.0)
        return L


def _V(q1: np.ndarray, q2: np.ndarray) -> tuple[np.ndarray, float]:
    """``V = [v1 v2 v3]`` of eq. (3) and ``m = ‖q2 − (q1ᵀq2) q1‖``."""
    w = q2 - (q1 @ q2) * q1
    m = float(np.linalg.norm(w))
    if m < 1e-12:
        raise MeasurementError('the two marks are seen along the same ray: V is undefined')
    v2 = w / m
    return np.column_stack([q1, v2, cross3(q1, v2)]), m


class SccFeatures(FeatureSet):
    """
    ``s_cc = (r_δ, b, ζ)`` (7 features), the previous set of the paper's ref. [13].

    ``ζ = log(V V*ᵀ)``; with ``ρ1 = ‖P1‖``, ``ρ2 = ‖P2‖`` (or ``‖P3‖``, the CC tip) scaled by r̂:

    - ``ṙ_δ = (r_δ²/r̂) bᵀ v``
    - ``ḃ = −(r_δ/r̂)(I − b bᵀ) v + [b]× ω``
    - ``ζ̇ = J(ζ) [ (1/ρ1)(α v1 v3ᵀ + v2 v3ᵀ − v3 v2ᵀ) v − ω ]``,
      ``α = ((q1ᵀq2) − ρ1/ρ2)/m``, ``J(ζ) = L_ω(ζ)`` with the ``−`` sign (left
      multiplication). Exact form of DESIGN.md §3; the paper's eq. (4) is its ζ ≈ 0 case.
    """

    name = 's_cc'
    size = 7
    labels = ('r_δ', 'b_x', 'b_y', 'b_z', 'ζ_x', 'ζ_y', 'ζ_z')
    names = ('r_delta', 'b_x', 'b_y', 'b_z', 'zeta_x', 'zeta_y', 'zeta_z')

    def _setup(self, desired):
        self.Vd, _ = self._frame(desired)

    @staticmethod
    def _marks(obs: Observation):
        try:
            return obs.q['P1'], obs.q[obs.second]
        except KeyError as exc:
            raise MeasurementError(f'mark {exc.args[0]} is not visible') from None

    def _frame(self, obs):
        return _V(*self._marks(obs))

    def features(self, obs):
        V, _ = self._frame(obs)
        return np.concatenate([[obs.sphere.r_delta], obs.sphere.b, log3(V @ self.Vd.T)])

    @classmethod
    def check_vector(cls, s, what='s'):
        """
        Refuse an ``s_cc = (r_δ, b, ζ)`` that no camera can measure (:class:`FeatureError`).

        ``R_DELTA_MIN ≤ r_δ < 1``, ``b`` unit (``UNIT_TOL``), ``‖ζ‖ ≤ π + THETA_TOL``
        (ζ = log(V V*ᵀ)).
        """
        s = super().check_vector(s, what)
        check_range(FeatureError, f'r_delta of {what}', s[0], R_DELTA_MIN, 1.0, hi_open=True)
        check_unit(FeatureError, f'b of {what}', s[1:4])
        check_thetau(s[4:], f'ζ of {what}')
        return s

    def depths_over_r(self, obs: Observation) -> tuple[float, float]:
        """``(‖P1‖/r, ‖P2‖/r)`` (or ``‖P3‖/r`` for the CC tip) from the image (DESIGN.md §2)."""
        q1, q2 = self._marks(obs)
        P1r = P_over_r(obs.sphere, q1)
        P2r = P3_over_r(obs.sphere, P1r, q2) if obs.kind == CC else P_over_r(obs.sphere, q2)
        return float(np.linalg.norm(P1r)), float(np.linalg.norm(P2r))

    def interaction(self, obs, r_hat, s=None):
        r_hat = check_radius(r_hat)
        sph = obs.sphere
        b, rd = sph.b, sph.r_delta
        q1, q2 = self._marks(obs)
        V, m = _V(q1, q2)
        v1, v2, v3 = V.T
        d1, d2 = self.depths_over_r(obs)
        rho1 = r_hat * d1
        alpha = ((q1 @ q2) - d1 / d2) / m
        zeta = log3(V @ self.Vd.T) if s is None else s[4:]
        J = L_omega(zeta, -1.0)
        L = np.zeros((7, 6))
        L[0, :3] = (rd * rd / r_hat) * b
        L[1:4, :3] = -(rd / r_hat) * (np.eye(3) - np.outer(b, b))
        L[1:4, 3:] = skew(b)
        A = (alpha * np.outer(v1, v3) + np.outer(v2, v3) - np.outer(v3, v2)) / rho1
        L[4:, :3] = J @ A
        L[4:, 3:] = -J
        return L


_CLASSES = {'s_n': SnFeatures, 's': STFeatures, 's_cc': SccFeatures}


def register_feature_set(name: str, cls: type) -> None:
    """
    Make ``make_feature_set(name, …)`` build ``cls`` (a :class:`FeatureSet`).

    For a baseline kept outside the paper's three sets, e.g. ``experiments/ibvs.py``.
    """
    if not (isinstance(cls, type) and issubclass(cls, FeatureSet)):
        raise TypeError(f'{cls!r} is not a FeatureSet subclass')
    _CLASSES.setdefault(name, cls)


def feature_labels(name: str) -> tuple:
    """Plot labels of the features of set ``name``."""
    return _CLASSES[name].labels


def check_feature_vector(name: str, s, what: str = 's') -> np.ndarray:
    """
    Return ``s`` as a float array if it can be a feature vector of set ``name``, else refuse.

    :class:`FeatureError` names the bound (each set's ``check_vector``); ``what`` names the
    vector ('s', 's*'). A registered set without bounds of its own checks size and finiteness.
    """
    try:
        cls = _CLASSES[name]
    except KeyError:
        raise ValueError(f'unknown feature set {name!r}: use one of {tuple(_CLASSES)}') \
            from None
    return cls.check_vector(s, what)


def feature_names(name: str) -> tuple:
    """ASCII names of the features of set ``name`` (message fields, file columns)."""
    return _CLASSES[name].names


def make_feature_set(name: str, desired: Observation) -> FeatureSet:
    """
    Build feature set ``name``: ``'s_n'``, ``'s'``, ``'s_cc'`` or a registered one.

    The set is anchored on the desired observation ``desired``.
    """
    try:
        cls = _CLASSES[name]
    except KeyError:
        raise ValueError(f'unknown feature set {name!r}: use one of {tuple(_CLASSES)}') \
            from None
    return cls(desired)
