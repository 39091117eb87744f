"""
From image measurements to the paper's geometric quantities (no ROS). DESIGN.md §2.

Inputs are in *normalized* image coordinates (``x̄ = K⁻¹ (u, v, 1)``); unit vectors
``q = x̄/‖x̄‖`` are the spherical projections (camera optical frame, z forward). The conic
algebra itself (fits, ellipses, blob moments → conic, silhouettes) is
:mod:`sphere_servo.core.conics`.

- :func:`sphere_from_conic`   conic C of the sphere's image → ``b``, ``r_δ``, ``s_n,t = b/r_δ``
- :func:`sphere_from_moments` the same from a blob's centroid and covariance
- :func:`depth_ratio`         ``‖P‖/r`` of a surface mark, eq. (11)–(12), σ = −1
- :func:`cRo_special`, :func:`cRo_cc`   partial pose ``ᶜR_o``, eqs. (8)–(14) and the CC form
- :func:`observe`             exact :class:`Observation` of a target from a pose (ground truth)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
import math

import numpy as np
import pinocchio as pin

from sphere_servo.core import linalg
# conic_from_ellipse: re-exported, its callers knew it from here
from sphere_servo.core.conics import conic_from_ellipse, conic_from_moments  # noqa: F401
from sphere_servo.core.geometry import GeometryError, normalize
from sphere_servo.core.targets import CC, mark_names, SPECIAL, Target
from sphere_servo.core.types import Mat3, Vec3


class MeasurementError(GeometryError):
    """The measurement does not define the requested quantity."""


@dataclass(frozen=True)
class SphereMeasurement:
    """
    The sphere's spherical-projection quantities.

    b          (3,) unit vector towards the centre O (dome-hat summit), camera frame.
    r_delta    ``r_δ = r/‖O‖ = sin θ`` ∈ (0, 1).
    quality    relative spread of the two "equal" eigenvalues of the conic (0 for an exact
               sphere image; grows with fitting error or a non-spherical body).
    """

    b: Vec3
    r_delta: float
    quality: float = 0.0

    @cached_property
    def s_nt(self) -> Vec3:
        """``s_n,t = b / r_δ = O / r`` (eq. 5)."""
        return self.b / self.r_delta


@dataclass(frozen=True)
class Observation:
    """
    Everything the features need from one image.

    sphere   the sphere measurement.
    q        unit vectors of the marks (camera frame), by name ('P1', 'P2' or 'P3').
    kind     'special' or 'cc': how to interpret the second mark.
    """

    sphere: SphereMeasurement
    q: dict = field(default_factory=dict)
    kind: str = SPECIAL

    @property
    def second(self) -> str:
        """Name of the second mark: 'P2' (special sphere) or 'P3' (CC tip)."""
        return mark_names(self.kind)[1]


# --- sphere ------------------------------------------------------------------------------
def sphere_from_conic(C: np.ndarray) -> SphereMeasurement:
    """
    Sphere quantities from the conic ``x̄ᵀ C x̄ = 0`` of its image (normalized coords).

    ``C ∝ b bᵀ − cos²θ I₃`` for any scale and sign (DESIGN.md §2): flip the sign so exactly
    one eigenvalue is positive; ``b`` = its eigenvector (``b_z > 0``),
    ``cos²θ = −λ₂/(λ₁ − λ₂)`` with λ₂ the mean of the two negative ones.
    Raises :class:`MeasurementError` for a conic that is not the image of a sphere in front of
    the camera (degenerate, not an ellipse, NaN).
    """
    C = np.asarray(C, dtype=float)
    if C.shape != (3, 3):
        raise MeasurementError(f'conic must be 3×3, got shape {C.shape}')
    if not math.isfinite(C.sum()):
        raise MeasurementError(f'conic contains NaN or inf: {C!r}')
    w, V = linalg.eigh(C + C.T)  # ascending eigenvalues (scale does not matter)
    w0, w1, w2 = w.tolist()
    eps = 1e-12 * max(abs(w0), abs(w2))
    if eps == 0.0:
        raise MeasurementError('degenerate conic: all zeros')
    if w2 > eps and w1 < -eps:       # one positive: b bᵀ − cos²θ I as is
        lam1, o1, o2, b = w2, w0, w1, V[:, 2].copy()  # a contiguous copy of the column
    elif w0 < -eps and w1 > eps:     # one negative: the sign is flipped
        lam1, o1, o2, b = -w0, -w1, -w2, V[:, 0].copy()
    else:
        raise MeasurementError(f'conic is not the image of a sphere (eigenvalues {w})')
    lam2 = 0.5 * (o1 + o2)
    if b[2] < 0:
        b = -b
    if b[2] <= 1e-12:
        raise MeasurementError('sphere centre is not in front of the camera')
    cos2 = -lam2 / (lam1 - lam2)
    r_delta = math.sqrt(max(0.0, 1.0 - cos2))
    if not 0.0 < r_delta < 1.0:
        raise MeasurementError(f'sphere image gives r_δ = {r_delta}, outside (0, 1)')
    quality = abs(o1 - o2) / abs(lam2)
    return SphereMeasurement(b=b, r_delta=r_delta, quality=quality)


def sphere_from_moments(centroid: np.ndarray, cov: np.ndarray) -> SphereMeasurement:
    """:func:`sphere_from_conic` of :func:`~sphere_servo.core.conics.conic_from_moments`."""
    return sphere_from_conic(conic_from_moments(centroid, cov))


# --- marks ------------------------------------------------------------------------------
def unit_ray(xy: np.ndarray) -> Vec3:
    """
    Map a normalized image point (x, y) to its unit vector ``q = x̄/‖x̄‖``.

    Raises :class:`MeasurementError` on NaN/inf (a point at infinity).
    """
    x, y = float(xy[0]), float(xy[1])
    n = math.sqrt(x * x + y * y + 1.0)
    if not math.isfinite(n):
        raise MeasurementError(f'image point contains NaN or inf: ({x}, {y})')
    return np.array([x / n, y / n, 1.0 / n])


def depth_ratio(sphere: SphereMeasurement, q: Vec3) -> float:
    """
    Compute ``‖P‖/r`` of a surface point seen along ``q`` (eq. 11–12, σ = −1).

    ``(cos φ − √(r_δ² − sin² φ)) / r_δ`` with ``cos φ = bᵀq``: the visible side. The root's
    argument is clamped at 0 (a mark measured just outside the silhouette, e.g. by noise).
    """
    cphi = float(sphere.b @ q)
    if cphi <= 0:
        raise MeasurementError('mark direction points away from the sphere')
    sin2 = max(0.0, 1.0 - cphi * cphi)
    return (cphi - math.sqrt(max(0.0, sphere.r_delta ** 2 - sin2))) / sphere.r_delta


def P_over_r(sphere: SphereMeasurement, q: Vec3) -> Vec3:
    """``P/r = (‖P‖/r) q`` for a surface mark."""
    return depth_ratio(sphere, q) * q


def P3_over_r(sphere: SphereMeasurement, P1r: Vec3, q3: Vec3) -> Vec3:
    """
    Compute ``P3/r`` of the CC tip seen along ``q3``.

    P3 lies on the tangent plane at P1, so with ``d = s_n,t − P1/r``,
    ``‖P3‖/r = (P1/r · d)/(q3 · d)`` (DESIGN.md §2).
    """
    d = sphere.s_nt - P1r
    den = float(q3 @ d)
    if abs(den) < 1e-12:
        raise MeasurementError('tangent tip ray is parallel to the tangent plane')
    rho = float(P1r @ d) / den
    if rho <= 0:
        raise MeasurementError('tangent tip would lie behind the camera')
    return rho * q3


def _unit(x: float, y: float, z: float, what: str) -> tuple[float, float, float]:
    n = math.sqrt(x * x + y * y + z * z)
    if not 1e-12 < n < math.inf:
        raise GeometryError(f'cannot normalize {what}: norm is {n}')
    return x / n, y / n, z / n


def _rot_from_r3_r2(r3: Vec3, a: Vec3) -> Mat3:
    """
    Build the rotation ``[r1 r2 r3]`` of a third axis and a second direction.

    ``r3 = n(r3)``, ``r2 = n(a − (aᵀr3) r3)``, ``r1 = r2 × r3`` (scalar arithmetic: this
    runs in every control step).
    """
    x, y, z = _unit(*r3.tolist(), 'r3')
    ax, ay, az = a.tolist()
    d = ax * x + ay * y + az * z
    u, v, w = _unit(ax - d * x, ay - d * y, az - d * z, 'r2 (marks aligned with the centre)')
    return np.array([[v * z - w * y, u, x], [w * x - u * z, v, y], [u * y - v * x, w, z]])


def cRo_special(sphere: SphereMeasurement, q1: Vec3, q2: Vec3) -> Mat3:
    """
    Partial pose of the special sphere, eqs. (8)–(14).

    ``r3 = n(s_n,t − P1/r)``, ``a = P2/r − P1/r``, ``r2 = n(a − (aᵀr3) r3)``,
    ``r1 = r2 × r3``, ``ᶜR_o = [r1 r2 r3]``.

    This *measured* frame is the rotation of a frame attached to the target (not the
    target's model frame); ``ᶜ*R_c = ᶜ*R_o ᶜR_oᵀ`` is independent of that choice.
    """
    P1r = P_over_r(sphere, q1)
    return _rot_from_r3_r2(sphere.s_nt - P1r, P_over_r(sphere, q2) - P1r)


def cRo_cc(sphere: SphereMeasurement, q1: Vec3, q3: Vec3) -> Mat3:
    """
    Partial pose of the CC target.

    ``r3 = n(s_n,t − P1/r)``, ``r2 = n(P3/r − P1/r)`` (orthogonalised against r3),
    ``r1 = r2 × r3``.
    """
    P1r = P_over_r(sphere, q1)
    return _rot_from_r3_r2(sphere.s_nt - P1r, P3_over_r(sphere, P1r, q3) - P1r)


def cRo_measured(obs: Observation) -> Mat3:
    """:func:`cRo_special` or :func:`cRo_cc` according to ``obs.kind``."""
    try:
        q1, q2 = obs.q['P1'], obs.q[obs.second]
    except KeyError as exc:
        raise MeasurementError(f'mark {exc.args[0]} is not visible') from None
    if obs.kind == CC:
        return cRo_cc(obs.sphere, q1, q2)
    return cRo_special(obs.sphere, q1, q2)


def model_cRo_offset(target: Target) -> Mat3:
    """
    Compute ``ᵒR_m``, the rotation of the measured frame in the target's model frame.

    The measured frame is built as in :func:`cRo_special` / :func:`cRo_cc` from the model
    marks, so that the measured ``ᶜR_o`` equals ``ᶜR_o(model) · ᵒR_m``.
    """
    r3 = -target.oP1 / np.linalg.norm(target.oP1)
    return _rot_from_r3_r2(r3, target.oP2 - target.oP1)


# --- ground truth ------------------------------------------------------------------------
def mark_visible(cMo: pin.SE3, target: Target, name: str) -> bool:
    """
    Tell whether mark ``name`` can be seen from ``cMo``, ignoring the image borders.

    A surface mark must face the camera; the CC tip must not be hidden by the sphere.
    """
    oP = target.marks()[name]
    cP = cMo.act(oP)
    if cP[2] <= 0:
        return False
    if target.kind == CC and name == 'P3':
        # occluded if the segment camera→P3 enters the body first
        cO = cMo.translation
        d = cP / np.linalg.norm(cP)
        bq = d @ cO
        disc = bq * bq - (cO @ cO - target.radius ** 2)
        if disc <= 0:
            return True
        t_near = bq - np.sqrt(disc)
        return not (0 < t_near < np.linalg.norm(cP))
    n_c = cMo.rotation @ target.surface_normal(oP)
    return float(n_c @ cP) < 0


def observe(cMo: pin.SE3, target: Target, require_visible: bool = True) -> Observation:
    """
    Exact observation of a *spherical* target seen from pose ``cMo`` (target in camera).

    Raises :class:`MeasurementError` if the sphere is not entirely in front of the camera or
    (with ``require_visible``) a mark is hidden.
    """
    if not target.is_sphere:
        raise MeasurementError('exact observation is defined for spherical targets only')
    cO = np.asarray(cMo.translation, dtype=float)
    dist = float(np.linalg.norm(cO))
    if dist <= target.radius * (1 + 1e-9):
        raise MeasurementError('camera is inside the sphere')
    b = cO / dist
    r_delta = target.radius / dist
    if b[2] <= r_delta:  # cone of the silhouette must be in front of the camera
        raise MeasurementError('sphere is not entirely in front of the camera')
    q = {}
    for name, oP in target.marks().items():
        if require_visible and not mark_visible(cMo, target, name):
            raise MeasurementError(f'mark {name} is hidden')
        q[name] = normalize(cMo.act(oP))
    return Observation(SphereMeasurement(b, r_delta), q, target.kind)
