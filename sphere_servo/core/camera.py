"""
Pinhole camera model (no ROS).

Pixel ``(u, v)`` ↔ normalized image point ``x̄ = (x, y, 1) = K⁻¹ (u, v, 1)`` (DESIGN.md §1),
with ``K = [[px, 0, u0], [0, py, v0], [0, 0, 1]]``. Optional plumb_bob distortion
``(k1, k2, t1, t2, k3)`` as in ``sensor_msgs/CameraInfo``: ``distort`` maps an ideal
normalized point to the distorted one, ``undistort`` inverts it iteratively.

The controller may be given *wrong* intrinsics while the renderer keeps the true ones
(the paper's calibration-error experiment): see :meth:`CameraIntrinsics.with_error`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
import math

import numpy as np

from sphere_servo.core.central import CameraError, CentralCamera, image_side, Lifted
from sphere_servo.core.distortion import det2, first_fold, odd_poly, radtan, undistort_radtan
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.types import Points2
from sphere_servo.core.validation import Bound, Violation


@dataclass(frozen=True)
class CameraIntrinsics(CentralCamera):
    """Intrinsics of a pinhole camera; pixels, with (0, 0) the centre of the top-left pixel."""

    px: float = 600.0
    py: float = 600.0
    u0: float = 320.0
    v0: float = 240.0
    width: int = 640
    height: int = 480
    dist: tuple = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self):
        """Refuse impossible intrinsics (:meth:`CentralCamera._check_intrinsics`)."""
        self._check_intrinsics(dict(zip(('k1', 'k2', 't1', 't2', 'k3'), self.dist)))
        if len(self.dist) != 5:
            raise CameraError(Violation('plumb_bob distortion d', list(self.dist), Bound.SHAPE,
                                        'plumb_bob distortion needs 5 coefficients'))
        self._check_principal_point()

    @property
    def K(self) -> np.ndarray:
        """3×3 intrinsic matrix."""
        return np.array([[self.px, 0.0, self.u0], [0.0, self.py, self.v0], [0.0, 0.0, 1.0]])

    @property
    def K_inv(self) -> np.ndarray:
        """3×3 inverse intrinsic matrix."""
        return np.array([[1.0 / self.px, 0.0, -self.u0 / self.px],
                         [0.0, 1.0 / self.py, -self.v0 / self.py],
                         [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    # --- projections --------------------------------------------------------------------
    def pixel_to_normalized(self, uv: Points2) -> Points2:
        """(N, 2) pixels → (N, 2) normalized ``(x, y)`` (undistorted if the model has it)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        xy = np.column_stack([(uv[:, 0] - self.u0) / self.px, (uv[:, 1] - self.v0) / self.py])
        return self.undistort(xy) if self.has_distortion else xy

    def normalized_to_pixel(self, xy: Points2) -> Points2:
        """(N, 2) normalized ``(x, y)`` → (N, 2) pixels (distorted if the model has it)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.has_distortion:
            xy = self.distort(xy)
        return np.column_stack([self.px * xy[:, 0] + self.u0, self.py * xy[:, 1] + self.v0])

    def project(self, cP: np.ndarray) -> Points2:
        """
        (N, 3) points in the camera optical frame → (N, 2) pixels.

        Points with z ≤ 0 are behind the camera and raise :class:`GeometryError`.
        """
        cP = np.asarray(cP, dtype=float).reshape(-1, 3)
        if np.any(cP[:, 2] <= 1e-12):
            raise GeometryError('cannot project a point at or behind the camera centre')
        if self.dist != self._NO_DISTORTION:  # refuse a ray beyond the distortion's fold
            self._refuse_outside(cP, self.valid(cP))
        return self.normalized_to_pixel(cP[:, :2] / cP[:, 2:3])

    def in_image(self, uv: Points2, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the image, ``margin`` pixels from the border."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin))

    def distort(self, xy: Points2) -> Points2:
        """plumb_bob: ideal normalized → distorted normalized."""
        k1, k2, t1, t2, k3 = self.dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xd = x * radial + 2 * t1 * x * y + t2 * (r2 + 2 * x * x)
        yd = y * radial + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
        return np.column_stack([xd, yd])

    def undistort(self, xy_d: Points2, iterations: int = 20) -> Points2:
        """Inverse of :meth:`distort` by fixed-point iteration (as OpenCV does)."""
        k1, k2, t1, t2, k3 = self.dist
        x, y = xy_d[:, 0].copy(), xy_d[:, 1].copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
            dx = 2 * t1 * x * y + t2 * (r2 + 2 * x * x)
            dy = t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
            x = (xy_d[:, 0] - dx) / radial
            y = (xy_d[:, 1] - dy) / radial
        return np.column_stack([x, y])

    # --- sensor_msgs/CameraInfo-shaped dict ---------------------------------------------
    def to_camera_info_fields(self) -> dict:
        """Fields of a ``sensor_msgs/CameraInfo`` (row-major k, p, r; plumb_bob d)."""
        K = self.K
        P = np.hstack([K, np.zeros((3, 1))])
        return {'width': int(self.width), 'height': int(self.height),
                'distortion_model': 'plumb_bob', 'd': [float(d) for d in self.dist],
                'k': [float(v) for v in K.ravel()], 'r': [float(v) for v in np.eye(3).ravel()],
                'p': [float(v) for v in P.ravel()]}

    @classmethod
    def from_camera_info_fields(cls, width, height, k, d=None) -> 'CameraIntrinsics':
        """Inverse of :meth:`to_camera_info_fields`; raises ``ValueError`` on bad values."""
        k = np.asarray(k, dtype=float).ravel()
        if k.size != 9:
            raise ValueError(f'CameraInfo.k must have 9 entries, got {k.size}')
        dist = tuple(float(v) for v in (d if d is not None and len(d) else [0.0] * 5))
        if len(dist) < 5:
            dist = dist + (0.0,) * (5 - len(dist))
        return cls(px=k[0], py=k[4], u0=k[2], v0=k[5], width=image_side('width', width),
                   height=image_side('height', height), dist=dist[:5])

    # --- the central-camera interface (core/central.py): lift, project, Jacobians, field --
    _NO_DISTORTION = (0.0,) * 5

    @cached_property
    def _fold(self) -> float:
        """Return the undistorted radius where plumb_bob's radial part stops increasing."""
        k1, k2, _, _, k3 = self.dist
        return first_fold((k1, k2, k3))

    @property
    def _has_tangential(self) -> bool:
        return self.dist[2] != 0.0 or self.dist[3] != 0.0

    @property
    def max_angle(self) -> float:
        """Return the half-angle of the valid field (rad): 90°, less if the distortion folds."""
        return math.atan(self._fold)

    def _radial_limit(self) -> tuple[float, bool]:
        if math.isinf(self._fold):
            return math.inf, False
        k1, k2, _, _, k3 = self.dist
        return float(odd_poly((k1, k2, k3), np.array([self._fold]))[0][0]), True

    def _distort_rays(self, P: np.ndarray, jacobian: bool):
        """Distort ``x̄ = (X/Z, Y/Z)`` by plumb_bob; valid for ``Z > 0`` inside the fold."""
        Z = P[:, 2]
        ok = Z > 1e-12 * np.sqrt(np.einsum('ij,ij->i', P, P))
        iz = 1.0 / np.where(ok, Z, 1.0)
        m = P[:, :2] * iz[:, None]
        if self.has_distortion:
            md, D = radtan(m, *self.dist)
            ok &= (np.einsum('ij,ij->i', m, m) < self._fold ** 2) & (det2(D) > 0)
        else:
            md, D = m, None
        if not jacobian:
            return md, ok, None
        J = np.zeros((len(P), 2, 3))                 # ∂x̄/∂P
        J[:, 0, 0] = J[:, 1, 1] = iz
        J[:, :, 2] = -m * iz[:, None]
        return md, ok, (J if D is None else D @ J)

    def _undistort(self, md: np.ndarray) -> Lifted:
        if self.has_distortion:
            m, ok = undistort_radtan(md, self.dist, self._fold)
        else:
            m, ok = md, np.isfinite(md).all(axis=1)
        q = np.empty((len(m), 3))
        q[:, :2] = m
        q[:, 2] = 1.0
        q /= np.sqrt(np.einsum('ij,ij->i', q, q))[:, None]
        return Lifted(q, ok)
