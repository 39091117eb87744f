"""
Detector (no ROS): image → the target's conic + the marks' image points. DESIGN.md §2.

For one ``rgb8`` / ``bgr8`` / ``mono8`` image and the camera it is *given* (possibly with
wrong intrinsics, for the calibration-error experiment — the detector just uses them):

1. :mod:`~sphere_servo.vision.image` checks the image;
2. :mod:`~sphere_servo.vision.silhouette` yields candidate blobs (global and local
   thresholds, :mod:`~sphere_servo.vision.blobs`) with the sub-pixel conic of each, in
   pixels, the most sphere-like first;
3. a candidate within the calibrated :class:`~sphere_servo.vision.scoring.FitBounds`
   (residual, edge coverage, departure from a sphere's image) gives the sphere, on the
   projection sphere: for a pinhole without distortion from its conic in *normalized*
   coordinates (:func:`~sphere_servo.core.measurement.sphere_from_conic`), through any
   other camera model (plumb_bob, equidistant fisheye, unified) from the small circle of
   its lifted edge points (:mod:`~sphere_servo.vision.cone`); both give the same sphere on
   a pinhole;
4. :mod:`~sphere_servo.vision.marks` finds the marks by colour on that sphere and measures
   their centres on it, their pixels lifted through the same camera; they must lie on it
   and fit the target's geometry (:class:`~sphere_servo.vision.scoring.MarkGeometry`).

The first *sure* candidate (its edge contrasted around most of it, tightly fitted) whose
marks are all found and consistent is the target: a distractor — another sphere, a disc, a
bright patch of background — has no such marks. A blob whose fit is not sure is tried
again grown down to the level of the background around it (a higher level may have cut
into the sphere's shaded side). Otherwise the candidate with the most marks is the target,
then the one with the best edge coverage and residual (pixel figures: the choice does not
depend on the intrinsics); one with no mark only when it is the only sphere-like object in
view (several: ambiguous, not detected). A fit outside the bounds is never published. When
nothing is chosen, ``found`` is False and ``not_detected`` says why (a
:class:`~sphere_servo.vision.reasons.Reason` and a detail) for the candidate that came
furthest.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math

import cv2
import numpy as np

from sphere_servo.core.central import CentralCamera
from sphere_servo.core.conics import (conic_pixels_to_normalized, ellipse_params, fit_conic,
                                      homogeneous, sampson_homogeneous)
from sphere_servo.core.measurement import (MeasurementError, Observation, sphere_from_conic,
                                           SphereMeasurement)
from sphere_servo.core.targets import DEFAULT_COLORS, mark_names, SPECIAL, Target
from sphere_servo.vision.cone import contour_px, fit_cone
from sphere_servo.vision.image import check_image, image_from_buffer, to_chroma
from sphere_servo.vision.marks import Mark, MarkFinder
from sphere_servo.vision.rays import camera_intrinsics, lift_of, ModelLift, PinholeLift
from sphere_servo.vision.reasons import NotDetected, Reason
from sphere_servo.vision.scoring import FitBounds, foreign_arc, MarkGeometry
from sphere_servo.vision.silhouette import Silhouette, SilhouetteFinder


@dataclass
class Detection:
    """
    What the detector found in one image.

    found          True when the sphere's conic was measured (marks may still be missing).
    reason         why not found, as a message ('' when found): ``str(not_detected)``.
    conic          3×3 conic of the sphere's image in NORMALIZED image coordinates
                   (``x̄ᵀ C x̄ = 0``, unit Frobenius norm) — through a camera model, the
                   sphere's cone ``qᵀ C q = 0`` of rays, the same thing for a pinhole — or
                   None.
    sphere         :class:`SphereMeasurement` from the conic (b, r_δ, quality), or None.
    quality        eigenvalue spread of the conic (0 for a perfect sphere image); a published
                   fit is within the detector's calibrated bounds.
    residual_px    RMS distance (px) of the kept edge points to the fitted silhouette.
    ellipse_px     ``((u_c, v_c), (full_axis_1, full_axis_2), angle_deg)`` for cv2.ellipse
                   (through a camera model: the conic of the edge pixels, which the
                   silhouette is only near the image centre).
    marks          name → :class:`~sphere_servo.vision.marks.Mark`.
    cut_by_border  the silhouette touches the image border (fit on the free contour only).
    n_edge_points  edge points used by the final fit.
    coverage       fraction of the edge profiles (on the image) that gave a kept edge point.
    not_detected   why not found (:class:`~sphere_servo.vision.reasons.NotDetected`),
                   None when found.
    contour_px     (n, 2) pixels of the silhouette through a camera model (its cone
                   projected), None on the conic path (the ellipse is the silhouette).
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
    not_detected: NotDetected | None = None
    coverage: float = float('nan')
    contour_px: np.ndarray | None = None

    @classmethod
    def missed(cls, why: NotDetected, marks: dict) -> 'Detection':
        """Build the detection of an image without a usable target."""
        return cls(False, str(why), marks=marks, not_detected=why)

    def to_observation(self, kind: str = SPECIAL) -> Observation:
        """
        Build the :class:`Observation` the features need.

        The sphere and the marks P1 and P2 ('special') or P1 and P3 ('cc'). Raises
        :class:`MeasurementError` when the sphere or one of those marks is missing.
        """
        names = mark_names(kind)
        if not self.found or self.sphere is None:
            raise MeasurementError(f'sphere not detected: {self.reason}')
        q = {}
        for name in names:
            m = self.marks.get(name)
            if m is None:
                raise MeasurementError(f'mark {name} is not visible')
            q[name] = m.q                  # raises why it is not visible
        return Observation(self.sphere, q, kind)


# the stages a candidate goes through; a miss further on says more about the image
_STAGE = {Reason.NO_BLOB: 0, Reason.TOO_SMALL: 1, Reason.CUT_BY_BORDER: 2,
          Reason.NOT_BODY_COLOURED: 3, Reason.NOT_ELLIPTICAL: 4, Reason.LOW_CONTRAST: 5,
          Reason.FEW_EDGE_POINTS: 5, Reason.EDGE_COVERAGE: 6, Reason.RESIDUAL: 6,
          Reason.NOT_A_SPHERE: 7, Reason.MARKS_INCONSISTENT: 8, Reason.COLOURS_SWAPPED: 9}


def _check_distinct(colors: dict, body_tol: float, mark_tol: float) -> None:
    """
    Raise ``ValueError`` unless the body and every mark differ in chromaticity.

    A mark within its tolerance of the body's colour (or of another mark's) could not be
    told from it: the detector would look for it in vain, or find the wrong one.
    """
    chroma = {k: to_chroma(np.asarray(c, float)) for k, c in colors.items()}
    names = [k for k in colors if k != 'body']
    for i, a in enumerate(names):
        d = float(np.linalg.norm(chroma[a] - chroma['body']))
        if d < 1.5 * body_tol + mark_tol:
            raise ValueError(f'mark {a} colour {colors[a]} is too close to the body '
                             f'{colors["body"]} in chromaticity ({d:.3f})')
        for b in names[i + 1:]:
            d = float(np.linalg.norm(chroma[a] - chroma[b]))
            if d < 2 * mark_tol:
                raise ValueError(f'marks {a} and {b} have too close colours {colors[a]}, '
                                 f'{colors[b]} ({d:.3f})')


def _inside(sil: Silhouette, u: float, v: float) -> bool:
    """Tell whether the pixel (u, v) lies inside the silhouette ``sil``."""
    C = sil.conic_px
    p, c = np.array([u, v, 1.0]), np.array([*sil.ellipse.centre, 1.0])
    return float(p @ C @ p) * float(c @ C @ c) > 0


@dataclass
class _Candidate:
    """A candidate that passed the bounds: its silhouette, conic, sphere and marks."""

    sil: Silhouette
    C_n: np.ndarray
    sphere: SphereMeasurement
    marks: dict
    n_marks: int
    sure: bool = False
    lift: PinholeLift | ModelLift | None = None     # how its pixels were lifted


class Detector:
    """
    Sphere + marks detector, configured by the target's description.

    colors          {'body': rgb, 'P1': rgb, 'P2' or 'P3': rgb} (rgb8 triplets).
    surface_marks   names of marks painted on the surface (centre by back-projection on the
                    sphere); the others (the CC tip 'P3') use the image of their centre.
    geometry        the marks' :class:`~sphere_servo.vision.scoring.MarkGeometry` (None: the
                    marks are not checked against each other).
    bounds          the :class:`~sphere_servo.vision.scoring.FitBounds` of a published fit.
    max_fits        largest number of sphere-like objects fitted in one image.
    conic_path      measure the sphere of a pinhole camera without distortion by its conic
                    in the image (True: the fast special case), or by the small circle of
                    its lifted edge as through any other model (False: the same sphere).
    min_area_px, min_contrast, body_chroma_tol, K, max_edge_points, coarse_step
                    the silhouette's (:class:`~sphere_servo.vision.silhouette.SilhouetteFinder`).
    chroma_tol, min_mark_px, mark_radius, min_mark_seen
                    the marks' (:class:`~sphere_servo.vision.marks.MarkFinder`).
    """

    def __init__(self, colors: dict | None = None, surface_marks=('P1', 'P2'), *,
                 geometry: MarkGeometry | None = None, bounds: FitBounds | None = None,
                 max_fits: int = 8, min_area_px: float = 30.0, min_contrast: float = 25.0,
                 chroma_tol: float = 0.12, body_chroma_tol: float = 0.08,
                 min_mark_px: float = 3.0, K: int = 3, max_edge_points: int = 100,
                 coarse_step: int = 4, mark_radius: float = float(np.radians(9.0)),
                 conic_path: bool = True, min_mark_seen: float = 0.8):
        self.colors = dict(DEFAULT_COLORS if colors is None else colors)
        if 'body' not in self.colors:
            raise ValueError("colors must contain 'body'")
        _check_distinct(self.colors, body_chroma_tol, chroma_tol)
        self.silhouette = SilhouetteFinder(
            self.colors['body'], min_area_px=min_area_px, min_contrast=min_contrast,
            body_chroma_tol=body_chroma_tol, K=K, max_edge_points=max_edge_points,
            coarse_step=coarse_step,
            marks=[c for k, c in self.colors.items() if k != 'body'], mark_chroma_tol=chroma_tol)
        self.marks = MarkFinder(self.colors, surface_marks, chroma_tol=chroma_tol,
                                min_mark_px=min_mark_px, mark_radius=mark_radius,
                                min_seen=min_mark_seen)
        self.mark_names = self.marks.mark_names
        self.geometry = geometry
        self.bounds = FitBounds() if bounds is None else bounds
        self.max_fits = int(max_fits)
        self.conic_path = bool(conic_path)
        self._lift = (None, None)   # (camera, its lift): a camera's table is looked up once
        self._cut_lift = (None, None)   # (camera, its model lift) for spheres cut by the border

    @classmethod
    def for_target(cls, target: Target, **kw) -> 'Detector':
        """
        Build the detector of ``target``: its colours, mark names, cap radius, marks' layout.

        The fit bounds follow the body's shape (:meth:`FitBounds.for_target`).
        """
        a, b = target.mark_names
        cols = target.colors
        colors = {'body': cols['body'], a: cols[a], b: cols.get(b, cols.get('P2'))}
        surface = (a, b) if target.kind == SPECIAL else (a,)
        kw.setdefault('mark_radius', target.mark_radius)
        if not target.is_sphere:        # the caps' area on the estimated sphere is not theirs
            kw.setdefault('min_mark_seen', 0.0)
        kw.setdefault('geometry', MarkGeometry.for_target(target))
        kw.setdefault('bounds', FitBounds.for_target(target))
        return cls(colors, surface, **kw)

    def lift(self, camera) -> PinholeLift | ModelLift:
        """Return how the pixels of ``camera`` are lifted (:func:`~.rays.lift_of`)."""
        last, lift = self._lift
        if last is not camera:
            lift = lift_of(camera, self.conic_path)
            self._lift = (camera, lift)
        return lift

    def cut_lift(self, camera, lift: PinholeLift | ModelLift) -> PinholeLift | ModelLift:
        """
        Return how the pixels of a sphere cut by the image border are lifted.

        Through the camera's model (the sphere's cone, 3 parameters, fitted to the lifted
        edge) when ``lift`` is the conic path's ``K`` and ``camera`` has a model: a general
        conic (5 parameters) fitted to the short arc a border leaves is ill-conditioned, and
        measures a sphere several per cent off with a small residual. Else ``lift``.
        """
        if lift.lifted or not isinstance(camera, CentralCamera):
            return lift
        last, cut = self._cut_lift
        if last is not camera:
            cut = lift_of(camera, conic_path=False)
            self._cut_lift = (camera, cut)
        return cut

    def detect(self, image: np.ndarray, encoding: str, camera) -> Detection:
        """
        Detect the target and its marks in ``image`` seen by ``camera``.

        ``image``: (H, W, 3) for rgb8/bgr8, (H, W) or (H, W, 1) for mono8, uint8;
        ``camera``: a :class:`~sphere_servo.core.central.CentralCamera` (a pinhole, a
        fisheye, a unified camera: its distortion is applied), or anything with px, py, u0,
        v0 (a pinhole without distortion). Raises ``ValueError`` on a bad
        image/encoding/intrinsics, or a camera of another size than the image's; returns
        ``Detection(found=False, not_detected=...)`` when there is no usable target (module
        docstring: the choice).
        """
        lift = self.lift(camera)
        img = check_image(image, encoding)
        if lift.lifted and img.shape[:2] != (lift.camera.height, lift.camera.width):
            raise ValueError(f'camera of {lift.camera.width}x{lift.camera.height} px for an '
                             f'image of {img.shape[1]}x{img.shape[0]}')
        rgb = None if img.ndim == 2 else (img if encoding == 'rgb8' else img[..., ::-1])
        found = self.silhouette.candidates(img, rgb)
        if isinstance(found, NotDetected):
            return Detection.missed(found, self.marks.not_visible())
        s = found.step
        todo = list(reversed(found.blobs))              # a stack: the next one last
        miss, accepted, seen = None, [], []
        while todo and len(seen) < self.max_fits:
            blob = todo.pop()
            u, v = blob.centre(s)
            if any(c.sure and _inside(c.sil, u, v) for c in accepted):
                continue                    # a part, or another level, of a sure fit
            blift = self.cut_lift(camera, lift) if blob.cut else lift
            sil = self.silhouette.fit(blob, img, rgb, s, blift if blift.lifted else None)
            if not isinstance(sil, NotDetected):
                (cu, cv_), _, _ = sil.ellipse
                if not any(_inside(o, cu, cv_) for o in seen):
                    seen.append(sil)        # a sphere-like object (bounds or not)
                sil = self._candidate(sil, img, encoding, rgb, blift)
            if isinstance(sil, NotDetected) or not sil.sure:
                # its level may have cut into the sphere's shaded side: try the blob grown
                # down to the level of the background around it, next
                grown = found.grown(blob)
                if grown is not None:
                    todo.append(grown)
            if isinstance(sil, NotDetected):
                if miss is None or _STAGE[sil.reason] > _STAGE[miss.reason]:
                    miss = sil
                continue
            if sil.sure and sil.n_marks == len(self.mark_names):
                return self._found(sil)         # the target: a sure fit, all its marks fit
            accepted.append(sil)
        if accepted:
            # most marks, then the edge contrasted around most of the contour, then the
            # tightest fit (of the levels of one object, the one that does not cut into its
            # shaded side); pixel figures only, so the choice does not depend on the
            # intrinsics the detector is given
            best = min(accepted, key=lambda c: (-c.n_marks, -c.sil.coverage, c.sil.rms_px))
            several = best.n_marks == 0 and len(seen) > 1
            if several or self._marks_beside(img, encoding, rgb, best):
                # a sphere without marks among other sphere-like objects, or one that lacks
                # marks whose colours are seen beside it (on the target it hides, or that
                # hides it): which is it?
                why = f'{len(seen)} in view' if several else 'its missing marks seen beside it'
                return Detection.missed(NotDetected(Reason.AMBIGUOUS, why),
                                        self.marks.not_visible())
            return self._found(best)
        # no blob with a contrasted edge, and the frame is the body's colour and bright
        early = miss is None or _STAGE[miss.reason] <= _STAGE[Reason.LOW_CONTRAST]
        if rgb is not None and early and self.silhouette.fills_frame(rgb):
            miss = NotDetected(Reason.TOO_LARGE, 'the body fills the frame')
        return Detection.missed(miss or NotDetected(Reason.NO_BLOB), self.marks.not_visible())

    def _candidate(self, sil: Silhouette, img, encoding: str, rgb, lift
                   ) -> '_Candidate | NotDetected':
        """Check one fitted silhouette against the bounds and measure its marks."""
        why = self.bounds.check(sil)
        if why is not None:
            return why
        if sil.cone is not None:
            C_n, sphere = sil.cone.conic, sil.cone.sphere
        else:
            C_n = conic_pixels_to_normalized(sil.conic_px, lift.px, lift.py, lift.u0, lift.v0)
            try:
                sphere = sphere_from_conic(C_n)
            except MeasurementError as exc:
                return NotDetected(Reason.NOT_A_SPHERE, str(exc))
        if sil.edge is not None and (sphere.quality > self.bounds.refit_quality
                                     or not self.bounds.sure(sil)):
            sil, C_n, sphere = self._drop_foreign_arc(sil, C_n, sphere, lift)
        why = self.bounds.check(sil, sphere)
        if why is not None:
            return why
        marks = self.marks.find(img, encoding, rgb, sphere, sil, lift)
        q = {}
        for name, m in marks.items():
            if not m.visible:
                continue
            if name in self.marks.surface_marks and self.geometry is not None \
                    and not self.geometry.on_sphere(sphere, m.q):
                marks[name] = Mark.lost(name, Reason.MARK_OFF_SPHERE, area_px=m.area_px)
                continue
            q[name] = m.q
        if self.geometry is not None and len(q) == len(self.geometry.names) \
                and set(q) == set(self.geometry.names):
            why = self.geometry.check(sphere, q)
            if why is not None:
                return why
        swapped = self.marks.swapped(marks, rgb, sil)
        if swapped:          # each mark found at the other's place: not a measurement
            return NotDetected(Reason.COLOURS_SWAPPED, swapped)
        return _Candidate(sil, C_n, sphere, marks, len(q), self.bounds.sure(sil), lift)

    def _marks_beside(self, img, encoding: str, rgb, cand: _Candidate) -> bool:
        """
        Tell whether the colour of a surface mark ``cand`` lacks is seen 3 px or more out.

        A body-coloured sphere beside the target, partly in front of it or behind it, may
        win with none or some of the target's marks (one near its limb, where the target
        hides it): a sphere that lacks surface marks is the target only when no blob
        (``min_mark_px``) of a lacking one's colour lies outside it (the CC tip P3 does).
        """
        lack = [i for i, n in enumerate(self.mark_names)
                if not cand.marks[n].visible and n in self.marks.surface_marks]
        if rgb is None or not lack:
            return False
        sil = cand.sil
        px, sel = self.marks.colour_pixels(img, encoding, rgb, sil.threshold)
        if px is None:
            return False
        pts = px[sel[:, lack].any(axis=1)]
        C = sil.conic_px
        c = np.array([*sil.ellipse.centre, 1.0])
        d = sampson_homogeneous(C, homogeneous(pts[:, 0], pts[:, 1])) * np.sign(c @ C @ c)
        pts = pts[d < -3.0]
        if len(pts) < self.marks.min_mark_px:
            return False
        m = np.zeros(img.shape[:2], np.uint8)
        m[pts[:, 1], pts[:, 0]] = 1
        st = cv2.connectedComponentsWithStats(m, connectivity=8)[2]
        return bool((st[1:, cv2.CC_STAT_AREA] >= self.marks.min_mark_px).any())

    @staticmethod
    def _drop_foreign_arc(sil: Silhouette, C_n, sphere: SphereMeasurement, lift):
        """
        Refit without a foreign arc of edge, if there is one and that makes a sphere's image.

        (:func:`~sphere_servo.vision.scoring.foreign_arc`.) The fit of the other points
        replaces the first one only when at least half the points remain and its quality is
        at most a third of the first one's.
        """
        E = sil.edge
        if sil.cone is not None:
            X = sil.cone.rays[:, sil.cone.keep]
            px_per_rad = float(np.median(sil.cone.scale[sil.cone.keep]))
        else:
            X = np.array([(E[0] - lift.u0) / lift.px, (E[1] - lift.v0) / lift.py,
                          np.ones(E.shape[1])])
            X /= np.sqrt((X * X).sum(axis=0))
            px_per_rad = 0.5 * (lift.px + lift.py)
        keep = foreign_arc(X, px_per_rad)
        if keep is None:
            return sil, C_n, sphere
        nk = int(np.count_nonzero(keep))
        if nk < max(10, 0.5 * len(keep)):
            return sil, C_n, sphere
        Ek = E[:, keep]
        C_px = fit_conic(Ek[:2].T)
        ep = ellipse_params(C_px)
        cone = None
        if sil.cone is not None:
            cone = fit_cone(lift, Ek)
            if isinstance(cone, NotDetected):
                return sil, C_n, sphere
            C2, sphere2, rms, nk = cone.conic, cone.sphere, cone.rms_px, int(cone.keep.sum())
            Ek = Ek[:, cone.keep]
        else:
            C2 = conic_pixels_to_normalized(C_px, lift.px, lift.py, lift.u0, lift.v0)
            try:
                sphere2 = sphere_from_conic(C2)
            except MeasurementError:
                return sil, C_n, sphere
            d = sampson_homogeneous(C_px, Ek)
            rms = math.sqrt(float(d @ d) / nk)
        if ep is None or sphere2.quality > sphere.quality / 3.0:
            return sil, C_n, sphere
        return (replace(sil, conic_px=C_px, rms_px=rms, n_points=nk, ellipse=ep,
                        coverage=nk / max(sil.n_profiles, 1), edge=Ek, cone=cone), C2, sphere2)

    @staticmethod
    def _found(cand: _Candidate) -> Detection:
        sil, sphere, lift = cand.sil, cand.sphere, cand.lift
        c, ax, ang = sil.ellipse
        contour = None
        if sil.cone is not None:
            contour = contour_px(lift.camera, sphere.b, sil.cone.theta)
        return Detection(True, '', cand.C_n, sphere, sphere.quality, sil.rms_px,
                         (c, (2.0 * ax[0], 2.0 * ax[1]), math.degrees(ang)), cand.marks,
                         sil.cut_by_border, sil.n_points, coverage=sil.coverage,
                         contour_px=contour)


def detect(image: np.ndarray, encoding: str, camera, target: Target | None = None,
           **kw) -> Detection:
    """One-shot :meth:`Detector.detect` (colours from ``target`` if given, else defaults)."""
    det = Detector.for_target(target, **kw) if target is not None else Detector(**kw)
    return det.detect(image, encoding, camera)


# the facade; image_from_buffer (home: vision.image) too, for the callers that decode
# a message's buffer before detecting
__all__ = ['DEFAULT_COLORS', 'Detection', 'Detector', 'Mark', 'camera_intrinsics', 'detect',
           'image_from_buffer']
