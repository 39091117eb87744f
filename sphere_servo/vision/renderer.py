"""
Ray-casting renderer of the marked targets (no ROS). DESIGN.md §1, §2, §5.

Every pixel ``(u, v)`` is a ray from the camera centre (camera optical frame: z forward, x
right, y down): ``x̄ = K⁻¹ (u, v, 1)`` for a pinhole without distortion, else the camera
model's lift (:mod:`~sphere_servo.core.central`: plumb_bob, equidistant fisheye, unified
catadioptric), so a fisheye or catadioptric image is exact to the border of its field; the
lifted rays are computed once per camera (:func:`~sphere_servo.vision.rays.pixel_rays`).
Pixels no valid ray reaches (outside a model's image circle) are black. The ray is
intersected with

- the body: a sphere S(O, r) or, for the balloon, the ellipsoid with semi-axes ``target.axes``
  (target frame ``o``), shaded Lambertian ``albedo · gain · (ambient + diffuse · max(0, n·l))``
  with ``ambient`` large enough that the shadowed side stays well above the background
  (DESIGN.md §2, first lesson);
- the marks, painted *on* the surface: a mark is the cap of surface points whose direction
  from O is within ``target.mark_radius`` of the mark's direction, so it is foreshortened
  and hidden on the far side by construction;
- for the CC target, the tangent stick P1→P3 (a thin cylinder) and the tip P3 (a small
  ball coloured like the second mark), depth-tested against the body.

Only the bounding box of the target's image is traced; pixels where the label (background,
body, mark, stick, tip) changes between neighbours are re-traced with 16 stratified
sub-samples (box-filter anti-aliasing, 16 distinct offsets along each axis; through a model,
a sub-sample's ray is its pixel's to first order, ``q + ∂q/∂u δu + ∂q/∂v δv``, and exact on
the edge of the image circle). The background
(:mod:`~sphere_servo.vision.backgrounds`) is a deterministic smooth gradient with
low-frequency texture, clutter, a two-level checkerboard or noise texture, or a given image,
with distractor spheres and discs drawn into it. Optional Gaussian noise (grey levels),
Gaussian blur (pixels) and lighting gain.
"""
from __future__ import annotations

import cv2
import numpy as np
import pinocchio as pin

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.central import CentralCamera
from sphere_servo.core.conics import conic_bbox, conic_normalized_to_pixels, sphere_silhouette
from sphere_servo.core.small_circle import circle_rays
from sphere_servo.core.targets import CC, Target
from sphere_servo.vision.backgrounds import draw_distractors, make_background
from sphere_servo.vision.rays import pixel_rays

# labels of what a ray hits first
MISS, BODY, MARK1, MARK2, STICK, TIP = 0, 1, 2, 3, 4, 5

# 16 stratified sub-pixel offsets in (−0.5, 0.5): distinct along x and along y
_N_SUB = 16
_SUB_X = (np.arange(_N_SUB) + 0.5) / _N_SUB - 0.5
_SUB_Y = ((np.arange(_N_SUB) * 5) % _N_SUB + 0.5) / _N_SUB - 0.5


class Renderer:
    """
    Ray-cast ``rgb8`` images of ``target`` seen by ``camera``.

    camera      the true camera: a :class:`~sphere_servo.core.central.CentralCamera` (a
                pinhole, distorted by its plumb_bob coefficients, a fisheye, a unified
                camera).
    target      :class:`~sphere_servo.core.targets.Target` (special, CC or balloon): its
                colours and cap radius are what is painted.
    background  'gradient' (default), 'clutter', 'flat', 'checker', 'noise' or an
                (H, W, 3) uint8 image (:func:`~sphere_servo.vision.backgrounds.make_background`);
                ``levels`` (lo, hi) and ``texture_px`` set the checkerboard and the noise
                texture.
    distractors :class:`~sphere_servo.vision.backgrounds.Distractor` spheres and discs
                (camera frame), drawn behind the target with the construction's light
                (a pinhole without distortion only).
    light_dir   (3,) direction *towards* the light in the camera optical frame (a light on
                the camera, slightly up-left, by default), normalized internally.
    ambient, diffuse, gain   shading ``gain · (ambient + diffuse · max(0, n·l))``; change
                ``gain``/``light_dir`` between frames for lighting changes.
    noise_sigma Gaussian noise std (grey levels) added to every channel; ``blur_sigma``
                Gaussian blur std (px) applied before the noise.
    seed        seeds the background texture and the noise (deterministic images).
    tip_radius, stick_radius   radii (m) of the CC tip ball and stick; default 0.12 r, 0.015 r.
    stick_color rgb8 colour of the CC stick.
    """

    def __init__(self, camera: CentralCamera, target: Target, *, background='gradient',
                 light_dir=(-0.35, -0.45, -0.82), ambient: float = 0.55,
                 diffuse: float = 0.45, gain: float = 1.0, noise_sigma: float = 0.0,
                 blur_sigma: float = 0.0, seed: int = 0, tip_radius: float | None = None,
                 stick_radius: float | None = None, stick_color=(200, 200, 190),
                 levels=(40, 70), texture_px: float = 24.0, distractors=()):
        if not isinstance(camera, CentralCamera):
            raise TypeError(f'camera must be a CentralCamera, got {type(camera).__name__}')
        if not isinstance(target, Target):
            raise TypeError(f'target must be a Target, got {type(target).__name__}')
        for name, val in (('ambient', ambient), ('diffuse', diffuse), ('gain', gain),
                          ('noise_sigma', noise_sigma), ('blur_sigma', blur_sigma)):
            if not np.isfinite(val) or val < 0:
                raise ValueError(f'{name} must be a finite number ≥ 0, got {val}')
        self.camera = camera
        self.target = target
        self.W, self.H = int(camera.width), int(camera.height)
        self.light_dir = np.asarray(light_dir, dtype=float)
        self.ambient, self.diffuse, self.gain = float(ambient), float(diffuse), float(gain)
        self.noise_sigma, self.blur_sigma = float(noise_sigma), float(blur_sigma)
        self._rng = np.random.default_rng(seed)
        self.background = make_background(background, self.W, self.H,
                                          np.random.default_rng(seed), levels=levels,
                                          texture_px=texture_px)
        # a pinhole without distortion: separable normalized coordinates, else lifted rays
        self._lifted = not (isinstance(camera, CameraIntrinsics) and not camera.has_distortion)
        if distractors:
            if self._lifted:
                raise ValueError('distractors are drawn for a pinhole camera without '
                                 f'distortion only, not a {type(camera).__name__}')
            self.background = draw_distractors(self.background, camera, distractors,
                                               self.light_dir, self.ambient, self.diffuse,
                                               self.gain)
        r = target.radius
        self.tip_radius = 0.12 * r if tip_radius is None else float(tip_radius)
        self.stick_radius = 0.015 * r if stick_radius is None else float(stick_radius)
        self.axes = np.full(3, r) if target.axes is None else np.asarray(target.axes, float)
        names = target.mark_names
        cols = target.colors
        self.albedo = np.zeros((6, 3), np.float32)
        self.albedo[BODY] = cols['body']
        self.albedo[MARK1] = cols[names[0]]
        self.albedo[MARK2] = cols.get(names[1], cols.get('P2'))
        self.albedo[STICK] = stick_color
        self.albedo[TIP] = self.albedo[MARK2]
        # surface caps: for CC only P1 is painted on the surface; P3 is the tip ball
        caps = [(MARK1, target.oP1)] + ([] if target.kind == CC else [(MARK2, target.oP2)])
        self._caps = [(lab, oP / np.linalg.norm(oP)) for lab, oP in caps]
        self._cos_mark = float(np.cos(target.mark_radius))
        self._bound_radius = float(np.max(self.axes))
        if self._lifted:
            self._rays = pixel_rays(camera)
            self.background[~self._rays.valid] = 0     # outside the image circle: black
        else:
            # normalized coordinates of the pixel centres: a (1, W) row, an (H, 1) column
            self._X = ((np.arange(self.W) - camera.u0) / camera.px).astype(np.float32)[None]
            self._Y = ((np.arange(self.H) - camera.v0) / camera.py).astype(np.float32)[:, None]

    # --- ray casting ---------------------------------------------------------------------
    def _trace(self, x: np.ndarray, y: np.ndarray, z, cMo: pin.SE3):
        """
        Trace rays ``d = (x, y, z)`` from the camera centre (any length; NaN: no ray).

        ``x``, ``y``, ``z``: broadcastable arrays, e.g. a (1, w) row and an (h, 1) column of
        normalized coordinates with ``z = 1.0``, or (h, w) lifted rays. Returns
        ``(label uint8, f float32)`` of the broadcast shape: what each ray hits first and
        its brightness ``gain · (ambient + diffuse · max(0, n·l))`` (meaningless where the
        label is MISS).
        """
        R = np.asarray(cMo.rotation)
        t = np.asarray(cMo.translation, dtype=float)
        light = self.light_dir / np.linalg.norm(self.light_dir)
        if self.target.is_sphere:
            # camera frame: |s d − O|² = r², d = (x, y, z); s = (d·O − √disc)/‖d‖².
            # Python-float coefficients keep float32 inputs in float32 (NEP 50).
            r = float(self.target.radius)
            tx, ty, tz = (float(v) for v in t)
            dO = x * tx + y * ty + z * tz
            dd = x * x + y * y + z * z
            disc = dO * dO - dd * float(t @ t - r * r)
            hit = (disc > 0) & (dO > 0)
            s = (dO - np.sqrt(np.maximum(disc, 0.0))) / dd
            # r n = s d − O: the Lambert term and the marks are affine in s
            lx, ly, lz = (float(v) for v in light)
            lam = (s * (x * lx + y * ly + z * lz) - float(t @ light)) * (1.0 / r)
            label = hit.astype(np.uint8)      # BODY where hit
            for lab, m_o in self._caps:
                m = R @ m_o
                mx, my, mz = (float(v) for v in m)
                on = (s * (x * mx + y * my + z * mz)) >= float(r * self._cos_mark + t @ m)
                label[on & hit] = lab
        else:
            # ellipsoid, in the target frame scaled to the unit sphere: p' = c' + s d'
            co = (-(R.T @ t) / self.axes).tolist()
            Rs = (R.T / self.axes[:, None]).tolist()   # d' = Rs (x, y, z)
            dx = Rs[0][0] * x + Rs[0][1] * y + Rs[0][2] * z
            dy = Rs[1][0] * x + Rs[1][1] * y + Rs[1][2] * z
            dz = Rs[2][0] * x + Rs[2][1] * y + Rs[2][2] * z
            a = dx * dx + dy * dy + dz * dz
            b = co[0] * dx + co[1] * dy + co[2] * dz
            disc = b * b - a * float(np.dot(co, co) - 1.0)
            s = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            hit = (disc > 0) & (s > 0)
            px, py, pz = co[0] + s * dx, co[1] + s * dy, co[2] + s * dz
            # outward normal in the target frame ∝ p_o / axes² = p' / axes
            l_o = (R.T @ light).tolist()
            ax = self.axes.tolist()
            nx, ny, nz = px * (1.0 / ax[0]), py * (1.0 / ax[1]), pz * (1.0 / ax[2])
            lam = (nx * l_o[0] + ny * l_o[1] + nz * l_o[2]) / np.sqrt(nx * nx + ny * ny
                                                                      + nz * nz)
            # marks: the point's direction from O (unscaled target frame) vs the mark's
            qx, qy, qz = px * ax[0], py * ax[1], pz * ax[2]
            qn = np.sqrt(qx * qx + qy * qy + qz * qz)
            label = hit.astype(np.uint8)
            for lab, m in self._caps:
                m0, m1, m2 = m.tolist()
                on = (qx * m0 + qy * m1 + qz * m2) >= self._cos_mark * qn
                label[on & hit] = lab
        shade = np.maximum(lam, 0.0)
        if self.target.kind == CC:
            depth = np.where(hit, s, np.float32(np.inf))
            label, shade = self._trace_cc(x, y, z, cMo, label, depth, shade)
        f = (self.gain * (self.ambient + self.diffuse * shade)).astype(np.float32)
        return label, f

    def _trace_cc(self, x, y, z, cMo, label, depth, shade):
        """
        Trace the stick (cylinder P1→P3) and the tip ball at P3 of the CC target.

        Depth-tested, in the camera frame: ``depth`` is the parameter s of the camera ray
        ``s (x, y, z)`` at the body hit (∞ on a miss). Returns the updated
        ``(label, shade)``.

        On the separable pixel grid (``x`` a (1, w) row, ``y`` an (h, 1) column) each part is
        traced only in its own image box: the tip ball's silhouette box, and for the stick
        the box of its two end balls of the stick's radius (the cylinder lies in their
        convex hull, whose image lies in the hull of theirs).
        """
        A = np.asarray(cMo.act(self.target.oP1), dtype=float)
        B = np.asarray(cMo.act(self.target.oP2), dtype=float)
        light = self.light_dir / np.linalg.norm(self.light_dir)
        # label, shade and depth are full, writable arrays of the rays' broadcast shape (see
        # _trace); the parts write into them in place
        grid = x.ndim == 2 and x.shape[0] == 1 and y.shape[1:] == (1,)
        for part, balls in ((self._trace_tip, [(B, self.tip_radius)]),
                            (self._trace_stick, [(A, self.stick_radius),
                                                 (B, self.stick_radius)])):
            win = self._window(x, y, balls) if grid else (slice(None), slice(None))
            if win is None:
                continue
            rows, cols = win
            xs, ys = (x[:, cols], y[rows, :]) if grid else (x, y)
            sub = (rows, cols) if grid else Ellipsis
            part(xs, ys, z, A, B, light, label[sub], shade[sub], depth[sub])
        return label, shade

    @staticmethod
    def _window(x, y, balls):
        """
        Find the window of the pixel grid whose rays can meet one of ``balls``.

        ``balls``: [(centre in the camera frame, radius)]; the grid is separable, ``x``
        (1, w), ``y`` (h, 1). Returns (rows, cols) slices, None if no ray can meet a ball,
        the whole grid if a ball is not entirely in front of the camera.
        """
        boxes = []
        for c, rad in balls:
            if c[2] <= rad * 1.0001:
                return slice(None), slice(None)
            box = conic_bbox(sphere_silhouette(c, rad))
            if box is None:
                return slice(None), slice(None)
            boxes.append(box)
        x0, x1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
        y0, y1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
        xr, yc = x[0], y[:, 0]                 # increasing (pixel → normalized, no distortion)
        c0, c1 = np.searchsorted(xr, x0) - 1, np.searchsorted(xr, x1) + 1
        r0, r1 = np.searchsorted(yc, y0) - 1, np.searchsorted(yc, y1) + 1
        c0, r0 = max(c0, 0), max(r0, 0)
        if c0 >= min(c1, xr.size) or r0 >= min(r1, yc.size):
            return None
        return slice(r0, r1), slice(c0, c1)

    def _trace_tip(self, x, y, z, A, B, light, label, shade, depth):
        """
        Trace the tip ball ``|s d − B|² = ρ²``.

        Writes TIP, its shade and depth where it is the nearest surface (``label``,
        ``shade``, ``depth``: views, updated in place).
        """
        rho = self.tip_radius
        B0, B1, B2 = B.tolist()
        lx, ly, lz = light.tolist()
        dd = x * x + y * y + z * z
        dB = x * B0 + y * B1 + z * B2
        disc = dB * dB - dd * float(B @ B - rho * rho)
        s = (dB - np.sqrt(np.maximum(disc, 0.0))) / dd
        on = (disc > 0) & (s > 0) & (s < depth)
        lam = (s * (x * lx + y * ly + z * lz) - float(B @ light)) * (1.0 / rho)
        label[on] = TIP
        shade[on] = np.maximum(np.broadcast_to(lam, on.shape)[on], 0.0)
        depth[on] = np.broadcast_to(s, on.shape)[on]

    def _trace_stick(self, x, y, z, A, B, light, label, shade, depth):
        """
        Trace the stick: the cylinder of axis ``A + σ w``, radius ρ, σ ∈ [0, L].

        Same in-place contract as :meth:`_trace_tip`.
        """
        w = B - A
        L = np.linalg.norm(w)
        w = w / L
        rho = self.stick_radius
        w0, w1, w2 = w.tolist()
        lx, ly, lz = light.tolist()
        dw = x * w0 + y * w1 + z * w2
        mx, my, mz = x - dw * w0, y - dw * w1, z - dw * w2
        k0, k1, k2 = (-A + (A @ w) * w).tolist()      # −A projected ⟂ w
        aa = np.maximum(mx * mx + my * my + mz * mz, 1e-30)
        bb = mx * k0 + my * k1 + mz * k2
        disc = bb * bb - aa * float(k0 * k0 + k1 * k1 + k2 * k2 - rho * rho)
        s = (-bb - np.sqrt(np.maximum(disc, 0.0))) / aa
        sig = s * dw - float(A @ w)             # (s d − A)·w
        on = (disc > 0) & (s > 0) & (s < depth) & (sig >= 0) & (sig <= float(L))
        # normal = (s d − A − σ w)/ρ; its dot with the light
        lam = (s * (x * lx + y * ly + z * lz) - float(A @ light) - sig * float(w @ light)) \
            * (1.0 / rho)
        label[on] = STICK
        shade[on] = np.maximum(lam[on], 0.0)

    # --- image -----------------------------------------------------------------------
    def _parts(self, cMo: pin.SE3) -> list:
        """(centre in the camera frame, radius) of balls that hold every part of the target."""
        parts = [(np.asarray(cMo.translation, dtype=float), self._bound_radius)]
        if self.target.kind == CC:
            oP1, oP2 = self.target.oP1, self.target.oP2
            parts.append((cMo.act(oP2), self.tip_radius))
            parts.append((cMo.act(0.5 * (oP1 + oP2)),
                          self.stick_radius + 0.5 * np.linalg.norm(oP2 - oP1)))
        return parts

    def _bbox(self, cMo: pin.SE3):
        """
        Find the pixel box ``(u0, u1, v0, v1)`` (half-open, clipped) of the target's image.

        ``None`` if nothing is visible; the whole image when a part's bounding ball is not
        entirely in front of a pinhole, or not entirely in a model's field.
        """
        if self._lifted:
            return self._bbox_lifted(cMo)
        full = (0, self.W, 0, self.H)
        boxes = []
        for c, rad in self._parts(cMo):
            dist = np.linalg.norm(c)
            if dist <= rad * 1.0001 or c[2] <= rad * 1.0001:
                if c[2] + rad <= 0:
                    continue          # entirely behind the camera
                return full
            cam = self.camera
            bb = conic_bbox(conic_normalized_to_pixels(sphere_silhouette(c, rad), cam.px,
                                                       cam.py, cam.u0, cam.v0))
            if bb is None:
                return full
            boxes.append(bb)
        return self._clip(boxes)

    def _bbox_lifted(self, cMo: pin.SE3):
        """
        :meth:`_bbox` through a camera model: the box of each ball's projected silhouette.

        The silhouette's cone (axis ``c/‖c‖``, half-angle ``asin(rad/‖c‖)``) is sampled at
        256 rays; the model maps the cap inside it one-to-one when the cone and its axis lie
        in the field, and the box of the samples is widened by 2 px for the arcs between
        them. A cone not in the field: the whole image.
        """
        full = (0, self.W, 0, self.H)
        cam = self.camera
        boxes = []
        for c, rad in self._parts(cMo):
            dist = float(np.linalg.norm(c))
            if dist <= rad * 1.0001:
                return full
            b = c / dist
            rays = np.vstack([b, circle_rays(b, float(np.arcsin(rad / dist)), 256)])
            if not cam.valid(rays).all():
                return full
            uv = cam.project(rays)
            boxes.append((uv[:, 0].min() - 2.0, uv[:, 0].max() + 2.0, uv[:, 1].min() - 2.0,
                          uv[:, 1].max() + 2.0))
        return self._clip(boxes)

    def _clip(self, boxes):
        """Return the union of the boxes (x0, x1, y0, y1), as whole pixels on the image."""
        if not boxes:
            return None
        x0 = min(b[0] for b in boxes)
        x1 = max(b[1] for b in boxes)
        y0 = min(b[2] for b in boxes)
        y1 = max(b[3] for b in boxes)
        u0, u1 = max(0, int(np.floor(x0)) - 1), min(self.W, int(np.ceil(x1)) + 2)
        v0, v1 = max(0, int(np.floor(y0)) - 1), min(self.H, int(np.ceil(y1)) + 2)
        if u0 >= u1 or v0 >= v1:
            return None
        return u0, u1, v0, v1

    def _sub_rays(self, eu: np.ndarray, ev: np.ndarray):
        """
        Rays (x, y, z), each (n, 16), of the 16 sub-samples of the pixels ``(eu, ev)``.

        Through a model: first order about the pixel's ray, exact (the model's lift) for a
        pixel on the edge of the image circle.
        """
        cam = self.camera
        if not self._lifted:
            xs = ((eu[:, None] + _SUB_X[None, :] - cam.u0) / cam.px).astype(np.float32)
            ys = ((ev[:, None] + _SUB_Y[None, :] - cam.v0) / cam.py).astype(np.float32)
            return xs, ys, 1.0
        T = self._rays
        out = []
        for k, comp in enumerate((T.x, T.y, T.z)):
            out.append(comp[ev, eu][:, None] + T.du[k, ev, eu][:, None] * _SUB_X[None, :]
                       + T.dv[k, ev, eu][:, None] * _SUB_Y[None, :])
        rim = T.rim[ev, eu]
        if rim.any():
            uu = eu[rim][:, None] + _SUB_X[None, :]
            vv = ev[rim][:, None] + _SUB_Y[None, :]
            q = cam.lift_where(np.column_stack([uu.ravel(), vv.ravel()])).rays
            for k in range(3):
                out[k][rim] = q[:, k].reshape(uu.shape)
        return tuple(out)

    def render(self, cMo: pin.SE3) -> np.ndarray:
        """
        Render the (H, W, 3) uint8 ``rgb8`` image of the target at pose ``cMo``.

        ``cMo``: the target frame in the camera optical frame (a ``pin.SE3``).
        """
        if not isinstance(cMo, pin.SE3):
            raise TypeError(f'cMo must be a pinocchio.SE3, got {type(cMo).__name__}')
        if not (np.all(np.isfinite(cMo.translation)) and np.all(np.isfinite(cMo.rotation))):
            raise ValueError('cMo contains NaN or inf')
        img = self.background.copy()
        box = self._bbox(cMo)
        if box is not None:
            u0, u1, v0, v1 = box
            if self._lifted:
                T = self._rays
                X, Y, Z = T.x[v0:v1, u0:u1], T.y[v0:v1, u0:u1], T.z[v0:v1, u0:u1]
            else:             # separable: a (1, w) row and an (h, 1) column
                X, Y, Z = self._X[:, u0:u1], self._Y[v0:v1], 1.0
            lab, f = self._trace(X, Y, Z, cMo)
            hit = lab != MISS
            # per-channel shaded colour f·albedo, uint8 (rounded, saturated)
            chans = [cv2.convertScaleAbs(f, alpha=float(self.albedo[BODY, c]))
                     for c in range(3)]
            # the marks, stick and tip pixels (labels above BODY) through one mask
            sel = lab > BODY
            if sel.any():
                vals = np.clip(f[sel][:, None] * self.albedo[lab[sel]] + 0.5, 0, 255
                               ).astype(np.uint8)
                for c in range(3):
                    chans[c][sel] = vals[:, c]
            roi = img[v0:v1, u0:u1]
            # anti-aliasing: pixels whose label differs from a 4-neighbour's are re-traced
            # with 16 stratified sub-samples and blended with the background (box filter)
            edge = np.zeros(lab.shape, bool)
            dv = lab[1:, :] != lab[:-1, :]
            du = lab[:, 1:] != lab[:, :-1]
            edge[1:, :] |= dv
            edge[:-1, :] |= dv
            edge[:, 1:] |= du
            edge[:, :-1] |= du
            ev, eu = np.nonzero(edge)
            if ev.size:
                slab, sf = self._trace(*self._sub_rays(eu + u0, ev + v0), cMo)
                # mean colour over the sub-samples: Σ_k (Σ f on label k) albedo_k / 16
                # + (fraction missed) · background
                acc = (slab == MISS).mean(axis=1, dtype=np.float32)[:, None] \
                    * roi[ev, eu].astype(np.float32)
                for k in range(BODY, TIP + 1):
                    on = slab == k
                    if k == BODY or on.any():
                        wk = np.where(on, sf, 0.0).sum(axis=1) * (1.0 / _N_SUB)
                        acc += wk[:, None] * self.albedo[k]
                acc = np.clip(acc + 0.5, 0, 255).astype(np.uint8)
                for c in range(3):
                    chans[c][ev, eu] = acc[:, c]
                hit |= edge
            cv2.copyTo(cv2.merge(chans), hit.view(np.uint8), roi)
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        if self.noise_sigma > 0:
            noise = self._rng.normal(0.0, self.noise_sigma, img.shape).astype(np.float32)
            img = np.clip(img + noise + 0.5, 0, 255).astype(np.uint8)
        return img
