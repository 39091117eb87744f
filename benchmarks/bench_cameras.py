"""
Benchmark of the camera models and the small-circle fit (issue 18).

Lifting a whole 640×480 image (what a renderer casts) and ~100 edge pixels (what the
detector lifts each frame) through each model, and the small-circle fit of 100 noisy edge
rays. Baselines beside them: the pinhole without distortion (a bare ``K⁻¹`` and a
normalisation) and an SVD of the 100×6 design matrix (the floor of an algebraic conic fit).
"""
from __future__ import annotations

import math

from benchmarks.bench_core import _median_us
import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera
from sphere_servo.core.small_circle import fit_small_circle

MODELS = {
    'pinhole': CameraIntrinsics(),
    'plumb_bob': CameraIntrinsics(dist=(-0.25, 0.08, 0.001, -0.0015, -0.01)),
    'plumb_bob radial': CameraIntrinsics(dist=(-0.25, 0.08, 0.0, 0.0, -0.01)),
    'fisheye equidistant': FisheyeCamera(),
    'fisheye k1..k4': FisheyeCamera(px=190.0, py=190.0, dist=(0.05, -0.01, 0.003, -0.0005)),
    'unified ξ=0.9': UnifiedCamera(),
    'unified + rad-tan': UnifiedCamera(xi=0.8, dist=(-0.1, 0.02, 0.001, -0.0005)),
}


def _edge(cam, n: int = 100) -> np.ndarray:
    """Pixels of a sphere's silhouette 30° off the axis (θ = 0.15 rad)."""
    b = np.array([math.sin(0.5), 0.0, math.cos(0.5)])
    e1, e2 = np.array([math.cos(0.5), 0.0, -math.sin(0.5)]), np.array([0.0, 1.0, 0.0])
    phi = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    q = math.cos(0.15) * b + math.sin(0.15) * (np.cos(phi)[:, None] * e1
                                               + np.sin(phi)[:, None] * e2)
    return cam.project(q)


def run(quick: bool = False) -> list[dict]:
    n_img, n_px = (3, 200) if quick else (10, 2000)
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    image = np.column_stack([u.ravel(), v.ravel()])
    rows = []
    base_img = _median_us(lambda: MODELS['pinhole'].lift_where(image), n_img) * 1e-6
    pin_edge = _edge(MODELS['pinhole'])
    base_px = _median_us(lambda: MODELS['pinhole'].lift(pin_edge), n_px) * 1e-6
    for name, cam in MODELS.items():
        edge = _edge(cam)
        t_img = _median_us(lambda: cam.lift_where(image), n_img) * 1e-6
        t_px = _median_us(lambda: cam.lift(edge), n_px) * 1e-6
        rows.append({'name': f'lift 640×480 px: {name}', 'value': t_img * 1e3, 'unit': 'ms',
                     'baseline': base_img * 1e3, 'baseline_name': 'pinhole',
                     'ratio': t_img / base_img, 'target': ''})
        rows.append({'name': f'lift 100 edge px: {name}', 'value': t_px * 1e6, 'unit': 'µs',
                     'baseline': base_px * 1e6, 'baseline_name': 'pinhole',
                     'ratio': t_px / base_px, 'target': ''})
    cam = MODELS['pinhole']
    rng = np.random.default_rng(0)
    edge = _edge(cam) + rng.normal(0.0, 0.3, (100, 2))
    q = cam.lift(edge)
    t_fit = _median_us(lambda: fit_small_circle(q), n_px) * 1e-6
    D = np.column_stack([edge[:, 0] ** 2, edge[:, 0] * edge[:, 1], edge[:, 1] ** 2,
                         edge[:, 0], edge[:, 1], np.ones(100)])
    t_svd = _median_us(lambda: np.linalg.svd(D, full_matrices=False), n_px) * 1e-6
    rows.append({'name': 'small-circle fit, 100 rays (0.3 px noise)', 'value': t_fit * 1e6,
                 'unit': 'µs', 'baseline': t_svd * 1e6, 'baseline_name': 'SVD 100×6',
                 'ratio': t_fit / t_svd, 'target': ''})
    return rows


if __name__ == '__main__':
    for row in run():
        print(row)
