"""
Conic algebra (no ROS): fit, distance, ellipse ↔ conic, boxes, silhouettes. DESIGN.md §2.

A conic is a symmetric 3×3 ``C`` with ``x̄ᵀ C x̄ = 0``, ``x̄ = (x, y, 1)``, defined up to
scale and sign; ``C = [[a, b, d], [b, c, e], [d, e, f]]`` is
``a x² + 2b xy + c y² + 2d x + 2e y + f = 0``. The same functions serve pixel and normalized
coordinates (``x̄ = K⁻¹ (u, v, 1)``, ``K = [[px, 0, u0], [0, py, v0], [0, 0, 1]]``); a
conic maps between them as ``C_n = Kᵀ C_px K``.

- fit: :func:`fit_conic` (algebraic, Hartley-normalized, weighted) and
  :func:`sampson_distance` (first-order geometric distance);
- ellipses: :func:`ellipse_params` (conic → :class:`Ellipse`), :func:`conic_from_ellipse`,
  :func:`conic_from_moments` (a filled blob), :func:`conic_from_rotated_rect`
  (``cv2.fitEllipse``'s result), :func:`conic_bbox`;
- :func:`conic_pixels_to_normalized`, :func:`conic_normalized_to_pixels`;
- silhouettes seen from the camera centre: :func:`sphere_silhouette` (``b bᵀ − cos²θ I``)
  and :func:`ellipsoid_silhouette` (the dual quadric projected); :func:`fit_circular_cone`
  (the sphere's cone of rays, fitted to unit rays).

Several functions take homogeneous rows ``P`` (3, N) = ``(x, y, 1)`` instead of (N, 2)
points and return plain floats: the detector calls them in its inner loop.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pinocchio as pin

from sphere_servo.core.geometry import GeometryError, require_finite
from sphere_servo.core.types import Conic, Points2


class ConicError(GeometryError):
    """A conic is undefined for the input (degenerate moments, a camera inside the body)."""


class Ellipse(NamedTuple):
    """
    A real ellipse, in plain floats.

    centre      ``(cx, cy)``.
    semi_axes   ``(a0, a1)``: ``a0`` along ``angle``, ``a1`` across it.
    angle       direction of the first axis (rad).
    """

    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    angle: float


# --- fit ------------------------------------------------------------------------------
def homogeneous(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Stack (N,) coordinates as (3, N) float64 rows ``x, y, 1``."""
    P = np.empty((3, len(x)))
    P[0] = x
    P[1] = y
    P[2] = 1.0
    return P


def fit_conic(xy: Points2, weights: np.ndarray | None = None) -> Conic:
    """
    Fit ``a x² + b xy + c y² + d x + e y + f = 0`` to (N, 2) points, N ≥ 5 (algebraic).

    Hartley normalization (centroid, RMS distance √2) and optional per-point weights.
    Returns the symmetric 3×3 conic in the input coordinates, unit Frobenius norm.
    """
    x = xy[:, 0].astype(np.float64)
    y = xy[:, 1].astype(np.float64)
    n = len(x)
    mx, my = float(x.sum()) / n, float(y.sum()) / n
    P = homogeneous(x, y)
    x -= mx
    y -= my
    sc = math.sqrt(2.0 / max(float(np.dot(x, x) + np.dot(y, y)) / n, 1e-300))
    return fit_conic_homogeneous(P, mx, my, sc, weights)


def fit_conic_homogeneous(P: np.ndarray, mx: float, my: float, sc: float,
                          weights: np.ndarray | None = None) -> Conic:
    """
    :func:`fit_conic` of the points given as (3, N) homogeneous rows ``(x, y, 1)``.

    The points are normalized by ``(p − (mx, my))·sc``: any centre inside the points and a
    scale ≈ √2 / RMS radius condition the scatter matrix as well as the exact centroid does
    (the detector passes its coarse ellipse's). Unit Frobenius norm.
    """
    import cv2  # only a fit needs OpenCV (its 6×6 eigen solver); the rest of core is numpy

    D = np.empty((6, P.shape[1]))
    # rows x'², x'y', y'², x', y', 1 with (x', y') = sc·(p − m): one affine product
    np.matmul(np.array([[sc, 0.0, -sc * mx], [0.0, sc, -sc * my]]), P, out=D[3:5])
    np.multiply(D[3:5], D[3], out=D[0:2])
    np.multiply(D[4], D[4], out=D[2])
    D[5] = 1.0
    S = (D if weights is None else D * weights) @ D.T
    _, _, V = cv2.eigen(S)                 # descending: the last row is the smallest
    a, b, c, d, e, f = V[5].tolist()
    # back to the input coordinates: x' = sc·(x − mx)
    s2 = sc * sc
    A, B, Cc = a * s2, b * s2, c * s2
    Dx = d * sc - 2.0 * A * mx - B * my
    Ey = e * sc - 2.0 * Cc * my - B * mx
    F = A * mx * mx + B * mx * my + Cc * my * my - sc * (d * mx + e * my) + f
    B, Dx, Ey = 0.5 * B, 0.5 * Dx, 0.5 * Ey
    k = 1.0 / math.sqrt(A * A + Cc * Cc + F * F + 2.0 * (B * B + Dx * Dx + Ey * Ey))
    A, B, Cc, Dx, Ey, F = A * k, B * k, Cc * k, Dx * k, Ey * k, F * k
    return np.array([[A, B, Dx], [B, Cc, Ey], [Dx, Ey, F]])


def sampson_homogeneous(C: Conic, P: np.ndarray) -> np.ndarray:
    """
    :func:`sampson_distance` of the points given as (3, N) homogeneous rows ``(x, y, 1)``.

    With ``G = C P``: ``pᵀCp / (2 ‖(G₀, G₁)‖)`` (one product instead of a dozen ufuncs).
    """
    G = C @ P
    alg = G[0] * P[0]
    alg += G[1] * P[1]
    alg += G[2]
    h = np.hypot(G[0], G[1])
    h *= 2.0
    alg /= np.maximum(h, 1e-300, out=h)
    return alg


def sampson_distance(C: Conic, xy: Points2) -> np.ndarray:
    """First-order geometric distance (N,) of (N, 2) points to the conic C (same units)."""
    return sampson_homogeneous(C, homogeneous(xy[:, 0], xy[:, 1]))


# --- ellipses -------------------------------------------------------------------------
def ellipse_params(C: Conic) -> Ellipse | None:
    """Centre, semi-axes and angle of the ellipse of the conic C, or None if not a real one."""
    (a, b, d), (_, c, e), (_, _, f) = np.asarray(C, dtype=float).tolist()
    det = a * c - b * b
    if not det or not math.isfinite(det):
        return None
    cx = (b * e - c * d) / det
    cy = (b * d - a * e) / det
    k = -(a * cx * cx + 2 * b * cx * cy + c * cy * cy + 2 * d * cx + 2 * e * cy + f)
    if k == 0:
        return None
    a, b, c = a / k, b / k, c / k
    # eigen-decomposition of [[a, b], [b, c]]
    m, h = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    w1, w2 = m - h, m + h
    if not (w1 > 0 and w2 > 0):
        return None
    ang = 0.5 * math.atan2(2 * b, a - c) + 0.5 * math.pi     # direction of w1 (long axis)
    return Ellipse((cx, cy), (1.0 / math.sqrt(w1), 1.0 / math.sqrt(w2)),
                   math.atan2(math.sin(ang), math.cos(ang)))


def conic_from_ellipse(center: np.ndarray, A: np.ndarray) -> Conic:
    """Conic of the ellipse ``(p − c)ᵀ A (p − c) = 1`` (A: 2×2 symmetric positive)."""
    c = np.asarray(center, dtype=float)
    Ac = A @ c
    C = np.empty((3, 3))
    C[:2, :2] = A
    C[:2, 2] = C[2, :2] = -Ac
    C[2, 2] = c @ Ac - 1.0
    return C


def conic_from_moments(centroid: np.ndarray, cov: np.ndarray) -> Conic:
    """
    Conic of a filled ellipse from its region centroid (2,) and covariance (2×2).

    The boundary is ``(p − c)ᵀ (4Σ)⁻¹ (p − c) = 1`` (DESIGN.md §2). Raises
    :class:`ConicError` when Σ is not positive definite, ``GeometryError`` on NaN or inf.
    """
    centroid = require_finite(centroid, 'blob centroid')
    cov = require_finite(cov, 'blob covariance')
    if np.linalg.det(cov) <= 0:
        raise ConicError('blob covariance is not positive definite')
    return conic_from_ellipse(centroid, np.linalg.inv(4.0 * cov))


def conic_from_rotated_rect(cx: float, cy: float, w: float, h: float,
                            angle_deg: float) -> Conic:
    """
    Conic of a ``cv2.RotatedRect`` ellipse, as ``cv2.fitEllipse`` returns it.

    Full axis ``w`` along ``angle_deg``, ``h`` across it, centre ``(cx, cy)`` (plain
    floats: this runs in the detector's inner loop).
    """
    a = math.radians(angle_deg)
    ca, sa = math.cos(a), math.sin(a)
    ia, ib = 4.0 / (w * w), 4.0 / (h * h)
    A00, A01, A11 = ca * ca * ia + sa * sa * ib, ca * sa * (ia - ib), sa * sa * ia + ca * ca * ib
    g0, g1 = -(A00 * cx + A01 * cy), -(A01 * cx + A11 * cy)
    return np.array([[A00, A01, g0], [A01, A11, g1], [g0, g1, -(g0 * cx + g1 * cy) - 1.0]])


def conic_bbox(C: Conic) -> tuple[float, float, float, float] | None:
    """
    Axis-aligned bounding box ``(x_min, x_max, y_min, y_max)`` of the ellipse of C.

    From its vertical and horizontal tangent lines ``lᵀ C⁻¹ l = 0`` with ``l = (1, 0, −x)``
    and ``(0, 1, −y)`` (any coordinates). None if the conic is not a real bounded ellipse.
    """
    try:
        D = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return None
    out = []
    for i in (0, 1):
        # D_ii − 2 x D_i2 + x² D_22 = 0
        a, b, c = D[2, 2], -2.0 * D[i, 2], D[i, i]
        disc = b * b - 4 * a * c
        if abs(a) < 1e-300 or disc < 0:
            return None
        s = np.sqrt(disc)
        out += sorted(((-b - s) / (2 * a), (-b + s) / (2 * a)))
    return tuple(out)


# --- pixels ↔ normalized --------------------------------------------------------------
def _unit(n00, n01, n02, n11, n12, n22) -> Conic:
    """Build the symmetric conic of these entries, scaled to unit Frobenius norm."""
    nrm = math.sqrt(n00 * n00 + n11 * n11 + n22 * n22
                    + 2.0 * (n01 * n01 + n02 * n02 + n12 * n12))
    return np.array([[n00, n01, n02], [n01, n11, n12], [n02, n12, n22]]) / nrm


def conic_pixels_to_normalized(C_px: Conic, px: float, py: float, u0: float,
                               v0: float) -> Conic:
    """``Kᵀ C_px K`` for the pinhole ``K`` (DESIGN.md §1), unit Frobenius norm."""
    (a, b, d), (_, c, e), (_, _, f) = C_px.tolist()
    gu, gv = a * u0 + b * v0 + d, b * u0 + c * v0 + e
    return _unit(px * px * a, px * py * b, px * gu, py * py * c, py * gv,
                 u0 * gu + v0 * gv + d * u0 + e * v0 + f)


def conic_normalized_to_pixels(C: Conic, px: float, py: float, u0: float,
                               v0: float) -> Conic:
    """``K⁻ᵀ C K⁻¹`` for the pinhole ``K`` (DESIGN.md §1), unit Frobenius norm."""
    (a, b, d), (_, c, e), (_, _, f) = np.asarray(C, dtype=float).tolist()
    # x = (u − u0)/px, y = (v − v0)/py: with (x0, y0) = (u0/px, v0/py), x = u/px − x0
    x0, y0 = u0 / px, v0 / py
    gx, gy = d - a * x0 - b * y0, e - b * x0 - c * y0
    return _unit(a / (px * px), b / (px * py), gx / px, c / (py * py), gy / py,
                 f - x0 * (d + gx) - y0 * (e + gy))


# --- cones of rays ----------------------------------------------------------------------
def fit_circular_cone(q: np.ndarray) -> tuple[np.ndarray, float]:
    """
    Fit the right circular cone ``b·q = c`` (``|b| = 1``) to unit rays ``q`` (3, N), N ≥ 3.

    A sphere's occluding contour is seen along such a cone (``b`` its centre's direction,
    ``c = cos θ``, DESIGN.md §2), whatever the camera that maps pixels to rays: the rays'
    ends lie on the plane ``b·x = c``, fitted by least squares (b: the eigenvector of the
    smallest eigenvalue of their scatter, c = b·mean). Returns ``(b, c)`` with ``c ≥ 0``.
    """
    qm = q.mean(axis=1)
    D = q - qm[:, None]
    _, V = np.linalg.eigh(D @ D.T)
    b = V[:, 0]
    c = float(b @ qm)
    if c < 0:
        b, c = -b, -c
    return b, c


# --- silhouettes ----------------------------------------------------------------------
def sphere_silhouette(cO: np.ndarray, radius: float) -> Conic:
    """
    Conic (normalized coordinates) of the silhouette of a ball seen from the camera centre.

    ``b bᵀ − cos²θ I`` with ``b = cO/‖cO‖``, ``sin θ = radius/‖cO‖``, for the ball of centre
    ``cO`` (camera frame) and radius ``radius`` (DESIGN.md §2). Raises :class:`ConicError`
    when the camera centre is not outside the ball.
    """
    dist = float(np.linalg.norm(cO))
    if not dist > radius:
        raise ConicError(f'the camera is inside the ball (distance {dist} ≤ radius {radius})')
    b = np.asarray(cO, float) / dist
    return np.outer(b, b) - (1.0 - (radius / dist) ** 2) * np.eye(3)


def ellipsoid_silhouette(cMo: pin.SE3, axes: np.ndarray) -> Conic:
    """
    Conic (normalized coordinates) of the occluding contour of an ellipsoid.

    The ellipsoid has semi-axes ``axes`` (3,) along the axes of its frame o, at pose
    ``cMo``. With ``Q`` its quadric in the camera frame, the contour seen from the camera
    centre is ``C = ((Q⁻¹)₃ₓ₃)⁻¹`` (the dual quadric projected by ``[I | 0]``); for a sphere
    that is ``∝ b bᵀ − cos²θ I``. Unit Frobenius norm. Raises :class:`ConicError` when the
    camera centre is not outside the ellipsoid.
    """
    axes = np.asarray(axes, dtype=float)
    oMc = cMo.inverse().homogeneous
    if float(np.sum((oMc[:3, 3] / axes) ** 2)) <= 1.0:
        raise ConicError('the camera is inside the ellipsoid')
    Qo = np.diag([*(1.0 / axes ** 2), -1.0])
    Qc = oMc.T @ Qo @ oMc
    dual = np.linalg.inv(Qc)[:3, :3]
    C = np.linalg.inv(dual)
    return C / np.linalg.norm(C)
