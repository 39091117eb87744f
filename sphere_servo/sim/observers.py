"""
Observers ``cMo -> Observation`` for the paper runner and the Monte Carlo study (no ROS).

- :func:`exact_observer`  analytic image of the target (sphere *or* ellipsoid) with, on
  request, the controller's wrong intrinsics (calibration error) and Gaussian pixel noise
  on the silhouette's contour points and on the marks (the conic is then re-fitted to the
  noisy contour, as the detector does). Fast: no image.
- :func:`image_observer`  render with the true camera, detect with the controller's camera
  (which may carry the calibration error): the real vision pipeline.

The silhouette of the body, a sphere or an ellipsoid, is
:func:`~sphere_servo.core.conics.ellipsoid_silhouette` (for a sphere ``∝ b bᵀ − cos²θ I``,
DESIGN.md §2).
A calibration error maps true normalized points ``x̄`` to believed ones ``A x̄`` with
``A = K_ctrl⁻¹ K_true``; the conic becomes ``A⁻ᵀ C A⁻¹``.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.conics import (conic_normalized_to_pixels, ellipse_params,
                                      ellipsoid_silhouette, fit_conic)
from sphere_servo.core.measurement import (mark_visible, MeasurementError, Observation,
                                           sphere_from_conic, unit_ray)
from sphere_servo.core.targets import Target


def silhouette_conic(cMo: pin.SE3, target: Target) -> np.ndarray:
    """3×3 conic of the target's occluding contour in (true) normalized coordinates."""
    axes = np.full(3, target.radius) if target.axes is None else target.axes
    if np.linalg.norm(cMo.translation) <= np.max(axes):
        raise MeasurementError('camera is inside (or too close to) the target')
    return ellipsoid_silhouette(cMo, axes)


def _ellipse_points(C_px: np.ndarray, n: int) -> np.ndarray:
    """``n`` points evenly spread in angle on the ellipse of conic ``C_px`` (pixels)."""
    ep = ellipse_params(C_px)
    if ep is None:
        raise MeasurementError('silhouette is not an ellipse')
    c, ax, ang = ep
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    return np.asarray(c) + (np.column_stack([ax[0] * np.cos(t), ax[1] * np.sin(t)]) @ R.T)


def exact_observer(target: Target, camera: CameraIntrinsics | None = None,
                   camera_ctrl: CameraIntrinsics | None = None, pixel_noise: float = 0.0,
                   seed: int = 0, contour_points: int = 64):
    """
    ``cMo -> Observation`` from the analytic image.

    camera       the true intrinsics (default :class:`CameraIntrinsics`).
    camera_ctrl  the intrinsics the controller believes (default: the true ones).
    pixel_noise  σ (px) of Gaussian noise on the contour points and mark centres.
    contour_points  how many contour points the noisy conic is fitted to (≥ 5, a conic's
                 degrees of freedom).
    ValueError at once on a ``pixel_noise`` not finite and ≥ 0 (NaN and −1 gave noise-free
    observations, inf a "target lost") or fewer than 5 contour points (a conic through 3
    fitted anything, 0 divided by zero); the observer raises :class:`MeasurementError`
    when the target is behind the camera or a mark hidden.
    """
    if not (isinstance(pixel_noise, (int, float, np.floating, np.integer))
            and np.isfinite(pixel_noise) and pixel_noise >= 0):
        raise ValueError(f'pixel_noise must be a finite number ≥ 0 (px), got {pixel_noise!r}')
    if (isinstance(contour_points, bool) or not isinstance(contour_points, (int, np.integer))
            or contour_points < 5):
        raise ValueError(f'contour_points must be an integer ≥ 5, got {contour_points!r}')
    cam = camera or CameraIntrinsics()
    ctrl = camera_ctrl or cam
    A = ctrl.K_inv @ cam.K
    A_inv = np.linalg.inv(A)
    exact_calib = camera_ctrl is None or np.allclose(A, np.eye(3))
    rng = np.random.default_rng(seed)
    marks = target.marks()

    def observe(cMo: pin.SE3) -> Observation:
        cO = cMo.translation
        if cO[2] <= 0:
            raise MeasurementError('target behind the camera')
        C = silhouette_conic(cMo, target)
        if pixel_noise > 0:
            C_px = conic_normalized_to_pixels(C, cam.px, cam.py, cam.u0, cam.v0)
            pts = _ellipse_points(C_px, contour_points)
            pts = pts + rng.normal(0.0, pixel_noise, pts.shape)
            C = fit_conic(ctrl.pixel_to_normalized(pts))
        elif not exact_calib:
            C = A_inv.T @ C @ A_inv
        sphere = sphere_from_conic(C)
        q = {}
        for name, oP in marks.items():
            if not mark_visible(cMo, target, name):
                raise MeasurementError(f'mark {name} is hidden')
            cP = cMo.act(oP)
            if pixel_noise > 0:
                uv = cam.project(cP)[0] + rng.normal(0.0, pixel_noise, 2)
                q[name] = unit_ray(ctrl.pixel_to_normalized(uv)[0])
            elif exact_calib:
                q[name] = cP / np.linalg.norm(cP)
            else:
                xb = A @ (cP / cP[2])
                q[name] = xb / np.linalg.norm(xb)
        return Observation(sphere, q, target.kind)

    return observe


def image_observer(target: Target, camera: CameraIntrinsics | None = None,
                   camera_ctrl: CameraIntrinsics | None = None, noise_sigma: float = 0.0,
                   seed: int = 0):
    """
    Build the observer ``cMo -> Observation`` of the real vision pipeline.

    Render with the true ``camera`` (grey-level noise ``noise_sigma``, seeded), detect with
    ``camera_ctrl`` (default: the true one).
    """
    from sphere_servo.vision.detector import Detector
    from sphere_servo.vision.renderer import Renderer
    cam = camera or CameraIntrinsics()
    ctrl = camera_ctrl or cam
    renderer = Renderer(cam, target, noise_sigma=noise_sigma, seed=seed)
    detector = Detector.for_target(target)

    def observe(cMo: pin.SE3) -> Observation:
        return detector.detect(renderer.render(cMo), 'rgb8', ctrl).to_observation(target.kind)

    return observe
