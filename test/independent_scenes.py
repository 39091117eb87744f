"""
Seeded scenes for the independent renderer (:mod:`independent_render`).

Cameras, poses, textured backgrounds that straddle the detector's threshold, distractors.

Nothing here imports ``sphere_servo.vision``; the targets' geometry comes from
``sphere_servo.core.targets`` (the description the detector is told about) and the truth
from plain geometry.
"""
from __future__ import annotations

import math

from independent_render import (Ball, Camera, Cap, Checker, Disc, Light, NoiseTexture,
                                render)
import numpy as np

#: the three camera configurations of the accuracy tests
CAMERAS = {
    'vga_f600': Camera(600.0, 600.0, 320.0, 240.0, 640, 480),
    'hd_f900': Camera(900.0, 900.0, 640.0, 360.0, 1280, 720),
    'vga_px450_py480': Camera(450.0, 480.0, 296.0, 262.0, 640, 480),
}

#: (lo, hi) levels of max(R, G, B) of the textured backgrounds: both sides of the body
#: threshold a global Otsu level would put between the background and the body
CONTRASTS = ((40, 70), (30, 80), (45, 62), (20, 95))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Draw a uniformly random rotation matrix (unit quaternion from a normal sample)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def incidence(R: np.ndarray, t: np.ndarray, oP: np.ndarray) -> float:
    """Angle (rad) between a surface mark's normal and the line of sight to it."""
    n = R @ (oP / np.linalg.norm(oP))
    P = R @ oP + t
    return math.acos(float(np.clip(-n @ P / np.linalg.norm(P), -1, 1)))


def silhouette_box(cam: Camera, cO: np.ndarray, r: float):
    """Unclipped pixel box (u0, u1, v0, v1) of a ball's image (None if not all in front)."""
    d = np.linalg.norm(cO)
    if cO[2] - r <= 1e-3:
        return None
    n = cO / d
    c = cO * (1 - (r / d) ** 2)
    rho = r * math.sqrt(1 - (r / d) ** 2)
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t = np.linspace(0, 2 * math.pi, 180, endpoint=False)
    uv = cam.project(c + rho * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2))
    return uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()


def in_view(cam: Camera, cO: np.ndarray, r: float, margin: float = 3.0) -> bool:
    """Tell whether the ball's image lies in the image, ``margin`` px from its border."""
    box = silhouette_box(cam, cO, r)
    return box is not None and box[0] >= margin and box[1] <= cam.width - 1 - margin \
        and box[2] >= margin and box[3] <= cam.height - 1 - margin


def random_poses(cam: Camera, target, n: int, seed: int, max_incidence_deg: float = 70.0,
                 dist=(0.25, 1.0)):
    """
    Draw ``n`` seeded poses (R, t) of the target (cRo, and O in the camera frame).

    Distance in ``dist`` (m), the sphere fully in the image (3 px margin), both marks on the
    visible side within ``max_incidence_deg`` of the line of sight. The centre's pixel is
    uniform over the image.
    """
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        d = rng.uniform(*dist)
        u, v = rng.uniform(0, cam.width), rng.uniform(0, cam.height)
        ray = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        t = ray / np.linalg.norm(ray) * d
        if not in_view(cam, t, target.radius):
            continue
        R = _facing_rotation(rng, target, t, max_incidence_deg)
        if R is not None:
            out.append((R, t))
    return out


def _facing_rotation(rng, target, t: np.ndarray, max_incidence_deg: float):
    """Draw a rotation; return it if both marks face the camera within the angle, else None."""
    R = random_rotation(rng)
    if all(incidence(R, t, oP) < math.radians(max_incidence_deg)
           for oP in (target.oP1, target.oP2)):
        return R
    return None


def target_ball(target, R: np.ndarray, t: np.ndarray, cap_angle: float | None = None) -> Ball:
    """Build the special sphere at pose (R, t) as a :class:`Ball` with its two painted caps."""
    ang = target.mark_radius if cap_angle is None else cap_angle
    cols = target.colors
    caps = tuple(Cap(R @ (oP / np.linalg.norm(oP)), ang, cols[name])
                 for name, oP in (('P1', target.oP1), ('P2', target.oP2)))
    return Ball(np.asarray(t, float), target.radius, cols['body'], caps)


def textured_background(rng: np.random.Generator | None, contrast=None, bank: int | None = 16,
                        index: int | None = None):
    """
    Draw a checkerboard or noise texture whose levels straddle the body threshold.

    With ``bank``, the texture is one of ``bank`` fixed ones per contrast (drawn by
    ``rng``, or ``index``), so that their full-image renderings can be cached
    (:func:`independent_render.background_image` is the slow part of a frame).
    """
    if bank is not None:
        k = int(rng.integers(bank)) if index is None else index
        if contrast is None:
            contrast = CONTRASTS[k % len(CONTRASTS)]
        rng = np.random.default_rng(1000 + k)
    lo, hi = CONTRASTS[rng.integers(len(CONTRASTS))] if contrast is None else contrast
    tint = tuple(rng.uniform(0.9, 1.0, 3))
    tint = tuple(np.asarray(tint) / max(tint))          # max(R, G, B) keeps lo and hi
    kind = rng.integers(3)
    if kind == 0:
        return Checker(lo, hi, float(rng.uniform(8, 48)), float(rng.uniform(0, math.pi)),
                       tuple(rng.uniform(0, 50, 2)), tint)
    return NoiseTexture(lo, hi, float(rng.uniform(10, 60)), int(rng.integers(1 << 30)),
                        binary=bool(kind == 1), tint=tint)


def random_light(rng: np.random.Generator) -> Light:
    """Draw a light within ~50° of the camera's axis (not on the camera)."""
    d = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), -1.0])
    return Light(direction=d / np.linalg.norm(d))


def distractor(kind: str, cam: Camera, target, t: np.ndarray, rng: np.random.Generator):
    """
    Place a sphere or a flat disc beside the target, not overlapping its image.

    kinds: 'same' (a body-coloured sphere of the target's size at its distance), 'larger'
    (1.6 × the radius), 'closer' (same radius, 0.6 × the distance), 'brighter' (white),
    'dimmer' (0.7 × the body colour), 'disc' (a flat white disc facing the camera, the
    target's size). Returns None when no free place was found.
    """
    r = target.radius
    body = np.asarray(target.colors['body'], float)
    rad, scale, col = r, 1.0, tuple(body)
    if kind == 'larger':
        rad = 1.6 * r
    elif kind == 'closer':
        scale = 0.6
    elif kind == 'brighter':
        col = (252.0, 252.0, 252.0)
    elif kind == 'dimmer':
        col = tuple(0.7 * body)
    elif kind == 'disc':
        col = (250.0, 250.0, 250.0)
    tb = silhouette_box(cam, t, r)
    depth = float(np.linalg.norm(t)) * scale
    for _ in range(200):
        u, v = rng.uniform(0, cam.width), rng.uniform(0, cam.height)
        ray = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        C = ray / np.linalg.norm(ray) * depth
        if not in_view(cam, C, rad):
            continue
        box = silhouette_box(cam, C, rad)
        gap = 4.0
        if box[0] > tb[1] + gap or box[1] < tb[0] - gap or box[2] > tb[3] + gap \
                or box[3] < tb[2] - gap:
            if kind == 'disc':
                return Disc(C, -C / np.linalg.norm(C), rad, col)
            return Ball(C, rad, col)
    return None


def scenes(cam: Camera, target, n: int, seed: int, *, distractor_kind: str | None = None,
           cap_angle: float | None = None, background=None, max_incidence_deg: float = 70.0):
    """
    Yield ``n`` seeded frames ``(image, R, t, distractor)`` of the special sphere.

    Poses of :func:`random_poses`, a textured background per frame (or ``background``), a
    random light, sensor noise; a distractor of ``distractor_kind`` placed beside the target
    (None when none fits), caps of ``cap_angle`` (default: the target's).
    """
    rng = np.random.default_rng(seed + 7919)
    for R, t in random_poses(cam, target, n, seed, max_incidence_deg):
        bg = textured_background(rng) if background is None else background
        objects = [target_ball(target, R, t, cap_angle)]
        extra = None
        if distractor_kind is not None:
            extra = distractor(distractor_kind, cam, target, t, rng)
            if extra is not None:
                objects.append(extra)
        yield render(cam, objects, bg, random_light(rng), rng=rng), R, t, extra


# --- wide cameras: poses over the whole field ------------------------------------------------
def ring_points(cO: np.ndarray, r: float, n: int = 180) -> np.ndarray:
    """(n, 3) points of a ball's occluding circle seen from the camera centre."""
    d = np.linalg.norm(cO)
    nrm = cO / d
    c = cO * (1 - (r / d) ** 2)
    rho = r * math.sqrt(1 - (r / d) ** 2)
    e1 = np.cross(nrm, [0.3, -0.5, 0.8])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return c + rho * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)


def wide_in_view(cam, cO: np.ndarray, r: float, margin: float = 3.0) -> bool:
    """Tell whether a ball's occluding circle projects inside a wide camera's image."""
    uv = cam.project(ring_points(cO, r))
    if not np.all(np.isfinite(uv)):
        return False
    # a ray the camera images maps back to itself (not beyond its field or a fold)
    x, y, z = cam.rays(uv[:, 0], uv[:, 1])
    P = ring_points(cO, r)
    back = np.column_stack([x, y, z]).astype(float)
    cosang = np.einsum('ij,ij->i', back, P) / np.linalg.norm(P, axis=1)
    return bool(np.all(cosang > 1 - 1e-6) and uv[:, 0].min() >= margin
                and uv[:, 0].max() <= cam.width - 1 - margin and uv[:, 1].min() >= margin
                and uv[:, 1].max() <= cam.height - 1 - margin)


def wide_poses(cam, target, n: int, seed: int, off_deg=(0.0, 95.0), dist=(0.2, 0.5),
               max_incidence_deg: float = 70.0):
    """
    Draw ``n`` seeded poses (R, t) for a wide camera: the centre ``off_deg`` from the axis.

    The direction of O uniform in azimuth and in the angle from the optical axis within
    ``off_deg`` (deg), the distance in ``dist`` (m), the sphere fully in the image (3 px
    margin), both marks within ``max_incidence_deg`` of the line of sight.
    """
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        off = math.radians(rng.uniform(*off_deg))
        az = rng.uniform(0, 2 * math.pi)
        b = np.array([math.sin(off) * math.cos(az), math.sin(off) * math.sin(az), math.cos(off)])
        t = b * rng.uniform(*dist)
        if not wide_in_view(cam, t, target.radius):
            continue
        R = _facing_rotation(rng, target, t, max_incidence_deg)
        if R is not None:
            out.append((R, t))
    return out


def wide_scenes(cam, target, n: int, seed: int, bank: int = 16, **kw):
    """
    Yield ``n`` seeded frames ``(image, R, t)`` of the special sphere seen by a wide camera.

    Poses of :func:`wide_poses` (``kw``), a textured background per frame (one of ``bank``
    per contrast, :func:`textured_background`), a light within ~50° of the line of sight to
    the sphere (a light near the camera), sensor noise.
    """
    rng = np.random.default_rng(seed + 7919)
    for R, t in wide_poses(cam, target, n, seed, **kw):
        b = t / np.linalg.norm(t)
        e1 = np.cross(b, [0.3, -0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(b, e1)
        d = -b + rng.uniform(-0.6, 0.6) * e1 + rng.uniform(-0.6, 0.6) * e2
        light = Light(direction=d / np.linalg.norm(d))
        img = render(cam, [target_ball(target, R, t)], textured_background(rng, bank=bank),
                     light, rng=rng)
        yield img, R, t
