"""Pose generators shared by the core tests (not a test module)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import MeasurementError, observe
from sphere_servo.core.targets import Target

from sphere_servo.experiments.scenarios import camera_at, CMO_DESIRED, CMO_FAR_START  # noqa: F401


def random_visible_poses(target: Target, n: int, seed: int = 0,
                         camera: CameraIntrinsics | None = None) -> list[pin.SE3]:
    """
    Draw ``n`` random poses ``cMo`` at 0.25–1.0 m that see the whole target.

    From each, the sphere is entirely in front of the camera and both marks are visible
    (and in the image, if ``camera`` is given).
    """
    rng = np.random.default_rng(seed)
    camera = camera or CameraIntrinsics()
    poses = []
    while len(poses) < n:
        d = rng.uniform(0.25, 1.0)
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2]) - 0.5  # the marked cap faces −z
        eye = d * direction / np.linalg.norm(direction)
        aim = rng.normal(size=3) * 0.2 * target.radius
        cMo = camera_at(eye, rng.uniform(-180, 180), aim)
        try:
            obs = observe(cMo, target)
        except MeasurementError:
            continue
        rays = np.array([obs.sphere.b, *obs.q.values()])
        if np.all(camera.in_image(camera.project(rays), margin=5)):
            poses.append(cMo)
    return poses


def moved(cMo: pin.SE3, xi: np.ndarray) -> pin.SE3:
    """Pose after the camera moves by the twist ``xi`` (camera frame) for unit time."""
    return pin.exp6(pin.Motion(np.asarray(xi, float))).inverse() * cMo
