"""
An independent renderer of marked spheres, for testing the detector on images it did not make.

It shares no code with ``sphere_servo.vision`` (numpy only, no OpenCV) and makes its own
choices wherever a renderer may: every pixel of an object's box is supersampled on a regular
``ss × ss`` grid (box-filter anti-aliasing of every edge: silhouettes, caps, checkers),
rays meet balls analytically (nearest root of ``|t d − O|² = r²``), the shading is a
wrapped Lambert term with a weak Blinn–Phong highlight under a light that is not on the
camera, the sensor adds signal-dependent Gaussian noise, and the backgrounds are
checkerboards and band-limited noise textures box-filtered over 4 × 4 samples per pixel (a
pixel partly covered by an object mixes the object's sub-samples with its background).

Conventions: camera optical frame (z forward, x right, y down); pixel ``(u, v)`` is the
square ``[u − ½, u + ½) × [v − ½, v + ½)`` with its centre at integer coordinates (the
OpenCV and ROS CameraInfo convention), ray ``d = ((u − cx)/fx, (v − cy)/fy, 1)`` for the
pinhole :class:`Camera`; the wide cameras (:class:`Fisheye`, Kannala–Brandt as OpenCV's
``cv2.fisheye`` extended beyond 90°, and :class:`Unified`, Mei's model) invert their own
projection formulas here, sub-sample by sub-sample, with no code of ``sphere_servo``. Rays
that no pixel of the camera sees (outside its image circle) are black.

Scene objects are given in the camera frame:

- :class:`Ball`: a sphere, optionally with painted caps (the surface points whose direction
  from the centre is within ``angle`` of ``direction``);
- :class:`Disc`: a flat disc of uniform colour (no shading: a print or a screen).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import functools
import math

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics and image size (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    wide = False

    def project(self, P: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of (N, 3) camera-frame points (z > 0)."""
        P = np.atleast_2d(P)
        return np.column_stack([self.fx * P[:, 0] / P[:, 2] + self.cx,
                                self.fy * P[:, 1] / P[:, 2] + self.cy])

    def rays(self, u: np.ndarray, v: np.ndarray):
        """Return the directions ``(x, y, z)`` (float32) of the pixels (u, v)."""
        return (((u - self.cx) / self.fx).astype(np.float32),
                ((v - self.cy) / self.fy).astype(np.float32), np.float32(1.0))


@dataclass(frozen=True)
class Fisheye:
    """
    Equidistant fisheye: ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``, ``θ = ∠(P, z)``.

    Pixel ``(fx θ_d cos φ + cx, fy θ_d sin φ + cy)`` (φ the azimuth); rays up to ``θ < π``
    where θ_d increases.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    k: tuple = (0.0, 0.0, 0.0, 0.0)
    wide = True

    def _td(self, t):
        k1, k2, k3, k4 = self.k
        t2 = t * t
        return t * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def project(self, P: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of (N, 3) camera-frame points."""
        P = np.atleast_2d(np.asarray(P, float))
        rho = np.hypot(P[:, 0], P[:, 1])
        td = self._td(np.arctan2(rho, P[:, 2]))
        s = np.where(rho > 0, td / np.maximum(rho, 1e-300), 0.0)
        return np.column_stack([self.fx * s * P[:, 0] + self.cx, self.fy * s * P[:, 1] + self.cy])

    def rays(self, u: np.ndarray, v: np.ndarray):
        """Return the unit directions ``(x, y, z)`` (float32) of pixels (u, v), NaN: none."""
        a = (np.asarray(u, float) - self.cx) / self.fx
        b = (np.asarray(v, float) - self.cy) / self.fy
        rd = np.hypot(a, b)
        t = np.minimum(rd, 3.0)
        for _ in range(40):                  # Newton on θ_d(θ) = r_d, from θ = r_d
            h = 1e-6
            f = self._td(t) - rd
            df = (self._td(t + h) - self._td(t - h)) / (2 * h)
            t = np.clip(t - f / np.where(np.abs(df) > 1e-9, df, 1e-9), 0.0, math.pi)
        ok = (np.abs(self._td(t) - rd) < 1e-9) & (t < math.pi)
        s = np.where(rd > 0, np.sin(t) / np.maximum(rd, 1e-300), 1.0)
        x, y, z = a * s, b * s, np.cos(t)
        for c in (x, y, z):
            c[~ok] = np.nan
        return x.astype(np.float32), y.astype(np.float32), z.astype(np.float32)


@dataclass(frozen=True)
class Unified:
    """
    Mei's unified model: ``q = P/‖P‖``, ``m = (q_x, q_y)/(q_z + ξ)``, rad-tan (k1 k2 p1 p2).

    Pixel ``(fx m_dx + cx, fy m_dy + cy)``; rays with ``q_z > −ξ`` (ξ ≤ 1).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    xi: float = 0.9
    d: tuple = (0.0, 0.0, 0.0, 0.0)
    wide = True

    def _distort(self, x, y):
        k1, k2, p1, p2 = self.d
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 * r2
        return (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)

    def project(self, P: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of (N, 3) camera-frame points."""
        P = np.atleast_2d(np.asarray(P, float))
        q = P / np.linalg.norm(P, axis=1)[:, None]
        x, y = self._distort(q[:, 0] / (q[:, 2] + self.xi), q[:, 1] / (q[:, 2] + self.xi))
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])

    def rays(self, u: np.ndarray, v: np.ndarray):
        """Return the unit directions ``(x, y, z)`` (float32) of the pixels (u, v)."""
        xd = (np.asarray(u, float) - self.cx) / self.fx
        yd = (np.asarray(v, float) - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        for _ in range(30):                  # fixed point, as OpenCV's undistortPoints
            fx, fy = self._distort(x, y)
            x, y = x - (fx - xd), y - (fy - yd)
        r2 = x * x + y * y
        lam = (self.xi + np.sqrt(1 + (1 - self.xi ** 2) * r2)) / (1 + r2)
        return ((lam * x).astype(np.float32), (lam * y).astype(np.float32),
                (lam - self.xi).astype(np.float32))


@dataclass(frozen=True)
class Cap:
    """A painted spherical cap: unit ``direction`` from the ball's centre, angular radius."""

    direction: np.ndarray
    angle: float
    colour: tuple


@dataclass(frozen=True)
class Ball:
    """A shaded sphere of centre ``centre`` (camera frame, m) and radius ``radius``."""

    centre: np.ndarray
    radius: float
    colour: tuple
    caps: tuple = ()


@dataclass(frozen=True)
class Disc:
    """A flat disc (unshaded, uniform ``colour``) of centre, unit normal and radius."""

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    colour: tuple


@dataclass(frozen=True)
class Light:
    """Wrapped Lambert + Blinn–Phong: ``albedo (ambient + diffuse·wrap) + 255·spec``."""

    direction: np.ndarray = field(default_factory=lambda: np.array([0.3, -0.5, -0.8]))
    ambient: float = 0.45
    diffuse: float = 0.55
    wrap: float = 0.25
    specular: float = 0.05
    shininess: float = 30.0


# --- backgrounds: functions of continuous pixel coordinates --------------------------------
@dataclass(frozen=True)
class Checker:
    """
    A checkerboard of two grey levels ``lo``, ``hi`` (on every channel, times ``tint``).

    Squares of ``size`` px, rotated by ``angle`` rad, shifted by ``offset`` px.
    """

    lo: float
    hi: float
    size: float
    angle: float = 0.0
    offset: tuple = (0.0, 0.0)
    tint: tuple = (1.0, 1.0, 1.0)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.angle), math.sin(self.angle)
        a = np.floor((c * u + s * v + self.offset[0]) / self.size)
        b = np.floor((-s * u + c * v + self.offset[1]) / self.size)
        odd = (a + b) % 2 == 1
        g = np.where(odd, self.hi, self.lo)
        return g[..., None] * np.asarray(self.tint, float)


@dataclass(frozen=True)
class NoiseTexture:
    """
    Band-limited noise: a sum of random plane waves, mapped to the levels ``lo`` … ``hi``.

    ``binary``: the field's sign picks ``lo`` or ``hi`` (blotches with sharp edges);
    otherwise the field is mapped linearly (clipped) onto ``[lo, hi]``. ``period`` is the
    typical feature size in px.
    """

    lo: float
    hi: float
    period: float
    seed: int
    binary: bool = True
    tint: tuple = (1.0, 1.0, 1.0)
    n_waves: int = 10

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        u, v = np.asarray(u, np.float32), np.asarray(v, np.float32)
        f = np.zeros(np.broadcast(u, v).shape, np.float32)
        for _ in range(self.n_waves):
            th = rng.uniform(0, 2 * math.pi)
            k = 2 * math.pi / (self.period * rng.uniform(0.6, 1.6))
            f += np.sin(np.float32(k * math.cos(th)) * u + np.float32(k * math.sin(th)) * v
                        + np.float32(rng.uniform(0, 2 * math.pi)))
        f /= math.sqrt(self.n_waves / 2.0)
        if self.binary:
            g = np.where(f > 0, self.hi, self.lo)
        else:
            g = self.lo + (self.hi - self.lo) * np.clip(0.5 + 0.35 * f, 0.0, 1.0)
        return g[..., None] * np.asarray(self.tint, np.float32)


@dataclass(frozen=True)
class Flat:
    """A uniform background colour."""

    colour: tuple = (40.0, 40.0, 40.0)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        shape = np.broadcast(u, v).shape
        return np.broadcast_to(np.asarray(self.colour, float), shape + (3,)).copy()


# --- ray casting -----------------------------------------------------------------------------
def _sub_grid(u0: int, u1: int, v0: int, v1: int, ss: int):
    """Sub-sample coordinates (ss·h, ss·w) of the pixels [u0, u1) × [v0, v1)."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    us = (np.arange(u0, u1)[:, None] + o[None, :]).ravel()
    vs = (np.arange(v0, v1)[:, None] + o[None, :]).ravel()
    return np.meshgrid(us, vs)


def _box_mean(a: np.ndarray, ss: int) -> np.ndarray:
    """Mean over ss × ss blocks of an (ss·h, ss·w, 3) array."""
    h, w = a.shape[0] // ss, a.shape[1] // ss
    rows = a.reshape(h, ss, w * ss * 3).sum(axis=1, dtype=np.float32)
    return rows.reshape(h, w, ss, 3).sum(axis=2) * np.float32(1.0 / (ss * ss))


def _ball_box(cam: Camera, b: Ball, margin: int = 2):
    """Pixel box (u0, u1, v0, v1) of a ball's image, from its sampled occluding circle."""
    cO = np.asarray(b.centre, float)
    d = np.linalg.norm(cO)
    if d <= b.radius or (cO[2] <= b.radius and not cam.wide):
        return 0, cam.width, 0, cam.height
    n = cO / d
    c = cO * (1 - (b.radius / d) ** 2)
    rho = b.radius * math.sqrt(1 - (b.radius / d) ** 2)
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t = np.linspace(0, 2 * math.pi, 256, endpoint=False)
    P = c + rho * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    return _clip_box(cam, cam.project(P), margin)


def _disc_box(cam: Camera, dsc: Disc, margin: int = 2):
    n = np.asarray(dsc.normal, float) / np.linalg.norm(dsc.normal)
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t = np.linspace(0, 2 * math.pi, 256, endpoint=False)
    rim = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
    P = np.asarray(dsc.centre) + dsc.radius * rim
    if np.any(P[:, 2] <= 1e-6):
        return 0, cam.width, 0, cam.height
    return _clip_box(cam, cam.project(P), margin)


def _clip_box(cam, uv, margin):
    u0 = max(0, int(math.floor(uv[:, 0].min())) - margin)
    u1 = min(cam.width, int(math.ceil(uv[:, 0].max())) + margin + 1)
    v0 = max(0, int(math.floor(uv[:, 1].min())) - margin)
    v1 = min(cam.height, int(math.ceil(uv[:, 1].max())) + margin + 1)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def _shade_rays(cam: Camera, objects, light: Light, u, v, background):
    """Colour (…, 3) of the rays through the sub-pixel points (u, v)."""
    f32 = np.float32
    x, y, z = cam.rays(u, v)
    dd = x * x + y * y + z * z
    depth = np.full(u.shape, np.inf, f32)
    col = np.empty(u.shape + (3,), f32)
    L = np.asarray(light.direction, float)
    L = L / np.linalg.norm(L)
    for ob in objects:
        if isinstance(ob, Ball):
            cO = np.asarray(ob.centre, float)
            dO = x * f32(cO[0]) + y * f32(cO[1]) + z * f32(cO[2])
            disc = dO * dO - dd * f32(cO @ cO - ob.radius ** 2)
            t = (dO - np.sqrt(np.maximum(disc, 0.0))) / dd
            hit = (disc >= 0) & (t > 0) & (t < depth)
            if not hit.any():
                continue
            th, xh, yh = t[hit], x[hit], y[hit]
            zh = z[hit] if np.ndim(z) else z
            # unit normal n = (t d − O)/r; unit view direction −t d/‖t d‖
            ir = f32(1.0 / ob.radius)
            nx = (th * xh - f32(cO[0])) * ir
            ny = (th * yh - f32(cO[1])) * ir
            nz = (th * zh - f32(cO[2])) * ir
            alb = np.empty(th.shape + (3,), f32)
            alb[:] = np.asarray(ob.colour, f32)
            for cap in ob.caps:
                m = np.asarray(cap.direction, float)
                on = nx * f32(m[0]) + ny * f32(m[1]) + nz * f32(m[2]) >= f32(math.cos(cap.angle))
                alb[on] = np.asarray(cap.colour, f32)
            ndl = nx * f32(L[0]) + ny * f32(L[1]) + nz * f32(L[2])
            wrap = np.maximum((ndl + f32(light.wrap)) / f32(1.0 + light.wrap), 0.0) ** 1.5
            iv = -1.0 / np.sqrt(xh * xh + yh * yh + zh * zh)
            hx, hy, hz = xh * iv + f32(L[0]), yh * iv + f32(L[1]), zh * iv + f32(L[2])
            ndh = (nx * hx + ny * hy + nz * hz) / np.sqrt(hx * hx + hy * hy + hz * hz)
            spec = f32(255.0 * light.specular) * np.maximum(ndh, 0.0) ** f32(light.shininess)
            spec[ndl <= 0] = 0.0
            shade = f32(light.ambient) + f32(light.diffuse) * wrap
            col[hit] = alb * shade[:, None] + spec[:, None]
            depth[hit] = th
        elif isinstance(ob, Disc):
            nrm = np.asarray(ob.normal, float) / np.linalg.norm(ob.normal)
            C = np.asarray(ob.centre, float)
            den = x * f32(nrm[0]) + y * f32(nrm[1]) + z * f32(nrm[2])
            with np.errstate(divide='ignore', invalid='ignore'):
                t = f32(C @ nrm) / den
            Px, Py, Pz = t * x - f32(C[0]), t * y - f32(C[1]), t * z - f32(C[2])
            hit = (t > 0) & (t < depth) & (Px * Px + Py * Py + Pz * Pz <= f32(ob.radius ** 2))
            col[hit] = np.asarray(ob.colour, f32)
            depth[hit] = t[hit]
    miss = np.isinf(depth)
    if miss.any():
        # the sub-samples that miss every object see their pixel's box-filtered background
        col[miss] = background[np.rint(v[miss]).astype(int), np.rint(u[miss]).astype(int)]
    if np.ndim(x):
        col[np.isnan(x)] = 0.0                # no ray: outside the image circle
    return col


def render(cam: Camera, objects, background, light: Light = Light(), *, ss: int = 4,
           noise: tuple = (1.5, 0.02), rng: np.random.Generator | None = None
           ) -> np.ndarray:
    """
    Render an (H, W, 3) uint8 rgb image.

    ``background``: a hashable callable ``(u, v) → (…, 3)`` grey levels, box-filtered over
    4 × 4 samples per pixel once (cached: :func:`background_image`). Every pixel of an
    object's box is the mean of ``ss × ss`` rays (those that miss every object see the
    pixel's background); the sensor adds Gaussian noise of
    variance ``noise[0]² + noise[1]·level`` per channel (``rng``), then rounds and clips.
    """
    bg = _background_image(cam, background, 4)
    img = bg.copy()
    boxes = []
    for ob in objects:
        box = _ball_box(cam, ob) if isinstance(ob, Ball) else _disc_box(cam, ob)
        if box is not None:
            boxes.append(box)
    for u0, u1, v0, v1 in _merge(boxes):
        U, V = _sub_grid(u0, u1, v0, v1, ss)
        img[v0:v1, u0:u1] = _box_mean(_shade_rays(cam, objects, light, U, V, bg), ss)
    if noise is not None and rng is not None:
        sigma = np.sqrt(np.float32(noise[0] ** 2) + np.float32(noise[1]) * img)
        img += rng.standard_normal(img.shape, np.float32) * sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _merge(boxes):
    """Merge overlapping boxes, so no pixel is rendered twice (order does not matter)."""
    out = [list(b) for b in boxes]
    changed = True
    while changed:
        changed = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    out[i] = [min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]),
                              max(a[3], b[3])]
                    del out[j]
                    changed = True
                    break
            if changed:
                break
    return [tuple(b) for b in out]


def background_image(cam: Camera, background, ss: int = 4) -> np.ndarray:
    """Render the (H, W, 3) float background, each pixel the mean of ``ss × ss`` samples."""
    return _background_image(cam, background, ss).copy()


@functools.lru_cache(maxsize=64)
def _background_image(cam: Camera, background, ss: int) -> np.ndarray:
    out = np.empty((cam.height, cam.width, 3), np.float32)
    step = max(1, 65536 // (cam.width * ss * ss))
    for v0 in range(0, cam.height, step):
        v1 = min(cam.height, v0 + step)
        U, V = _sub_grid(0, cam.width, v0, v1, ss)
        out[v0:v1] = _box_mean(background(U, V), ss)
    if cam.wide:                               # no ray outside the image circle: black
        v, u = np.mgrid[0:cam.height, 0:cam.width]
        out[np.isnan(cam.rays(u.astype(float), v.astype(float))[0])] = 0.0
    return out
