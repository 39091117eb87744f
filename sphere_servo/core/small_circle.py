"""
The sphere measured on the projection sphere: a small-circle fit to lifted edge rays.

For any central camera (DESIGN.md §2), the occluding contour of the sphere S(O, r) seen from
the projection centre is the cone of the unit rays ``q`` with ``bᵀq = cos θ``, ``b = O/‖O‖``,
``sin θ = r_δ = r/‖O‖``: a small circle of the projection sphere, the dome's base. Lifting
the silhouette's edge pixels through the camera model (``CentralCamera.lift``) and fitting
that circle gives ``b`` and ``r_δ`` whatever the camera; on a pinhole camera it agrees with
the conic path (:func:`~sphere_servo.core.measurement.sphere_from_conic`).

:func:`fit_small_circle`:

1. Algebraic initialisation: the plane ``bᵀq = c`` through the rays (total least squares:
   ``b`` the smallest principal axis of the rays' scatter about their mean, ``c = bᵀq̄``;
   ``b`` is oriented so that ``c > 0``, the cap smaller than a hemisphere). Its residual is
   ``cos φ − cos θ ≈ −sin θ (φ − θ)``: the geometric residual to first order.
2. Gauss–Newton on the geometric residuals ``φ_i − θ``, ``φ_i = ∠(b, q_i)``, over ``b`` on
   S² (two tangent coordinates) and ``θ``.
3. Robust to outliers as the image conic fit is (mark notches, the CC stick, clutter): the
   rays whose residual is more than ``max(3σ, tol)`` from the median (σ from the MAD) are
   dropped and the circle refitted, a few rounds. Residuals are angles, or — given a
   ``scale`` per ray, e.g. the pixels per radian across the silhouette there — pixels, so
   that the rule is the image conic fit's.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from sphere_servo.core import linalg
from sphere_servo.core.geometry import cross3, normalize
from sphere_servo.core.measurement import MeasurementError, SphereMeasurement

MIN_POINTS = 5
_YZX, _ZXY = np.array([1, 2, 0]), np.array([2, 0, 1])
_EX, _EY = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class SmallCircleFit:
    """
    Result of :func:`fit_small_circle`.

    sphere     :class:`SphereMeasurement`: ``b``, ``r_δ = sin θ``, and ``quality``, the RMS
               angular residual of the inliers divided by θ (0 for an exact sphere image;
               grows with the fitting error or a non-spherical body).
    theta      half-angle θ of the silhouette cone (rad).
    rms        RMS angular residual of the inliers (rad).
    inliers    (N,) bool, the rays kept.
    residuals  (N,) angular residuals ``φ_i − θ`` of every ray (rad; > 0 outside).
    """

    sphere: SphereMeasurement
    theta: float
    rms: float
    inliers: np.ndarray
    residuals: np.ndarray | None = None


def _rays(rays) -> np.ndarray:
    q = np.asarray(rays, dtype=float)
    if q.ndim != 2 or q.shape[1] != 3:
        raise MeasurementError(f'rays must be an (N, 3) array, got shape {q.shape}')
    if not np.all(np.isfinite(q)):
        raise MeasurementError('rays contain NaN or inf')
    n = np.sqrt(np.einsum('ij,ij->i', q, q))
    if np.any(n < 1e-12):
        raise MeasurementError('a ray has zero length')
    return q / n[:, None]


def _plane(q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Fit the plane ``bᵀq = c`` (``c ≥ 0``, ``‖b‖ = 1``) to weighted rays."""
    sw = float(w.sum())
    mean = (w @ q) / sw
    d = q - mean
    S = (d * w[:, None]).T @ d
    ev, V = linalg.eigh(S)
    if not ev[1] > 1e-12 * ev[2]:
        raise MeasurementError('edge rays do not span a circle (coincident or on one line)')
    b = V[:, 0].copy()
    c = float(b @ mean)
    if c < 0:
        b, c = -b, -c
    return b, c


def _angles(b: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Return ``φ_i = ∠(b, q_i)`` as ``atan2(‖q_i × b‖, q_iᵀb)``, accurate at any angle."""
    cr = q[:, _YZX] * b[_ZXY]
    cr -= q[:, _ZXY] * b[_YZX]
    return np.arctan2(np.sqrt(np.einsum('ij,ij->i', cr, cr)), q @ b)


def _median(x: np.ndarray) -> float:
    k = len(x) // 2
    p = np.partition(x, (k - 1, k))
    return float(p[k]) if len(x) % 2 else 0.5 * float(p[k - 1] + p[k])


def _refine(b: np.ndarray, q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Gauss–Newton on ``φ_i − θ`` over ``b`` (tangent coordinates) and ``θ``."""
    phi = _angles(b, q)
    theta = float(w @ phi) / float(w.sum())
    for _ in range(20):
        # tangent basis of b
        e1 = normalize(cross3(b, _EX if abs(b[0]) < 0.9 else _EY))
        e2 = cross3(b, e1)
        s = np.maximum(np.sin(phi), 1e-300)
        # ∂φ/∂α along b + α e: −(eᵀq)/sin φ
        J = np.column_stack([-(q @ e1) / s, -(q @ e2) / s, -np.ones(len(q))])
        r = phi - theta
        Jw = J * w[:, None]
        try:
            step = linalg.solve(Jw.T @ J, -(Jw.T @ r))
        except np.linalg.LinAlgError:
            raise MeasurementError('edge rays do not determine a circle') from None
        b = normalize(b + step[0] * e1 + step[1] * e2)
        theta += float(step[2])
        phi = _angles(b, q)
        if math.hypot(*step) <= 1e-13:
            break
    else:
        if math.hypot(*step) > 1e-9:
            raise MeasurementError(f'small-circle fit did not converge (last step {step})')
    return b, theta


def fit_small_circle(rays, weights=None, *, tol: float = 1e-6, rounds: int = 3,
                     scale=None) -> SmallCircleFit:
    """
    Fit the dome's base circle ``bᵀq = cos θ`` to (N, 3) edge rays (any length).

    ``weights`` (N,) ≥ 0 are optional per-ray weights (e.g. the inverse angular variance of
    a pixel's lift); ``tol`` is the smallest outlier threshold, for exact or nearly exact
    data (σ from the MAD is then ~0); ``rounds`` of outlier rejection. ``scale`` (N,) > 0:
    the rejection rule and ``tol`` are on the residuals times ``scale`` (rad without).

    Raises :class:`MeasurementError` for fewer than :data:`MIN_POINTS` rays (or inliers),
    NaN, rays that do not span a circle, or a circle that is not a sphere's silhouette (a
    great circle, r_δ = 1: the camera on the surface).
    """
    q = _rays(rays)
    if len(q) < MIN_POINTS:
        raise MeasurementError(f'a small-circle fit needs {MIN_POINTS} rays, got {len(q)}')
    if weights is None:
        w = np.ones(len(q))
    else:
        w = np.asarray(weights, dtype=float).ravel()
        if w.shape != (len(q),) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise MeasurementError('weights must be N finite values >= 0')
    g = 1.0
    if scale is not None:
        g = np.asarray(scale, dtype=float).ravel()
        if g.shape != (len(q),) or not np.all(np.isfinite(g)) or np.any(g <= 0):
            raise MeasurementError('scale must be N finite values > 0')
    keep = w > 0
    for it in range(rounds + 1):
        if np.count_nonzero(keep) < MIN_POINTS:
            raise MeasurementError(f'only {np.count_nonzero(keep)} consistent edge rays '
                                   f'(< {MIN_POINTS})')
        qk, wk = q[keep], w[keep]
        b, c = _plane(qk, wk)
        if c <= 1e-9:
            raise MeasurementError('edge rays lie on a great circle: not the silhouette of a '
                                   'sphere in front of the projection centre (r_δ = 1)')
        b, theta = _refine(b, qk, wk)
        d = (_angles(b, q) - theta) * g
        dk = d[keep]
        med = _median(dk)
        sigma = 1.4826 * _median(np.abs(dk - med))
        inl = keep & (np.abs(d - med) < max(3.0 * sigma, tol))
        if it == rounds or np.array_equal(inl, keep):
            break
        keep = inl
    if not 0.0 < theta < 0.5 * math.pi:
        raise MeasurementError(f'small circle of radius {math.degrees(theta):.3f}° is not a '
                               f'sphere silhouette')
    d = d / g
    rk = d[keep]
    rms = math.sqrt(float(rk @ rk) / len(rk))
    sphere = SphereMeasurement(b=b, r_delta=math.sin(theta), quality=rms / theta)
    return SmallCircleFit(sphere=sphere, theta=theta, rms=rms, inliers=keep, residuals=d)


def circle_rays(b, theta: float, n: int) -> np.ndarray:
    """
    Return (n, 3) unit rays evenly spaced on the small circle ``bᵀq = cos θ`` (b unit).

    The silhouette of a sphere of ``b``, ``θ = asin r_δ``, to be projected by any camera.
    """
    b = normalize(np.asarray(b, dtype=float))
    e1 = normalize(cross3(b, _EX if abs(b[0]) < 0.9 else _EY))
    e2 = cross3(b, e1)
    t = np.linspace(0.0, 2.0 * math.pi, int(n), endpoint=False)
    ring = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
    return math.cos(theta) * b + math.sin(theta) * ring


def sphere_from_rays(rays, weights=None, **kw) -> SphereMeasurement:
    """Return the :class:`SphereMeasurement` of :func:`fit_small_circle`."""
    return fit_small_circle(rays, weights, **kw).sphere
