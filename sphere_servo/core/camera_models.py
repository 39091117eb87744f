"""
Wide-angle central camera models and the CameraInfo factory (no ROS). DESIGN.md §1.

Each model has the interface of :class:`~sphere_servo.core.central.CentralCamera` (lift,
project, their Jacobians, the valid field, ``in_image``, ``with_error``) and a
``sensor_msgs/CameraInfo`` encoding (:meth:`to_camera_info_fields`); the pinhole + plumb_bob
model is :class:`~sphere_servo.core.camera.CameraIntrinsics`.

- :class:`FisheyeCamera`  equidistant fisheye (Kannala–Brandt, OpenCV's ``cv2.fisheye``):
  with ``θ`` the ray's angle from the optical axis and ``φ`` its azimuth,
  ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``, ``m_d = θ_d (cos φ, sin φ)``;
  ``θ = atan2(√(X² + Y²), Z)``, so rays at and beyond 90° (Z ≤ 0) are imaged too.
  CameraInfo: ``distortion_model: equidistant``, ``d = [k1, k2, k3, k4]``.
- :class:`UnifiedCamera`  unified central model (Geyer, Barreto; Mei & Rives 2007): the ray
  goes to the unit sphere, ``q = P/‖P‖``, the sphere's centre is shifted by ξ along the axis,
  ``m_u = (q_x, q_y)/(q_z + ξ)``, then Mei's radial-tangential distortion (k1 k2 p1 p2) and
  the generalised focal lengths γ1 = px, γ2 = py. ξ = 0 is a pinhole, ξ = 1 a parabolic
  mirror (paracatadioptric), ξ ≈ 0.9 a hyperbolic one or a wide fisheye, ξ > 1 a fisheye
  whose image ends at the limit circle ``‖m_u‖ = 1/√(ξ² − 1)``. Field: ``cos θ > −min(ξ, 1/ξ)``.
  CameraInfo (ROS has no standard name): ``distortion_model: unified``,
  ``d = [ξ, k1, k2, p1, p2]``, ``k = [γ1, 0, u0, 0, γ2, v0, 0, 0, 1]`` (OpenCV ``omnidir`` and
  Kalibr's ``omni`` + ``radtan`` parameters, in this order).

:func:`camera_from_camera_info_fields` builds the right model from CameraInfo fields and
refuses what it cannot honour (an unknown model, a wrong number of coefficients, skew, NaN,
a focal length ≤ 0, ξ < 0, a distortion that folds inside the image) with ``ValueError``.
With ``binning_x``, ``binning_y`` and ``roi`` it is the camera of the published image that
these derive from the calibrated one (:func:`camera_info_reduction`, image_geometry's
convention: :class:`~sphere_servo.core.central.Reduction`).
"""
from __future__ import annotations

from collections.abc import Mapping, Set as AbstractSet
from dataclasses import dataclass, field, replace
from functools import cached_property
import math

import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CameraError, CentralCamera, image_side, Lifted, Reduction
from sphere_servo.core.distortion import (det2, first_fold, odd_poly, radtan, solve_odd_poly,
                                          undistort_radtan)
from sphere_servo.core.validation import Bound, check_whole, refuse, Violation


def camera_info_fields(cam, model: str, d) -> dict:
    """Fields of a ``sensor_msgs/CameraInfo`` of ``cam`` (row-major k, r = I, p = [K | 0])."""
    K = cam.K
    P = np.hstack([K, np.zeros((3, 1))])
    return {'width': int(cam.width), 'height': int(cam.height), 'distortion_model': model,
            'd': [float(v) for v in d], 'k': [float(v) for v in K.ravel()],
            'r': [float(v) for v in np.eye(3).ravel()], 'p': [float(v) for v in P.ravel()]}


# --- equidistant fisheye (Kannala–Brandt) ---------------------------------------------------
def _theta_over_sin(theta: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``θ/sin θ`` and ``(θ/sin θ)'/sin θ = (sin θ − θ cos θ)/sin³ θ``.

    Both by their series below 0.01 rad, where the quotients cancel.
    """
    small = theta < 1e-2
    t2 = theta * theta
    with np.errstate(divide='ignore', invalid='ignore'):
        u = np.where(small, 1.0 + t2 * (1 / 6 + t2 * (7 / 360 + t2 * 31 / 15120)), theta / s)
        du = np.where(small, 1 / 3 + t2 * (2 / 15 + t2 * 2 / 63),
                      (s - theta * np.cos(theta)) / (s * s * s))
    return u, du


@dataclass(frozen=True)
class FisheyeCamera(CentralCamera):
    """
    Equidistant fisheye ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``, as ``cv2.fisheye``.

    Zero skew. Valid field: ``θ < min(π, θ_fold)``, θ_fold where θ_d stops increasing.
    The default sees 180° inside a 640×480 image's height (θ = 90° at 150·π/2 = 236 px).
    """

    px: float = 150.0
    py: float = 150.0
    u0: float = 320.0
    v0: float = 240.0
    width: int = 640
    height: int = 480
    dist: tuple = field(default=(0.0, 0.0, 0.0, 0.0))

    def __post_init__(self):
        if len(self.dist) != 4:
            raise ValueError(f'equidistant distortion needs 4 coefficients (k1..k4), got '
                             f'{len(self.dist)}')
        self._check_intrinsics({f'k{i + 1}': k for i, k in enumerate(self.dist)})
        self._check_unfolded()
        self._check_principal_point()

    _has_tangential = False

    @cached_property
    def max_angle(self) -> float:
        """Half-angle of the valid field (rad): π, or the fold of θ_d(θ) if sooner."""
        return min(math.pi, first_fold(self.dist))

    def _radial_limit(self) -> tuple[float, bool]:
        theta = self.max_angle
        return float(odd_poly(self.dist, np.array([theta]))[0][0]), theta < math.pi

    def _distort_rays(self, P: np.ndarray, jacobian: bool):
        rho = np.hypot(P[:, 0], P[:, 1])
        ok = (np.hypot(rho, P[:, 2]) > 0) & (np.arctan2(rho, P[:, 2]) < self.max_angle)
        if not ok.all():                             # the optical axis in place of the others
            P = np.where(ok[:, None], P, np.array([0.0, 0.0, 1.0]))
            rho = np.hypot(P[:, 0], P[:, 1])
        X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
        R = np.hypot(rho, Z)
        theta = np.arctan2(rho, Z)
        s = rho / R                                  # sin θ
        u, du = _theta_over_sin(theta, s)
        t2 = theta * theta
        k1, k2, k3, k4 = self.dist
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        g = u * poly                                 # θ_d / sin θ
        Pxy = P[:, :2] / R[:, None]                  # sin θ (cos φ, sin φ)
        md = g[:, None] * Pxy
        if not jacobian:
            return md, ok, None
        # m_d = g(θ) P_xy / R;  g'(θ) ∇θ = G1 (Z X, Z Y, −ρ²)/R³ with G1 = g'(θ)/sin θ
        G1 = du * poly + 2.0 * u * u * (k1 + t2 * (2 * k2 + t2 * (3 * k3 + t2 * 4 * k4)))
        q = P / R[:, None]
        J = np.zeros((len(P), 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = g / R
        J -= (g / R)[:, None, None] * Pxy[:, :, None] * q[:, None, :]
        grad = np.column_stack([Z * X, Z * Y, -rho * rho]) / (R * R * R)[:, None]
        J += (G1[:, None, None] * Pxy[:, :, None]) * grad[:, None, :]
        return md, ok, J

    def _undistort(self, md: np.ndarray) -> Lifted:
        rd = np.hypot(md[:, 0], md[:, 1])
        theta, ok = solve_odd_poly(self.dist, rd, self.max_angle)
        with np.errstate(divide='ignore', invalid='ignore'):
            w = np.where(rd > 0, np.sin(theta) / rd, 1.0)
        q = np.empty((len(md), 3))
        q[:, :2] = md * w[:, None]
        q[:, 2] = np.cos(theta)
        return Lifted(q, ok)

    def to_camera_info_fields(self) -> dict:
        """Fields of a ``sensor_msgs/CameraInfo``: ``equidistant``, ``d = [k1, k2, k3, k4]``."""
        return camera_info_fields(self, 'equidistant', self.dist)


# --- unified central model (Geyer / Barreto / Mei) -------------------------------------------
@dataclass(frozen=True)
class UnifiedCamera(CentralCamera):
    """
    Unified central model: ``m_u = (q_x, q_y)/(q_z + ξ)`` for ``q = P/‖P‖``, then Mei's rad-tan.

    ``dist = (k1, k2, p1, p2)``; ``px, py`` are the generalised focal lengths γ1, γ2. The
    default is a catadioptric camera with ξ = 0.9, whose field reaches 154° from the axis.
    """

    px: float = 300.0
    py: float = 300.0
    u0: float = 320.0
    v0: float = 240.0
    width: int = 640
    height: int = 480
    xi: float = 0.9
    dist: tuple = field(default=(0.0, 0.0, 0.0, 0.0))

    def __post_init__(self):
        if len(self.dist) != 4:
            raise ValueError(f'unified distortion needs 4 coefficients (k1 k2 p1 p2), got '
                             f'{len(self.dist)}')
        self._check_intrinsics({'xi': self.xi, **dict(zip(('k1', 'k2', 'p1', 'p2'), self.dist))})
        if self.xi < 0:
            refuse(CameraError, 'xi', self.xi, Bound.RANGE, 'the unified model needs xi >= 0')
        self._check_unfolded()
        self._check_principal_point()

    @property
    def _radtan(self) -> tuple:
        k1, k2, p1, p2 = self.dist
        return k1, k2, p1, p2, 0.0

    @property
    def _has_tangential(self) -> bool:
        return self.dist[2] != 0.0 or self.dist[3] != 0.0

    @cached_property
    def _rho_limit(self) -> float:
        """Radius of ``m_u`` where the field ends naturally: ``1/√(ξ² − 1)`` for ξ > 1."""
        if not self.xi > 1.0:
            return math.inf
        # ξ − 1 is exact near 1, and a product overflows to inf (limit 0), not an error
        return 1.0 / math.sqrt((self.xi - 1.0) * (self.xi + 1.0))

    @cached_property
    def _rho_max(self) -> float:
        """Radius of ``m_u`` where the field ends: the natural limit or the radial fold."""
        return min(self._rho_limit, first_fold(self.dist[:2]))

    @cached_property
    def _cos_min(self) -> float:
        """``cos θ`` at the natural edge of the field: ``−min(ξ, 1/ξ)``."""
        return -min(self.xi, 1.0 / self.xi) if self.xi > 0 else 0.0

    @cached_property
    def max_angle(self) -> float:
        """Half-angle of the valid field (rad): ``acos(−min(ξ, 1/ξ))`` or the radial fold."""
        if math.isinf(self._rho_max) or self._rho_max == self._rho_limit:
            return math.acos(self._cos_min)
        q = self._mei_lift(np.array([[self._rho_max, 0.0]]))
        return math.atan2(q[0, 0], q[0, 2])

    def _radial_limit(self) -> tuple[float, bool]:
        rho = self._rho_max
        if math.isinf(rho):
            return math.inf, False
        return float(odd_poly(self.dist[:2], np.array([rho]))[0][0]), rho < self._rho_limit

    def _distort_rays(self, P: np.ndarray, jacobian: bool):
        R = np.sqrt(np.einsum('ij,ij->i', P, P))
        Z = P[:, 2]
        ok = (R > 0) & (Z > (self._cos_min + 1e-12) * R)
        R = np.where(ok, R, 1.0)
        xi = self.xi
        with np.errstate(divide='ignore', invalid='ignore'):  # ‖P‖ (q_z + ξ), no cancellation
            d = np.where(Z >= 0, Z + xi * R,                  # for Z < 0 (exact for ξ = 1)
                         (xi * xi * np.einsum('ij,ij->i', P[:, :2], P[:, :2])
                          + (xi * xi - 1.0) * Z * Z) / (xi * R - Z))
        d = np.where(ok, d, 1.0)
        m = P[:, :2] / d[:, None]
        md, D = radtan(m, *self._radtan)
        if math.isfinite(self._rho_max) or self._has_tangential:
            ok &= (np.hypot(m[:, 0], m[:, 1]) < self._rho_max) & (det2(D) > 0)
        if not jacobian:
            return md, ok, None
        # ∂m/∂P = [I₂ | 0]/d − m ∇dᵀ/d,  ∇d = e_z + ξ P/R
        grad = self.xi * P / R[:, None]
        grad[:, 2] += 1.0
        J = -(m / d[:, None])[:, :, None] * grad[:, None, :]
        J[:, 0, 0] += 1.0 / d
        J[:, 1, 1] += 1.0 / d
        return md, ok, D @ J

    def _mei_lift(self, m: np.ndarray) -> np.ndarray:
        """
        Lift undistorted ``m_u`` to the unit sphere (Mei's inverse of the ξ projection).

        With ``ρ² = ‖m_u‖²``, ``λ = (ξ + √(1 + (1 − ξ²) ρ²))/(1 + ρ²)``,
        ``q = (λ m_u, λ − ξ)``; ``λ − ξ`` is evaluated as ``(1 − ξ² ρ²)/(√(…) + ξ ρ²)``,
        which does not cancel.
        """
        xi = self.xi
        r2 = np.einsum('ij,ij->i', m, m)
        root = np.sqrt(np.maximum(1.0 + (1.0 - xi * xi) * r2, 0.0))
        lam = (xi + root) / (1.0 + r2)
        q = np.empty((len(m), 3))
        q[:, :2] = m * lam[:, None]
        q[:, 2] = (1.0 - xi * xi * r2) / (root + xi * r2)
        return q

    def _undistort(self, md: np.ndarray) -> Lifted:
        m, ok = undistort_radtan(md, self._radtan, self._rho_max)
        return Lifted(self._mei_lift(m), ok)

    def to_camera_info_fields(self) -> dict:
        """Fields of a ``sensor_msgs/CameraInfo``: ``unified``, ``d = [ξ, k1, k2, p1, p2]``."""
        return camera_info_fields(self, 'unified', (self.xi, *self.dist))


# --- sensor_msgs/CameraInfo → model ----------------------------------------------------------
MODELS = ('plumb_bob', 'equidistant', 'unified')


def camera_from_camera_info_fields(width, height, k, d=(), distortion_model: str = 'plumb_bob',
                                   r=None, p=None, *, binning_x=0, binning_y=0, roi=None):
    """
    Build the camera model of ``sensor_msgs/CameraInfo`` fields.

    The inverse of every model's ``to_camera_info_fields``: :class:`CameraIntrinsics` for
    ``plumb_bob`` (5 d), :class:`FisheyeCamera` for ``equidistant`` (4 d),
    :class:`UnifiedCamera` for ``unified`` (5 d: ξ, k1, k2, p1, p2). An empty ``d`` with
    ``plumb_bob``, ``equidistant`` or an empty model name means no distortion. ``r`` and
    ``p`` (rectification, stereo projection) do not change how a raw image is lifted and are
    not used. ``binning_x``, ``binning_y`` and ``roi`` = (x_offset, y_offset, width,
    height) (defaults: none) make it the camera of the reduced image
    (:func:`camera_info_reduction`, :func:`reduced_camera`): the calibrated camera is built
    and checked over its whole image, then reduced.

    Raises :class:`~sphere_servo.core.central.CameraError` (a ``ValueError``) for an unknown
    model, a wrong number of coefficients, a K with skew or not of the form
    ``[fx 0 cx; 0 fy cy; 0 0 1]``, non-finite or impossible values (a focal length ≤ 0 or out
    of its physical range, a principal point far outside the image, ξ < 0; see
    ``CentralCamera._check_intrinsics``) and a distortion that folds inside the image.
    """
    reduction = camera_info_reduction(width, height, binning_x, binning_y, roi)
    return reduced_camera(_calibrated_camera(width, height, k, d, distortion_model), reduction)


def _calibrated_camera(width, height, k, d, distortion_model):
    k = np.asarray(k, dtype=float).ravel()
    if k.size != 9:
        refuse(CameraError, 'CameraInfo.k', k.tolist(), Bound.SHAPE,
               f'CameraInfo.k must have 9 entries (9 finite ones), got {k.size}')
    if not np.all(np.isfinite(k)):
        refuse(CameraError, 'CameraInfo.k', k.tolist(), Bound.FINITE,
               'CameraInfo.k must be 9 finite entries')
    if not np.any(k):  # what a camera driver publishes before a calibration
        refuse(CameraError, 'px', 0.0, Bound.RANGE,
               'focal lengths must be > 0 (a K of zeros: the camera is not calibrated)')
    for name, f in (('px', k[0]), ('py', k[4])):  # before the form
        if not f > 0.0:
            refuse(CameraError, name, float(f), Bound.RANGE, 'focal lengths must be > 0')
    if k[1] != 0.0 or k[3] != 0.0 or k[6] != 0.0 or k[7] != 0.0 or k[8] != 1.0:
        refuse(CameraError, 'CameraInfo.k', k.tolist(), Bound.UNSUPPORTED,
               'CameraInfo.k must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)')
    d = [float(v) for v in (d if d is not None else ())]
    model = distortion_model or ('plumb_bob' if not d else None)
    n = {'plumb_bob': 5, 'equidistant': 4, 'unified': 5}.get(model)
    if n is None:
        refuse(CameraError, 'distortion_model', f'{distortion_model!r} with {len(d)} '
               'coefficients', Bound.UNSUPPORTED,
               f'unsupported distortion_model; supported: {", ".join(MODELS)}')
    if not d and model != 'unified':
        d = [0.0] * n
    if len(d) != n:
        refuse(CameraError, 'CameraInfo.d', d, Bound.SHAPE,
               f'distortion_model {model!r} needs {n} coefficients in d')
    kw = {'px': float(k[0]), 'py': float(k[4]), 'u0': float(k[2]), 'v0': float(k[5]),
          'width': image_side('width', width), 'height': image_side('height', height)}
    if model == 'equidistant':
        return FisheyeCamera(**kw, dist=tuple(d))
    if model == 'unified':
        return UnifiedCamera(**kw, xi=d[0], dist=tuple(d[1:]))
    cam = CameraIntrinsics(**kw, dist=tuple(d))
    cam._check_unfolded()
    return cam


def camera_info_reduction(width, height, binning_x=0, binning_y=0, roi=None
                          ) -> Reduction | None:
    """
    Return how CameraInfo ``binning_x``, ``binning_y`` and ``roi`` reduce the calibrated image.

    image_geometry's rules: a binning of 0 means 1; an ``roi`` = (x_offset, y_offset, width,
    height) of zero width and height (all zeros, the default, or None) is the full image
    ``(0, 0, width, height)``. None when the published image is the calibrated one. The
    ``roi``'s ``do_rectify`` is not taken: this package lifts the raw pixels through the
    distortion model, and a raw roi is the same in both cases. Refused
    (:class:`~sphere_servo.core.central.CameraError`, naming the fields and their values):
    a binning or an roi entry that is not a whole number ≥ 0, an roi that is no sequence of
    4 (a set or a dict: their order is no field order), a binning larger than the
    image, an roi of zero width but not zero height (or the reverse), one of zero size at an
    offset (image_geometry's full image is all four zero), an roi that leaves the
    calibrated ``width × height`` image, and a published image of no pixel.
    """
    bx = check_whole(CameraError, 'CameraInfo.binning_x', binning_x, 0) or 1
    by = check_whole(CameraError, 'CameraInfo.binning_y', binning_y, 0) or 1
    if roi is None:
        roi = (0, 0, 0, 0)
    try:   # a set's or a dict's order is no field order: (x, y, w, h) of a set is any
        values = None if isinstance(roi, (AbstractSet, Mapping)) else list(roi)
    except TypeError:
        values = None
    if values is None or len(values) != 4:
        refuse(CameraError, 'CameraInfo.roi', roi, Bound.SHAPE,
               '4 whole numbers (x_offset, y_offset, width, height)')
    roi = tuple(check_whole(CameraError, f'CameraInfo.roi.{n}', v, 0)
                for n, v in zip(('x_offset', 'y_offset', 'width', 'height'), values))
    if roi[2] == roi[3] == 0 and roi[:2] != (0, 0):
        # image_geometry takes only all four zero as the full image: this is an roi of no
        # pixel, at an offset
        refuse(CameraError, 'CameraInfo.roi (x_offset, y_offset, width, height)', roi,
               Bound.GEOMETRY, 'all four 0 (the full image) or a width and height > 0')
    if bx == by == 1 and roi[2] == roi[3] == 0:
        return None
    W, H = image_side('width', width), image_side('height', height)
    x, y, w, h = roi
    if w == h == 0:  # RegionOfInterest.msg: a size of (0, 0) is the full resolution
        x, y, w, h = roi = (0, 0, W, H)
    if (w == 0) != (h == 0):
        refuse(CameraError, 'CameraInfo.roi (x_offset, y_offset, width, height)', roi,
               Bound.GEOMETRY, 'roi.width and roi.height are both 0 (the full image) or '
               'both > 0')
    for a, n, off, size, full in (('x', 'width', x, w, W), ('y', 'height', y, h, H)):
        if off + size > full:
            refuse(CameraError, f'CameraInfo.roi.{a}_offset + roi.{n}',
                   f'{off} + {size} = {off + size}', Bound.RANGE,
                   f'≤ {n} = {full}: the roi must lie inside the calibrated {W}x{H} image')
    check_whole(CameraError, 'CameraInfo.binning_x', bx, 1, W, f'≤ width = {W}')
    check_whole(CameraError, 'CameraInfo.binning_y', by, 1, H, f'≤ height = {H}')
    red = Reduction(W, H, bx, by, roi)
    if 0 in red.size:
        refuse(CameraError, 'reduced image size', f'{red.size[0]}x{red.size[1]}', Bound.RANGE,
               f'at least 1x1: roi.width // binning_x = {w} // {bx} = {w // bx}, '
               f'roi.height // binning_y = {h} // {by} = {h // by}')
    return None if red.size == (W, H) else red


def reduced_camera(camera, reduction: Reduction | None):
    """
    Return ``camera`` (of the calibrated image) made the camera of the reduced image.

    The same model, distortion and field, with the K of
    :class:`~sphere_servo.core.central.Reduction` and its size; ``camera`` itself when
    ``reduction`` is None. CameraError if no camera has the reduced intrinsics, by the
    bounds every camera has (``CentralCamera._check_intrinsics``, the model's field), whose
    violation then names the binning that divided a refused focal length, and the binning
    and roi that made the reduced image (a 1×96 binning of a 640×480 camera with fy = 610
    leaves a 640×5 image whose fy = 610/96 = 6.35 px is under 0.01 × 640: refused naming
    binning_y, not a focal length the camera_info never had).
    """
    if reduction is None:
        return camera
    (x, y, _, _), bx, by = reduction.roi, reduction.binning_x, reduction.binning_y
    w, h = reduction.size
    try:
        return replace(camera, px=camera.px / bx, py=camera.py / by, u0=(camera.u0 - x) / bx,
                       v0=(camera.v0 - y) / by, width=w, height=h, reduction=reduction)
    except CameraError as exc:
        if exc.violation is None:
            raise
        raise CameraError(_reduced_violation(exc.violation, camera, reduction)) from None


#: a focal length of the reduced camera → its CameraInfo name and the binning dividing it
_BINNED = {'px': ('fx', 'binning_x'), 'py': ('fy', 'binning_y')}


def _reduced_violation(v: Violation, camera, red: Reduction) -> Violation:
    """Return ``v`` (of the reduced camera) naming the binning and roi that made its value."""
    quantity = v.quantity
    if quantity in _BINNED:  # e.g. 'py = fy / binning_y = 610.0 / 96'
        f, binning = _BINNED[quantity]
        quantity = (f'{quantity} = {f} / {binning} = {getattr(camera, quantity)!r} / '
                    f'{getattr(red, binning)}')
    return Violation(quantity, v.value, v.bound, f"{v.limit}; the camera_info's {red} leave a "
                     f'{red.size[0]}x{red.size[1]} image')


def calibrated_camera(camera):
    """
    Return the camera of the calibrated image that ``camera``'s reduction was made from.

    The inverse of :func:`reduced_camera` (``camera`` itself when it has no reduction): the
    camera a CameraInfo's own fields describe, before its binning and roi.
    """
    red = camera.reduction
    if red is None:
        return camera
    u0, v0 = red.to_full(camera.u0, camera.v0)
    return replace(camera, px=camera.px * red.binning_x, py=camera.py * red.binning_y, u0=u0,
                   v0=v0, width=red.full_width, height=red.full_height, reduction=None)


def check_camera_for_image(camera, width: int, height: int, applies_distortion: bool):
    """
    Return ``camera`` if it is the camera of an image of ``width × height`` pixels, else refuse.

    :class:`~sphere_servo.core.central.CameraError` when

    - the camera's size differs from the image's (both sizes named, and the CameraInfo
      binning and roi that made the camera's size, if any): its K belongs to another
      resolution or another camera;
    - ``applies_distortion`` is False (the consumer uses K only, e.g. the conic of the
      silhouette in the normalized plane) and the camera is not a distortion-free pinhole: a
      consumer that ignored a model or its coefficients would measure a wrong sphere, with
      no sign of it. A consumer that lifts pixels through the model (``lift``, which every
      model's distortion enters) passes True.

    The intrinsics themselves were checked when the camera was built.
    """
    if (int(camera.width), int(camera.height)) != (int(width), int(height)):
        red = getattr(camera, 'reduction', None)
        refuse(CameraError, 'camera size', f'{int(camera.width)}x{int(camera.height)}',
               Bound.MISMATCH, f'the size of the image, {int(width)}x{int(height)}'
               + ('' if red is None else f" (the camera size comes from the camera_info's "
                  f'{red})'))
    if not applies_distortion:
        if not isinstance(camera, CameraIntrinsics):
            refuse(CameraError, 'camera model', type(camera).__name__, Bound.UNSUPPORTED,
                   'a pinhole: this consumer uses K only and would ignore the model')
        if camera.has_distortion:
            refuse(CameraError, 'plumb_bob distortion d', list(camera.dist),
                   Bound.UNSUPPORTED, 'zero: this consumer uses K only and would ignore it')
    return camera
