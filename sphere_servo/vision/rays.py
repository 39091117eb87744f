"""
The rays of a camera's pixels (no ROS): what the renderer casts and the detector lifts.

A central camera (:mod:`~sphere_servo.core.central`) maps each pixel ``(u, v)`` to a unit
ray ``q`` of its projection sphere (DESIGN.md §1: z forward, x right, y down). Lifting every
pixel of a 640×480 image costs 30–150 ms depending on the model, so the table is computed
once per camera (:func:`pixel_rays`, cached on the camera's value: a camera rebuilt from the
same ``camera_info`` finds it).

:class:`PixelRays` holds, per pixel centre (integer ``u, v``): the ray, whether a valid ray
reaches it (outside a model's image circle, none), the derivatives ``∂q/∂u``, ``∂q/∂v``
(a sub-pixel ray to first order, for anti-aliasing) and the pixel's solid angle
``‖∂q/∂u × ∂q/∂v‖`` (sr: the surface a pixel sees, for area-weighted means on the sphere).
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math

import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CentralCamera

#: cameras whose tables are kept (a detector, a renderer and a study's few cameras)
CACHED_CAMERAS = 6


@dataclass(frozen=True, eq=False)
class PixelRays:
    """
    The lift of every pixel centre of a camera, (H, W) arrays.

    x, y, z    float32 components of the unit rays (NaN where not ``valid``).
    valid      bool: a valid ray reaches the pixel centre.
    du, dv     (3, H, W) float32 ``∂q/∂u``, ``∂q/∂v`` (0 where not valid).
    solid      float32 solid angle of the pixel (sr; 0 where not valid).
    rim        bool: valid pixels with an invalid 4-neighbour (the image circle's edge),
               where a sub-pixel ray is not the first-order one of the pixel centre.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    valid: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    solid: np.ndarray
    rim: np.ndarray

    def rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(3, N) float64 rays of the integer pixels ``(u, v)`` (NaN where not valid)."""
        return np.stack([self.x[v, u], self.y[v, u], self.z[v, u]]).astype(np.float64)


def _compute(camera: CentralCamera) -> PixelRays:
    W, H = int(camera.width), int(camera.height)
    v, u = np.mgrid[0:H, 0:W]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    q, ok = camera.lift_where(uv)
    du = np.zeros((3, H * W), np.float32)
    dv = np.zeros((3, H * W), np.float32)
    solid = np.zeros(H * W, np.float32)
    if ok.any():
        J = camera.ray_jacobian(q[ok])                     # (n, 3, 2)
        du[:, ok], dv[:, ok] = J[:, :, 0].T, J[:, :, 1].T
        solid[ok] = np.linalg.norm(np.cross(J[:, :, 0], J[:, :, 1]), axis=1)
    valid = ok.reshape(H, W)
    bad = ~valid
    near_bad = np.zeros_like(bad)
    near_bad[1:] |= bad[:-1]
    near_bad[:-1] |= bad[1:]
    near_bad[:, 1:] |= bad[:, :-1]
    near_bad[:, :-1] |= bad[:, 1:]
    q32 = q.astype(np.float32).T.reshape(3, H, W)
    tables = [np.ascontiguousarray(c) for c in q32]
    for a in (*tables, du, dv, solid):
        a.setflags(write=False)
    return PixelRays(*tables, valid, du.reshape(3, H, W), dv.reshape(3, H, W),
                     solid.reshape(H, W), valid & near_bad)


@functools.lru_cache(maxsize=CACHED_CAMERAS)
def pixel_rays(camera: CentralCamera) -> PixelRays:
    """Return the :class:`PixelRays` of ``camera`` (computed once per camera value)."""
    return _compute(camera)


# --- what the detector lifts: pixels → rays, through K or through a camera model -------------
class PinholeLift:
    """
    Pixels ↔ rays of a pinhole without distortion, by ``K`` alone (the conic path's camera).

    ``px, py, u0, v0``: the intrinsics the detector is given (possibly wrong).
    """

    lifted = False

    def __init__(self, px: float, py: float, u0: float, v0: float):
        self.px, self.py, self.u0, self.v0 = px, py, u0, v0

    def pixels(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the (3, N) unit rays of pixels ``(u, v)`` and their solid angles (N,).

        ``q = x̄/‖x̄‖``, ``x̄ = K⁻¹ (u, v, 1)``; a pixel's solid angle is
        ``1/(px py ‖x̄‖³)``.
        """
        q = np.empty((3, len(u)))
        q[0] = (u - self.u0) * (1.0 / self.px)
        q[1] = (v - self.v0) * (1.0 / self.py)
        q[2] = 1.0
        k = np.sqrt(q[0] * q[0] + q[1] * q[1] + 1.0)
        np.divide(1.0, k, out=k)
        q *= k
        k *= k * k
        k *= 1.0 / (self.px * self.py)
        return q, k

    def project(self, q: np.ndarray) -> np.ndarray | None:
        """Return the pixel (2,) of a unit ray, None if it is not in front of the camera."""
        if not q[2] > 1e-12:
            return None
        return np.array([self.px * q[0] / q[2] + self.u0, self.py * q[1] / q[2] + self.v0])


class ModelLift:
    """
    Pixels ↔ rays through a camera model (any :class:`~sphere_servo.core.central.CentralCamera`).

    Integer pixels from the camera's table (:func:`pixel_rays`), sub-pixel ones by the
    model's lift.
    """

    lifted = True

    def __init__(self, camera: CentralCamera):
        self.camera = camera
        self.table = pixel_rays(camera)

    def pixels(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the (3, N) rays of integer pixels ``(u, v)`` and their solid angles (N,)."""
        u, v = np.asarray(u, np.intp), np.asarray(v, np.intp)
        return self.table.rays(u, v), self.table.solid[v, u].astype(np.float64)

    def lift(self, uv: np.ndarray):
        """:meth:`~sphere_servo.core.central.CentralCamera.lift_where` of (N, 2) pixels."""
        return self.camera.lift_where(uv)

    def project(self, q: np.ndarray) -> np.ndarray | None:
        """Return the pixel (2,) of a unit ray, None if it is outside the model's field."""
        q = np.asarray(q, float).reshape(1, 3)
        if not self.camera.valid(q)[0]:
            return None
        return self.camera.project(q)[0]


def camera_intrinsics(camera) -> tuple[float, float, float, float]:
    """``(px, py, u0, v0)`` of anything with those attributes; ``ValueError`` if unusable."""
    vals = []
    for name in ('px', 'py', 'u0', 'v0'):
        try:
            v = float(getattr(camera, name))
        except (AttributeError, TypeError, ValueError):
            raise ValueError(f'camera intrinsics lack a numeric {name!r}') from None
        vals.append(v)
    if not all(map(math.isfinite, vals)):
        raise ValueError(f'camera intrinsics must be finite, got px, py, u0, v0 = {vals}')
    if vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f'focal lengths must be > 0, got px={vals[0]}, py={vals[1]}')
    return tuple(vals)


def lift_of(camera, conic_path: bool = True) -> PinholeLift | ModelLift:
    """
    Return how the detector lifts pixels of ``camera``.

    A :class:`~sphere_servo.core.central.CentralCamera` with a distortion or another model
    than the pinhole: through the model; else (a distortion-free pinhole, or anything with
    finite ``px, py, u0, v0``, :func:`camera_intrinsics`) by ``K`` — unless
    ``conic_path`` is False: then a pinhole camera is lifted through its model too.
    """
    if isinstance(camera, CentralCamera) and (
            not conic_path or not (isinstance(camera, CameraIntrinsics)
                                   and not camera.has_distortion)):
        return ModelLift(camera)
    return PinholeLift(*camera_intrinsics(camera))
