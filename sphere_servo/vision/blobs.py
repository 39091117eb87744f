"""
Candidate blobs of the sphere (no ROS): global, then local, thresholds of ``V = max(R, G, B)``.

Marks are as bright as the body in V, so they neither hole nor notch the silhouette. The
blobs are found in the image subsampled by ``s`` (nearest), in coarse pixels:

1. the global Otsu level of V separates the bright blobs (outer contours: holes are
   ignored);
2. a blob whose contour is not elliptical may be the sphere merged with bright background
   (a checker square, a blotch of texture, a clutter shape): it is split into its pixels
   of the sphere's colours, and, when the values of V inside it are bimodal, again at a
   threshold *local to it*, just above its lower class (the background inside the merge);
   its parts become candidates in turn;
3. on demand (:meth:`BlobFinder.grow`), an elliptical blob is grown down to a level local
   to it, just above the background around it, when a higher level may have cut into the
   sphere's shaded side.

Each :class:`Blob` carries its contour, the level that separated it and how elliptical its
contour is; the silhouette's fit (:mod:`~sphere_servo.vision.silhouette`) and the
detector's scoring (:mod:`~sphere_servo.vision.detector`) decide which one is the sphere.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import cv2
import numpy as np

from sphere_servo.core.conics import conic_from_rotated_rect
from sphere_servo.core.types import Image

# a contour point within max(1 coarse px, this fraction of the mean semi-axis) of the
# contour's own ellipse counts as on it (quantization of a disc's contour: ~0.5 px)
ON_ELLIPSE = 0.08
# at least this fraction of the free contour on its ellipse: elliptical (not split)
ELLIPTICAL = 0.85
# circularity 4πA/P² of a contour as round as a small disc's (a pixel chain's perimeter is
# ~10 % longer than the circle's)
ROUND = 0.7


@dataclass(frozen=True)
class Blob:
    """
    A candidate region of the coarse image.

    contour      (N, 2) int32 outer contour, coarse pixels.
    free         (M,) bool: the contour points not on the image border.
    threshold    level of V that separated it (grey levels).
    area         its area (coarse px²).
    level        0 for the global threshold, k after k local splits (or a growth).
    ellipticity  fraction of its free contour within tolerance of that contour's ellipse.
    grown        grown down from another blob (:meth:`BlobFinder.grow`).
    """

    contour: np.ndarray
    free: np.ndarray
    threshold: float
    area: float
    level: int
    ellipticity: float
    grown: bool = False

    def centre(self, s: int) -> tuple[float, float]:
        """Return the centre of its box, in full-resolution pixels (found at step ``s``)."""
        x, y, w, h = cv2.boundingRect(self.contour)
        return (x + 0.5 * (w - 1)) * s, (y + 0.5 * (h - 1)) * s

    @property
    def cut(self) -> bool:
        """Tell whether the blob touches the image border."""
        return not bool(self.free.all())

    @property
    def border_fraction(self) -> float:
        """Return the fraction of its contour on the image border."""
        return 1.0 - float(np.count_nonzero(self.free)) / len(self.free)


def coarse_v(img: Image, s: int) -> Image:
    """``V = max(R, G, B)`` (or the grey level) of the pixels ``(s·i, s·j)``."""
    H, W = img.shape[:2]
    hs, ws = H // s, W // s
    if img.ndim == 3:
        # rows by a strided view, columns as the first pixel of each group of s (numpy: no
        # thread hand-offs for a 160×120 image)
        g = img[:hs * s:s, :ws * s].reshape(hs, ws, 3 * s)
        return np.maximum(np.maximum(g[..., 0], g[..., 1]), g[..., 2])
    return np.ascontiguousarray(img[:hs * s:s, :ws * s:s])


def ellipticity(pts: np.ndarray, closed: bool = True) -> float:
    """
    Fraction of the (N, 2) contour points within tolerance of the contour's ellipse.

    A closed contour's ellipse is that of its polygon's moments, ``(p − c)ᵀ (4Σ)⁻¹ (p − c)
    = 1`` (DESIGN.md §2; cheap, and off for a merged or ragged blob); the points of an open
    one (a blob cut by the border) are fitted by ``cv2.fitEllipseDirect``. The distance of
    a point is ``|√(qᵀ A q) − 1| · √(a₀ a₁)`` (radial, in units of the mean semi-axis).
    """
    if len(pts) < 8:
        return 0.0
    f = pts.astype(np.float32)
    if closed:
        mo = cv2.moments(f)
        if mo['m00'] <= 0:
            return 0.0
        cx, cy = mo['m10'] / mo['m00'], mo['m01'] / mo['m00']
        a, b, c = (4.0 * mo['mu20'] / mo['m00'], 4.0 * mo['mu11'] / mo['m00'],
                   4.0 * mo['mu02'] / mo['m00'])
        det = a * c - b * b
        if det <= 1e-9:
            return 0.0
        A00, A01, A11 = c / det, -b / det, a / det       # (4Σ)⁻¹
        mean_axis = math.sqrt(math.sqrt(det))
    else:
        (cx, cy), (w, h), ang = cv2.fitEllipseDirect(f)
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(w)
                and math.isfinite(h) and w > 0.5 and h > 0.5):
            return 0.0
        C = conic_from_rotated_rect(cx, cy, w, h, ang)
        A00, A01, A11 = float(C[0, 0]), float(C[0, 1]), float(C[1, 1])
        mean_axis = 0.5 * math.sqrt(w * h)
    f -= np.array([cx, cy], np.float32)
    q = f @ np.array([[A00, A01], [A01, A11]], np.float32)
    q *= f
    q2 = q[:, 0] + q[:, 1]                              # (p − c)ᵀ A (p − c)
    tol = max(1.0, ON_ELLIPSE * mean_axis) / mean_axis
    on = (q2 > (1.0 - tol) ** 2) & (q2 < (1.0 + tol) ** 2)
    return float(np.count_nonzero(on)) / len(q2)


class BlobFinder:
    """
    Find the candidate blobs of a coarse V image.

    min_area        smallest blob (coarse px²).
    min_contrast    smallest gap between the two classes of V inside a blob for a local
                    split (grey levels).
    max_blobs       largest number of blobs taken from one threshold of one region.
    max_level       largest number of nested local splits.
    coloured        ``(ys, xs) → (N,) bool``: the coarse pixels that have the sphere's colours
                    (body or marks); None (mono8) for no colour split.
    """

    def __init__(self, min_area: float, min_contrast: float, max_blobs: int = 8,
                 max_level: int = 2, coloured=None):
        self.min_area = float(min_area)
        self.min_contrast = float(min_contrast)
        self.max_blobs = int(max_blobs)
        self.max_level = int(max_level)
        self.coloured = coloured

    def level(self, vals: np.ndarray) -> tuple[float, float] | None:
        """
        Find the level just above the lower class of the uint8 values ``vals`` (any shape).

        Otsu's level t_o splits the values in two classes; a level between a dark
        background and a shaded sphere is best just above the background's bright end, so
        that the sphere's shaded side stays above it: ``min(t_o, p95 + min_contrast/2)``
        with p95 the lower class's 95th percentile. Returns that level and the upper
        class's mean minus the lower one's (None when a class is empty).
        """
        t_o, _ = cv2.threshold(vals.reshape(-1, 1), 0, 255,
                               cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        hist = np.bincount(vals.ravel(), minlength=256).astype(np.float64)
        k = int(t_o) + 1
        n_lo, n_hi = float(hist[:k].sum()), float(hist[k:].sum())
        if n_lo < 1 or n_hi < 1:
            return None
        g = np.arange(256, dtype=np.float64)
        gap = float(hist[k:] @ g[k:]) / n_hi - float(hist[:k] @ g[:k]) / n_lo
        p95 = int(np.searchsorted(np.cumsum(hist[:k]), 0.95 * n_lo))
        return min(float(t_o), p95 + 0.5 * self.min_contrast), gap

    def find(self, Vs: Image) -> tuple[list[Blob], float]:
        """Return the candidate blobs of ``Vs`` (largest first per level) and its level."""
        thr, mask = cv2.threshold(Vs, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        thr = float(thr)
        out: list[Blob] = []
        self._collect(Vs, mask, thr, 0, (0, 0), out)
        return out, thr

    def _collect(self, Vs, mask, thr: float, level: int, off, out: list) -> None:
        hs, ws = Vs.shape
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE,
                                       offset=off)
        ranked = sorted((c for c in contours if len(c) >= 8), key=cv2.contourArea,
                        reverse=True)
        cands = ranked[:self.max_blobs]
        # a small sphere among more bright patches of background than max_blobs: the round
        # ones of the others too (circularity 4πA/P² of a disc's contour ≥ 0.8; background
        # patches are ragged or long)
        for c in ranked[self.max_blobs:]:
            if len(cands) >= 2 * self.max_blobs:
                break
            a = cv2.contourArea(c)
            if a < self.min_area:
                break
            if 4.0 * math.pi * a >= ROUND * cv2.arcLength(c, True) ** 2:
                cands.append(c)
        for c in cands:
            area = cv2.contourArea(c)
            if area < self.min_area:
                break
            pts = c.reshape(-1, 2)
            free = ((pts[:, 0] > 0) & (pts[:, 0] < ws - 1) & (pts[:, 1] > 0)
                    & (pts[:, 1] < hs - 1))
            e = ellipticity(pts[free], bool(free.all()))
            out.append(Blob(pts, free, thr, area, level, e))
            if e < ELLIPTICAL and level < self.max_level:
                self._split(Vs, c, thr, level, out)

    def grow(self, Vs: Image, blob: Blob) -> Blob | None:
        """
        Grow an elliptical blob down to a threshold local to it, if that is lower.

        A level set for the whole image (or for a merge) can cut into the sphere's shaded
        side. Around the blob, beyond a band of 0.3 of its radius (where the cut-off shaded
        side lies), the background's bright end is the 90th percentile of V (of the pixels
        below the blob's level: others are other bright objects); the local threshold is
        that plus ``min_contrast / 2``. The blob's component at that level is
        a candidate too, if it is still elliptical (not merged with the background): the
        grown blob, or None.
        """
        hs, ws = Vs.shape
        c, thr, area = blob.contour.reshape(-1, 1, 2), blob.threshold, blob.area
        x, y, w, h = cv2.boundingRect(c)
        band = max(1, int(round(0.3 * math.sqrt(area / math.pi))))
        g = max(2, (max(w, h) + 3) // 4) + band
        x0, y0, x1, y1 = max(0, x - g), max(0, y - g), min(ws, x + w + g), min(hs, y + h + g)
        fill = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.drawContours(fill, [c], 0, 255, -1, offset=(-x0, -y0))
        cv2.drawContours(fill, [c], 0, 255, 2 * band + 1, offset=(-x0, -y0))
        crop = Vs[y0:y1, x0:x1]
        ring = crop[fill == 0]
        ring = ring[ring <= thr]                # not other objects as bright as the blob
        if ring.size < 8:
            return None
        k = int(0.9 * (ring.size - 1))
        t = float(np.partition(ring, k)[k]) + 0.5 * self.min_contrast
        if t > thr - 2.0:
            return None
        sub = (crop > t).view(np.uint8)
        contours, _ = cv2.findContours(sub, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE,
                                       offset=(x0, y0))
        p0 = (float(c[0, 0, 0]), float(c[0, 0, 1]))
        for cg in contours:
            if len(cg) >= 8 and cv2.pointPolygonTest(cg, p0, False) >= 0:
                a = cv2.contourArea(cg)
                pts = cg.reshape(-1, 2)
                free = ((pts[:, 0] > 0) & (pts[:, 0] < ws - 1) & (pts[:, 1] > 0)
                        & (pts[:, 1] < hs - 1))
                e = ellipticity(pts[free], bool(free.all()))
                if a > area and e >= ELLIPTICAL:
                    return Blob(pts, free, t, a, blob.level + 1, e, grown=True)
                return None
        return None

    def _split(self, Vs, c, thr: float, level: int, out: list) -> None:
        """
        Split a blob by colour, and at a threshold local to it if the V inside it is bimodal.

        Otsu's level of the values inside the blob separates a lower class (the background
        merged with the sphere) from an upper one; the local threshold is just above the
        lower class, ``median + max(3σ, 3) + min_contrast / 2`` (σ from its MAD), and at
        most Otsu's level, so that the sphere's shaded side stays inside.
        """
        x, y, w, h = cv2.boundingRect(c)
        fill = np.zeros((h, w), np.uint8)
        cv2.drawContours(fill, [c], 0, 255, -1, offset=(-x, -y))
        crop = Vs[y:y + h, x:x + w]
        # the blob's own pixels (its holes are not in it: a blob merged with a texture
        # surrounds darker background)
        inside = (fill > 0) & (crop > thr)
        if self.coloured is not None:
            # coloured clutter merged with the sphere (as bright as its shaded side, so that
            # no level separates them): keep the pixels of the sphere's colours
            yy, xx = np.nonzero(inside)
            col = self.coloured(yy + y, xx + x)
            if np.count_nonzero(~col) >= 0.05 * len(col):
                sub = np.zeros_like(fill)
                sub[yy[col], xx[col]] = 1
                self._collect(Vs, sub, thr, level + 1, (x, y), out)
        vals = crop[inside]
        if vals.size < 2 * self.min_area:
            return
        lv = self.level(vals)
        if lv is None or lv[1] < self.min_contrast:
            return
        t = lv[0]
        if t <= thr:
            return
        sub = ((crop > t) & inside).view(np.uint8)
        self._collect(Vs, sub, t, level + 1, (x, y), out)
