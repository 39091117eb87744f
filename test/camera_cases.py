"""Camera models and ray helpers shared by the camera and small-circle tests (not a test)."""
from __future__ import annotations

import math

import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera

#: one of each model and regime: radial + tangential, fold-limited fields, 180°+ fields,
#: the unified model's limit circle (ξ > 1) inside the image
MODELS = {
    'pinhole': CameraIntrinsics(),
    'plumb_bob': CameraIntrinsics(dist=(-0.25, 0.08, 0.001, -0.0015, -0.01)),
    'fisheye': FisheyeCamera(),                                  # θ_d = θ, f = 150 px
    'fisheye_kb': FisheyeCamera(px=190.0, py=190.0, dist=(0.05, -0.01, 0.003, -0.0005)),
    'catadioptric': UnifiedCamera(xi=0.9),
    'parabolic': UnifiedCamera(xi=1.0),
    'unified_fisheye': UnifiedCamera(px=280.0, py=280.0, xi=1.6,
                                     dist=(-0.05, 0.01, 0.0005, -0.0003)),
    'unified_distorted': UnifiedCamera(xi=0.8, dist=(-0.1, 0.02, 0.001, -0.0005)),
}


def rays_at(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Return unit rays at angle θ from the optical axis and azimuth φ."""
    return np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                            np.cos(theta)])


def field_rays(cam, n: int, seed: int, edge: float = 1.0) -> np.ndarray:
    """
    Return seeded rays over the field of ``cam``.

    Uniform in area up to ``edge · max_angle``, a dense band within 1e-2 … 1e-5 of that
    edge, and the optical axis; only the valid ones (tangential terms may end the field a
    little sooner in some directions).
    """
    rng = np.random.default_rng(seed)
    tmax = edge * cam.max_angle
    theta = np.arccos(1.0 - rng.uniform(0.0, 1.0, n) * (1.0 - math.cos(tmax)))
    band = tmax * (1.0 - 10.0 ** rng.uniform(-5.0, -2.0, n // 4))
    theta = np.concatenate([[0.0], theta, band])
    q = rays_at(theta, rng.uniform(0.0, 2.0 * math.pi, len(theta)))
    ok = cam.valid(q)
    assert ok.mean() > 0.9
    return q[ok]


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the angles between rows of two ray arrays (accurate when small)."""
    c = np.cross(a, b)
    return np.arctan2(np.linalg.norm(c, axis=1), np.einsum('ij,ij->i', a, b))


def small_circle(b, theta: float, n: int, seed: int, arc=(0.0, 2.0 * math.pi)) -> np.ndarray:
    """Return ``n`` seeded unit rays on the circle ``bᵀq = cos θ``, azimuths in ``arc``."""
    b = np.asarray(b, dtype=float) / np.linalg.norm(b)
    e1 = np.cross(b, [0.3, -0.5, 0.8])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(b, e1)
    phi = np.random.default_rng(seed).uniform(arc[0], arc[1], n)
    return (math.cos(theta) * b
            + math.sin(theta) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
