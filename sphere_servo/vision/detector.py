"""Detector (no ROS): image → the sphere's conic + the marks' image points. DESIGN.md §2.

Pipeline for one ``rgb8`` / ``bgr8`` / ``mono8`` image and the intrinsics it is *given*
(possibly wrong, for the calibration-error experiment — the detector just uses them):

1. ``V = max(R, G, B)`` (marks are as bright as the body in V, so they neither hole nor notch
   the silhouette), Otsu threshold, outer contours (holes are ignored: "fill the holes").
2. Pick the candidate blob that is bright, contrasted, elliptical and body-coloured.
3. Sub-pixel edge: along the coarse ellipse's normal at each contour point that is *not on
   the image border*, the edge offset is the area under the anti-aliased step,
   ``e = Σ_j c(o_j) − (K + ½)`` with ``c = (I − I_out)/(I_in − I_out)`` clipped to [0, 1],
   unit-spaced samples ``o_j = −K … K`` (exact for a box-filtered or blurred straight edge;
   robust to the shading gradient because the levels are taken just inside and outside).
4. Conic fit to the edge points in *normalized* coordinates (algebraic, Hartley-normalized,
   Sampson-reweighted, outliers — mark notches, the CC stick — rejected), then
   :func:`~sphere_servo.core.measurement.sphere_from_conic`.
5. Marks by colour (chromaticity, configurable). A surface mark's centre is *not* its image
   centroid (a painted cap is foreshortened, DESIGN.md §2): each pixel is back-projected on
   the estimated sphere (eq. 11–12), weighted by the surface area it covers, and the mean
   surface normal gives the cap's centre. The CC tip P3 (a small ball off the surface) is its
   image centroid.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from sphere_servo.core.measurement import (MeasurementError, Observation, SphereMeasurement,
                                conic_from_moments, sphere_from_conic, unit_ray)
from sphere_servo.core.targets import SPECIAL, Target, mark_names

ENCODINGS = ('rgb8', 'bgr8', 'mono8')
_CHANNELS = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}

_K3 = np.ones((3, 3), np.uint8)

DEFAULT_COLORS = {'body': (235, 235, 225), 'P1': (220, 30, 30), 'P2': (30, 60, 220)}


# --- sensor_msgs/Image buffer → ndarray ---------------------------------------------------
def image_from_buffer(height: int, width: int, step: int, encoding: str, data) -> np.ndarray:
    """A ``sensor_msgs/Image``-like raw buffer → ndarray, without cv_bridge.

    Returns (H, W, 3) uint8 for ``rgb8``/``bgr8`` (channel order unchanged) or (H, W) uint8
    for ``mono8``; a view on ``data`` when possible. Raises ``ValueError`` on an unsupported
    encoding, a zero size, a ``step`` smaller than a row, or ``len(data) != step · height``.
    """
    if encoding not in _CHANNELS:
        raise ValueError(f'unsupported image encoding {encoding!r}: use one of {ENCODINGS}')
    height, width, step = int(height), int(width), int(step)
    if height <= 0 or width <= 0:
        raise ValueError(f'image has zero size: {width}x{height}')
    ch = _CHANNELS[encoding]
    if step < width * ch:
        raise ValueError(f'step {step} is smaller than a row of {width} {encoding} pixels '
                         f'({width * ch} bytes)')
    buf = np.frombuffer(bytes(data) if not isinstance(data, (bytes, bytearray, memoryview,
                                                            np.ndarray)) else data,
                        dtype=np.uint8)
    if buf.size != step * height:
        raise ValueError(f'image data has {buf.size} bytes, but step·height = '
                         f'{step}·{height} = {step * height}')
    rows = buf.reshape(height, step)[:, :width * ch]
    return rows.reshape(height, width, ch) if ch == 3 else rows


# --- results ------------------------------------------------------------------------------
@dataclass
class Mark:
    """One mark. ``uv_px`` (2,) pixel and ``xy_normalized`` (2,) normalized image point of its
    centre (None when not visible); ``area_px`` its (weighted) image area; ``partial``: a
    surface cap cut by the limb, whose centre comes from its visible boundary arc (or, if
    that cannot be measured, the mark is reported not visible)."""

    name: str
    uv_px: np.ndarray | None = None
    xy_normalized: np.ndarray | None = None
    visible: bool = False
    area_px: float = 0.0
    partial: bool = False

    @property
    def q(self) -> np.ndarray:
        """Unit vector of the mark's centre (camera frame)."""
        if not self.visible or self.xy_normalized is None:
            raise MeasurementError(f'mark {self.name} is not visible')
        return unit_ray(self.xy_normalized)


@dataclass
class Detection:
    """What the detector found in one image.

    found       True when the sphere's conic was measured (marks may still be missing).
    reason      why not found ('' when found).
    conic       3×3 conic of the sphere's image in NORMALIZED image coordinates
                (``x̄ᵀ C x̄ = 0``), or None.
    sphere      :class:`SphereMeasurement` from the conic (b, r_δ, quality), or None.
    quality     eigenvalue spread of the conic (0 for a perfect sphere image).
    residual_px RMS distance (px) of the kept edge points to the fitted ellipse.
    ellipse_px  ``((u_c, v_c), (full_axis_1, full_axis_2), angle_deg)`` for cv2.ellipse.
    marks       name → :class:`Mark`.
    cut_by_border  the silhouette touches the image border (fit on the free contour only).
    n_edge_points  edge points used by the final fit.
    """

    found: bool
    reason: str = ''
    conic: np.ndarray | None = None
    sphere: SphereMeasurement | None = None
    quality: float = float('nan')
    residual_px: float = float('nan')
    ellipse_px: tuple | None = None
    marks: dict = field(default_factory=dict)
    cut_by_border: bool = False
    n_edge_points: int = 0

    def to_observation(self, kind: str = SPECIAL) -> Observation:
        """:class:`Observation` for the features: the sphere and the marks P1 and P2 ('special')
        or P1 and P3 ('cc'). Raises :class:`MeasurementError` when the sphere or one of those
        marks is missing."""
        names = mark_names(kind)
        if not self.found or self.sphere is None:
            raise MeasurementError(f'sphere not detected: {self.reason}')
        q = {}
        for name in names:
            m = self.marks.get(name)
            if m is None or not m.visible:
                raise MeasurementError(f'mark {name} is not visible')
            q[name] = m.q
        return Observation(self.sphere, q, kind)


# --- helpers -------------------------------------------------------------------------------
def _intrinsics(camera) -> tuple[float, float, float, float]:
    vals = []
    for name in ('px', 'py', 'u0', 'v0'):
        try:
            v = float(getattr(camera, name))
        except (AttributeError, TypeError, ValueError):
            raise ValueError(f'camera intrinsics lack a numeric {name!r}') from None
        vals.append(v)
    if not all(map(math.isfinite, vals)):
        raise ValueError(f'camera intrinsics must be finite, got px, py, u0, v0 = {vals}')
    if vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f'focal lengths must be > 0, got px={vals[0]}, py={vals[1]}')
    return tuple(vals)


def fit_conic(xy: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Algebraic conic fit ``a x² + b xy + c y² + d x + e y + f = 0`` to (N, 2) points, N ≥ 5,
    with Hartley normalization (centroid, RMS distance √2) and optional per-point weights.
    Returns the symmetric 3×3 conic in the input coordinates."""
    x = xy[:, 0].astype(np.float64)
    y = xy[:, 1].astype(np.float64)
    n = len(x)
    mx, my = float(x.sum()) / n, float(y.sum()) / n
    P = _homog(x, y)
    x -= mx
    y -= my
    sc = math.sqrt(2.0 / max(float(np.dot(x, x) + np.dot(y, y)) / n, 1e-300))
    return _fit_conic_P(P, mx, my, sc, weights)


def _fit_conic_P(P: np.ndarray, mx: float, my: float, sc: float,
                 weights: np.ndarray | None = None) -> np.ndarray:
    """:func:`fit_conic` of the points given as (3, N) homogeneous rows ``(x, y, 1)``,
    normalized by ``(p − (mx, my))·sc`` (any centre inside the points and scale ≈ √2 / RMS
    radius condition the scatter matrix as well as the exact centroid does: the detector
    passes its coarse ellipse's). Unit Frobenius norm."""
    D = np.empty((6, P.shape[1]))
    # rows x'², x'y', y'², x', y', 1 with (x', y') = sc·(p − m): one affine product
    np.matmul(np.array([[sc, 0.0, -sc * mx], [0.0, sc, -sc * my]]), P, out=D[3:5])
    np.multiply(D[3:5], D[3], out=D[0:2])
    np.multiply(D[4], D[4], out=D[2])
    D[5] = 1.0
    S = (D if weights is None else D * weights) @ D.T
    _, _, V = cv2.eigen(S)                 # descending: the last row is the smallest
    a, b, c, d, e, f = V[5].tolist()
    # back to the input coordinates: x' = sc·(x − mx)
    s2 = sc * sc
    A, B, Cc = a * s2, b * s2, c * s2
    Dx = d * sc - 2.0 * A * mx - B * my
    Ey = e * sc - 2.0 * Cc * my - B * mx
    F = A * mx * mx + B * mx * my + Cc * my * my - sc * (d * mx + e * my) + f
    B, Dx, Ey = 0.5 * B, 0.5 * Dx, 0.5 * Ey
    k = 1.0 / math.sqrt(A * A + Cc * Cc + F * F + 2.0 * (B * B + Dx * Dx + Ey * Ey))
    A, B, Cc, Dx, Ey, F = A * k, B * k, Cc * k, Dx * k, Ey * k, F * k
    return np.array([[A, B, Dx], [B, Cc, Ey], [Dx, Ey, F]])


def _homog(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(3, N) float64 rows x, y, 1."""
    P = np.empty((3, len(x)))
    P[0] = x
    P[1] = y
    P[2] = 1.0
    return P


def _sampson_P(C: np.ndarray, P: np.ndarray) -> np.ndarray:
    """:func:`sampson_distance` of the points given as (3, N) homogeneous rows ``(x, y, 1)``:
    with ``G = C P``, ``pᵀCp / (2 ‖(G₀, G₁)‖)`` (one product instead of a dozen ufuncs)."""
    G = C @ P
    alg = G[0] * P[0]
    alg += G[1] * P[1]
    alg += G[2]
    h = np.hypot(G[0], G[1])
    h *= 2.0
    alg /= np.maximum(h, 1e-300, out=h)
    return alg


def _sampson_xy(C: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:func:`sampson_distance` of the points (x, y) given as two (N,) arrays."""
    return _sampson_P(C, _homog(x, y))


def sampson_distance(C: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """First-order geometric distance of (N, 2) points to the conic C (same units)."""
    return _sampson_xy(C, xy[:, 0], xy[:, 1])


def ellipse_params(C: np.ndarray):
    """Centre (2,), semi-axes (2,) and angle (rad, of the first axis) of the ellipse of the
    conic C, or None if C is not a real ellipse."""
    ep = _ellipse_floats(np.asarray(C, dtype=float).tolist())
    return None if ep is None else (np.array(ep[0]), np.array(ep[1]), ep[2])


def _ellipse_floats(C: list):
    """:func:`ellipse_params` of the conic given as nested lists, in plain floats:
    ``((cx, cy), (a0, a1), angle)`` or None."""
    (a, b, d), (_, c, e), (_, _, f) = C
    det = a * c - b * b
    if not det or not math.isfinite(det):
        return None
    cx = (b * e - c * d) / det
    cy = (b * d - a * e) / det
    k = -(a * cx * cx + 2 * b * cx * cy + c * cy * cy + 2 * d * cx + 2 * e * cy + f)
    if k == 0:
        return None
    a, b, c = a / k, b / k, c / k
    # eigen-decomposition of [[a, b], [b, c]]
    m, h = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    w1, w2 = m - h, m + h
    if not (w1 > 0 and w2 > 0):
        return None
    ang = 0.5 * math.atan2(2 * b, a - c) + 0.5 * math.pi     # direction of w1 (long axis)
    return ((cx, cy), (1.0 / math.sqrt(w1), 1.0 / math.sqrt(w2)),
            math.atan2(math.sin(ang), math.cos(ang)))

def _conic_from_rrect(cx: float, cy: float, w: float, h: float, angle_deg: float) -> np.ndarray:
    """Conic (3×3, pixels) of a ``cv2.RotatedRect`` ellipse: full axis ``w`` along
    ``angle_deg``, ``h`` across it (plain floats: this runs in the detector's inner loop)."""
    a = math.radians(angle_deg)
    ca, sa = math.cos(a), math.sin(a)
    ia, ib = 4.0 / (w * w), 4.0 / (h * h)
    A00, A01, A11 = ca * ca * ia + sa * sa * ib, ca * sa * (ia - ib), sa * sa * ia + ca * ca * ib
    g0, g1 = -(A00 * cx + A01 * cy), -(A01 * cx + A11 * cy)
    return np.array([[A00, A01, g0], [A01, A11, g1], [g0, g1, -(g0 * cx + g1 * cy) - 1.0]])


def _chroma_test(c: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, w)`` such that an rgb row ``p`` has its chromaticity ``p/Σp`` within ``tol`` of
    ``c`` iff ``((p @ Q)² @ w) < 0``: ``p @ Q = (p − c·Σp, Σp)`` and ``w = (1, 1, 1, −tol²)``
    (``|p − c·Σp|² < tol²·(Σp)²``; one matrix product instead of a division per channel)."""
    Q = np.empty((3, 4), np.float32)
    Q[:, :3] = np.eye(3) - np.asarray(c, float)[None, :]
    Q[:, 3] = 1.0
    return Q, np.array([1.0, 1.0, 1.0, -tol * tol], np.float32)


# --- detector ------------------------------------------------------------------------------
class Detector:
    """Sphere + marks detector, configured by the colours of the body and the marks.

    colors          {'body': rgb, 'P1': rgb, 'P2' or 'P3': rgb} (rgb8 triplets).
    surface_marks   names of marks painted on the surface (centre by back-projection on the
                    sphere); the others (the CC tip 'P3') use their image centroid.
    min_area_px     smallest blob accepted as the sphere.
    min_contrast    smallest difference (grey levels of V) between the body just inside its
                    edge and the background just outside.
    chroma_tol      largest chromaticity distance of a pixel to a configured colour.
    min_mark_px     smallest weighted area of a visible mark.
    K               half-length (px) of the edge profiles (sub-pixel step).
    max_edge_points largest number of edge points of the final fit.
    coarse_step     subsampling of the image in which the blob is found (1: none).
    mark_radius     angular radius (rad) of the painted caps (fits a cap cut by the limb).
    """

    def __init__(self, colors: dict | None = None, surface_marks=('P1', 'P2'), *,
                 min_area_px: float = 30.0, min_contrast: float = 25.0,
                 chroma_tol: float = 0.12, body_chroma_tol: float = 0.08,
                 min_mark_px: float = 3.0, K: int = 3, max_edge_points: int = 100,
                 coarse_step: int = 4, mark_radius: float = float(np.radians(9.0))):
        self.colors = dict(DEFAULT_COLORS if colors is None else colors)
        if 'body' not in self.colors:
            raise ValueError("colors must contain 'body'")
        self.mark_names = tuple(k for k in self.colors if k != 'body')
        self.surface_marks = set(surface_marks)
        self.min_area_px = float(min_area_px)
        self.min_contrast = float(min_contrast)
        self.chroma_tol = float(chroma_tol)
        self.body_chroma_tol = float(body_chroma_tol)
        self.min_mark_px = float(min_mark_px)
        self.K = int(K)
        self.max_edge_points = int(max_edge_points)
        self.coarse_step = max(1, int(coarse_step))
        self._chroma = {k: self._to_chroma(np.asarray(v, float)) for k, v in
                        self.colors.items()}
        Q, w = _chroma_test(self._chroma['body'], 1.5 * self.body_chroma_tol)
        self._body_test = {False: Q, True: np.ascontiguousarray(Q[::-1])}, w
        self.cos_mark = float(np.cos(mark_radius))
        self.limb_px = 1.5       # a cap's (grown) pixels this close to the silhouette (px):
        #                          the cap is treated as cut by the limb
        body = np.asarray(self.colors['body'], float)
        # (3, 2): rgb → (a, b) with rgb ≈ a·mark + b·body (least squares)
        self._unmix = {k: np.linalg.pinv(np.column_stack([np.asarray(v, float), body])).T
                       for k, v in self.colors.items() if k != 'body'}
        for k, U in self._unmix.items():        # columns a and a + b: α = a / (a + b)
            U[:, 1] += U[:, 0]
        # all marks' chromaticity tests in one product: (3, 4·n) and block weights (4·n, n)
        tests = [_chroma_test(self._chroma[k], self.chroma_tol) for k in self.mark_names]
        self._mark_Q = np.hstack([Q for Q, _ in tests]) if tests else np.zeros((3, 0), np.float32)
        self._mark_w = np.zeros((4 * len(tests), len(tests)), np.float32)
        for i, (_, w) in enumerate(tests):
            self._mark_w[4 * i:4 * i + 4, i] = w

    @classmethod
    def for_target(cls, target: Target, **kw) -> 'Detector':
        """Detector for the colours and mark names of ``target``."""
        a, b = target.mark_names
        cols = target.colors
        colors = {'body': cols['body'], a: cols[a], b: cols.get(b, cols.get('P2'))}
        surface = (a, b) if target.kind == SPECIAL else (a,)
        kw.setdefault('mark_radius', target.mark_radius)
        return cls(colors, surface, **kw)

    @staticmethod
    def _to_chroma(rgb: np.ndarray) -> np.ndarray:
        tot = rgb[..., 0] + rgb[..., 1] + rgb[..., 2]     # (a last-axis .sum is slow)
        return rgb / np.maximum(tot, 1e-9)[..., None]

    # --- public ---------------------------------------------------------------------------
    def detect(self, image: np.ndarray, encoding: str, camera) -> Detection:
        """Detect the sphere and the marks in ``image`` ((H, W, 3) for rgb8/bgr8, (H, W) or
        (H, W, 1) for mono8, uint8) with the intrinsics ``camera`` (anything with px, py, u0,
        v0; a :class:`CameraIntrinsics`). Raises ``ValueError`` on a bad image/encoding/
        intrinsics; returns ``Detection(found=False, reason=...)`` when there is no usable
        target."""
        px, py, u0, v0 = _intrinsics(camera)
        img = self._check_image(image, encoding)
        H, W = img.shape[:2]
        rgb = None if img.ndim == 2 else (img if encoding == 'rgb8' else img[..., ::-1])
        # find the blob on a subsampled image (nearest: pixel (i, j) is pixel (s·i, s·j));
        # everything at full resolution happens along the blob's edge and in its box only
        s = max(1, min(self.coarse_step, min(H, W) // 60))
        res = self._find(img, rgb, s, W, H)
        if isinstance(res, str) and s > 1 and res.startswith(('no bright', 'largest blob')):
            res = self._find(img, rgb, 1, W, H)         # a tiny target: full resolution
        if isinstance(res, str):
            reason = res
            if rgb is not None and self._fills_frame(rgb):
                reason = 'target too large for the image (the body fills the frame)'
            return Detection(False, reason, marks={n: Mark(n) for n in self.mark_names})
        C_px, resid, n_pts, ep, cut, thr = res
        # C_n = Kᵀ C_px K / ‖·‖ with K = [[px, 0, u0], [0, py, v0], [0, 0, 1]] (floats)
        (a, b, d), (_, c, e), (_, _, f) = C_px.tolist()
        gu, gv = a * u0 + b * v0 + d, b * u0 + c * v0 + e
        n00, n01, n11 = px * px * a, px * py * b, py * py * c
        n02, n12 = px * gu, py * gv
        n22 = u0 * gu + v0 * gv + d * u0 + e * v0 + f
        nrm = math.sqrt(n00 * n00 + n11 * n11 + n22 * n22
                        + 2.0 * (n01 * n01 + n02 * n02 + n12 * n12))
        C_n = np.array([[n00, n01, n02], [n01, n11, n12], [n02, n12, n22]]) / nrm
        try:
            sphere = sphere_from_conic(C_n)
        except MeasurementError as exc:
            return Detection(False, f'fitted conic is not a sphere image: {exc}',
                             marks={n: Mark(n) for n in self.mark_names})
        c, ax, ang = ep
        det = Detection(True, '', C_n, sphere, sphere.quality, resid,
                        (c, (2.0 * ax[0], 2.0 * ax[1]), math.degrees(ang)), {}, cut, n_pts)
        det.marks = self._marks(img, encoding, rgb, thr, sphere, (px, py, u0, v0), ep, C_px)
        return det

    # --- steps ----------------------------------------------------------------------------
    @staticmethod
    def _check_image(image, encoding: str) -> np.ndarray:
        if encoding not in _CHANNELS:
            raise ValueError(f'unsupported image encoding {encoding!r}: use one of '
                             f'{ENCODINGS}')
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise ValueError(f'image must be uint8, got {img.dtype}')
        if img.ndim == 3 and img.shape[2] == 1 and encoding == 'mono8':
            img = img[..., 0]
        want = 3 if _CHANNELS[encoding] == 3 else 2
        if img.ndim != want or (want == 3 and img.shape[2] != 3):
            raise ValueError(f'{encoding} image must have shape '
                             f'{"(H, W, 3)" if want == 3 else "(H, W)"}, got {img.shape}')
        if img.size == 0:
            raise ValueError(f'image has zero size: shape {img.shape}')
        return np.ascontiguousarray(img)

    def _find(self, img, rgb, s: int, W: int, H: int):
        """Threshold ``V = max(R, G, B)`` of the image subsampled by ``s`` (Otsu), take the
        largest outer contours and fit each until one is the sphere. Returns
        ``(C_px, rms_px, n_points, cut_by_border, threshold)`` or a reason string."""
        hs, ws = H // s, W // s
        if img.ndim == 3:
            # V of the pixels (s·i, s·j): rows by a strided view, columns as the first
            # pixel of each group of s (numpy: no thread hand-offs for a 160×120 image)
            g = img[:hs * s:s, :ws * s].reshape(hs, ws, 3 * s)
            Vs = np.maximum(np.maximum(g[..., 0], g[..., 1]), g[..., 2])
        else:
            Vs = np.ascontiguousarray(img[:hs * s:s, :ws * s:s])
        thr, mask = cv2.threshold(Vs, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cands = sorted((c for c in contours if len(c) >= 8), key=cv2.contourArea,
                       reverse=True)[:6]
        reason = 'no bright blob in the image'
        for cnt in cands:
            area = cv2.contourArea(cnt) * s * s
            if area < self.min_area_px:
                reason = f'largest blob too small ({area:.0f} px < {self.min_area_px:.0f})'
                break
            pts = cnt.reshape(-1, 2)
            bx, by, bw, bh = cv2.boundingRect(cnt)
            cut = bx <= 0 or by <= 0 or bx + bw >= ws or by + bh >= hs
            if cut:
                on_border = ((pts[:, 0] <= 0) | (pts[:, 0] >= ws - 1) | (pts[:, 1] <= 0)
                             | (pts[:, 1] >= hs - 1))
                free = pts[~on_border]
            else:
                free = pts
            if len(free) < 8 or len(free) < 0.3 * len(pts):
                reason = ('target too large for the image (too little of its contour is '
                          'inside)' if cut else 'blob too small')
                continue
            if img.ndim == 3:
                # keep the contour points whose inside (2 px towards the blob's centre) is
                # body-coloured: a bright clutter shape or a mark merged with the sphere
                # must not pull the coarse ellipse
                f = free.astype(np.float32)
                dv = f.sum(axis=0) / len(f) - f
                dn = np.hypot(dv[:, 0], dv[:, 1])
                np.maximum(dn, 1e-9, out=dn)
                dv *= (2.0 / dn)[:, None]
                dv += f
                dv += 0.5
                # flat index of the full-resolution pixel (s·i, s·j)
                qi = dv.astype(np.intp) @ np.array([s * 3, s * 3 * W], np.intp)
                body = self._is_body(img.reshape(-1)[qi[:, None] + np.arange(3)],
                                     bgr=rgb is not img)
                if np.count_nonzero(body) < max(8, 0.3 * len(free)):
                    reason = 'blob is not body-coloured'
                    continue
                free = free[body]
            res = self._fit_blob(free.astype(np.float32) * s, img, rgb, s, W, H)
            if isinstance(res, str):
                reason = res
                continue
            return res + (cut, float(thr))
        return reason

    @staticmethod
    def _robust_ellipse(pts: np.ndarray, min_keep: int, tol_min: float, rounds: int = 4):
        """``cv2.fitEllipse`` on float32 (N, 2) points, dropping the points far from the fit
        (a lump on the contour: clutter touching the sphere, the CC stick) until it is tight.
        Returns ``((cx, cy), (semi-axis along angle, the other), angle_rad)`` or None."""
        P = _homog(pts[:, 0], pts[:, 1])
        for _ in range(rounds + 1):
            if len(pts) < max(6, min_keep):
                return None
            (cx, cy), (w, h), a = cv2.fitEllipseDirect(pts)
            if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(w)
                    and math.isfinite(h) and w > 0.5 and h > 0.5):
                return None
            C = _conic_from_rrect(cx, cy, w, h, a)
            d = np.abs(_sampson_P(C, P))
            rr = (cx, cy), (0.5 * w, 0.5 * h), math.radians(a)
            k = len(d) // 2
            keep = d < max(tol_min, 4.5 * float(np.partition(d, k)[k]))
            if np.count_nonzero(keep) == len(keep):
                break
            pts, P = pts[keep], P[:, keep]
        return rr

    _trig_cache: dict = {}

    @classmethod
    def _trig(cls, N: int) -> np.ndarray:
        """(2, N): cos and sin of N angles evenly spaced on [0, 2π)."""
        cs = cls._trig_cache.get(N)
        if cs is None:
            t = np.linspace(0.0, 2 * math.pi, N, endpoint=False)
            cs = cls._trig_cache[N] = np.stack([np.cos(t), np.sin(t)])
        return cs

    def _fit_blob(self, free: np.ndarray, img, rgb, s: int, W: int, H: int):
        """Sub-pixel ellipse from the free (not on the border) contour points of a blob,
        (N, 2) float32 full-resolution pixels (found at step ``s``). Returns
        ``(C_px, rms_px, n_points, ellipse_params)`` or a reason string.

        Along the coarse ellipse's outward normals (points on the image only), V is sampled
        (bilinear) at unit steps over ±(2s + 4) px; on each profile the edge is the largest
        fall of V (a mild preference for the middle keeps a nearby clutter edge from
        winning), and its sub-pixel offset is the area under the anti-aliased step in a
        window of M = K + 1 samples inside and K outside the nearest sample,
        ``e = Σ_j c(o_j) − (M + ½)``, ``c = (I − I_out)/(S − I_out)`` clipped to [0, 1]
        (exact for a box-filtered or blurred straight edge); the inside level S is
        extrapolated from 2 and 3 px inside, since the body's shade changes quickly near
        the limb. (Written for speed: one remap, flat gathers, float scalars.)"""
        n0 = len(free)
        if n0 > 400:
            free = free[np.linspace(0, n0 - 1, 400).astype(int)]
        ep = self._robust_ellipse(free, int(0.3 * min(n0, 400)), 1.0 * s)
        if ep is None:
            return 'blob is not elliptical'
        (cx, cy), (a0, a1), ang = ep
        per = math.pi * (3 * (a0 + a1) - math.sqrt((3 * a0 + a1) * (a0 + 3 * a1)))
        N = int(min(max(per / 1.5, 24), self.max_edge_points))
        ca, sa = math.cos(ang), math.sin(ang)
        # rows: point x, y (about the centre) and normal x, y (unnormalized)
        G = np.array([[a0 * ca, -a1 * sa], [a0 * sa, a1 * ca],
                      [ca / a0, -sa / a1], [sa / a0, ca / a1]]) @ self._trig(N)
        G[0] += cx
        G[1] += cy
        G[2:] /= np.hypot(G[2], G[3])
        L = 2 * s + 4
        hx, hy = 0.5 * (W - 1), 0.5 * (H - 1)
        bw = math.hypot(a0 * ca, a1 * sa)           # half-extents of the ellipse's box
        bh = math.hypot(a0 * sa, a1 * ca)
        if abs(cx - hx) + bw + L > hx - 1.0 or abs(cy - hy) + bh + L > hy - 1.0:
            px_, py_, nx, ny = G
            ok = ((np.abs(px_ - hx) + L * np.abs(nx) <= hx - 1.0)
                  & (np.abs(py_ - hy) + L * np.abs(ny) <= hy - 1.0))
            G = G[:, ok]
            N = G.shape[1]
            if N < 10:
                return 'too few clean edge points'
        px_, py_, nx, ny = G
        P = 2 * L + 1
        # sample maps (2, N·P): point + offset · normal, for offsets −L … L
        maps = G[2:, :, None] * self._offsets(L)
        maps += G[:2, :, None]
        maps = maps.astype(np.float32).reshape(2, 1, N * P)
        prof3 = cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR)
        K, M = self.K, self.K + 1
        color = prof3.ndim == 3
        if color:
            prof3 = prof3.reshape(N, P, 3)
            prof = np.maximum(np.maximum(prof3[..., 0], prof3[..., 1]), prof3[..., 2])
        else:
            prof = prof3.reshape(N, P)
        # the edge lies between samples j and j + 1 where V falls most (the window
        # j − M … j + K must fit in the profile)
        drop = np.subtract(prof[:, M:P - K], prof[:, M + 1:P - K + 1], dtype=np.float32)
        drop *= self._drop_weight(L)[:, M:P - K]
        jj = drop.argmax(axis=1)                    # j − M
        base, pick, win3, win1 = self._indices(N, P, K)
        jf = jj + base                              # flat index of sample j
        if color:
            # a mixed pixel's V = max(R, G, B) is not linear in its coverage when the
            # background's largest channel is not the body's: measure the step in the one
            # channel with the largest inside − outside contrast (a mark at the limb is as
            # bright as the body in its own channel)
            # the pixels at j − M (body test), j − 1 and j + K (contrast), (N, 3, 3)
            px3 = prof3.reshape(-1, 3)[jf[:, None] + pick]
            dc = px3[:, 1].astype(np.int16) - px3[:, 2]
            if rgb is not img:                 # bgr8: ties broken as for rgb8
                ch = 2 - dc[:, ::-1].argmax(axis=1)
            else:
                ch = dc.argmax(axis=1)
            win = prof3.reshape(-1)[(jf * 3 + ch)[:, None] + win3]
        else:
            win = prof.reshape(-1)[jf[:, None] + win1]
        # win: samples j − 2 … j + K in the chosen channel
        win = win.astype(np.float32)
        i3, i2 = win[:, 0], win[:, 1]
        i_out = 0.5 * (win[:, -1] + win[:, -2])
        contrast = i2 - i_out
        k = N // 2
        med = float(np.partition(contrast, k)[k])
        if med < self.min_contrast:
            return f'blob contrast {med:.0f} < {self.min_contrast:.0f}'
        # coverage of the samples j … j + K; the M samples inside count 1 each
        S = (i2 - i3)[:, None] * self._o1(K)        # S − I_out
        S += contrast[:, None]
        np.maximum(S, 1e-6, out=S)
        cov = win[:, 2:] - i_out[:, None]
        cov /= S
        np.minimum(np.maximum(cov, 0.0, out=cov), 1.0, out=cov)      # (np.clip is slower)
        csum = cov.sum(axis=1)
        good = (contrast > 0.5 * self.min_contrast) & (csum < 2.5)
        if color:
            # the edge is the body's only where the inside (M px in) is body-coloured
            body = self._is_body(px3[:, 0], bgr=rgb is not img)
            if np.count_nonzero(body) < 0.5 * N:
                return 'blob is not body-coloured'
            good &= body
        ng = np.count_nonzero(good)
        if ng < 10:
            return 'too few clean edge points'
        e = (csum + (jj - (L + 0.5 - M)))[good]     # offset from the ellipse point
        Gg = G[:, good]
        E = np.empty((3, ng))                       # the edge points, homogeneous rows
        np.multiply(Gg[2:], e, out=E[:2])
        E[:2] += Gg[:2]
        E[2] = 1.0
        sc = 2.0 / math.sqrt(a0 * a0 + a1 * a1)     # Hartley scale of the coarse ellipse
        C = _fit_conic_P(E, cx, cy, sc)
        for _ in range(3):
            d = _sampson_P(C, E)
            k = len(d) // 2
            med = float(np.partition(d, k)[k])
            ad = np.abs(d - med)
            sigma = 1.4826 * float(np.partition(ad, k)[k])
            keep = ad < max(3.0 * sigma, 0.3)
            nk = np.count_nonzero(keep)
            if nk < 10:
                return 'too few clean edge points'
            if nk == len(keep):
                break
            E = E[:, keep]
            C = _fit_conic_P(E, cx, cy, sc)
        else:
            d = _sampson_P(C, E)
        ep = _ellipse_floats(C.tolist())
        if ep is None:
            return 'blob is not elliptical'
        rms = math.sqrt(float(d @ d) / len(d))
        return C, rms, len(d), ep

    _offs_cache: dict = {}

    @classmethod
    def _offsets(cls, L: int) -> np.ndarray:
        o = cls._offs_cache.get(L)
        if o is None:
            o = cls._offs_cache[L] = np.arange(-L, L + 1, dtype=np.float64)
        return o

    _idx_cache: dict = {}

    @classmethod
    def _indices(cls, N: int, P: int, K: int):
        """Index helpers of the edge profiles: the flat index of sample M of each of the N
        profiles (P samples each), the offsets of samples −M, −1, K, and those of the
        window −2 … K in a 3-channel and a 1-channel profile."""
        v = cls._idx_cache.get((N, P, K))
        if v is None:
            M = K + 1
            v = cls._idx_cache[(N, P, K)] = (
                np.arange(M, N * P, P), np.array([-M, -1, K]),
                np.arange(-6, 3 * K + 1, 3), np.arange(-2, K + 1))
        return v

    _o1_cache: dict = {}

    @classmethod
    def _o1(cls, K: int) -> np.ndarray:
        o = cls._o1_cache.get(K)
        if o is None:
            o = cls._o1_cache[K] = np.arange(1, K + 2, dtype=np.float32)[None, :]
        return o

    _dw_cache: dict = {}

    @classmethod
    def _drop_weight(cls, L: int) -> np.ndarray:
        w = cls._dw_cache.get(L)
        if w is None:
            mid = np.arange(-L, L, dtype=np.float32) + 0.5
            w = cls._dw_cache[L] = (1.0 - 0.5 * (mid / (L + 1)) ** 2)[None, :]
        return w

    def _fills_frame(self, rgb: np.ndarray) -> bool:
        """All four corners and the centre of the image are body-coloured."""
        H, W = rgb.shape[:2]
        k = max(1, min(H, W) // 20)
        patches = [rgb[:k, :k], rgb[:k, -k:], rgb[-k:, :k], rgb[-k:, -k:],
                   rgb[H // 2 - k // 2:H // 2 + k // 2 + 1, W // 2 - k // 2:W // 2 + k // 2 + 1]]
        return all(np.linalg.norm(self._to_chroma(p.reshape(-1, 3).mean(axis=0))
                                  - self._chroma['body']) < self.body_chroma_tol
                   for p in patches)

    def _is_body(self, pix: np.ndarray, bgr: bool = False) -> np.ndarray:
        """(N,) bool: the (N, 3) rgb (bgr if ``bgr``) pixels have the body's chromaticity
        (within 1.5 ``body_chroma_tol``)."""
        Q, w = self._body_test
        y = pix.astype(np.float32) @ Q[bgr]
        y *= y
        return (y @ w) < 0.0

    def _marks(self, img, encoding, rgb, thr, sphere, intr, ep, C_px) -> dict:
        marks = {n: Mark(n) for n in self.mark_names}
        if rgb is None:                       # mono8: no colour, no marks
            return marks
        px, py, u0, v0 = intr
        H, W = img.shape[:2]
        (ecx, ecy), ax, _ = ep
        # the CC tip can lie outside the disc; surface marks cannot
        off_surface = any(n not in self.surface_marks for n in self.mark_names)
        rad = (1.7 if off_surface else 1.0) * max(ax) + 3
        x0, x1 = max(0, int(ecx - rad)), min(W, int(ecx + rad) + 1)
        y0, y1 = max(0, int(ecy - rad)), min(H, int(ecy + rad) + 1)
        if x0 >= x1 or y0 >= y1:
            return marks
        # one pass over the box: saturated (max − min ≥ 0.27 max, HSV S ≥ 69) and bright
        # enough (not the dark background) are the mark candidates
        hsv = cv2.cvtColor(img[y0:y1, x0:x1],
                           cv2.COLOR_RGB2HSV if encoding == 'rgb8' else cv2.COLOR_BGR2HSV)
        cand = cv2.findNonZero(cv2.inRange(hsv, (0, 69, math.ceil(0.75 * thr)),
                                           (255, 255, 255)))
        if cand is None:
            return marks
        cand = cand.reshape(-1, 2)
        roi = rgb[y0:y1, x0:x1]
        # (N, n_marks): chromaticity within chroma_tol of each mark's
        y = roi[cand[:, 1], cand[:, 0]].astype(np.float32) @ self._mark_Q
        y *= y
        sel_all = (y @ self._mark_w) < 0.0
        # inside of the silhouette: the sign of the conic at the ellipse's centre
        (ca, cb, cd), (_, cc, ce), (_, _, cf) = C_px.tolist()
        inside = 1.0 if (ca * ecx * ecx + 2 * cb * ecx * ecy + cc * ecy * ecy + 2 * cd * ecx
                         + 2 * ce * ecy + cf) > 0 else -1.0
        for i, name in enumerate(self.mark_names):
            sel = sel_all[:, i]
            if not sel.any():
                continue
            pts = cand[sel]
            # components on the selected pixels' box only
            lx, ly, bw, bh = cv2.boundingRect(pts)
            m = np.zeros((bh, bw), np.uint8)
            rel = pts - (lx, ly)
            ry, rx = rel[:, 1], rel[:, 0]
            m[ry, rx] = 1
            nlab, lab, st, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            if nlab < 2:
                continue
            if nlab > 2:
                st = st[1:]
                areas = st[:, cv2.CC_STAT_AREA]
                b = int(np.argmax(areas))
                # the largest blob and the pieces next to it (an occluder can split a mark)
                bx, by, bw, bh = st[b, :4].tolist()
                reach = max(bw, bh)
                near = ((areas >= 0.05 * areas[b]) & (st[:, 0] <= bx + bw + reach)
                        & (st[:, 0] + st[:, 2] >= bx - reach) & (st[:, 1] <= by + bh + reach)
                        & (st[:, 1] + st[:, 3] >= by - reach))
                if not near.all():
                    lut = np.zeros(nlab, bool)
                    lut[1:] = near
                    pts = pts[lut[lab[ry, rx]]]
            # a painted cap is convex in the image: fill its convex hull, so that a thin
            # occluder (the CC stick lies across P1's cap) does not bias the centre; its
            # box in roi coordinates, grown by 2 px for the anti-aliased rim
            hull = cv2.convexHull(pts)
            hx, hy, hw, hh = cv2.boundingRect(hull)
            gx0, gy0 = max(0, hx - 2), max(0, hy - 2)
            gx1 = min(roi.shape[1], hx + hw + 2)
            gy1 = min(roi.shape[0], hy + hh + 2)
            full = np.zeros((gy1 - gy0, gx1 - gx0), np.uint8)
            cv2.fillConvexPoly(full, hull - np.array([gx0, gy0], np.int32), 1)
            yy, xx = np.nonzero(cv2.dilate(full, _K3))
            ox, oy = x0 + gx0, y0 + gy0
            rim = None
            if name in self.surface_marks:
                # coverage by unmixing: pixel = a·shade·mark + b·shade·body, α = a/(a + b)
                ab = roi[gy0:gy1, gx0:gx1][yy, xx].astype(np.float64) @ self._unmix[name]
                alpha = ab[:, 0] / np.maximum(ab[:, 1], 1e-9)
                np.minimum(np.maximum(alpha, 0.0, out=alpha), 1.0, out=alpha)
                inner = cv2.erode(full, _K3)[yy, xx]       # 1 inside, 0 on the rim
                np.maximum(alpha, inner, out=alpha)
                # (nearly) cut by the limb? The distance to the silhouette is concave inside
                # it, so over the hull's box it is smallest at a corner; the grown pixels are
                # within 2 px of the hull: only a cap whose box has a corner within
                # limb_px + 4 px of the silhouette (or outside it) needs per-pixel distances
                bu0, bv0 = x0 + hx - 0.5, y0 + hy - 0.5
                near_limb = False
                for cu, cv_ in ((bu0, bv0), (bu0 + hw, bv0), (bu0, bv0 + hh),
                                (bu0 + hw, bv0 + hh)):
                    g0 = ca * cu + cb * cv_ + cd
                    g1 = cb * cu + cc * cv_ + ce
                    alg = inside * (g0 * cu + g1 * cv_ + cd * cu + ce * cv_ + cf)
                    if alg < (self.limb_px + 4.0) * 2.0 * math.hypot(g0, g1):
                        near_limb = True
                        break
                Ppx = _homog(xx, yy)
                Ppx[0] += ox
                Ppx[1] += oy
                if near_limb:
                    dsil = np.abs(_sampson_P(C_px, Ppx))
                    if float(dsil.min()) < self.limb_px:
                        # the visible part's mean is biased; use the boundary with the body,
                        # away from the silhouette
                        rim = ((inner == 0) & (alpha > 0.2) & (alpha < 0.8)
                               & (dsil > self.limb_px + 1.0))
            else:
                # an off-surface ball (CC tip): its filled hull, binary (its rim may blend
                # with the background, whose chromaticity says nothing of coverage)
                alpha = full[yy, xx].astype(np.float64)
            area = float(alpha.sum())
            if area < self.min_mark_px:
                continue
            if name in self.surface_marks:
                Kinv = np.array([[1.0 / px, 0.0, -u0 / px], [0.0, 1.0 / py, -v0 / py],
                                 [0.0, 0.0, 1.0]])
                res = self._cap_centre(sphere, Kinv @ Ppx, alpha, rim, hits=not near_limb)
                if res is None:
                    marks[name] = Mark(name, area_px=area, partial=rim is not None)
                    continue
                xy = res[0]
            else:
                xy = self._ball_centre(xx + float(ox), yy + float(oy), alpha,
                                       (px, py, u0, v0))
                if xy is None:
                    continue
            uv = np.array([px * xy[0] + u0, py * xy[1] + v0])
            marks[name] = Mark(name, uv, xy, True, area, partial=rim is not None)
        return marks

    @staticmethod
    def _ball_centre(u, v, w, intr) -> np.ndarray | None:
        """Image of a ball's centre from its filled blob (pixels ``u, v``, weights ``w``):
        the blob's moments (Sheppard-corrected, +1/12 px²) give its ellipse, whose conic is
        that of a sphere (DESIGN.md §2), and ``b`` of :func:`sphere_from_conic` is the
        direction of the ball's centre — unlike the blob centroid, which perspective shifts
        outwards."""
        px, py, u0, v0 = intr
        sw = w.sum()
        cu, cv_ = np.sum(w * u) / sw, np.sum(w * v) / sw
        du, dv = u - cu, v - cv_
        S = np.array([[np.sum(w * du * du), np.sum(w * du * dv)],
                      [np.sum(w * du * dv), np.sum(w * dv * dv)]]) / sw + np.eye(2) / 12.0
        A = np.diag([1.0 / px, 1.0 / py])
        c_n = np.array([(cu - u0) / px, (cv_ - v0) / py])
        try:
            b = sphere_from_conic(conic_from_moments(c_n, A @ S @ A.T)).b
        except MeasurementError:
            return c_n
        return b[:2] / b[2]

    @staticmethod
    def _on_sphere(sphere: SphereMeasurement, X: np.ndarray, hits: bool = False):
        """Back-project normalized image points ``X`` (3, N) = ``(x̄, 1)`` on the estimated
        sphere (eq. 11–12, units of r). Returns ``(k, rho, nn, cos_i)``: ``k`` = 1/‖x̄‖
        (so ``q = k·X`` is the unit ray), ``rho`` = ‖P‖/r, ``nn`` = ‖ρq − s_n,t‖ (1 on the
        sphere; less for a ray that misses it, which meets its closest point) and ``cos_i``
        the cosine of the viewing incidence; the unit surface normal is
        ``n = (ρq − s_n,t)/nn``. (Scalar rows: ``|q| = 1`` turns the 3-vector norms and
        dot products into ``b·q`` and ``s·q``.) ``hits``: every ray is known to meet the
        sphere (pixels well inside the silhouette), so ``nn`` is 1 (returned as None)."""
        k = np.hypot(X[0], X[1])
        np.hypot(k, 1.0, out=k)
        np.divide(1.0, k, out=k)
        rd = sphere.r_delta
        sq = sphere.s_nt @ X
        sq *= k
        bq = rd * sq                              # b = r_δ s_n,t
        root = bq * bq
        root += rd * rd - 1.0
        np.maximum(root, 0.0, out=root)
        np.sqrt(root, out=root)
        rho = bq - root
        rho *= 1.0 / rd
        if hits:
            return k, rho, None, sq - rho
        # ‖ρq − s‖² = ρ² − 2ρ s·q + ‖s‖²
        ss = float(sphere.s_nt @ sphere.s_nt)
        nn = rho * (rho - 2.0 * sq)
        nn += ss
        np.maximum(nn, 1e-24, out=nn)
        np.sqrt(nn, out=nn)
        cos_i = sq - rho
        cos_i /= nn
        return k, rho, nn, cos_i

    def _cap_centre(self, sphere: SphereMeasurement, X, w, rim=None, hits: bool = False):
        """Centre of a painted cap from its pixels (normalized coords ``X`` (3, N) =
        ``(x̄, 1)``, coverage ``w``).

        Whole cap: back-project the pixels on the sphere (units of r, eq. 11–12), weight
        each by the surface area of its footprint (``‖P‖² / (‖x̄‖³ cos i)``) and average the
        unit normals (DESIGN.md §2, second lesson).

        ``rim`` (bool mask of the pixels on the cap's boundary with the body, away from the
        silhouette) is given when the cap is cut by the limb: then the visible part's mean
        is biased towards the camera, and the centre comes instead from the cap's boundary
        circle, ``n·m = cos(mark_radius)`` on the sphere, fitted (Gauss–Newton on the unit
        m, weights cos² i for the back-projection's sensitivity, outliers — the CC stick —
        dropped) to the rim pixels' normals.

        Returns ``(xy of s_n,t + m, m)`` or None when the centre cannot be measured (it
        faces away from the camera, or too little rim is visible)."""
        k, rho, nn, cos_i = self._on_sphere(sphere, X, hits and rim is None)
        s_nt = sphere.s_nt
        # Σ wa·n with n = (ρ k X − s)/nn and wa = w ρ² k³ / max(cos i, 0.1)
        t = rho * k
        c = t * t
        c *= k
        c *= w
        c /= np.maximum(cos_i, 0.1)
        if nn is not None:
            c /= nn
        m = X @ (c * t) - float(c.sum()) * s_nt
        m /= max(math.sqrt(float(m @ m)), 1e-300)
        if rim is not None:
            if np.count_nonzero(rim) < 8:
                return None
            ir = 1.0 / nn[rim]
            nb = X[:, rim] * (rho[rim] * k[rim] * ir) - s_nt[:, None] * ir
            cb = np.maximum(cos_i[rim], 0.05)
            wb = cb * cb
            cosr = self.cos_mark
            # the weighted sums over the rim as moments: Σ w n nᵀ and Σ w n, so that
            # each step costs 3×3 products (J_a = t_a·n, residual m·n − cos r)
            S, mu = (nb * wb) @ nb.T, nb @ wb
            for it in range(6):
                # tangent basis (t1, t2) at m, then one weighted Gauss–Newton step
                mx, my, mz = m.tolist()
                if abs(mx) < 0.9:
                    t1x, t1y, t1z = 0.0, -mz, my
                else:
                    t1x, t1y, t1z = mz, 0.0, -mx
                tn = 1.0 / math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
                t1x, t1y, t1z = t1x * tn, t1y * tn, t1z * tn
                t2 = (my * t1z - mz * t1y, mz * t1x - mx * t1z, mx * t1y - my * t1x)
                T = np.array([m.tolist(), [t1x, t1y, t1z], t2])
                (m0, a11, a12), (m1, _, a22) = (T[1:] @ S @ T.T).tolist()
                _, v1, v2 = (T @ mu).tolist()
                g1, g2 = m0 - cosr * v1, m1 - cosr * v2
                det = a11 * a22 - a12 * a12
                if det < 1e-18:
                    return None
                d1, d2 = -(a22 * g1 - a12 * g2) / det, -(a11 * g2 - a12 * g1) / det
                m = np.array([mx + d1 * t1x + d2 * t2[0], my + d1 * t1y + d2 * t2[1],
                              mz + d1 * t1z + d2 * t2[2]])
                m /= math.sqrt(float(m @ m))
                if it == 1:                     # drop outliers once (the CC stick's rim)
                    r = np.abs(m @ nb - cosr)
                    kk = len(r) // 2
                    keep = r < max(3.0 * 1.4826 * float(np.partition(r, kk)[kk]), 2e-3)
                    if np.count_nonzero(keep) < 8:
                        return None
                    nb, wb = nb[:, keep], wb[keep]
                    S, mu = (nb * wb) @ nb.T, nb @ wb
                elif max(abs(d1), abs(d2)) < 1e-7:
                    break
        P = s_nt + m
        if P[2] <= 0 or float(m @ P) >= 0:      # the centre faces away: not measurable
            return None
        return P[:2] / P[2], m

def detect(image: np.ndarray, encoding: str, camera, target: Target | None = None,
           **kw) -> Detection:
    """One-shot :meth:`Detector.detect` (colours from ``target`` if given, else defaults)."""
    det = Detector.for_target(target, **kw) if target is not None else Detector(**kw)
    return det.detect(image, encoding, camera)
