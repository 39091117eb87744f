"""
A painted cap's centre from the first moments of its image (no ROS). DESIGN.md §2.

Near the limb the back-projection of a cap's pixels on the sphere is ill-conditioned (a
pixel's footprint grows as 1/cos i, and its position on the sphere moves fast with the
silhouette's error), and a small sphere leaves too little of the cap's rim to fit. The
cap's *image* is well measured though: its coverage-weighted centroid. For a unit normal
m at the cap's centre, the cap's points ``n = m cos φ + (e₁ cos ψ + e₂ sin ψ) sin φ``
(φ ≤ ρ, the cap's angular radius) are ``P/r = s_n,t + n``; those that face the camera
(``n·P < 0``) project to ``x = P_xy / P_z`` with the normalized image area
``dA cos i / ‖P‖² · ‖x̄‖³ = dA cos i ‖P‖ / P_z³`` per surface area ``dA``. Their weighted
mean is the centroid the cap would have; chord steps on m (two tangent angles, a
forward-difference Jacobian) match it to the measured one. A cap cut by the limb is
handled by the same model (its hidden part does not project).

Through any central camera (a fisheye, a catadioptric) the image is not a plane, but its
pixels are rays: the mean of the cap's rays weighted by their solid angles
(``dA cos i / ‖P‖²`` per surface area) depends on the camera centre only.
:func:`predicted_direction` predicts it, in gnomonic coordinates of a given frame, and
:func:`match_centroid` matches it the same way.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

from sphere_servo.core.measurement import SphereMeasurement
from sphere_servo.core.types import Vec3


class CapCentre(NamedTuple):
    """A cap's centre (``MarkFinder.cap_centre``): its unit ray (None: not measured), area seen."""

    ray: Vec3 | None
    seen: float


@functools.lru_cache(maxsize=16)
def _cap_samples(rho: float, rings: int = 8, per_ring: int = 16) -> np.ndarray:
    """
    (3, N) points of a cap of angular radius ``rho`` about +z, equal surface area each.

    Stratified: ``cos φ`` at the mid-points of ``rings`` equal steps over [cos ρ, 1] (equal
    areas), ``per_ring`` angles ψ, shifted by half a step every other ring.
    """
    c = 1.0 - (np.arange(rings) + 0.5) / rings * (1.0 - math.cos(rho))
    s = np.sqrt(1.0 - c * c)
    psi = (np.arange(per_ring)[None, :] + 0.5 * (np.arange(rings)[:, None] % 2)) \
        * (2 * math.pi / per_ring)
    return np.stack([(s[:, None] * np.cos(psi)).ravel(), (s[:, None] * np.sin(psi)).ravel(),
                     np.repeat(c, per_ring)])


def tangent_basis(m: np.ndarray) -> np.ndarray:
    """Rows t1, t2, m: an orthonormal frame whose third axis is the unit m (plain floats)."""
    mx, my, mz = m.tolist()
    if abs(mx) < 0.9:
        a, b, c = 0.0, -mz, my
    else:
        a, b, c = mz, 0.0, -mx
    k = 1.0 / math.sqrt(a * a + b * b + c * c)
    a, b, c = a * k, b * k, c * k
    return np.array([[a, b, c], [my * c - mz * b, mz * a - mx * c, mx * b - my * a],
                     [mx, my, mz]])


def predicted_centroid(sphere: SphereMeasurement, m: np.ndarray, rho: float
                       ) -> np.ndarray | None:
    """Predict the normalized image centroid (2,) of the cap (m, ρ) (None: hidden)."""
    n = tangent_basis(m).T @ _cap_samples(rho)                  # (3, N) unit normals
    P = n + sphere.s_nt[:, None]
    facing = -np.einsum('ij,ij->j', n, P)                # ‖P‖ cos i
    z = P[2]
    ok = (facing > 0) & (z > 0)
    if not ok.all():
        if not ok.any():
            return None
        P, facing, z = P[:, ok], facing[ok], z[ok]
    iz = 1.0 / z
    w = facing * iz * iz * iz                            # cos i ‖P‖ / P_z³
    sw = float(w.sum())
    w *= iz
    return (P[:2] @ w) / sw


def predicted_direction(sphere: SphereMeasurement, m: np.ndarray, rho: float,
                        frame: np.ndarray) -> np.ndarray | None:
    """
    Predict the mean direction of the cap (m, ρ)'s rays, weighted by their solid angles.

    As gnomonic coordinates (2,) in ``frame`` (rows e1, e2, a: ``(e1·d, e2·d)/(a·d)``);
    None when the cap is hidden.
    """
    n = tangent_basis(m).T @ _cap_samples(rho)                  # (3, N) unit normals
    P = n + sphere.s_nt[:, None]
    facing = -np.einsum('ij,ij->j', n, P)                # ‖P‖ cos i
    ok = facing > 0
    if not ok.all():
        if not ok.any():
            return None
        P, facing = P[:, ok], facing[ok]
    pp = np.einsum('ij,ij->j', P, P)
    d = frame @ (P @ (facing / (pp * pp)))               # Σ (cos i/‖P‖²) P/‖P‖
    return d[:2] / d[2]


def visible_solid_angle(sphere: SphereMeasurement, m: np.ndarray, rho: float) -> float:
    """Solid angle (sr) of the part of the cap (m, ρ) that faces the camera (Σ dA cos i/‖P‖²)."""
    n = tangent_basis(m).T @ _cap_samples(rho, 16, 32)          # (3, N) unit normals
    P = n + sphere.s_nt[:, None]
    facing = -np.einsum('ij,ij->j', n, P)                # ‖P‖ cos i
    ok = facing > 0
    pp = np.einsum('ij,ij->j', P[:, ok], P[:, ok])
    return 2 * math.pi * (1 - math.cos(rho)) / n.shape[1] * float((facing[ok] / pp ** 1.5).sum())


def _jacobian_inv(sphere, m, rho, c, predict, h: float = 1e-4) -> np.ndarray | None:
    """Invert d(centroid)/d(tangent angles) at m, by forward differences."""
    B = tangent_basis(m)
    J = np.empty((2, 2))
    for a in range(2):
        ma = m + h * B[a]
        ca = predict(sphere, ma / math.sqrt(float(ma @ ma)), rho)
        if ca is None:
            return None
        J[:, a] = (ca - c) / h
    det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    if abs(det) < 1e-18:
        return None
    return np.array([[J[1, 1], -J[0, 1]], [-J[1, 0], J[0, 0]]]) / det


def match_centroid(sphere: SphereMeasurement, m0: np.ndarray, rho: float,
                   centroid: np.ndarray, predict=predicted_centroid, iters: int = 6,
                   tol: float = 1e-4) -> np.ndarray | None:
    """
    Find the unit normal m whose cap (radius ``rho``) images with the normalized ``centroid``.

    ``predict(sphere, m, rho)``: the model of the measured figure (the normalized image
    centroid, :func:`predicted_centroid`, or a mean direction,
    :func:`predicted_direction`). Chord steps from ``m0`` (the back-projected mean, close)
    over the two tangent angles: the Jacobian (forward differences) of the first point,
    renewed after a long step. None when the model has no visible cap or the Jacobian is
    singular.
    """
    m = np.asarray(m0, float) / np.linalg.norm(m0)
    Ji = None
    for _ in range(iters):
        c = predict(sphere, m, rho)
        if c is None:
            return None
        if Ji is None:
            Ji = _jacobian_inv(sphere, m, rho, c, predict)
            if Ji is None:
                return None
        d0, d1 = (Ji @ (centroid - c)).tolist()
        step = math.hypot(d0, d1)
        if step > 0.05:                                  # far: a new Jacobian next time
            Ji = None
            if step > 0.2:                               # keep the linearization honest
                d0, d1 = d0 * 0.2 / step, d1 * 0.2 / step
        B = tangent_basis(m)
        m = m + d0 * B[0] + d1 * B[1]
        m /= math.sqrt(float(m @ m))
        if step < tol:
            break
    return m


# (cos ψ, sin ψ, 1) at 96 angles: a cap's rim and the limb as one product with a frame
_PSI = np.linspace(0.0, 2 * math.pi, 96, endpoint=False)
_CIRCLE = np.vstack([np.cos(_PSI), np.sin(_PSI), np.ones_like(_PSI)])


def outside_share(sphere: SphereMeasurement, ray: np.ndarray, rho: float, q: np.ndarray,
                  cov: np.ndarray, w_sr: np.ndarray, tol_px: float,
                  at_most: float | None = None) -> float:
    """
    Share of a mark's coverage lying more than ``tol_px`` outside the image of its cap.

    ``ray``: the measured centre's unit ray, ``rho`` the cap's angular radius; ``q`` (3, N)
    the mark's pixels' unit rays, ``cov`` their coverage, ``w_sr`` their solid angles. The
    visible part of the cap (m, ρ) is bounded by the arcs of its rim that face the camera
    and the arcs of the limb within it; the hull of those, in gnomonic coordinates about
    ``b`` scaled to pixels (by ``1/√w_sr``: any central camera), is compared with the
    pixels at least half covered. A cable of the mark's colour across the cap, or a colour
    fringe along the limb, taken for a cap spreads beyond the cap its centre predicts.

    ``at_most``: the caller only asks whether the share exceeds it. A pixel whose ray meets
    the sphere inside the cap lies inside the visible cap's image, which the hull is
    inscribed in (96 points: within 0.06 % of the cap's image radius, far below
    ``tol_px``), so the share of the others bounds it; when that bound is at most
    ``at_most`` it is returned without the hull (the usual mark: the bound is 0).
    """
    s, b, rd = sphere.s_nt, sphere.b, sphere.r_delta
    sr = float(s @ ray)
    m = (sr - math.sqrt(max(sr * sr - float(s @ s) + 1.0, 0.0))) * ray - s
    m /= math.sqrt(float(m @ m))
    T, F = tangent_basis(m), tangent_basis(b)
    sin_rho, cos_rho = math.sin(rho), math.cos(rho)
    k = math.sqrt(1.0 - rd * rd)
    # (3, 96) each: the rim's normals and the limb's, as products with the frames
    ring = T.T @ (_CIRCLE * np.array([[sin_rho], [sin_rho], [cos_rho]]))
    limb = F.T @ (_CIRCLE * np.array([[k], [k], [-rd]]))
    # the rim's points that face the camera (n·P < 0, P = s + n), the limb's in the cap
    on_rim, on_limb = s @ ring < -1.0, m @ limb >= cos_rho
    conf = cov >= 0.5
    n_conf = np.count_nonzero(conf)
    if np.count_nonzero(on_rim) + np.count_nonzero(on_limb) < 3 or not n_conf:
        return 1.0 if n_conf else 0.0
    if at_most is not None:
        # over every pixel, then the confident ones' share: cheaper than taking their columns
        sq = s @ q
        disc = sq * sq
        disc += 1.0 - float(s @ s)
        t = sq - np.sqrt(np.maximum(disc, 0.0))       # the near hit ρ (units of r)
        cos_m = t * (m @ q)
        cos_m -= float(s @ m)                          # n·m, n = ρq − s
        miss = disc < 0.0
        miss |= cos_m < cos_rho
        miss &= conf
        out = cov[miss].sum() / cov[conf].sum()
        if out <= at_most:
            return float(out)
    c, qc = cov[conf], q[:, conf]
    n = np.hstack([ring[:, on_rim], limb[:, on_limb]])
    w = np.sort(w_sr[conf])
    scale = 1.0 / math.sqrt(0.5 * float(w[(len(w) - 1) // 2] + w[len(w) // 2]))   # median
    G = F @ (n + s[:, None])
    H = cv2.convexHull((G[:2] / G[2] * scale).T.astype(np.float32))[:, 0].astype(float)
    g = F @ qc
    g = g[:2] / g[2] * scale
    # the distance outside a convex polygon is at least the largest over its edges' lines
    e = np.vstack((H[1:], H[:1])) - H
    length = np.maximum(np.hypot(e[:, 0], e[:, 1]), 1e-12)
    nrm = e[:, ::-1] * np.array([1.0, -1.0]) / length[:, None]
    off = (nrm * H).sum(axis=1)
    if float(nrm[0] @ H.mean(axis=0)) > off[0]:
        nrm, off = -nrm, -off                           # outward normals
    d = (nrm @ g - off[:, None]).max(axis=0)
    return float(c[d > tol_px].sum() / c.sum())
