"""
The silhouette measured on the projection sphere (no ROS): lifted edge → the sphere's cone.

Through any camera model (:mod:`~sphere_servo.core.central`) the sphere's occluding contour
is the small circle ``bᵀq = cos θ`` of the projection sphere (DESIGN.md §2). The silhouette's
sub-pixel edge points (:mod:`~sphere_servo.vision.silhouette`, in pixels) are lifted through
the model and the circle fitted to their rays
(:func:`~sphere_servo.core.small_circle.fit_small_circle`), its residuals in pixels: each
ray's angular residual times the pixels per radian across the silhouette at that point
(``scale``, from the model's Jacobian), so the outlier rule (``max(3σ, 0.3 px)``, σ from the
MAD) and the RMS are the pinhole conic fit's and the calibrated
:class:`~sphere_servo.vision.scoring.FitBounds` hold. On a pinhole camera without
distortion this is the same sphere as the conic path (a test checks it); the conic path
stays there, for speed.

``quality`` — the departure of the silhouette from a sphere's image, which the bounds test —
is the conic path's figure on a virtual pinhole looking along ``b``: the relative spread of
the two "equal" eigenvalues of the general conic fitted to the gnomonic projection of the
kept rays about ``b``. The eigenvalues of a cone do not change when the camera turns, so for
a pinhole it is the figure the conic path gives.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from sphere_servo.core.conics import fit_circular_cone, fit_conic
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import sphere_from_conic, SphereMeasurement
from sphere_servo.core.small_circle import circle_rays, fit_small_circle, MIN_POINTS
from sphere_servo.vision.caps import tangent_basis
from sphere_servo.vision.reasons import NotDetected, Reason

#: the smallest outlier threshold of the edge residuals (px), the conic fit's
MIN_OUTLIER_PX = 0.3
#: edge points a fit needs (the conic path's)
MIN_EDGE_POINTS = 10


@dataclass(frozen=True)
class ConeFit:
    """
    The sphere's cone fitted to lifted edge points.

    sphere   :class:`SphereMeasurement`: ``b``, ``r_δ = sin θ``, ``quality`` (module).
    theta    half-angle θ of the cone (rad).
    keep     (n,) bool: the edge points kept (lifted, and not outliers).
    rays     (3, n) unit rays of the edge points (NaN where a point is not lifted).
    scale    (n,) pixels per radian across the silhouette at each point (NaN where not lifted).
    rms_px   RMS of the kept points' residuals (px).
    """

    sphere: SphereMeasurement
    theta: float
    keep: np.ndarray
    rays: np.ndarray
    scale: np.ndarray
    rms_px: float

    @property
    def conic(self) -> np.ndarray:
        """Return the cone ``qᵀ C q = 0``, ``C = b bᵀ − cos²θ I`` (unit Frobenius norm)."""
        return cone_conic(self.sphere.b, self.theta)


def cone_conic(b: np.ndarray, theta: float) -> np.ndarray:
    """
    Return ``b bᵀ − cos²θ I`` with unit Frobenius norm: the cone of a sphere's silhouette.

    For a pinhole it is the sphere's conic in normalized coordinates (DESIGN.md §2).
    """
    C = np.outer(b, b) - math.cos(theta) ** 2 * np.eye(3)
    return C / np.linalg.norm(C)


def edge_scale(camera, q: np.ndarray, b: np.ndarray) -> np.ndarray:
    """
    Pixels per radian across a silhouette of axis ``b`` at its unit rays ``q`` (N, 3).

    ``‖J t‖`` with ``J = ∂(u, v)/∂P`` at ``q`` and ``t`` the unit tangent of the sphere at
    ``q`` pointing away from ``b`` (the direction a residual of the cone moves a ray).
    """
    t = q * (q @ b)[:, None] - b
    t /= np.maximum(np.linalg.norm(t, axis=1), 1e-300)[:, None]
    J = camera.project_jacobian(q)
    return np.linalg.norm(np.einsum('nij,nj->ni', J, t), axis=1)


def cone_quality(q: np.ndarray, b: np.ndarray) -> float:
    """
    Departure of the rays (N, 3) from a sphere's silhouette, as the conic path measures it.

    The general conic fitted to their gnomonic projection about ``b`` (a virtual pinhole
    looking along b); the relative spread of its two "equal" eigenvalues (module).
    """
    p = q @ tangent_basis(b).T
    xy = p[:, :2] / p[:, 2:3]
    return sphere_from_conic(fit_conic(xy)).quality


def fit_cone(lift, E: np.ndarray, tol_px: float = MIN_OUTLIER_PX) -> ConeFit | NotDetected:
    """
    Fit the sphere's cone to the edge points ``E`` (3, n) (homogeneous pixels ``(u, v, 1)``).

    ``lift``: a :class:`~sphere_servo.vision.rays.ModelLift`. The plane through every
    lifted ray gives ``b`` for the pixel scale; the fit weights each ray by ``scale²`` (it
    minimises the pixel residuals) and drops the outliers (module). Returns the
    :class:`ConeFit`, or why not (too few points, no sphere's silhouette).
    """
    n = E.shape[1]
    rays, ok = lift.lift(E[:2].T)
    if np.count_nonzero(ok) < MIN_EDGE_POINTS:
        return NotDetected(Reason.FEW_EDGE_POINTS, f'{np.count_nonzero(ok)} in the field')
    q = rays[ok]
    scale = np.full(n, np.nan)
    try:
        # the plane through the rays gives b closely enough for the pixel scale
        g = edge_scale(lift.camera, q, fit_circular_cone(q.T)[0])
        fit = fit_small_circle(q, g * g, tol=tol_px, scale=g)
    except GeometryError as exc:     # MeasurementError: not a circle; outside the field
        return NotDetected(Reason.NOT_A_SPHERE, str(exc))
    scale[ok] = g
    keep = np.zeros(n, bool)
    keep[ok] = fit.inliers
    nk = int(np.count_nonzero(keep))
    if nk < max(MIN_EDGE_POINTS, MIN_POINTS):
        return NotDetected(Reason.FEW_EDGE_POINTS, f'{nk} inliers')
    rk = fit.residuals[fit.inliers] * g[fit.inliers]
    try:
        quality = cone_quality(q[fit.inliers], fit.sphere.b)
    except GeometryError as exc:
        return NotDetected(Reason.NOT_A_SPHERE, str(exc))
    sphere = SphereMeasurement(fit.sphere.b, fit.sphere.r_delta, quality)
    return ConeFit(sphere, fit.theta, keep, rays.T, scale, math.sqrt(float(rk @ rk) / nk))


#: rays sampled on a detection's contour (:func:`contour_px`)
CONTOUR_SAMPLES = 90


def contour_px(camera, b: np.ndarray, theta: float, n: int = CONTOUR_SAMPLES) -> np.ndarray:
    """(m, 2) pixels of the cone's silhouette through ``camera`` (its rays in the field)."""
    q = circle_rays(b, theta, n)
    q = q[camera.valid(q)]
    return camera.project(q) if len(q) else np.zeros((0, 2))


def limb_distance(camera, sphere: SphereMeasurement, theta: float, q: np.ndarray,
                  uv: np.ndarray) -> np.ndarray:
    """
    Signed distance (px, > 0 inside) of the pixels ``uv`` (rows u, v) to the cone's silhouette.

    ``q`` (3, N): the pixels' unit rays. Each pixel is measured to the image of the
    silhouette point on its great circle through ``b`` (the nearest point on the sphere,
    and within a fraction of a pixel the nearest in the image where that matters, near the
    limb); where that point is outside the camera's field, the angle times the pixels per
    radian there.
    """
    b = sphere.b
    cphi = b @ q
    t = q - b[:, None] * cphi
    sphi = np.sqrt(np.einsum('ij,ij->j', t, t))
    t /= np.maximum(sphi, 1e-300)
    edge = (math.cos(theta) * b[:, None] + math.sin(theta) * t).T
    sign = np.where(np.arctan2(sphi, cphi) < theta, 1.0, -1.0)
    ok = camera.valid(edge)
    out = np.empty(q.shape[1])
    if ok.any():
        e_uv = camera.project(edge[ok])
        out[ok] = np.hypot(uv[0][ok] - e_uv[:, 0], uv[1][ok] - e_uv[:, 1])
    if not ok.all():
        out[~ok] = 1e3                 # far: the silhouette there is not imaged
    return sign * out
