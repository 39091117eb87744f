"""
Backgrounds and distractors of the renderer (no ROS): the scene behind the target.

Backgrounds (:func:`make_background`):

- 'gradient': a dark smooth gradient with low-frequency texture; 'clutter': the same plus
  random dark-to-mid coloured shapes and lines; 'flat': grey 40;
- 'checker': a checkerboard of two grey levels ``levels = (lo, hi)`` of max(R, G, B), squares
  of ``texture_px``, randomly rotated and shifted; 'noise': blotches of the same two
  levels (the sign of a band-limited random field of feature size ``texture_px``). With
  levels on both sides of the level a global threshold puts between the background and the
  body (e.g. 40 and 70), they are the hard case of a detector; both are box-filtered
  (4 × 4 samples per pixel) and slightly tinted;
- or an (H, W, 3) uint8 image used as is.

Distractors (:class:`Distractor`): spheres (shaded like the target's body) and flat discs
(uniform colour), given in the camera frame, drawn into the background with 4 × 4
supersampled edges — so behind the target, whatever their depth.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import cv2
import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.conics import conic_bbox, conic_normalized_to_pixels, sphere_silhouette

BACKGROUNDS = ('gradient', 'clutter', 'flat', 'checker', 'noise')
_SS = 4                                         # samples per pixel and axis (box filter)


def _sub_grid(w: int, h: int, u0: float = 0.0, v0: float = 0.0):
    """(h·ss, w·ss) sub-sample pixel coordinates of the box [u0, u0 + w) × [v0, v0 + h)."""
    o = (np.arange(_SS) + 0.5) / _SS - 0.5
    us = (u0 + np.arange(w)[:, None] + o[None, :]).ravel().astype(np.float32)
    vs = (v0 + np.arange(h)[:, None] + o[None, :]).ravel().astype(np.float32)
    return np.meshgrid(us, vs)


def _box_mean(a: np.ndarray) -> np.ndarray:
    """Mean over the ss × ss blocks of an (h·ss, w·ss[, c]) array."""
    h, w = a.shape[0] // _SS, a.shape[1] // _SS
    return a.reshape(h, _SS, w, _SS, *a.shape[2:]).mean(axis=(1, 3))


def _two_levels(kind: str, width: int, height: int, levels, texture_px: float,
                rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 checkerboard or noise blotches of two levels, box-filtered."""
    lo, hi = (float(x) for x in levels)
    u, v = _sub_grid(width, height)
    if kind == 'checker':
        a = rng.uniform(0, math.pi)
        off = rng.uniform(0, texture_px, 2)
        ca, sa = math.cos(a), math.sin(a)
        i = np.floor((ca * u + sa * v + off[0]) / texture_px)
        j = np.floor((-sa * u + ca * v + off[1]) / texture_px)
        on = (i + j) % 2 == 1
    else:
        f = np.zeros(u.shape, np.float32)
        for _ in range(10):
            th = rng.uniform(0, 2 * math.pi)
            k = 2 * math.pi / (texture_px * rng.uniform(0.6, 1.6))
            f += np.sin(np.float32(k * math.cos(th)) * u + np.float32(k * math.sin(th)) * v
                        + np.float32(rng.uniform(0, 2 * math.pi)))
        on = f > 0
    return _box_mean(np.where(on, np.float32(hi), np.float32(lo)))


def make_background(kind, width: int, height: int, rng: np.random.Generator, *,
                    levels=(40, 70), texture_px: float = 24.0) -> np.ndarray:
    """Make the (H, W, 3) uint8 background (see the module)."""
    if isinstance(kind, np.ndarray):
        bg = np.asarray(kind)
        if bg.shape != (height, width, 3) or bg.dtype != np.uint8:
            raise ValueError(f'background image must be ({height}, {width}, 3) uint8, '
                             f'got {bg.shape} {bg.dtype}')
        return bg.copy()
    if kind not in BACKGROUNDS:
        raise ValueError(f'background must be one of {BACKGROUNDS} or an image, got {kind!r}')
    if kind == 'flat':
        return np.full((height, width, 3), 40, np.uint8)
    if kind in ('checker', 'noise'):
        lo, hi = levels
        if not (0 <= lo <= 255 and 0 <= hi <= 255) or not texture_px > 0:
            raise ValueError(f'texture levels must be in 0..255 and its size > 0, got '
                             f'{levels}, {texture_px}')
        g = _two_levels(kind, width, height, levels, float(texture_px), rng)
        tint = rng.uniform(0.9, 1.0, 3)
        tint /= tint.max()                      # max(R, G, B) keeps the two levels
        return np.clip(g[..., None] * tint + 0.5, 0, 255).astype(np.uint8)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    un, vn = u / width, v / height
    base = np.stack([25 + 25 * un + 10 * vn, 30 + 20 * vn, 45 + 25 * (1 - un)], axis=-1)
    tex = np.zeros((height, width), np.float32)
    for _ in range(6):
        fx, fy = rng.uniform(2, 12, size=2)
        ph = rng.uniform(0, 2 * np.pi)
        tex += np.sin(2 * np.pi * (fx * un + fy * vn) + ph).astype(np.float32)
    bg = base + 3.0 * tex[..., None]
    if kind == 'clutter':
        for _ in range(12):
            col = tuple(float(c) for c in rng.uniform(20, 110, size=3))
            cx, cy = rng.uniform(0, width), rng.uniform(0, height)
            if rng.random() < 0.5:
                ax = rng.uniform(10, 60, size=2)
                cv2.ellipse(bg, (int(cx), int(cy)), (int(ax[0]), int(ax[1])),
                            float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA)
            else:
                w, h = rng.uniform(10, 80, size=2)
                cv2.rectangle(bg, (int(cx), int(cy)), (int(cx + w), int(cy + h)), col, -1)
        for _ in range(6):
            p0 = rng.uniform(0, [width, height]).astype(int)
            p1 = rng.uniform(0, [width, height]).astype(int)
            cv2.line(bg, tuple(int(x) for x in p0), tuple(int(x) for x in p1),
                     tuple(float(c) for c in rng.uniform(40, 120, size=3)), 2, cv2.LINE_AA)
    return np.clip(bg, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Distractor:
    """
    A sphere or a flat disc in the scene, not the target.

    kind     'sphere' (shaded, with the renderer's light) or 'disc' (uniform colour,
             facing the camera).
    centre   (3,) its centre in the camera optical frame (m), in front of the camera.
    radius   its radius (m).
    color    rgb8 albedo (sphere) or colour (disc).
    """

    kind: str
    centre: tuple
    radius: float
    color: tuple = (235, 235, 225)

    def __post_init__(self):
        if self.kind not in ('sphere', 'disc'):
            raise ValueError(f"distractor kind must be 'sphere' or 'disc', got {self.kind!r}")
        c = np.asarray(self.centre, float)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or not self.radius > 0 \
                or np.linalg.norm(c) <= self.radius or c[2] <= self.radius:
            raise ValueError(f'distractor must be a ball of radius > 0 wholly in front of the '
                             f'camera, got centre {self.centre}, radius {self.radius}')


def draw_distractors(bg: np.ndarray, camera: CameraIntrinsics, distractors, light,
                     ambient: float, diffuse: float, gain: float) -> np.ndarray:
    """
    Draw the distractors into the (H, W, 3) uint8 background ``bg`` (a copy, far first).

    A sphere is shaded ``gain · (ambient + diffuse · max(0, n·l))`` (the target's model),
    a disc facing the camera (its plane ⟂ its centre's ray) has its colour; each is traced
    at 4 × 4 sub-samples per pixel of its box (undistorted pinhole).
    """
    out = bg.astype(np.float32)
    H, W = bg.shape[:2]
    lx, ly, lz = (np.asarray(light, float) / np.linalg.norm(light)).tolist()
    for d in sorted(distractors, key=lambda d: -float(np.linalg.norm(d.centre))):
        cO = np.asarray(d.centre, float)
        # a disc facing the camera images a little wider than the ball of its radius
        r_box = d.radius * (1.0 if d.kind == 'sphere' else 1.1)
        box = conic_bbox(conic_normalized_to_pixels(sphere_silhouette(cO, r_box),
                                                    camera.px, camera.py, camera.u0,
                                                    camera.v0))
        if box is None:
            continue
        u0, u1 = max(0, int(math.floor(box[0])) - 1), min(W, int(math.ceil(box[1])) + 2)
        v0, v1 = max(0, int(math.floor(box[2])) - 1), min(H, int(math.ceil(box[3])) + 2)
        if u0 >= u1 or v0 >= v1:
            continue
        u, v = _sub_grid(u1 - u0, v1 - v0, u0, v0)
        x, y = (u - camera.u0) / camera.px, (v - camera.v0) / camera.py
        col = np.asarray(d.color, np.float32)
        if d.kind == 'sphere':
            dO = x * cO[0] + y * cO[1] + cO[2]
            dd = x * x + y * y + 1.0
            disc = dO * dO - dd * float(cO @ cO - d.radius ** 2)
            hit = disc > 0
            t = (dO - np.sqrt(np.maximum(disc, 0.0))) / dd
            lam = (t * (x * lx + y * ly + lz) - float(cO @ (lx, ly, lz))) / d.radius
            f = gain * (ambient + diffuse * np.maximum(lam, 0.0))
            val = f[..., None] * col
        else:
            n = cO / np.linalg.norm(cO)
            t = float(cO @ n) / (x * n[0] + y * n[1] + n[2])
            hit = (t * x - cO[0]) ** 2 + (t * y - cO[1]) ** 2 + (t - cO[2]) ** 2 \
                <= d.radius ** 2
            val = np.broadcast_to(col, hit.shape + (3,))
        roi = out[v0:v1, u0:u1]
        cover = _box_mean(hit.astype(np.float32))[..., None]
        paint = _box_mean(np.where(hit[..., None], val, 0.0).astype(np.float32))
        out[v0:v1, u0:u1] = roi * (1.0 - cover) + paint
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)
