"""
A cap's image centroid (vision.caps) against the independent renderer's painted caps.

The model projects the visible part of the cap (m, ρ) of the measured sphere; the truth is
the coverage-weighted centroid of a cap ray-cast by test/independent_render.py, seen
frontally, obliquely, near the limb and cut by it.
"""
from __future__ import annotations

import math

from independent_render import Ball, Camera, Cap, Flat, Light, render
import numpy as np
import pytest

from sphere_servo.core.measurement import SphereMeasurement
from sphere_servo.vision.caps import match_centroid, predicted_centroid

CAM = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
UNIFORM = Light(ambient=1.0, diffuse=0.0, specular=0.0)


def cap_normal(beta_deg: float, az: float, cO: np.ndarray) -> np.ndarray:
    """Return the unit normal β from the direction towards the camera (−O), at ``az``."""
    w = -cO / np.linalg.norm(cO)
    e1 = np.cross(w, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    b = math.radians(beta_deg)
    return math.cos(b) * w + math.sin(b) * (math.cos(az) * e1 + math.sin(az) * e2)


def rendered_centroid(cO, r, m, rho):
    """Measure the cap's normalized image centroid in a ray-cast image (white body, black cap)."""
    img = render(CAM, [Ball(cO, r, (255, 255, 255), (Cap(m, rho, (0, 0, 0)),))],
                 Flat((255, 255, 255)), UNIFORM, noise=None).astype(float)
    w = 1.0 - img[..., 0] / 255.0
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    x, y = (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy
    return np.array([(w * x).sum(), (w * y).sum()]) / w.sum()


@pytest.mark.parametrize('beta,deg', [(0.0, 9.0), (40.0, 9.0), (70.0, 12.0), (78.0, 9.0),
                                      (76.0, 9.0), (80.0, 15.0)])
def test_predicted_centroid_matches_the_painted_cap(beta, deg):
    """Within 0.05 px, also for caps cut by the limb (β + ρ beyond acos r_δ ≈ 84°)."""
    cO, r = np.array([0.04, -0.03, 0.45]), 0.05
    m = cap_normal(beta, 0.7, cO)
    rho = math.radians(deg)
    sphere = SphereMeasurement(cO / np.linalg.norm(cO), r / np.linalg.norm(cO))
    got = predicted_centroid(sphere, m, rho)
    want = rendered_centroid(cO, r, m, rho)
    assert np.linalg.norm(got - want) * CAM.fx < 0.05, (got - want) * CAM.fx


@pytest.mark.parametrize('beta', [20.0, 65.0, 80.0])
def test_matching_the_centroid_recovers_the_cap_centre(beta):
    cO, r = np.array([-0.05, 0.02, 0.6]), 0.05
    sphere = SphereMeasurement(cO / np.linalg.norm(cO), r / np.linalg.norm(cO))
    m = cap_normal(beta, 2.1, cO)
    rho = math.radians(9.0)
    start = m + np.array([0.03, -0.02, 0.01])
    got = match_centroid(sphere, start / np.linalg.norm(start), rho,
                         rendered_centroid(cO, r, m, rho))
    assert math.degrees(math.acos(min(1.0, float(got @ m)))) < 0.2


def test_outside_share_bound_gives_the_exact_decision(monkeypatch):
    """
    ``at_most``: the cheap bound never hides a share above it, and it bounds the share.

    Every call the detector makes on the corpus frames (both renderers, camera models,
    the CC target, cables and fringes of the adversarial renders' kind absent or present),
    and the same marks with their coverage spread by a stripe of pixels beside the cap.
    """
    from detector_corpus import cases
    import sphere_servo.vision.caps as caps
    import sphere_servo.vision.marks as marks
    calls = []

    def spy(*args, **kw):
        calls.append(args)
        return caps.outside_share(*args, **kw)
    monkeypatch.setattr(marks, 'outside_share', spy)
    for k, (_, make, img, enc, cam) in enumerate(cases()):
        if k % 2 == 0:
            make().detect(img, enc, cam)
    assert len(calls) > 50
    above = 0
    for sphere, ray, rho, q, cov, w_sr, tol in calls:
        # the mark as measured, then with a third of its pixels pushed 5–25 px off the cap
        side = np.cross(ray, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side)
        variants = [q]
        for step in (0.01, 0.04):
            shifted = q.copy()
            shifted[:, ::3] += step * side[:, None]
            variants.append(shifted / np.linalg.norm(shifted, axis=0))
        for qq in variants:
            exact = caps.outside_share(sphere, ray, rho, qq, cov, w_sr, tol)
            for limit in (0.1, 0.3):
                fast = caps.outside_share(sphere, ray, rho, qq, cov, w_sr, tol, at_most=limit)
                assert (fast > limit) == (exact > limit)
                assert fast >= exact - 1e-12
                above += exact > limit
    assert above > 10      # the shifted marks do cross the limits
