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
- :func:`validated_observation`  the physical bounds a measurement from outside (a message,
  a bag) must meet before use; :func:`validated_sphere` the sphere's part
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
from sphere_servo.core.targets import CC, KINDS, mark_names, SPECIAL, Target
from sphere_servo.core.types import Mat3, Vec3
from sphere_servo.core.validation import Bound, check_range, check_unit, refuse, UNIT_TOL

#: smallest ``r_δ = r/‖O‖`` a measurement may have: a sphere 10⁹ radii away subtends 1e-9
#: rad, four orders under the finest pixel of any camera (~1e-5 rad), so no image measures
#: it; its ``s_n,t = 1/r_δ`` would exceed 1e9 (``features.S_NT_MAX``).
R_DELTA_MIN = 1e-9
#: how far (rad) a surface mark's ray may pass outside the silhouette cone: a mark is on the
#: visible cap, so its ray meets the sphere; noise and a limb-cut mark move a measured ray
#: by far less than 0.01 rad (6 px at a 600 px focal length), a wrong one by more.
LIMB_TOL = 0.01
#: half-angle (rad) of a pinhole's valid field: rays with z > 0
PINHOLE_FIELD = 0.5 * math.pi


class MeasurementError(GeometryError):
    """The measurement does not define the requested quantity, or breaks a physical bound."""


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
        """``s_n,t = b / r_δ = O / r`` (eq. 5); :class:`MeasurementError` unless 0 < r_δ < 1."""
        if not 0.0 < self.r_delta < 1.0:
            _refuse_r_delta(self.r_delta)
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
    argument is clamped at 0 (a mark measured just outside the silhouette, e.g. by noise;
    :func:`validated_observation` refuses one farther out than ``LIMB_TOL``).
    Raises :class:`MeasurementError` unless 0 < r_δ < 1 and ``cos φ > 0``.
    """
    r_delta = sphere.r_delta
    if not 0.0 < r_delta < 1.0:
        _refuse_r_delta(r_delta)
    cphi = float(sphere.b @ q)
    if not cphi > 0:
        refuse(MeasurementError, 'bᵀq of a mark', cphi, Bound.GEOMETRY,
               'bᵀq > 0: a surface mark is on the side of the sphere facing the camera')
    sin2 = max(0.0, 1.0 - cphi * cphi)
    return (cphi - math.sqrt(max(0.0, r_delta * r_delta - sin2))) / r_delta


def _refuse_r_delta(r_delta) -> None:
    refuse(MeasurementError, 'r_delta', r_delta, Bound.RANGE,
           '0 < r_delta < 1: the camera is outside the sphere')


def P_over_r(sphere: SphereMeasurement, q: Vec3) -> Vec3:
    """``P/r = (‖P‖/r) q`` for a surface mark."""
    return depth_ratio(sphere, q) * q


def P3_over_r(sphere: SphereMeasurement, P1r: Vec3, q3: Vec3) -> Vec3:
    """
    Compute ``P3/r`` of the CC tip seen along ``q3``.

    P3 lies on the tangent plane at P1, so with ``d = s_n,t − P1/r``,
    ``‖P3‖/r = (P1/r · d)/(q3 · d)`` (DESIGN.md §2).

    Raises :class:`MeasurementError` (``GEOMETRY``) where the tip's ray does not meet the
    tangent plane in front of the camera: the CC tip rule.
    """
    d = sphere.s_nt - P1r
    den = float(q3 @ d)
    if abs(den) < 1e-12:
        refuse(MeasurementError, 'P3 ray · (s_n,t − P1/r)', den, Bound.GEOMETRY,
               '|q3 · d| ≥ 1e-12: the tip ray meets the tangent plane at P1')
    rho = float(P1r @ d) / den
    if not rho > 0:
        refuse(MeasurementError, '‖P3‖/r', rho, Bound.GEOMETRY,
               '‖P3‖/r > 0: the tip, on the tangent plane at P1, is in front of the camera')
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


def observe(cMo: pin.SE3, target: Target, require_visible: bool = True,
            max_angle: float = 0.5 * math.pi) -> Observation:
    """
    Exact observation of a *spherical* target seen from pose ``cMo`` (target in camera).

    ``max_angle``: the half-angle (rad) of the camera's field about the optical axis (a
    central camera's ``max_angle``; π/2, in front of the camera, for a pinhole). Raises
    :class:`MeasurementError` if the sphere's silhouette cone is not entirely within that
    field — ``∠(b, z) + asin r_δ < max_angle``, for π/2 the same as ``b_z > r_δ`` — or (with
    ``require_visible``) a mark is hidden.
    """
    if not target.is_sphere:
        raise MeasurementError('exact observation is defined for spherical targets only')
    cO = np.asarray(cMo.translation, dtype=float)
    dist = float(np.linalg.norm(cO))
    if dist <= target.radius * (1 + 1e-9):
        raise MeasurementError('camera is inside the sphere')
    b = cO / dist
    r_delta = target.radius / dist
    if max_angle == 0.5 * math.pi:
        if b[2] <= r_delta:  # cone of the silhouette must be in front of the camera
            raise MeasurementError('sphere is not entirely in front of the camera')
    elif math.acos(max(-1.0, min(1.0, float(b[2])))) + math.asin(r_delta) >= max_angle:
        raise MeasurementError('sphere is not entirely in the camera field')
    q = {}
    for name, oP in target.marks().items():
        if require_visible and not mark_visible(cMo, target, name):
            raise MeasurementError(f'mark {name} is hidden')
        q[name] = normalize(cMo.act(oP))
    return Observation(SphereMeasurement(b, r_delta), q, target.kind)


# --- validation of a measurement from outside ----------------------------------------------
def _angle(a: Vec3, b: Vec3) -> float:
    """Angle between unit vectors (atan2 of ‖a × b‖ and aᵀb: exact near 0 and π)."""
    ax, ay, az = (float(v) for v in a)  # in floats: np.cross costs ~10 µs a call
    bx, by, bz = (float(v) for v in b)
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


def validated_sphere(sphere: SphereMeasurement, field: float = PINHOLE_FIELD,
                     unit_tol: float = UNIT_TOL) -> SphereMeasurement:
    """
    Return ``sphere`` (b as a float array) if it is physically possible, else refuse it.

    Bounds (each refused with :class:`MeasurementError`, the quantity and its value):

    - ``b`` finite, unit: ``|‖b‖ − 1| ≤ unit_tol`` (b = O/‖O‖);
    - ``R_DELTA_MIN ≤ r_δ < 1``: ``r_δ = r/‖O‖`` < 1 as the camera is outside the sphere,
      and no image resolves a sphere smaller than ``R_DELTA_MIN`` (see there);
    - the silhouette cone inside the camera's valid field of half-angle ``field`` (rad):
      ``∠(b, z) + asin(r_δ) < field``. For a pinhole (``field = π/2``) that is
      ``b_z > r_δ``; a central camera whose field exceeds 90° (a fisheye, a catadioptric)
      passes its own ``max_angle``;
    - ``quality`` finite and ≥ 0.
    """
    b = check_unit(MeasurementError, 'b', sphere.b, unit_tol)
    r_delta = check_range(MeasurementError, 'r_delta', sphere.r_delta, R_DELTA_MIN, 1.0,
                          hi_open=True)
    field = check_range(MeasurementError, 'camera field half-angle', field, 0.0, math.pi,
                        lo_open=True)
    edge = _angle(b / math.sqrt(float(b @ b)), np.array([0.0, 0.0, 1.0])) + math.asin(r_delta)
    if not edge < field:
        refuse(MeasurementError, 'silhouette edge angle ∠(b, z) + asin(r_delta)', edge,
               Bound.FIELD, f'< {field:.6g} rad, the sphere entirely in the camera field'
               + (' (pinhole: b_z > r_delta)' if field == PINHOLE_FIELD else ''))
    quality = check_range(MeasurementError, 'quality', sphere.quality, 0.0)
    return SphereMeasurement(b, r_delta, quality)


def validated_observation(obs: Observation, field: float = PINHOLE_FIELD,
                          limb_tol: float = LIMB_TOL,
                          unit_tol: float = UNIT_TOL) -> Observation:
    """
    Return ``obs`` (arrays copied) if it is physically possible, else refuse it.

    A measurement from outside (a message, a bag) passes this before use. Bounds, each
    refused with :class:`MeasurementError` naming the quantity and its value:

    - the sphere: :func:`validated_sphere` (with ``field``, ``unit_tol``);
    - ``kind`` one of ``KINDS``; mark names those of the kind ('P1', 'P2' or 'P1', 'P3');
      a missing mark is allowed (the target is then lost for the features, not invalid);
    - each mark's ray ``q`` finite and unit (``unit_tol``);
    - a surface mark (P1, P2) on the visible cap: its ray meets the sphere, i.e. its angle
      to b is at most the silhouette's ``asin(r_δ)`` plus ``limb_tol`` rad (``depth_ratio``
      clamps the small excess that noise gives; a larger one is impossible);
    - the CC tip rule (P1 and P3 both seen): the tip ray meets the tangent plane at P1 in
      front of the camera (:func:`P3_over_r`), at a point distinct from P1.
    """
    if obs.kind not in KINDS:
        refuse(MeasurementError, 'target kind', obs.kind, Bound.RANGE, f'one of {KINDS}')
    sphere = validated_sphere(obs.sphere, field, unit_tol)
    names = mark_names(obs.kind)
    limb = math.asin(sphere.r_delta) + check_range(MeasurementError, 'limb tolerance',
                                                   limb_tol, 0.0)
    q = {}
    for name, ray in obs.q.items():
        if name not in names:
            refuse(MeasurementError, 'mark name', name, Bound.RANGE,
                   f'one of {names} for a {obs.kind} target')
        q[name] = ray = check_unit(MeasurementError, f'{name} ray', ray, unit_tol)
        if name == 'P3':
            continue
        off = _angle(sphere.b, ray / math.sqrt(float(ray @ ray)))
        if off > limb:
            refuse(MeasurementError, f'angle between b and the {name} ray', off,
                   Bound.GEOMETRY, f'≤ asin(r_delta) + {limb_tol:g} = {limb:.6g} rad: a '
                   'surface mark lies on the visible cap')
    if obs.kind == CC and 'P1' in q and 'P3' in q:
        P1r = P_over_r(sphere, q['P1'])
        P3r = P3_over_r(sphere, P1r, q['P3'])
        gap = float(np.linalg.norm(P3r - P1r))
        if not gap > 1e-9:
            refuse(MeasurementError, '‖P3 − P1‖/r', gap, Bound.GEOMETRY,
                   '> 1e-9: the tip is off the sphere, at the end of the tangent stick')
    return Observation(sphere, q, obs.kind)
