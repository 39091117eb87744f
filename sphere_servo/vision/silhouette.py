"""
The sphere's silhouette (no ROS): candidate blob → sub-pixel edge → conic. DESIGN.md §2.

1. Candidate blobs of ``V = max(R, G, B)`` (:mod:`~sphere_servo.vision.blobs`: a global
   Otsu level, then levels local to each merged blob), the elliptical ones first.
2. For one blob: its contour points that are not on the image border and whose inside is
   body-coloured give a coarse ellipse.
3. Sub-pixel edge: along the coarse ellipse's normal at each point on the image, the edge
   offset is the area under the anti-aliased step,
   ``e = Σ_j c(o_j) − (K + ½)`` with ``c = (I − I_out)/(I_in − I_out)`` clipped to [0, 1],
   unit-spaced samples ``o_j = −K … K`` (exact for a box-filtered or blurred straight edge;
   robust to the shading gradient because the levels are taken just inside and outside).
4. Conic fit to the edge points (algebraic, Hartley-normalized, Sampson-reweighted,
   outliers — mark notches, the CC stick — rejected), in pixels; or, through a camera model
   (a fisheye, a catadioptric, a distorted pinhole: their silhouettes are not conics), the
   sphere's cone fitted to the lifted edge points (:mod:`~sphere_servo.vision.cone`), the
   pixel conic of its points then only drawing it.

Steps 1–3 are in pixels and assume no camera model (a silhouette through any central
camera is a smooth oval that a coarse ellipse follows within a pixel, well inside the edge
profiles); the detector maps the conic to rays. :meth:`SilhouetteFinder.candidates` lists
the blobs, and :meth:`SilhouetteFinder.fit` gives for one a :class:`Silhouette` (with the
figures the detector scores it by: residual, edge coverage, contrast) or a
:class:`~sphere_servo.vision.reasons.NotDetected` whose
:class:`~sphere_servo.vision.reasons.Reason` says why.
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math

import cv2
import numpy as np

from sphere_servo.core.conics import (conic_from_rotated_rect, Ellipse, ellipse_params,
                                      fit_conic_homogeneous, homogeneous, sampson_homogeneous)
from sphere_servo.core.types import Conic, Image
from sphere_servo.vision.blobs import Blob, BlobFinder, coarse_v, ELLIPTICAL
from sphere_servo.vision.cone import ConeFit, fit_cone
from sphere_servo.vision.image import chroma_test, to_chroma
from sphere_servo.vision.reasons import NotDetected, Reason

# a blob with less than this fraction of its contour off the image border is not fitted
MIN_FREE_CONTOUR = 0.3
# the brightest level of V a body filling the frame may have at its dimmest corner
# (below, a body-coloured frame is a dim, grey background, not the sphere)
FILLS_FRAME_MIN_V = 80


@dataclass(frozen=True)
class Silhouette:
    """
    The sphere's silhouette in one image, in pixels.

    conic_px       3×3 conic of the fitted ellipse (pixels, unit Frobenius norm).
    rms_px         RMS Sampson distance of the kept edge points to it.
    n_points       edge points kept by the final fit.
    ellipse        its :class:`~sphere_servo.core.conics.Ellipse`.
    cut_by_border  the blob touches the image border (fitted on its free contour only).
    threshold      level of V (grey levels) that separated the blob.
    coverage       fraction of the edge profiles on the image that gave a kept edge point
                   (1: the edge is contrasted and body-coloured all around).
    contrast       median step of V across the edge (grey levels).
    edge           (3, n) the kept edge points, homogeneous pixels ``(u, v, 1)``.
    n_profiles     edge profiles on the image.
    cone           the sphere's :class:`~sphere_servo.vision.cone.ConeFit` through a camera
                   model (None: the conic path; ``conic_px`` is then the fit).
    """

    conic_px: Conic
    rms_px: float
    n_points: int
    ellipse: Ellipse
    cut_by_border: bool
    threshold: float
    coverage: float = 1.0
    contrast: float = float('nan')
    edge: np.ndarray | None = None
    n_profiles: int = 0
    cone: ConeFit | None = None


@dataclass(frozen=True)
class Candidates:
    """
    The candidate blobs of one image, the most sphere-like first.

    blobs     the :class:`~sphere_servo.vision.blobs.Blob` list.
    step      the subsampling they were found at (full-resolution pixel = step · coarse).
    """

    blobs: list
    step: int
    finder: BlobFinder
    Vs: Image

    def grown(self, blob: Blob) -> Blob | None:
        """Return ``blob`` grown down to a level local to it (:meth:`BlobFinder.grow`)."""
        return None if blob.grown or blob.ellipticity < ELLIPTICAL \
            else self.finder.grow(self.Vs, blob)


def robust_ellipse(pts: np.ndarray, min_keep: int, tol_min: float,
                   rounds: int = 4) -> Ellipse | None:
    """
    Fit ``cv2.fitEllipseDirect`` to float32 (N, 2) points, dropping those far from the fit.

    Points far from the ellipse (a lump on the contour: clutter touching the sphere, the CC
    stick) are dropped until it is tight. None when too few points remain or the fit
    degenerates.
    """
    P = homogeneous(pts[:, 0], pts[:, 1])
    for _ in range(rounds + 1):
        if len(pts) < max(6, min_keep):
            return None
        (cx, cy), (w, h), a = cv2.fitEllipseDirect(pts)
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(w)
                and math.isfinite(h) and w > 0.5 and h > 0.5):
            return None
        C = conic_from_rotated_rect(cx, cy, w, h, a)
        d = np.abs(sampson_homogeneous(C, P))
        rr = Ellipse((cx, cy), (0.5 * w, 0.5 * h), math.radians(a))
        k = len(d) // 2
        keep = d < max(tol_min, 4.5 * float(np.partition(d, k)[k]))
        if np.count_nonzero(keep) == len(keep):
            break
        pts, P = pts[keep], P[:, keep]
    return rr


@functools.lru_cache(maxsize=None)
def _trig(N: int) -> np.ndarray:
    """(2, N): cos and sin of N angles evenly spaced on [0, 2π)."""
    t = np.linspace(0.0, 2 * math.pi, N, endpoint=False)
    return np.stack([np.cos(t), np.sin(t)])


@functools.lru_cache(maxsize=None)
def _offsets(L: int) -> np.ndarray:
    """Sample offsets −L … L along a profile."""
    return np.arange(-L, L + 1, dtype=np.float64)


@functools.lru_cache(maxsize=None)
def _indices(N: int, P: int, K: int):
    """
    Index helpers of the edge profiles.

    The flat index of sample M of each of the N profiles (P samples each), the offsets of
    samples −M, −1, K, and those of the window −2 … K in a 3-channel and a 1-channel
    profile.
    """
    M = K + 1
    return (np.arange(M, N * P, P), np.array([-M, -1, K]), np.arange(-6, 3 * K + 1, 3),
            np.arange(-2, K + 1))


@functools.lru_cache(maxsize=None)
def _o1(K: int) -> np.ndarray:
    """(1, K + 1): the distances 1 … K + 1 of the window's samples from the inside level."""
    return np.arange(1, K + 2, dtype=np.float32)[None, :]


@functools.lru_cache(maxsize=None)
def _drop_weight(L: int) -> np.ndarray:
    """(1, 2L): the mild preference for an edge near the middle of the profile."""
    mid = np.arange(-L, L, dtype=np.float32) + 0.5
    return (1.0 - 0.5 * (mid / (L + 1)) ** 2)[None, :]


class SilhouetteFinder:
    """
    Find and fit the sphere's silhouette, configured by the body's colour.

    body            rgb8 colour of the body.
    min_area_px     smallest blob accepted as the sphere.
    min_contrast    smallest difference (grey levels of V) between the body just inside its
                    edge and the background just outside.
    body_chroma_tol largest chromaticity distance of a body pixel to ``body`` (1.5 times
                    that for the edge's inside samples).
    K               half-length (px) of the edge profiles (sub-pixel step).
    max_edge_points largest number of edge points of the final fit.
    coarse_step     subsampling of the image in which the blob is found (1: none).
    marks, mark_chroma_tol
                    rgb8 colours of the marks and their chromaticity tolerance: a blob
                    merged with coloured clutter is split into its pixels of the body's
                    and the marks' colours (:class:`~sphere_servo.vision.blobs.BlobFinder`).
    """

    def __init__(self, body, *, min_area_px: float = 30.0, min_contrast: float = 25.0,
                 body_chroma_tol: float = 0.08, K: int = 3, max_edge_points: int = 100,
                 coarse_step: int = 4, marks=(), mark_chroma_tol: float = 0.12):
        self.min_area_px = float(min_area_px)
        self.min_contrast = float(min_contrast)
        self.body_chroma_tol = float(body_chroma_tol)
        self.K = int(K)
        self.max_edge_points = int(max_edge_points)
        self.coarse_step = max(1, int(coarse_step))
        self.body_chroma = to_chroma(np.asarray(body, float))
        Q, w = chroma_test(self.body_chroma, 1.5 * self.body_chroma_tol)
        self._body_test = {False: Q, True: np.ascontiguousarray(Q[::-1])}, w
        # the sphere's colours (body and marks) in one product: (3, 4k), block weights (4k, k)
        tests = [(Q, w)] + [chroma_test(to_chroma(np.asarray(c, float)), mark_chroma_tol)
                            for c in marks]
        Qs = np.hstack([t[0] for t in tests])
        self._sphere_test = {False: Qs, True: np.ascontiguousarray(Qs[::-1])}
        self._sphere_w = np.zeros((4 * len(tests), len(tests)), np.float32)
        for i, (_, wi) in enumerate(tests):
            self._sphere_w[4 * i:4 * i + 4, i] = wi

    def candidates(self, img: Image, rgb: Image | None) -> 'Candidates | NotDetected':
        """
        Find the candidate blobs of ``img``, the most sphere-like first, and their step.

        ``img`` is checked uint8, ``rgb`` its rgb view (None for mono8). The blobs are
        found on a subsampled image (nearest: pixel (i, j) is pixel (s·i, s·j)), the
        elliptical ones first, then by decreasing area; :meth:`fit` works at full
        resolution along a blob's edge only. A tiny target is searched for at full
        resolution when the coarse image has no blob large enough. Returns the
        :class:`Candidates`, or why there is none.
        """
        H, W = img.shape[:2]
        s = max(1, min(self.coarse_step, min(H, W) // 60))
        finder, Vs = self._finder(img, rgb, s)
        blobs, _ = finder.find(Vs)
        if not blobs and s > 1:
            s = 1                                       # a tiny target: full resolution
            finder, Vs = self._finder(img, rgb, s)
            blobs, _ = finder.find(Vs)
        if not blobs:
            return self._no_blob(img, rgb, s)
        blobs.sort(key=lambda b: (b.ellipticity < ELLIPTICAL, -b.area))
        return Candidates(blobs, s, finder, Vs)

    def _finder(self, img: Image, rgb: Image | None, s: int) -> tuple[BlobFinder, Image]:
        """Build the blob finder for step ``s`` and the coarse V image it works on."""
        coloured = None
        if rgb is not None:
            coloured = functools.partial(self._sphere_coloured, img, rgb is not img, s)
        finder = BlobFinder(self.min_area_px / (s * s), self.min_contrast, coloured=coloured)
        return finder, coarse_v(img, s)

    def _sphere_coloured(self, img: Image, bgr: bool, s: int, ys: np.ndarray,
                         xs: np.ndarray) -> np.ndarray:
        """(N,) bool: the pixels (s·y, s·x) of ``img`` have the body's or a mark's colour."""
        y = img[ys * s, xs * s].astype(np.float32) @ self._sphere_test[bgr]
        y *= y
        return ((y @ self._sphere_w) < 0.0).any(axis=1)

    def _no_blob(self, img: Image, rgb: Image | None, s: int) -> NotDetected:
        """Say why there is no candidate: the body fills the frame, a tiny blob, or none."""
        if rgb is not None and self.fills_frame(rgb):
            return NotDetected(Reason.TOO_LARGE, 'the body fills the frame')
        Vs = coarse_v(img, s)
        _, mask = cv2.threshold(Vs, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if contours:
            area = max(cv2.contourArea(c) for c in contours) * s * s
            if 0 < area < self.min_area_px:
                return NotDetected(Reason.TOO_SMALL,
                                   f'{area:.0f} px < {self.min_area_px:.0f}')
        return NotDetected(Reason.NO_BLOB)

    def fills_frame(self, rgb: Image) -> bool:
        """
        Tell whether the body fills the frame.

        All four corners and the centre of the image are body-coloured and bright (a dim
        grey background has the body's chromaticity too); and, a grey wall being as
        body-coloured as an off-white body, each is at least twice as close to the body's
        chromaticity as to neutral grey, or — for a body too close to grey to tell —
        their brightness varies as a shaded sphere's does (by 15 grey levels or more).
        """
        H, W = rgb.shape[:2]
        k = max(1, min(H, W) // 20)
        patches = [rgb[:k, :k], rgb[:k, -k:], rgb[-k:, :k], rgb[-k:, -k:],
                   rgb[H // 2 - k // 2:H // 2 + k // 2 + 1, W // 2 - k // 2:W // 2 + k // 2 + 1]]
        means = [p.reshape(-1, 3).mean(axis=0) for p in patches]
        grey = np.full(3, 1.0 / 3.0)
        tinted = np.linalg.norm(self.body_chroma - grey) >= 0.01
        for m in means:
            c = to_chroma(m)
            d_body = np.linalg.norm(c - self.body_chroma)
            if m.max() < FILLS_FRAME_MIN_V or d_body >= self.body_chroma_tol:
                return False
            if tinted and 2.0 * d_body > np.linalg.norm(c - grey):
                return False
        v = [float(m.max()) for m in means]
        return tinted or max(v) - min(v) >= 15.0

    def _is_body(self, pix: np.ndarray, bgr: bool = False) -> np.ndarray:
        """(N,) bool: the (N, 3) rgb (bgr if ``bgr``) pixels have the body's chromaticity."""
        Q, w = self._body_test
        y = pix.astype(np.float32) @ Q[bgr]
        y *= y
        return (y @ w) < 0.0

    def fit(self, blob: Blob, img: Image, rgb: Image | None, s: int, lift=None
            ) -> Silhouette | NotDetected:
        """
        Fit the sub-pixel silhouette of one blob found at step ``s``.

        Its free contour (off the image border; at least ``MIN_FREE_CONTOUR`` of it) and,
        in colour, only the points whose inside is body-coloured give the coarse ellipse
        (:meth:`_fit_blob`). ``lift``: a :class:`~sphere_servo.vision.rays.ModelLift` to
        fit the sphere's cone through (None: the conic in pixels).
        """
        H, W = img.shape[:2]
        free = blob.contour[blob.free]
        if len(free) < 8 or len(free) < MIN_FREE_CONTOUR * len(blob.contour):
            return NotDetected(Reason.CUT_BY_BORDER,
                               f'{blob.border_fraction:.0%} of its contour on the border, '
                               f'> {1 - MIN_FREE_CONTOUR:.0%}')
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
                return NotDetected(Reason.NOT_BODY_COLOURED)
            free = free[body]
        return self._fit_blob(free.astype(np.float32) * s, img, rgb, s, W, H, blob.cut,
                              blob.threshold, lift)

    def _fit_blob(self, free: np.ndarray, img, rgb, s: int, W: int, H: int, cut: bool,
                  thr: float, lift=None) -> Silhouette | NotDetected:
        """
        Fit the sub-pixel ellipse of a blob from its free contour points.

        ``free``: the (N, 2) float32 full-resolution pixels of the contour not on the border
        (found at step ``s``); ``cut`` and ``thr`` (the blob's level) are passed into the
        result.

        Along the coarse ellipse's outward normals (points on the image only), V is sampled
        (bilinear) at unit steps over ±(2s + 4) px; on each profile the edge is the largest
        fall of V from inside the blob's level ``thr`` (a mild preference for the middle
        keeps a nearby clutter edge from winning), and its sub-pixel offset is the area
        under the anti-aliased step in a window of M = K + 1 samples inside and K outside
        the nearest sample,
        ``e = Σ_j c(o_j) − (M + ½)``, ``c = (I − I_out)/(S − I_out)`` clipped to [0, 1]
        (exact for a box-filtered or blurred straight edge); the inside level S is
        extrapolated from 2 and 3 px inside, since the body's shade changes quickly near
        the limb. (Written for speed: one remap, flat gathers, float scalars.)
        """
        n0 = len(free)
        if n0 > 400:
            free = free[np.linspace(0, n0 - 1, 400).astype(int)]
        ep = robust_ellipse(free, int(0.3 * min(n0, 400)), 1.0 * s)
        if ep is None:
            return NotDetected(Reason.NOT_ELLIPTICAL)
        (cx, cy), (a0, a1), ang = ep
        per = math.pi * (3 * (a0 + a1) - math.sqrt((3 * a0 + a1) * (a0 + 3 * a1)))
        N = int(min(max(per / 1.5, 24), self.max_edge_points))
        ca, sa = math.cos(ang), math.sin(ang)
        # rows: point x, y (about the centre) and normal x, y (unnormalized)
        G = np.array([[a0 * ca, -a1 * sa], [a0 * sa, a1 * ca],
                      [ca / a0, -sa / a1], [sa / a0, ca / a1]]) @ _trig(N)
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
                return NotDetected(Reason.FEW_EDGE_POINTS, f'{N} on the image')
        P = 2 * L + 1
        # sample maps (2, N·P): point + offset · normal, for offsets −L … L
        maps = G[2:, :, None] * _offsets(L)
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
        drop *= _drop_weight(L)[:, M:P - K]
        # only a fall whose inside (M px in) is as bright as the blob: a background edge
        # next to the sphere (a checker square darker than the blob's level) is not its edge
        drop[prof[:, :P - K - M] < thr] = 0.0
        jj = drop.argmax(axis=1)                    # j − M
        has_fall = drop[np.arange(N), jj] > 0.0
        base, pick, win3, win1 = _indices(N, P, K)
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
        med_contrast = float(np.partition(contrast, k)[k])
        if med_contrast < self.min_contrast:
            return NotDetected(Reason.LOW_CONTRAST,
                               f'{med_contrast:.0f} < {self.min_contrast:.0f}')
        # coverage of the samples j … j + K; the M samples inside count 1 each
        S = (i2 - i3)[:, None] * _o1(K)             # S − I_out
        S += contrast[:, None]
        np.maximum(S, 1e-6, out=S)
        cov = win[:, 2:] - i_out[:, None]
        cov /= S
        np.minimum(np.maximum(cov, 0.0, out=cov), 1.0, out=cov)      # (np.clip is slower)
        csum = cov.sum(axis=1)
        good = (contrast > 0.5 * self.min_contrast) & (csum < 2.5) & has_fall
        if color:
            # the edge is the body's only where the inside (M px in) is body-coloured
            body = self._is_body(px3[:, 0], bgr=rgb is not img)
            if np.count_nonzero(body) < 0.5 * N:
                return NotDetected(Reason.NOT_BODY_COLOURED, 'along the edge')
            good &= body
        ng = np.count_nonzero(good)
        if ng < 10:
            return NotDetected(Reason.FEW_EDGE_POINTS, f'{ng} clean')
        e = (csum + (jj - (L + 0.5 - M)))[good]     # offset from the ellipse point
        Gg = G[:, good]
        E = np.empty((3, ng))                       # the edge points, homogeneous rows
        np.multiply(Gg[2:], e, out=E[:2])
        E[:2] += Gg[:2]
        E[2] = 1.0
        sc = 2.0 / math.sqrt(a0 * a0 + a1 * a1)     # Hartley scale of the coarse ellipse
        if lift is not None:
            return self._fit_cone(lift, E, cx, cy, sc, cut, thr, N, med_contrast)
        C = fit_conic_homogeneous(E, cx, cy, sc)
        for _ in range(3):
            d = sampson_homogeneous(C, E)
            k = len(d) // 2
            med = float(np.partition(d, k)[k])
            ad = np.abs(d - med)
            sigma = 1.4826 * float(np.partition(ad, k)[k])
            keep = ad < max(3.0 * sigma, 0.3)
            nk = np.count_nonzero(keep)
            if nk < 10:
                return NotDetected(Reason.FEW_EDGE_POINTS, f'{nk} inliers')
            if nk == len(keep):
                break
            E = E[:, keep]
            C = fit_conic_homogeneous(E, cx, cy, sc)
        else:
            d = sampson_homogeneous(C, E)
        ep = ellipse_params(C)
        if ep is None:
            return NotDetected(Reason.NOT_ELLIPTICAL, 'the fitted conic')
        rms = math.sqrt(float(d @ d) / len(d))
        return Silhouette(C, rms, len(d), ep, cut, thr, len(d) / N, med_contrast, E, N)

    @staticmethod
    def _fit_cone(lift, E: np.ndarray, cx: float, cy: float, sc: float, cut: bool,
                  thr: float, N: int, med_contrast: float) -> Silhouette | NotDetected:
        """Fit the sphere's cone through a camera model to the edge points ``E`` (3, n)."""
        cone = fit_cone(lift, E)
        if isinstance(cone, NotDetected):
            return cone
        Ek = E[:, cone.keep]
        C = fit_conic_homogeneous(Ek, cx, cy, sc)     # drawn, and the inside of the image
        ep = ellipse_params(C)
        if ep is None:
            return NotDetected(Reason.NOT_ELLIPTICAL, 'the conic of the edge')
        nk = Ek.shape[1]
        return Silhouette(C, cone.rms_px, nk, ep, cut, thr, nk / N, med_contrast, Ek, N, cone)
