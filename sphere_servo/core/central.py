"""
The interface of a central camera model (no ROS).

The distortion algebra the models share is :mod:`~sphere_servo.core.distortion`. A central
camera (one projection centre, DESIGN.md §1: optical frame z forward, x right,
y down) images a ray — a point ``P`` of the camera frame, at any positive scale — at the pixel

    (u, v) = (px·x_d + u0, py·y_d + v0)

where ``m_d = (x_d, y_d)`` is the *distorted normalized* point the model computes from the
ray (pinhole: ``x̄ = P/Z`` then plumb_bob; fisheye: Kannala–Brandt; unified: Mei), pixels
with (0, 0) the centre of the top-left pixel. :class:`CentralCamera` is the interface every
model offers (the frozen dataclass base of models with fields ``px, py, u0, v0, width,
height``):

- ``lift(uv)``            (N, 2) pixels → (N, 3) unit rays ``q`` on the projection sphere
- ``lift_where(uv)``      the same without refusing: NaN rays where ``ok`` is False
- ``project(P)``          (N, 3) rays or points → (N, 2) pixels
- ``project_jacobian(P)`` (N, 2, 3) ``∂(u, v)/∂P``; ``lift_jacobian(uv)`` (N, 3, 2) ``∂q/∂(u, v)``
  (``ray_jacobian(q)`` the same at rays)
- ``valid(P)``            (N,) which rays the model images; ``max_angle`` the half-angle
  of that field from the optical axis (rad); ``in_image``, ``width``, ``height``;
  ``in_view(P, margin)`` the rays imaged inside the image (never refuses)
- ``with_error(px, py, u0, v0)``  the same model with relative intrinsics errors
- ``reduction``           None, or the :class:`Reduction` (CameraInfo binning and roi) that
  made this camera's image from a calibrated one (``camera_models.reduced_camera``)

``project`` and ``lift`` refuse (:class:`GeometryError`) a ray outside the valid field or a
pixel no valid ray reaches, instead of returning a folded or extrapolated answer. The
models are radially symmetric up to tangential terms: along a radius, the distorted radius
is an increasing function of the ray's angle up to the field's edge, where the function
either ends naturally (a point at infinity, the fisheye's 180°, the unified model's limit
circle) or stops increasing (a *fold* of the distortion polynomial, beyond which the model
is not invertible). With tangential terms the field can end slightly nearer than
``max_angle`` (the radial field) in some directions; ``valid`` tells exactly.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import NamedTuple

import numpy as np

from sphere_servo.core.distortion import det2
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.types import Points2, Points3
from sphere_servo.core.validation import (Bound, check_number, check_range, check_whole, refuse,
                                          Violation)

_AXIS = np.array([0.0, 0.0, 1.0])

#: largest image side (px): the largest sensors are ~20 000 px wide; CameraInfo's uint32
#: would allow 4·10⁹, and a buffer that size cannot exist
MAX_IMAGE_SIDE = 100_000
#: focal lengths (px) relative to the image's larger side S: at 0.01 S a pinhole sees
#: ±88.9° across the image and a fisheye puts its whole 180° into 1.6 % of it; at 10⁴ S
#: the image spans 0.006°, beyond any telescope on a camera. Outside, K is corrupt.
FOCAL_RATIO_MIN, FOCAL_RATIO_MAX = 1e-2, 1e4
#: the principal point within this many image sizes of the image (a crop moves it off the
#: centre, by a fraction of the image; farther is a corrupt K)
PRINCIPAL_POINT_MARGIN = 1.0


class CameraError(GeometryError):
    """Camera parameters that no camera has, or a camera unusable for the given image."""


def image_side(name: str, value) -> int:
    """Return an image's ``width`` or ``height`` as an int, or refuse it (CameraError)."""
    return check_whole(CameraError, name, value, 1, MAX_IMAGE_SIDE,
                       f'image size must be a whole number of pixels in [1, {MAX_IMAGE_SIDE}]')


class Lifted(NamedTuple):
    """Rays of :meth:`CentralCamera.lift_where`: (N, 3) unit rays, NaN where not ``ok``."""

    rays: Points3
    ok: np.ndarray


@dataclass(frozen=True)
class Reduction:
    """
    How an image derives from the calibrated one: ``sensor_msgs/CameraInfo`` binning and roi.

    image_geometry's convention (``PinholeCameraModel``, REP 104): the calibrated image is
    ``full_width × full_height``; the published image is its ``roi = (x_offset, y_offset,
    width, height)`` decimated by ``binning_x × binning_y`` (each ≥ 1), of ``width //
    binning_x × height // binning_y`` pixels, and its pixel ``(u, v)`` is the calibrated
    image's ``(x_offset + binning_x·u, y_offset + binning_y·v)``. So its K is ``fx/bx, fy/by,
    (cx − x_offset)/bx, (cy − y_offset)/by`` and its distortion is the calibrated one (it acts
    on normalized coordinates, or on the unit sphere). That is exact for nearest-pixel
    decimation (``image_proc``'s crop_decimate by default: one pixel of each block); binning
    that averages a block centres the pixel ``(b − 1)/2`` calibrated pixels further, a
    quarter of a published pixel at 2×2, which this convention does not model.
    Built and checked by ``camera_models.camera_info_reduction``.
    """

    full_width: int
    full_height: int
    binning_x: int
    binning_y: int
    roi: tuple[int, int, int, int]

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) of the published image."""
        return self.roi[2] // self.binning_x, self.roi[3] // self.binning_y

    def to_full(self, u: float, v: float) -> tuple[float, float]:
        """Return the calibrated image's coordinates of the published image's ``(u, v)``."""
        return self.roi[0] + self.binning_x * u, self.roi[1] + self.binning_y * v

    def __str__(self) -> str:
        return (f'binning_x = {self.binning_x}, binning_y = {self.binning_y}, roi (x_offset, '
                f'y_offset, width, height) = {self.roi} of the calibrated '
                f'{self.full_width}x{self.full_height} image')


# --- the interface ---------------------------------------------------------------------------
@dataclass(frozen=True)
class CentralCamera:
    """
    Base: lift, project, their Jacobians and the field of a central camera model.

    A model implements ``_distort_rays(P, jacobian) -> (m_d, ok, J)`` (distorted normalized
    points of (N, 3) points, the valid-field mask and, if asked, ``∂m_d/∂P`` (N, 2, 3)),
    ``_undistort(m_d) -> Lifted``, ``max_angle``, ``_radial_limit() -> (radius, is_fold)``
    (the distorted radius where the field ends along a radius, and whether it ends at a
    distortion fold) and ``_has_tangential``.

    ``reduction`` (keyword only, not compared): the :class:`Reduction` that made this
    camera's image from a calibrated one, or None. It bounds the principal point by the
    calibrated image, not by a crop that may lie far from it, and names itself when the
    camera does not fit an image (``camera_models.check_camera_for_image``).
    """

    reduction: Reduction | None = field(default=None, kw_only=True, compare=False, repr=False)

    # --- pixels ↔ distorted normalized ----------------------------------------------------
    def _md(self, uv: np.ndarray) -> Points2:
        return np.column_stack([(uv[:, 0] - self.u0) / self.px, (uv[:, 1] - self.v0) / self.py])

    @property
    def K(self) -> np.ndarray:
        """3×3 matrix of the focal lengths and principal point (pixels)."""
        return np.array([[self.px, 0.0, self.u0], [0.0, self.py, self.v0], [0.0, 0.0, 1.0]])

    def in_image(self, uv: Points2, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the image, ``margin`` pixels from the border."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin))

    def with_error(self, px: float = 0.0, py: float = 0.0, u0: float = 0.0,
                   v0: float = 0.0):
        """
        Return the model with intrinsics off by *relative* errors (``px=0.35``: +35 %).

        Raises :class:`CameraError` naming the error parameter when the errors make the
        camera impossible: not finite, a focal length ``px·(1 + e) ≤ 0`` (``e ≤ −1``), or
        intrinsics outside the bounds of :meth:`_check_intrinsics`.
        """
        errors = {'px': px, 'py': py, 'u0': u0, 'v0': v0}
        for name, e in errors.items():
            e = errors[name] = check_number(CameraError, f'intrinsics error {name}', e)
            if name in ('px', 'py') and not e > -1.0:
                refuse(CameraError, f'intrinsics error {name}', e, Bound.RANGE,
                       f'> −1, so that the focal length {name}·(1 + e) stays > 0')
        try:
            return replace(self, **{n: getattr(self, n) * (1.0 + e) for n, e in errors.items()})
        except CameraError as exc:  # say which error parameter made it impossible
            v = exc.violation
            if v is None:
                raise
            named = ([v.quantity] if v.quantity in errors else
                     [n for n, e in errors.items() if e != 0.0])
            cause = ', '.join(f'{n} = {errors[n]!r}' for n in named)
            raise CameraError(Violation(f'{v.quantity} with intrinsics error {cause}',
                                        v.value, v.bound, v.limit)) from None

    # --- the parameters' bounds -----------------------------------------------------------
    def _check_intrinsics(self, coefficients: dict) -> None:
        """
        Refuse (:class:`CameraError`) intrinsics that no camera has.

        Every value finite (the distortion ``coefficients`` too, by name); the image size
        ``1 ≤ width, height ≤ MAX_IMAGE_SIDE``; focal lengths > 0 and within
        ``[FOCAL_RATIO_MIN, FOCAL_RATIO_MAX] × max(width, height)`` (so ``fx = 1e300`` is
        refused here, not left to overflow in a projection).
        """
        for name in ('px', 'py', 'u0', 'v0'):
            check_number(CameraError, name, getattr(self, name))
        for name, c in coefficients.items():
            check_number(CameraError, name, c)
        side = max(image_side(name, getattr(self, name)) for name in ('width', 'height'))
        lo, hi = FOCAL_RATIO_MIN * side, FOCAL_RATIO_MAX * side
        for name in ('px', 'py'):
            f = getattr(self, name)
            if not f > 0:
                refuse(CameraError, name, f, Bound.RANGE, 'focal lengths must be > 0')
            if not lo <= f <= hi:
                refuse(CameraError, name, f, Bound.RANGE,
                       f'focal lengths must be within [{FOCAL_RATIO_MIN:g}, '
                       f'{FOCAL_RATIO_MAX:g}] × max(width, height) = [{lo:g}, {hi:g}] px')

    def _check_principal_point(self) -> None:
        """
        Refuse a principal point farther than ``PRINCIPAL_POINT_MARGIN`` image sizes out.

        That is ``−m·W ≤ u0 ≤ (1 + m)·W`` and the same for ``v0`` with H (:class:`CameraError`),
        in the calibrated image when the camera has a ``reduction``.
        """
        m = PRINCIPAL_POINT_MARGIN
        u0, v0, W, H, where = self.u0, self.v0, self.width, self.height, ''
        red = self.reduction
        if red is not None:  # a crop far from the centre is no corrupt K
            (u0, v0), W, H = red.to_full(u0, v0), red.full_width, red.full_height
            where = ' of the calibrated image'
        for name, value, size in (('u0', u0, W), ('v0', v0, H)):
            check_range(CameraError, name + where, value, -m * size, (1.0 + m) * size)

    # --- rays ↔ pixels --------------------------------------------------------------------
    @staticmethod
    def _scaled(P: Points3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Scale rays to ``max |P_i| = 1``: a ray's scale is free, and then nothing overflows.

        Returns the scaled rays, the scales, and which rows are finite and non-zero (the
        others become the optical axis, to be refused by the caller).
        """
        s = np.abs(P).max(axis=1, initial=0.0)
        good = np.isfinite(s) & (s > 0)
        s = np.where(good, s, 1.0)
        return np.where(good[:, None], P / s[:, None], _AXIS), s, good

    def valid(self, P: Points3) -> np.ndarray:
        """Tell which rays (points, any positive scale) the model images one-to-one, (N,)."""
        Pn, _, good = self._scaled(np.asarray(P, dtype=float).reshape(-1, 3))
        return self._distort_rays(Pn, False)[1] & good

    def _refuse_outside(self, P: Points3, ok: np.ndarray) -> None:
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise GeometryError(f'{(~ok).sum()} of {len(P)} rays are outside the field of the '
                                f'{type(self).__name__} (max {math.degrees(self.max_angle):.1f}° '
                                f'from the axis), e.g. {P[i].tolist()}')

    def _projected(self, P, jacobian: bool):
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        Pn, scale, good = self._scaled(P)
        md, ok, J = self._distort_rays(Pn, jacobian)
        self._refuse_outside(P, ok & good)
        uv = np.column_stack([self.px * md[:, 0] + self.u0, self.py * md[:, 1] + self.v0])
        if not jacobian:
            return uv
        J = J / scale[:, None, None]             # proj(P) = proj(P/s): ∂/∂P = J(P/s)/s
        J[:, 0] *= self.px
        J[:, 1] *= self.py
        return uv, J

    def project(self, P: Points3) -> Points2:
        """
        Project (N, 3) rays or points of the camera optical frame to (N, 2) pixels.

        Raises :class:`GeometryError` if any ray is outside the field (:meth:`valid`).
        """
        return self._projected(P, False)

    def project_jacobian(self, P: Points3) -> np.ndarray:
        """Return ``∂(u, v)/∂P`` (N, 2, 3) at (N, 3) points (``J P = 0``: scale is free)."""
        return self._projected(P, True)[1]

    def lift_where(self, uv: Points2) -> Lifted:
        """
        Lift (N, 2) pixels to :class:`Lifted` unit rays, without refusing.

        The rays are NaN and ``ok`` False where no valid ray reaches the pixel (outside the
        image circle, beyond a fold, a NaN pixel).
        """
        md = self._md(np.asarray(uv, dtype=float).reshape(-1, 2))
        fin = np.isfinite(md).all(axis=1) & (np.abs(md).max(axis=1, initial=0.0) < 1e150)
        q, ok = self._undistort(np.where(fin[:, None], md, 0.0))
        ok &= fin
        q[~ok] = np.nan
        return Lifted(q, ok)

    def lift(self, uv: Points2) -> Points3:
        """
        Lift (N, 2) pixels to (N, 3) unit rays ``q`` on the projection sphere.

        Raises :class:`GeometryError` if a pixel is not the image of a ray in the field.
        """
        q, ok = self.lift_where(uv)
        if not ok.all():
            uv = np.asarray(uv, dtype=float).reshape(-1, 2)
            i = int(np.flatnonzero(~ok)[0])
            raise GeometryError(f'{(~ok).sum()} of {len(ok)} pixels are not the image of a ray '
                                f'in the field of the {type(self).__name__}, e.g. '
                                f'{uv[i].tolist()}')
        return q

    def lift_jacobian(self, uv: Points2) -> np.ndarray:
        """Return ``∂q/∂(u, v)`` (N, 3, 2) of :meth:`lift` (:meth:`ray_jacobian` of its rays)."""
        return self.ray_jacobian(self.lift(uv))

    def ray_jacobian(self, q: Points3) -> np.ndarray:
        """
        Return ``∂q/∂(u, v)`` (N, 3, 2) of the lift at the pixels of (N, 3) unit rays ``q``.

        ``q`` is unit and ``project(q) = uv``, so with ``J = ∂(u, v)/∂P`` at ``q`` (null
        vector ``q``) the derivative is ``Jᵀ (J Jᵀ)⁻¹``, the right inverse orthogonal to ``q``.
        Raises :class:`GeometryError` if a ray is outside the field.
        """
        J = self.project_jacobian(q)
        A = J @ J.transpose(0, 2, 1)
        d = det2(A)
        inv = np.empty_like(A)
        inv[:, 0, 0], inv[:, 1, 1] = A[:, 1, 1] / d, A[:, 0, 0] / d
        inv[:, 0, 1], inv[:, 1, 0] = -A[:, 0, 1] / d, -A[:, 1, 0] / d
        return J.transpose(0, 2, 1) @ inv

    def in_view(self, P: Points3, margin: float = 0.0) -> np.ndarray:
        """
        Tell which rays (points, any positive scale) are imaged inside the image, (N,).

        A ray in the valid field whose pixel is ``margin`` pixels inside the border; never
        refuses (a ray outside the field, behind a pinhole, NaN: False).
        """
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        ok = self.valid(P)
        out = np.zeros(len(P), bool)
        if ok.any():
            out[ok] = self.in_image(self.project(P[ok]), margin)
        return out

    # --- the field inside the image -------------------------------------------------------
    def _check_unfolded(self) -> None:
        """
        Raise :class:`CameraError` if the distortion folds inside the image.

        That is: a pixel inside the model's natural field that no valid ray reaches. Also
        refused: an image that sees no ray at all.
        """
        W, H = self.width - 0.5, self.height - 0.5
        cu = np.array([-0.5, W, W, -0.5])
        cv = np.array([-0.5, -0.5, H, H])
        far = float(np.hypot((cu - self.u0) / self.px, (cv - self.v0) / self.py).max())
        near = math.hypot((min(max(self.u0, -0.5), W) - self.u0) / self.px,
                          (min(max(self.v0, -0.5), H) - self.v0) / self.py)
        limit, is_fold = self._radial_limit()
        name = type(self).__name__
        if near >= limit:
            refuse(CameraError, f'{name} field', self, Bound.FIELD,
                   f'no pixel of the {self.width}x{self.height} image is in the field of the '
                   'model')
        if limit * max(self.px, self.py) < 1.0:
            # e.g. a unified ξ ≫ γ: its limit circle 1/√(ξ² − 1) is a fraction of a pixel
            refuse(CameraError, f'{name} field', self, Bound.FIELD,
                   f'the field of the model images into {limit * max(self.px, self.py):.3g} '
                   'px about the principal point, less than one pixel')
        if is_fold and far >= limit:
            refuse(CameraError, f'{name} distortion', self, Bound.GEOMETRY,
                   f'the distortion folds inside the image (it stops increasing at '
                   f'{math.degrees(self.max_angle):.1f}° from the axis, a distorted radius '
                   f'{limit:.4g} < {far:.4g} at the farthest corner): not invertible')
        if self._has_tangential:
            u, v = np.meshgrid(np.linspace(-0.5, W, 65), np.linspace(-0.5, H, 49))
            uv = np.column_stack([u.ravel(), v.ravel()])
            md = self._md(uv)
            inside = np.hypot(md[:, 0], md[:, 1]) < 0.99 * limit
            ok = self.lift_where(uv[inside]).ok
            bad = uv[inside][~ok][:1]
            if not bad.size:
                bad = self._tangential_fold_in_image()
            if bad.size:
                refuse(CameraError, f'{name} distortion', self, Bound.GEOMETRY,
                       'the tangential distortion folds inside the image near pixel '
                       f'{bad[0].tolist()}')

    def _tangential_fold_in_image(self, n_az: int = 360, n_theta: int = 512) -> Points2:
        """
        Return a pixel (1, 2) of the image where the field's one-to-one sheet ends, or (0, 2).

        Rays along ``n_az`` azimuths up to ``max_angle``: the first one the model does not
        image one-to-one (``det ∂m_d/∂m ≤ 0``, a fold of the tangential terms) is where the
        inner sheet ends; imaged inside the image, pixels near it have two rays (the inner
        sheet's lift succeeds there, so a grid of lifts does not see it).
        """
        # short of the field's edge, where rays leave the field by rounding, not by a fold
        th = np.linspace(0.0, self.max_angle * (1.0 - 1e-4), n_theta)[1:]
        az = np.linspace(0.0, 2.0 * math.pi, n_az, endpoint=False)
        T, A = np.meshgrid(th, az)                      # (n_az, n_theta − 1)
        P = np.stack([np.sin(T) * np.cos(A), np.sin(T) * np.sin(A), np.cos(T)], -1)
        md, ok, _ = self._distort_rays(P.reshape(-1, 3), False)
        ok = ok.reshape(T.shape)
        rows = np.flatnonzero(~ok.all(axis=1))
        first = np.argmin(ok[rows], axis=1)             # the first ray off the sheet
        md = md.reshape(*T.shape, 2)[rows, first]
        uv = np.column_stack([self.px * md[:, 0] + self.u0, self.py * md[:, 1] + self.v0])
        return uv[self.in_image(uv)][:1]
