"""Seeded random camera poses of a target for the detector's tests and benchmark (no ROS)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.conics import conic_bbox, conic_normalized_to_pixels, sphere_silhouette
from sphere_servo.core.measurement import mark_visible
from sphere_servo.core.targets import Target


def silhouette_px_conic(cMo: pin.SE3, target: Target, cam: CameraIntrinsics) -> np.ndarray:
    """Ground-truth conic of the sphere's image in pixels (DESIGN.md §2)."""
    return conic_normalized_to_pixels(sphere_silhouette(cMo.translation, target.radius),
                                      cam.px, cam.py, cam.u0, cam.v0)


def incidence_deg(cMo: pin.SE3, oP: np.ndarray) -> float:
    """Angle (deg) between the surface normal at the mark ``oP`` and the line of sight."""
    n = cMo.rotation @ (oP / np.linalg.norm(oP))
    cP = cMo.act(oP)
    return float(np.degrees(np.arccos(-n @ cP / np.linalg.norm(cP))))


def random_poses(target: Target, cam: CameraIntrinsics, n: int, seed: int,
                 max_incidence: float | None = 90.0, spread=(0.4, 0.3)) -> list[pin.SE3]:
    """
    Draw ``n`` seeded poses at 0.25–1.0 m, the sphere fully in the image (2 px margin).

    The sphere centre's direction is within ``spread`` (normalized x, y) of the optical
    axis, the orientation uniformly random. With ``max_incidence`` (deg) set, the target's
    marks also face the camera (core ``mark_visible``: the CC tip unoccluded), project at
    least 12 px inside the image, and the surface marks' centres are seen within
    ``max_incidence`` of their normal; ``None`` skips those mark conditions.
    """
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        d = rng.uniform(0.25, 1.0)
        ray = np.array([rng.uniform(-spread[0], spread[0]), rng.uniform(-spread[1], spread[1]),
                        1.0])
        cMo = pin.SE3(pin.exp3(rng.normal(size=3) * 2.0), ray / np.linalg.norm(ray) * d)
        box = conic_bbox(silhouette_px_conic(cMo, target, cam))
        if box is None or box[0] < 2 or box[1] > cam.width - 3 or box[2] < 2 \
                or box[3] > cam.height - 3:
            continue
        if max_incidence is not None:
            if not all(mark_visible(cMo, target, k) for k in target.mark_names):
                continue
            marks_uv = cam.project(np.array([cMo.act(p) for p in (target.oP1, target.oP2)]))
            if not cam.in_image(marks_uv, margin=12).all():
                continue
            if incidence_deg(cMo, target.oP1) > max_incidence:
                continue
            if target.kind == 'special' and incidence_deg(cMo, target.oP2) > max_incidence:
                continue
        out.append(cMo)
    return out
