"""
Red and blue swapped: an ``rgb8`` image labelled ``bgr8`` (or the reverse), told by colour.

A driver or a bridge that mislabels its buffer swaps R and B. When a mark's colour swapped
is close to another mark's (the special sphere's red P1 and blue P2), each passes the other's
colour test and is measured at the other's place: a wrong ᶜR_o, with nothing else amiss.
:class:`SwapCheck` tells it from the marks' core colours (:func:`core_colour`) referred to
the body's colour in the same image (:func:`body_colour`).
"""
from __future__ import annotations

import math

import numpy as np

from sphere_servo.core.types import Image
from sphere_servo.vision.image import to_chroma

# counts added to each channel before the logs of _direction (a channel near 0 is noise)
_EPS = 2.0
# 200 points spread evenly over the unit disc (a sunflower): where body_colour looks
_DISC = np.sqrt((np.arange(200) + 0.5) / 200) * np.array(
    [np.cos(np.arange(200) * 2.39996323), np.sin(np.arange(200) * 2.39996323)])


def _median_rows(a: np.ndarray) -> np.ndarray:
    """Return the per-column (upper) median of the rows of ``a`` (N ≥ 1, 3), as floats."""
    k = len(a) // 2
    return np.partition(a, k, axis=0)[k].astype(float)


def _span(pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the largest and the smallest channel of the rows of ``pix`` (N, 3)."""
    # (a reduction over the last axis of 3 is several times slower than two ufuncs)
    r, g, b = pix[:, 0], pix[:, 1], pix[:, 2]
    return np.maximum(np.maximum(r, g), b), np.minimum(np.minimum(r, g), b)


def core_colour(pix: np.ndarray) -> np.ndarray:
    """
    Return a mark's own colour (3,) from the rgb rows ``pix`` (uint8) of its filled hull.

    The median of its most saturated quarter: the pixels least mixed with the body or the
    background (mixing desaturates), and not the stick across P1's cap.
    """
    hi, lo = _span(pix)
    sat = (hi - lo) / np.maximum(hi, 1, dtype=np.float32)
    k = (3 * len(sat)) // 4
    return _median_rows(pix[sat >= np.partition(sat, k)[k]])


def body_colour(rgb: Image, ellipse) -> np.ndarray | None:
    """
    Return the body's colour (3,) as ``rgb`` shows it inside the silhouette, or None.

    ``ellipse``: the silhouette's (:class:`~sphere_servo.core.conics.Ellipse`). The
    per-channel median of the pixels at fixed points of its disc up to 4 px from the limb
    (at most 95 % of its axes), the marks (saturation ≥ 0.5: the body's under a 20 % colour
    cast is 0.36, a mark's core 0.86), the shadow and clipped pixels left out; None with
    fewer than 10 of them. Out to the limb, not the inner 70 % only: an over-exposed body is
    often clipped but for its shaded rim, and under two lights of different colours the
    rim sees the other light too.
    """
    H, W = rgb.shape[:2]
    (cx, cy), (a0, a1), ang = ellipse
    # 4 px inside the limb (blur, anti-aliasing), a fraction 4/a of a semi-axis a
    s0 = min(0.95, max(0.0, 1.0 - 4.0 / max(a0, 1e-9)))
    s1 = min(0.95, max(0.0, 1.0 - 4.0 / max(a1, 1e-9)))
    ca, sa = math.cos(ang), math.sin(ang)
    uv = np.array([[a0 * s0 * ca, -a1 * s1 * sa], [a0 * s0 * sa, a1 * s1 * ca]]) @ _DISC
    uv += ((cx,), (cy,))
    np.minimum(np.maximum(uv, 0.0, out=uv), ((W - 1,), (H - 1,)), out=uv)  # np.clip: slower
    u, v = uv.astype(np.intp)
    pix = rgb[v, u].astype(np.int16)
    hi, lo = _span(pix)
    body = pix[(2 * lo > hi) & (hi < 250) & (10 * hi >= 3 * int(hi.max()))]
    return _median_rows(body) if len(body) >= 10 else None


def _direction(c, body) -> list[float]:
    """
    Return the unit direction of colour ``c`` from the body's ``body``, in log chromaticity.

    ``log(c + ε) − log(body + ε)`` less its mean over the three channels (ε = :data:`_EPS`
    counts: a channel near 0 is noise): a channel gain (white balance, a coloured light)
    adds the same to both logs and cancels, and a power-law tone curve (a gamma) scales the
    difference, leaving its direction. (A plane through 0 in rgb, the linear model of a
    mark mixed with the body, is bent by a gamma: with γ = 1.5 the swapped blue mark read
    as red lay closer to red's plane than to its own.)
    """
    d = [math.log(c[i] + _EPS) - math.log(body[i] + _EPS) for i in range(3)]
    m = (d[0] + d[1] + d[2]) / 3.0
    d = [x - m for x in d]
    n = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return [x / max(n, 1e-300) for x in d]


def _angle(u, v) -> float:
    """Return the angle (deg) between the unit 3-vectors ``u`` and ``v``."""
    x = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
    return math.degrees(math.atan2(math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]),
                                   u[0] * v[0] + u[1] * v[1] + u[2] * v[2]))


class SwapCheck:
    """
    ``check(marks, rgb, sil)``: why the marks' colours are the target's swapped, or ''.

    ``colors``: the target's ({'body': rgb, mark name: rgb}); ``chroma_tol``: the marks'
    colour test's. A mark counts when another mark's colour, R and B swapped, passes its
    test (for the default red and blue, each the other's). Each visible such mark's core
    colour (:attr:`~sphere_servo.vision.marks.Mark.colour`) is referred to the body's seen
    inside the silhouette (:func:`body_colour`; the target's when none is seen) as a
    direction in log chromaticity (:func:`_direction`: channel gains cancel, a gamma keeps
    it), and compared with two hypotheses: as labelled (its own colour from the target's
    body) and swapped (the other mark's from the body, both swapped). A mark whose two
    hypotheses are less than :attr:`min_sep` (deg) apart does not vote (a colour that is its
    own swap, or a red and a blue that are each other's on a grey body: no colour tells).
    Swapped when the marks' angles to the labelled directions sum to at least their floors
    (:attr:`floor`, or :attr:`rel_floor` of the hypotheses' separation when that is less)
    and their angles to the swapped ones to at most :attr:`ratio` of that sum: evidence
    pooled over the marks, so that one mark whose colour a neighbour's bleeds into (chroma
    subsampling of a small target) or that gamma or noise leaves in between neither vetoes
    a swap nor alone fakes one. README, "Detection": what was measured, and what no colour
    can tell.
    """

    floor = 8.0
    rel_floor = 0.8
    min_sep = 4.0
    ratio = 0.6

    def __init__(self, colors: dict, mark_names, chroma_tol: float):
        body = [float(x) for x in colors['body']]
        # name → the directions (as labelled, swapped) of the mark's colour from the body's
        self.hyps = {}
        for k in mark_names:
            ck = to_chroma(np.asarray(colors[k], float))
            near = min(mark_names, key=lambda j: float(np.linalg.norm(
                to_chroma(np.asarray(colors[j], float)[::-1]) - ck)))
            cj = [float(x) for x in colors[near]][::-1]
            if np.linalg.norm(to_chroma(np.asarray(cj)) - ck) < chroma_tol:
                own, alt = _direction([float(x) for x in colors[k]], body), \
                    _direction(cj, body[::-1])
                sep = _angle(own, alt)
                # a colour that reads as itself swapped (magenta, a red and a blue that are
                # each other's swap on a grey body) tells nothing: no vote
                if sep >= self.min_sep:
                    self.hyps[k] = (own, alt, min(self.floor, self.rel_floor * sep))
        self.body = body

    def __call__(self, marks: dict, rgb: Image | None, sil) -> str:
        """Return why the marks' colours are the target's swapped, or '' (class docstring)."""
        names = [n for n, m in marks.items()
                 if m.visible and m.colour is not None and n in self.hyps]
        if not names or rgb is None:
            return ''
        seen = body_colour(rgb, sil.ellipse)
        seen = self.body if seen is None else seen.tolist()
        votes = []   # (name, angle to the labelled direction, to the swapped one), deg
        floor = 0.0
        for n in names:
            v = _direction(marks[n].colour.tolist(), seen)
            own, alt, f = self.hyps[n]
            votes.append((n, _angle(v, own), _angle(v, alt)))
            floor += f
        own = sum(o for _, o, _ in votes)
        if own >= floor and sum(a for _, _, a in votes) <= self.ratio * own:
            return 'is the image bgr8 labelled rgb8, or rgb8 labelled bgr8? (' + ', '.join(
                f'{n}: {o:.0f}° from its colour, {a:.0f}° from the swapped one'
                for n, o, a in votes) + ')'
        return ''
