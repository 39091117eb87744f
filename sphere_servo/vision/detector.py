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

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..core.measurement import (MeasurementError, Observation, SphereMeasurement,
                                conic_from_moments, sphere_from_conic, unit_ray)
from ..core.targets import CC, SPECIAL, Target

ENCODINGS = ('rgb8', 'bgr8', 'mono8')
_CHANNELS = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}

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
    centre (None when not visible); ``area_px`` its (weighted) image area."""

    name: str
    uv_px: np.ndarray | None = None
    xy_normalized: np.ndarray | None = None
    visible: bool = False
    area_px: float = 0.0

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
        if kind not in (SPECIAL, CC):
            raise ValueError(f"kind must be 'special' or 'cc', got {kind!r}")
        if not self.found or self.sphere is None:
            raise MeasurementError(f'sphere not detected: {self.reason}')
        names = ('P1', 'P2') if kind == SPECIAL else ('P1', 'P3')
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
    if not all(np.isfinite(vals)):
        raise ValueError(f'camera intrinsics must be finite, got px, py, u0, v0 = {vals}')
    if vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f'focal lengths must be > 0, got px={vals[0]}, py={vals[1]}')
    return tuple(vals)


def fit_conic(xy: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Algebraic conic fit ``a x² + b xy + c y² + d x + e y + f = 0`` to (N, 2) points, N ≥ 5,
    with Hartley normalization (centroid, RMS distance √2) and optional per-point weights.
    Returns the symmetric 3×3 conic in the input coordinates."""
    m = xy.mean(axis=0)
    sc = np.sqrt(2.0) / max(np.sqrt(np.mean(np.sum((xy - m) ** 2, axis=1))), 1e-300)
    x = (xy[:, 0] - m[0]) * sc
    y = (xy[:, 1] - m[1]) * sc
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    Dw = D if weights is None else D * weights[:, None]
    _, V = np.linalg.eigh(Dw.T @ D)           # smallest eigenvector of the scatter matrix
    a, b, c, d, e, f = V[:, 0]
    Cn = np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])
    T = np.array([[sc, 0, -sc * m[0]], [0, sc, -sc * m[1]], [0, 0, 1.0]])
    C = T.T @ Cn @ T
    return C / np.linalg.norm(C)


def sampson_distance(C: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """First-order geometric distance of (N, 2) points to the conic C (same units)."""
    X = np.column_stack([xy, np.ones(len(xy))])
    CX = X @ C
    alg = np.sum(CX * X, axis=1)
    g = 2.0 * CX[:, :2]
    return alg / np.maximum(np.linalg.norm(g, axis=1), 1e-300)


def ellipse_params(C: np.ndarray):
    """Centre (2,), semi-axes (2,) and angle (rad, of the first axis) of the ellipse of the
    conic C, or None if C is not a real ellipse."""
    A = C[:2, :2]
    bvec = C[:2, 2]
    try:
        c = -np.linalg.solve(A, bvec)
    except np.linalg.LinAlgError:
        return None
    k = -(c @ A @ c + 2 * bvec @ c + C[2, 2])
    w, V = np.linalg.eigh(A / k) if k != 0 else (np.array([-1.0, -1.0]), None)
    if np.any(w <= 0):
        return None
    axes = 1.0 / np.sqrt(w)
    return c, axes, float(np.arctan2(V[1, 0], V[0, 0]))


def _depth_ratio_v(b: np.ndarray, r_delta: float, q: np.ndarray) -> np.ndarray:
    """Vectorized ``‖P‖/r`` of eq. (11)–(12), σ = −1, root clamped at 0 (DESIGN.md §2)."""
    cphi = q @ b
    sin2 = np.maximum(0.0, 1.0 - cphi * cphi)
    return (cphi - np.sqrt(np.maximum(0.0, r_delta ** 2 - sin2))) / r_delta


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
    """

    def __init__(self, colors: dict | None = None, surface_marks=('P1', 'P2'), *,
                 min_area_px: float = 30.0, min_contrast: float = 25.0,
                 chroma_tol: float = 0.12, body_chroma_tol: float = 0.08,
                 min_mark_px: float = 3.0, K: int = 3, max_edge_points: int = 300):
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
        self._chroma = {k: self._to_chroma(np.asarray(v, float)) for k, v in
                        self.colors.items()}

    @classmethod
    def for_target(cls, target: Target, **kw) -> 'Detector':
        """Detector for the colours and mark names of ``target``."""
        a, b = target.mark_names
        cols = target.colors
        colors = {'body': cols['body'], a: cols[a], b: cols.get(b, cols.get('P2'))}
        surface = (a, b) if target.kind == SPECIAL else (a,)
        return cls(colors, surface, **kw)

    @staticmethod
    def _to_chroma(rgb: np.ndarray) -> np.ndarray:
        return rgb / np.maximum(rgb.sum(axis=-1, keepdims=True), 1e-9)

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
        if img.ndim == 3:
            c0, c1, c2 = cv2.split(img)
            V = cv2.max(cv2.max(c0, c1), c2)
            rgb = img if encoding == 'rgb8' else img[..., ::-1]
        else:
            V, rgb = img, None
        thr, mask = cv2.threshold(V, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cands = sorted((c for c in contours if len(c) >= 8), key=cv2.contourArea,
                       reverse=True)[:6]
        reason = 'no bright blob in the image'
        for cnt in cands:
            area = cv2.contourArea(cnt)
            if area < self.min_area_px:
                reason = f'largest blob too small ({area:.0f} px < {self.min_area_px:.0f})'
                break
            res = self._fit_blob(cnt.reshape(-1, 2), V, rgb, W, H)
            if isinstance(res, str):
                reason = res
                continue
            C_px, resid, n_pts, cut = res
            K = np.array([[px, 0, u0], [0, py, v0], [0, 0, 1.0]])
            C_n = K.T @ C_px @ K
            C_n = C_n / np.linalg.norm(C_n)
            try:
                sphere = sphere_from_conic(C_n)
            except MeasurementError as exc:
                reason = f'fitted conic is not a sphere image: {exc}'
                continue
            ep = ellipse_params(C_px)
            c, ax, ang = ep
            det = Detection(True, '', C_n, sphere, sphere.quality, resid,
                            ((float(c[0]), float(c[1])), (float(2 * ax[0]), float(2 * ax[1])),
                             float(np.degrees(ang))), {}, cut, n_pts)
            det.marks = self._marks(img, rgb, V, float(thr), sphere, (px, py, u0, v0), ep)
            return det
        if rgb is not None and self._fills_frame(rgb):
            reason = 'target too large for the image (the body fills the frame)'
        return Detection(False, reason, marks={n: Mark(n) for n in self.mark_names})

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

    def _fit_blob(self, pts: np.ndarray, V: np.ndarray, rgb, W: int, H: int):
        """Sub-pixel ellipse of one outer contour ((N, 2) int pixels). Returns
        ``(C_px, rms_px, n_points, cut_by_border)`` or a reason string."""
        on_border = ((pts[:, 0] <= 0) | (pts[:, 0] >= W - 1) | (pts[:, 1] <= 0)
                     | (pts[:, 1] >= H - 1))
        cut = bool(on_border.any())
        free = pts[~on_border].astype(np.float64)
        if len(free) < 12 or len(free) < 0.3 * len(pts):
            return ('target too large for the image (too little of its contour is inside)'
                    if cut else 'blob too small')
        if len(free) > self.max_edge_points:
            free = free[np.linspace(0, len(free) - 1, self.max_edge_points).astype(int)]
        C = fit_conic(free)
        if ellipse_params(C) is None:
            return 'blob is not elliptical'
        # coarse robust fit: something bright touching the sphere (clutter, the CC stick)
        # adds a lump to the outer contour; drop the worst points until the fit is tight
        n0 = len(free)
        for _ in range(6):
            d = np.abs(sampson_distance(C, free))
            tol = max(1.5, 2.5 * 1.4826 * np.median(d))
            keep = d < tol
            if keep.all():
                break
            if keep.sum() < max(12, 0.3 * n0):
                return 'blob is not elliptical'
            free = free[keep]
            C = fit_conic(free)
            if ellipse_params(C) is None:
                return 'blob is not elliptical'
        # normals (outward) from the coarse conic's gradient
        X = np.column_stack([free, np.ones(len(free))])
        g = (X @ C)[:, :2]
        ep = ellipse_params(C)
        if ep is None:
            return 'blob is not elliptical'
        n = g * np.sign(np.sum(g * (free - ep[0]), axis=1))[:, None]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        K = self.K
        offs = np.arange(-K, K + 1, dtype=np.float64)
        # profiles sampled (bilinear) in a float copy of the blob's box only
        x0, y0 = max(0, int(free[:, 0].min()) - K - 2), max(0, int(free[:, 1].min()) - K - 2)
        x1 = min(W, int(free[:, 0].max()) + K + 3)
        y1 = min(H, int(free[:, 1].max()) + K + 3)
        Vf = V[y0:y1, x0:x1].astype(np.float32)
        mx = (free[:, 0:1] - x0 + offs[None, :] * n[:, 0:1]).astype(np.float32)
        my = (free[:, 1:2] - y0 + offs[None, :] * n[:, 1:2]).astype(np.float32)
        prof = cv2.remap(Vf, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        i_out = prof[:, -2:].mean(axis=1)
        # the body's shade changes quickly near the limb (its normal turns away): take the
        # inside level from the samples 1 and 2 px inside the contour, extrapolated linearly
        # across the edge, S(o) = I(−1) + (o + 1)(I(−1) − I(−2))
        i1, i2 = prof[:, K - 1], prof[:, K - 2]
        contrast = i1 - i_out
        if np.median(contrast) < self.min_contrast:
            return f'blob contrast {np.median(contrast):.0f} < {self.min_contrast:.0f}'
        if rgb is not None and not self._body_coloured(rgb, free, n):
            return 'blob is not body-coloured'
        good = contrast > 0.5 * self.min_contrast
        S = i1[:, None] + (offs[None, :] + 1.0) * (i1 - i2)[:, None]
        cov = np.clip((prof - i_out[:, None]) / np.maximum(S - i_out[:, None], 1e-6), 0, 1)
        cov[:, :K] = 1.0                      # at and beyond 1 px inside: body
        e = cov.sum(axis=1) - (K + 0.5)
        edge = free + e[:, None] * n
        inside = (edge[:, 0] > 0.5) & (edge[:, 0] < W - 1.5) & (edge[:, 1] > 0.5) \
            & (edge[:, 1] < H - 1.5)
        edge = edge[good & inside & (np.abs(e) < K - 0.5)]
        if len(edge) < 10:
            return 'too few clean edge points'
        C = fit_conic(edge)
        for _ in range(2):
            d = sampson_distance(C, edge)
            sigma = 1.4826 * np.median(np.abs(d - np.median(d)))
            keep = np.abs(d) < max(3.0 * sigma, 0.3)
            if keep.sum() < 10:
                return 'too few clean edge points'
            edge = edge[keep]
            C = fit_conic(edge)
        if ellipse_params(C) is None:
            return 'blob is not elliptical'
        rms = float(np.sqrt(np.mean(sampson_distance(C, edge) ** 2)))
        return C, rms, len(edge), cut

    def _fills_frame(self, rgb: np.ndarray) -> bool:
        """All four corners and the centre of the image are body-coloured."""
        H, W = rgb.shape[:2]
        k = max(1, min(H, W) // 20)
        patches = [rgb[:k, :k], rgb[:k, -k:], rgb[-k:, :k], rgb[-k:, -k:],
                   rgb[H // 2 - k // 2:H // 2 + k // 2 + 1, W // 2 - k // 2:W // 2 + k // 2 + 1]]
        return all(np.linalg.norm(self._to_chroma(p.reshape(-1, 3).mean(axis=0))
                                  - self._chroma['body']) < self.body_chroma_tol
                   for p in patches)

    def _body_coloured(self, rgb: np.ndarray, pts: np.ndarray, n: np.ndarray) -> bool:
        """Median chromaticity a few pixels inside the edge matches the body colour."""
        p = np.round(pts - (self.K + 1) * n).astype(int)
        H, W = rgb.shape[:2]
        p[:, 0] = np.clip(p[:, 0], 0, W - 1)
        p[:, 1] = np.clip(p[:, 1], 0, H - 1)
        ch = self._to_chroma(rgb[p[:, 1], p[:, 0]].astype(np.float64))
        return float(np.linalg.norm(np.median(ch, axis=0) - self._chroma['body'])) \
            < self.body_chroma_tol

    def _marks(self, img, rgb, V, thr, sphere, intr, ep) -> dict:
        marks = {n: Mark(n) for n in self.mark_names}
        if rgb is None:                       # mono8: no colour, no marks
            return marks
        px, py, u0, v0 = intr
        H, W = V.shape
        c, ax, _ = ep
        # the CC tip can lie outside the disc; surface marks cannot
        off_surface = any(n not in self.surface_marks for n in self.mark_names)
        rad = (1.7 if off_surface else 1.0) * float(np.max(ax)) + 3
        x0, x1 = max(0, int(c[0] - rad)), min(W, int(c[0] + rad) + 1)
        y0, y1 = max(0, int(c[1] - rad)), min(H, int(c[1] + rad) + 1)
        if x0 >= x1 or y0 >= y1:
            return marks
        roi = rgb[y0:y1, x0:x1]
        # saturated (max − min ≥ 0.27 max) and bright enough (not the dark background)
        c0, c1, c2 = roi[..., 0], roi[..., 1], roi[..., 2]
        vmax = V[y0:y1, x0:x1]
        vmin = cv2.min(cv2.min(np.ascontiguousarray(c0), np.ascontiguousarray(c1)),
                       np.ascontiguousarray(c2))
        sat = cv2.subtract(vmax, vmin)
        cand = (sat.astype(np.uint16) * 100 >= 27 * vmax.astype(np.uint16)) \
            & (vmax >= 0.75 * thr)
        cy, cx = np.nonzero(cand)
        if cy.size == 0:
            return marks
        pix = roi[cy, cx].astype(np.float64)
        ch = self._to_chroma(pix)
        body = self._chroma['body']
        for name in self.mark_names:
            mc = self._chroma[name]
            sel = np.linalg.norm(ch - mc, axis=1) < self.chroma_tol
            if not sel.any():
                continue
            m = np.zeros(cand.shape, np.uint8)
            m[cy[sel], cx[sel]] = 1
            nlab, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            if nlab < 2:
                continue
            best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
            # the largest blob and the pieces next to it (an occluder can split a mark)
            bx, by, bw, bh = stats[best, :4]
            reach = max(bw, bh)
            parts = [k for k in range(1, nlab)
                     if stats[k, cv2.CC_STAT_AREA] >= 0.05 * stats[best, cv2.CC_STAT_AREA]
                     and stats[k, 0] <= bx + bw + reach and stats[k, 0] + stats[k, 2]
                     >= bx - reach and stats[k, 1] <= by + bh + reach
                     and stats[k, 1] + stats[k, 3] >= by - reach]
            bx = min(stats[k, 0] for k in parts)
            by = min(stats[k, 1] for k in parts)
            bw = max(stats[k, 0] + stats[k, 2] for k in parts) - bx
            bh = max(stats[k, 1] + stats[k, 3] for k in parts) - by
            bx0, by0 = max(0, bx - 2), max(0, by - 2)
            bx1, by1 = min(lab.shape[1], bx + bw + 2), min(lab.shape[0], by + bh + 2)
            comp = np.isin(lab[by0:by1, bx0:bx1], parts).astype(np.uint8)
            # a painted cap is convex in the image: fill its convex hull, so that a thin
            # occluder (the CC stick lies across P1's cap) does not bias the centre
            hull = cv2.convexHull(cv2.findNonZero(comp))
            full = np.zeros_like(comp)
            cv2.fillConvexPoly(full, hull, 1)
            grown = cv2.dilate(full, np.ones((3, 3), np.uint8))
            yy, xx = np.nonzero(grown)
            p = roi[by0 + yy, bx0 + xx].astype(np.float64)
            dv = mc - body
            alpha = np.clip((self._to_chroma(p) - body) @ dv / (dv @ dv), 0.0, 1.0)
            if name in self.surface_marks:
                inner = cv2.erode(full, np.ones((3, 3), np.uint8))[yy, xx] > 0
                alpha[inner] = 1.0
            else:
                # an off-surface ball (CC tip): its filled hull, binary (its rim may blend
                # with the background, whose chromaticity says nothing of coverage)
                alpha = full[yy, xx].astype(np.float64)
            area = float(alpha.sum())
            if area < self.min_mark_px:
                continue
            u = x0 + bx0 + xx.astype(np.float64)
            v = y0 + by0 + yy.astype(np.float64)
            xn = (u - u0) / px
            yn = (v - v0) / py
            if name in self.surface_marks:
                xy = self._cap_centre(sphere, xn, yn, alpha)
            else:
                xy = self._ball_centre(u, v, alpha, (px, py, u0, v0))
            if xy is None:
                continue
            uv = np.array([px * xy[0] + u0, py * xy[1] + v0])
            marks[name] = Mark(name, uv, xy, True, area)
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
    def _cap_centre(sphere: SphereMeasurement, xn, yn, w) -> np.ndarray | None:
        """Centre of a painted cap from its pixels (normalized coords, weights ``w``):
        back-project on the sphere (units of r, eq. 11–12), weight each by the surface area
        of its footprint (``‖P‖² / (‖x̄‖³ cos i)``), average the unit normals, and project
        ``s_n,t + n̄`` back to the image (DESIGN.md §2, second lesson)."""
        xb = np.column_stack([xn, yn, np.ones_like(xn)])
        nrm = np.linalg.norm(xb, axis=1)
        q = xb / nrm[:, None]
        rho = _depth_ratio_v(sphere.b, sphere.r_delta, q)
        Pr = rho[:, None] * q
        nv = Pr - sphere.s_nt
        nv /= np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-12)
        cos_i = np.clip(-np.sum(nv * q, axis=1), 0.1, 1.0)
        wa = w * rho ** 2 / (nrm ** 3 * cos_i)
        nbar = (wa[:, None] * nv).sum(axis=0)
        if np.linalg.norm(nbar) < 1e-12:
            return None
        P = sphere.s_nt + nbar / np.linalg.norm(nbar)
        if P[2] <= 0:
            return None
        return P[:2] / P[2]


def detect(image: np.ndarray, encoding: str, camera, target: Target | None = None,
           **kw) -> Detection:
    """One-shot :meth:`Detector.detect` (colours from ``target`` if given, else defaults)."""
    det = Detector.for_target(target, **kw) if target is not None else Detector(**kw)
    return det.detect(image, encoding, camera)
