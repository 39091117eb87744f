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


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.sqrt(v @ v)), 1e-300)


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
    per-channel median of the pixels at fixed points of its inner 70 %, the marks
    (saturation ≥ 0.5: the body's under a 20 % colour cast is 0.36, a mark's core 0.86), the
    shadow and clipped pixels left out; None with fewer than 10 of them.
    """
    H, W = rgb.shape[:2]
    (cx, cy), (a0, a1), ang = ellipse
    ca, sa = 0.7 * math.cos(ang), 0.7 * math.sin(ang)
    uv = np.array([[a0 * ca, -a1 * sa], [a0 * sa, a1 * ca]]) @ _DISC
    uv += ((cx,), (cy,))
    np.clip(uv, 0.0, ((W - 1,), (H - 1,)), out=uv)
    u, v = uv.astype(np.intp)
    pix = rgb[v, u].astype(np.int16)
    hi, lo = _span(pix)
    body = pix[(2 * lo > hi) & (hi < 250) & (10 * hi >= 3 * int(hi.max()))]
    return _median_rows(body) if len(body) >= 10 else None


class SwapCheck:
    """
    ``check(marks, rgb, sil)``: why the marks' colours are the target's swapped, or ''.

    ``colors``: the target's ({'body': rgb, mark name: rgb}); ``chroma_tol``: the marks'
    colour test's. A mark counts when another mark's colour, R and B swapped, passes its
    test (for the default red and blue, each the other's). Each visible such mark is
    compared by its core colour (:attr:`~sphere_servo.vision.marks.Mark.colour`) with two
    hypotheses: as labelled (its own colour mixed with the body's: a plane through 0 in rgb)
    and swapped (the other mark's colour and the body's, both swapped). Under each, the
    colour is first divided by the channel gains the body seen inside the silhouette gives
    against that hypothesis' body colour (:func:`body_colour`), so that a white balance or a
    coloured light does not pass for a swap. Swapped when every such mark lies at least
    :attr:`floor` off the plane as labelled (distance of the unit rgb vector) and at most
    half as far from the swapped one. Measured on the 136 colour frames of the detector's
    corpus under six sets of channel gains: as labelled, own ≤ 0.030 and swapped ≥ 0.059;
    with R and B swapped, own ≥ 0.087 and swapped ≤ 0.035 (README, "Detection").
    """

    floor = 0.05

    def __init__(self, colors: dict, mark_names, chroma_tol: float):
        body = np.asarray(colors['body'], float)
        # name → the hypotheses (as labelled, swapped), each (plane normal, body) in floats
        self.planes = {}
        for k in mark_names:
            ck = to_chroma(np.asarray(colors[k], float))
            near = min(mark_names, key=lambda j: float(np.linalg.norm(
                to_chroma(np.asarray(colors[j], float)[::-1]) - ck)))
            cj = np.asarray(colors[near], float)[::-1]
            if np.linalg.norm(to_chroma(cj) - ck) < chroma_tol:
                self.planes[k] = (
                    (_unit(np.cross(np.asarray(colors[k], float), body)).tolist(),
                     body.tolist()),
                    (_unit(np.cross(cj, body[::-1])).tolist(), body[::-1].tolist()))

    def __call__(self, marks: dict, rgb: Image | None, sil) -> str:
        """Return why the marks' colours are the target's swapped, or '' (class docstring)."""
        names = [n for n, m in marks.items()
                 if m.visible and m.colour is not None and n in self.planes]
        if not names or rgb is None:
            return ''
        seen = body_colour(rgb, sil.ellipse)
        seen = (1.0, 1.0, 1.0) if seen is None else np.maximum(seen, 1.0).tolist()
        votes = []   # (name, distance as labelled, swapped): 3-vectors, in floats
        for n in names:
            c = marks[n].colour.tolist()
            d = []
            for normal, body in self.planes[n]:
                x = [c[i] * body[i] / seen[i] for i in range(3)]
                d.append(abs(sum(x[i] * normal[i] for i in range(3)))
                         / max(math.sqrt(sum(v * v for v in x)), 1e-300))
            votes.append((n, *d))
        if all(own >= self.floor and alt <= 0.5 * own for _, own, alt in votes):
            return 'is the image bgr8 labelled rgb8, or rgb8 labelled bgr8? (' + ', '.join(
                f'{n}: {own:.3f} off its colour, {alt:.3f} off the swapped one'
                for n, own, alt in votes) + ')'
        return ''
