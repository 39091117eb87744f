"""
The marks (no ROS): colour blobs → centres back-projected on the sphere. DESIGN.md §2.

Marks are found by colour (chromaticity, configurable) in the box of the silhouette. Their
pixels are lifted to rays through the camera the sphere was measured with
(:mod:`~sphere_servo.vision.rays`: ``K⁻¹`` for a pinhole, the model's lift for a fisheye or a
catadioptric). A surface mark's centre is *not* its image centroid (a painted cap is
foreshortened, DESIGN.md §2): each pixel's ray is back-projected on the estimated sphere
(eq. 11–12), weighted by the surface area it covers (its solid angle over the cosine of the
incidence), and the mean surface normal gives the cap's centre; a cap cut by the limb is
measured from its boundary arc instead. The CC tip P3 (a small ball off the surface) is
along the mean of its blob's rays weighted by their solid angles: the direction of a
ball's centre, whatever the camera (its silhouette is a circle of the projection sphere
about that direction).
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

from sphere_servo.core.conics import homogeneous, sampson_homogeneous
from sphere_servo.core.measurement import MeasurementError, SphereMeasurement
from sphere_servo.core.types import Image, Vec3
from sphere_servo.vision.caps import (CapCentre, match_centroid, outside_share,
                                      predicted_direction, tangent_basis, visible_solid_angle)
from sphere_servo.vision.cone import limb_distance
from sphere_servo.vision.image import chroma_test, components, row_ends, to_chroma
from sphere_servo.vision.reasons import NotDetected, Reason
from sphere_servo.vision.silhouette import Silhouette
from sphere_servo.vision.swap import core_colour, SwapCheck

_K3 = np.ones((3, 3), np.uint8)


@dataclass
class Mark:
    """
    One mark.

    name           'P1', 'P2' or 'P3'.
    uv_px          (2,) pixel of its centre (None when not visible).
    ray            (3,) unit ray of its centre, camera frame (None when not visible).
    visible        its centre was measured.
    area_px        its (coverage-weighted) image area.
    partial        a surface cap cut by the limb, whose centre comes from its visible
                   boundary arc (or, if that cannot be measured, the mark is reported not
                   visible).
    missing        why it is not visible (a :class:`NotDetected` naming the mark), None
                   when visible.
    colour         (3,) rgb of its core, None when not visible: it tells a mark from
                   another one's colour swapped (:mod:`~sphere_servo.vision.swap`).
    """

    name: str
    uv_px: np.ndarray | None = None
    ray: np.ndarray | None = None
    visible: bool = False
    area_px: float = 0.0
    partial: bool = False
    missing: NotDetected | None = None
    colour: np.ndarray | None = None

    @classmethod
    def lost(cls, name: str, reason: Reason, detail: str = '', area_px: float = 0.0,
             partial: bool = False) -> 'Mark':
        """Build a mark that is not visible, and why."""
        return cls(name, area_px=area_px, partial=partial,
                   missing=NotDetected(reason, detail, name))

    @property
    def q(self) -> np.ndarray:
        """Return the unit vector of the mark's centre (camera frame)."""
        if not self.visible or self.ray is None:
            raise MeasurementError(self.why)
        return self.ray.copy()

    @property
    def why(self) -> str:
        """Why it is not visible, as a message ('' when visible)."""
        return '' if self.visible else str(self.missing) if self.missing is not None \
            else f'mark {self.name} is not visible'


class Backprojection(NamedTuple):
    """
    Rays back-projected on the estimated sphere (units of r), one value per ray ``q``.

    rho     ``‖P‖/r`` (eq. 11–12, σ = −1: the visible side).
    nn      ``‖ρq − s_n,t‖`` (1 on the sphere; less for a ray that misses it, which meets
            its closest point); None when every ray is known to hit the sphere.
    cos_i   cosine of the viewing incidence; the unit surface normal is
            ``n = (ρq − s_n,t)/nn``.
    """

    rho: np.ndarray
    nn: np.ndarray | None
    cos_i: np.ndarray


def on_sphere(sphere: SphereMeasurement, q: np.ndarray, hits: bool = False) -> Backprojection:
    """
    Back-project unit rays ``q`` (3, N) on the estimated sphere.

    Scalar rows: ``|q| = 1`` turns the 3-vector norms and dot products into ``b·q`` and
    ``s·q``. ``hits``: every ray is known to meet the sphere (pixels well inside the
    silhouette), so ``nn`` is 1 (returned as None).
    """
    rd = sphere.r_delta
    sq = sphere.s_nt @ q
    bq = rd * sq                              # b = r_δ s_n,t
    root = bq * bq
    root += rd * rd - 1.0
    np.maximum(root, 0.0, out=root)
    np.sqrt(root, out=root)
    rho = bq - root
    rho *= 1.0 / rd
    if hits:
        return Backprojection(rho, None, sq - rho)
    # ‖ρq − s‖² = ρ² − 2ρ s·q + ‖s‖²
    ss = float(sphere.s_nt @ sphere.s_nt)
    nn = rho * (rho - 2.0 * sq)
    nn += ss
    np.maximum(nn, 1e-24, out=nn)
    np.sqrt(nn, out=nn)
    cos_i = sq - rho
    cos_i /= nn
    return Backprojection(rho, nn, cos_i)


def ball_centre(q: np.ndarray, w: np.ndarray) -> Vec3:
    """
    Direction (unit) of a ball's centre from the rays ``q`` (3, N) of its filled blob.

    ``w``: each pixel's coverage times its solid angle. The blob's rays fill the circle of
    the projection sphere about the centre's direction (the ball's silhouette cone), so
    their solid-angle mean lies along it, for any central camera — unlike the blob's image
    centroid, which perspective shifts outwards.
    """
    m = q @ w
    return m / max(float(np.sqrt(m @ m)), 1e-300)


class MarkFinder:
    """
    Find the marks and measure their centres, configured by the colours.

    colors          {'body': rgb, 'P1': rgb, 'P2' or 'P3': rgb} (rgb8 triplets).
    surface_marks   names of marks painted on the surface (centre by back-projection on the
                    sphere); the others (the CC tip 'P3') use the image of their centre.
    chroma_tol      largest chromaticity distance of a pixel to a mark's colour.
    min_mark_px     smallest weighted area of a visible mark.
    mark_radius     angular radius (rad) of the painted caps (fits a cap cut by the limb).
    min_seen        a whole cap (away from the limb) whose measured area on the sphere is
                    less than this fraction of the painted one is not measured: part of it
                    was not classified as the mark (0: not checked, for a body that is not a
                    sphere, where the area on the estimated sphere is not the cap's).
    """

    # a cap's (grown) pixels this close to the silhouette (px): the cap may be cut by the limb
    limb_px = 1.5
    # a cap cut by the limb by more than this (rad) is not measured from its image centroid
    max_cut = math.radians(2.0)
    # the largest fraction of a cap's rim pixels with a channel clipped at 255 (rim fit)
    max_clipped = 0.1
    # the largest share of a mark's pixels farther than spread_px outside the cap its
    # centre predicts (a cable of its colour across it, a colour fringe along the limb)
    max_spread, spread_px = 0.1, 2.0

    def __init__(self, colors: dict, surface_marks, *, chroma_tol: float = 0.12,
                 min_mark_px: float = 3.0, mark_radius: float = float(np.radians(9.0)),
                 min_seen: float = 0.8):
        self.mark_names = tuple(k for k in colors if k != 'body')
        self.surface_marks = set(surface_marks)
        # a mark off the surface (the CC tip) comes with a stick that may lie across a cap
        self.has_stick = any(n not in self.surface_marks for n in self.mark_names)
        self.chroma_tol = float(chroma_tol)
        self.min_mark_px = float(min_mark_px)
        self.mark_radius = float(mark_radius)
        self.min_seen = float(min_seen)
        self.cos_mark = float(np.cos(mark_radius))
        # the painted cap's area on the unit sphere (units of r²)
        self.cap_area = 2.0 * math.pi * (1.0 - self.cos_mark)
        body = np.asarray(colors['body'], float)
        # (3, 2): rgb → (a, b) with rgb ≈ a·mark + b·body (least squares)
        self._unmix = {k: np.linalg.pinv(np.column_stack([np.asarray(colors[k], float),
                                                          body])).T
                       for k in self.mark_names}
        for k, U in self._unmix.items():        # columns a and a + b: α = a / (a + b)
            U[:, 1] += U[:, 0]
        # all marks' chromaticity tests in one product: (3, 4·n) and block weights (4·n, n)
        tests = [chroma_test(to_chroma(np.asarray(colors[k], float)), self.chroma_tol)
                 for k in self.mark_names]
        self._mark_Q = np.hstack([Q for Q, _ in tests]) if tests else np.zeros((3, 0), np.float32)
        self._mark_w = np.zeros((4 * len(tests), len(tests)), np.float32)
        for i, (_, w) in enumerate(tests):
            self._mark_w[4 * i:4 * i + 4, i] = w
        self.swapped = SwapCheck(colors, self.mark_names, self.chroma_tol)

    def not_visible(self, reason: Reason = Reason.MARK_NOT_FOUND, detail: str = '') -> dict:
        """Name → an invisible :class:`Mark`, for every mark, and why."""
        return {n: Mark.lost(n, reason, detail) for n in self.mark_names}

    def colour_pixels(self, img: Image, encoding: str, rgb: Image, level: float):
        """
        Pixels (N, 2) ``(x, y)`` of ``img`` that may be a mark's, and (N, n_marks) which.

        Saturated (max − min ≥ 0.27 max, HSV S ≥ 69), bright enough (V ≥ 0.75 ``level``:
        not the dark background), of chromaticity within chroma_tol of a mark's; (None,
        None) when no pixel is saturated and bright.
        """
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV if encoding == 'rgb8' else cv2.COLOR_BGR2HSV)
        cand = cv2.findNonZero(cv2.inRange(hsv, (0, 69, math.ceil(0.75 * level)),
                                           (255, 255, 255)))
        if cand is None:
            return None, None
        cand = cand.reshape(-1, 2)
        y = rgb[cand[:, 1], cand[:, 0]].astype(np.float32) @ self._mark_Q
        y *= y
        return cand, (y @ self._mark_w) < 0.0

    def find(self, img: Image, encoding: str, rgb: Image | None, sphere: SphereMeasurement,
             sil: Silhouette, lift) -> dict:
        """
        Name → :class:`Mark` for every mark, seen in ``img``.

        ``rgb`` is its rgb view (None for mono8: no colour, no marks), ``sphere`` and
        ``sil`` the sphere measured from the silhouette, ``lift`` how the camera's pixels
        are lifted to rays (:mod:`~sphere_servo.vision.rays`).
        """
        if rgb is None:
            return self.not_visible(detail='a mono8 image has no colour')
        marks = self.not_visible(detail='no pixel of its colour on the sphere')
        H, W = img.shape[:2]
        (ecx, ecy), ax, _ = sil.ellipse
        # the CC tip can lie outside the disc; surface marks cannot
        rad = (1.7 if self.has_stick else 1.0) * max(ax) + 3
        x0, x1 = max(0, int(ecx - rad)), min(W, int(ecx + rad) + 1)
        y0, y1 = max(0, int(ecy - rad)), min(H, int(ecy + rad) + 1)
        if x0 >= x1 or y0 >= y1:
            return marks
        roi = rgb[y0:y1, x0:x1]
        cand, sel_all = self.colour_pixels(img[y0:y1, x0:x1], encoding, roi, sil.threshold)
        if cand is None:
            return marks
        C_px = sil.conic_px
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
            nlab, lab, st = components(m, len(pts))
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
            hull = cv2.convexHull(row_ends(pts))
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
                pix = roi[gy0:gy1, gx0:gx1][yy, xx]
                ab = pix.astype(np.float64) @ self._unmix[name]
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
                Ppx = homogeneous(xx, yy)
                Ppx[0] += ox
                Ppx[1] += oy
                q, w_sr = lift.pixels(Ppx[0], Ppx[1])
                if near_limb:
                    dsig = (inside * sampson_homogeneous(C_px, Ppx) if sil.cone is None
                            else limb_distance(lift.camera, sphere, sil.cone.theta, q, Ppx))
                    dsil = np.abs(dsig)
                    # a pixel on the limb is partly background, which the unmixing (mark
                    # vs body) does not know: its mark coverage is at most its coverage by
                    # the sphere
                    np.minimum(alpha, np.clip(0.5 + dsig, 0.0, 1.0), out=alpha)
                    if float(dsil.min()) < self.limb_px:
                        # the visible part's mean is biased; use the boundary with the body,
                        # away from the silhouette
                        rim = ((inner == 0) & (alpha > 0.2) & (alpha < 0.8)
                               & (dsil > self.limb_px + 1.0))
                        if np.count_nonzero(pix[rim].max(axis=1) >= 255) \
                                > self.max_clipped * max(np.count_nonzero(rim), 1):
                            # clipped levels are no mix of the mark's and the body's
                            # colours: the rim the unmixing finds is not the cap's
                            marks[name] = Mark.lost(name, Reason.MARK_UNMEASURABLE,
                                                    'its rim is clipped (over-exposed)',
                                                    partial=True)
                            continue
            else:
                # an off-surface ball (CC tip): its filled hull, binary (its rim may blend
                # with the background, whose chromaticity says nothing of coverage)
                alpha = full[yy, xx].astype(np.float64)
                pix = roi[gy0:gy1, gx0:gx1][yy, xx]
            area = float(alpha.sum())
            if area < self.min_mark_px:
                marks[name] = Mark.lost(name, Reason.MARK_NOT_FOUND,
                                        f'{area:.1f} px < {self.min_mark_px:.0f}', area)
                continue
            # the hull's box is the pixels' box
            if min(x0 + hx, y0 + hy) <= 0 or x0 + hx + hw >= W or y0 + hy + hh >= H:
                # the image border hides part of the mark: its visible part's mean is not
                # its centre, and no rim model knows where the border cuts it
                marks[name] = Mark.lost(name, Reason.MARK_CUT_BY_BORDER, area_px=area,
                                        partial=True)
                continue
            if name in self.surface_marks:
                alpha *= w_sr                   # coverage × solid angle: the rays' weights
                ray, seen = self.cap_centre(sphere, q, alpha, rim, hits=not near_limb)
                if ray is not None and seen < self.min_seen:
                    # a whole cap whose measured area is a fraction of the painted one: part
                    # of it was not classified as the mark (clipped colours, an occluder)
                    marks[name] = Mark.lost(name, Reason.MARK_INCOMPLETE,
                                            f'{100 * seen:.0f} % of its area seen', area,
                                            partial=rim is not None)
                    continue
                if ray is None:
                    marks[name] = Mark.lost(name, Reason.MARK_UNMEASURABLE, area_px=area,
                                            partial=True) if rim is not None else \
                        Mark.lost(name, Reason.MARK_FACES_AWAY,
                                  'its centre on the sphere faces away', area)
                    continue
                out = outside_share(sphere, ray, self.mark_radius, q, alpha / w_sr, w_sr,
                                    self.spread_px, at_most=self.max_spread)
                if out > self.max_spread:       # not the cap that its centre predicts
                    marks[name] = Mark.lost(name, Reason.MARK_NOT_A_CAP,
                                            f'{100 * out:.0f} % of it outside', area)
                    continue
            else:
                q, w_sr = lift.pixels(xx + ox, yy + oy)
                ray = ball_centre(q, alpha * w_sr)
            uv = lift.project(ray)
            if uv is None:                      # beyond the camera's field: not imaged
                marks[name] = Mark.lost(name, Reason.MARK_FACES_AWAY,
                                        'its centre is outside the camera field', area)
                continue
            marks[name] = Mark(name, uv, ray, True, area, partial=rim is not None,
                               colour=core_colour(pix))
        return marks

    def cap_centre(self, sphere: SphereMeasurement, q: np.ndarray, w: np.ndarray,
                   rim: np.ndarray | None = None, hits: bool = False) -> CapCentre:
        """
        Measure the unit ray of a painted cap's centre from its pixels (:class:`CapCentre`).

        ``q`` (3, N): the pixels' unit rays, ``w`` their coverage times their solid angle.

        Whole cap: back-project the rays on the sphere (units of r, eq. 11–12), weight
        each by the surface area of its footprint (``ρ² w / cos i``) and average the unit
        normals (DESIGN.md §2, second lesson).

        ``rim`` (bool mask of the pixels on the cap's boundary with the body, away from the
        silhouette) is given when the cap's image touches the limb: then the visible part's
        mean is biased towards the camera if the cap is cut, and the back-projection is
        ill-conditioned there; the centre comes instead from the cap's boundary circle,
        ``n·m = cos(mark_radius)`` on the sphere, fitted (Gauss–Newton on the unit m, weights
        cos² i for the back-projection's sensitivity, outliers — the CC stick — dropped) to
        the rim pixels' normals; when too little rim is seen for that (a small sphere),
        from the mean direction of the cap's rays
        (:func:`~sphere_servo.vision.caps.match_centroid` with
        :func:`~sphere_servo.vision.caps.predicted_direction`: the visible part of the cap
        of radius ``mark_radius`` about m, seen from the camera centre).

        Returns the direction of ``s_n,t + m`` (m: the unit normal at the centre), or None
        when the centre cannot be measured (it faces away from the camera, or the cap's
        model finds no visible part), and the fraction of the cap's area
        ``2π (1 − cos mark_radius)`` (units of r²) the weights cover; near the limb, of the
        solid angle of the visible part of the cap its centre predicts (NaN if none).
        """
        rho, nn, cos_i = on_sphere(sphere, q, hits and rim is None)
        s_nt = sphere.s_nt
        # Σ wa·n with n = (ρ q − s)/nn and wa = w ρ² / max(cos i, 0.1)
        c = rho * rho
        c *= w
        c /= np.maximum(cos_i, 0.1)
        if nn is not None:
            c /= nn
        area = float(c.sum())
        seen = area / self.cap_area if rim is None else math.nan
        m = q @ (c * rho) - area * s_nt
        m /= max(math.sqrt(float(m @ m)), 1e-300)
        if rim is not None:
            # near the limb: the rim's circle (outliers, e.g. the CC stick, dropped) or, when
            # too little rim is seen (a small sphere), the cap's mean direction (caps)
            m_rim = self._fit_rim(m, q, rho, nn, cos_i, s_nt, rim)
            if m_rim is None and self._cut_by(sphere, m) < self.max_cut:
                F = tangent_basis(sphere.b)       # gnomonic coordinates about b
                d = F @ (q @ w)
                m_rim = match_centroid(sphere, m, self.mark_radius, d[:2] / d[2],
                                       functools.partial(predicted_direction, frame=F))
                if m_rim is not None and self._cut_by(sphere, m_rim) >= self.max_cut:
                    m_rim = None        # a cap mostly hidden: its centroid says too little
            if m_rim is None:
                return CapCentre(None, seen)
            # the area measured over the area of the visible part of the cap m_rim predicts
            m = m_rim
            seen = float(w.sum()) / max(visible_solid_angle(sphere, m, self.mark_radius), 1e-300)
        P = s_nt + m
        if float(m @ P) >= 0:                   # the centre faces away: not measurable
            return CapCentre(None, seen)
        return CapCentre(P / math.sqrt(float(P @ P)), seen)

    def _cut_by(self, sphere: SphereMeasurement, m: np.ndarray) -> float:
        """
        Angle (rad) by which the cap of centre normal ``m`` reaches beyond the limb.

        A surface point of normal n is seen iff ``n·(−b) > r_δ``; the cap's farthest point is
        ``β + ρ`` from −b (β: the angle of m, ρ: the cap's radius). Negative: wholly seen.
        """
        beta = math.acos(max(-1.0, min(1.0, -float(m @ sphere.b))))
        return beta + self.mark_radius - math.acos(sphere.r_delta)

    def _fit_rim(self, m, q, rho, nn, cos_i, s_nt, rim) -> np.ndarray | None:
        """Fit the unit normal m at the cap's centre to its rim pixels (:meth:`cap_centre`)."""
        if np.count_nonzero(rim) < 8:
            return None
        ir = 1.0 / nn[rim]
        nb = q[:, rim] * (rho[rim] * ir) - s_nt[:, None] * ir
        cb = np.maximum(cos_i[rim], 0.05)
        wb = cb * cb
        cosr = self.cos_mark
        # the weighted sums over the rim as moments: Σ w n nᵀ and Σ w n, so that
        # each step costs 3×3 products (J_a = t_a·n, residual m·n − cos r)
        S, mu = (nb * wb) @ nb.T, nb @ wb
        for it in range(6):
            # tangent basis (t1, t2) at m, then one weighted Gauss–Newton step
            T = tangent_basis(m)[[2, 0, 1]]             # rows m, t1, t2
            (m0, a11, a12), (m1, _, a22) = (T[1:] @ S @ T.T).tolist()
            _, v1, v2 = (T @ mu).tolist()
            g1, g2 = m0 - cosr * v1, m1 - cosr * v2
            det = a11 * a22 - a12 * a12
            if det < 1e-18:
                return None
            d1, d2 = -(a22 * g1 - a12 * g2) / det, -(a11 * g2 - a12 * g1) / det
            m = m + d1 * T[1] + d2 * T[2]
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
        return m
