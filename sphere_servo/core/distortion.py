"""
The distortion algebra the central camera models share (no ROS). DESIGN.md §1.

- odd radial polynomials ``f(x) = x (1 + c1 x² + c2 x⁴ + …)`` (:func:`odd_poly`), where they
  stop increasing (:func:`first_fold`) and their inverse on the increasing branch
  (:func:`solve_odd_poly`): the radial part of plumb_bob, of Kannala–Brandt's ``θ_d(θ)`` and
  of Mei's rad-tan;
- the radial-tangential distortion (:func:`radtan`, plumb_bob's and Mei's order) and its
  inverse (:func:`undistort_radtan`).
"""
from __future__ import annotations

from functools import lru_cache
import math

import numpy as np

from sphere_servo.core.types import Points2

_EPS = float(np.finfo(float).eps)


# --- odd radial polynomials f(x) = x (1 + c1 x² + c2 x⁴ + …) ------------------------------
def odd_poly(coeffs, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate ``f(x) = x (1 + c1 x² + c2 x⁴ + …)`` and ``f'(x)`` (Horner, vectorised)."""
    s = x * x
    q = np.zeros_like(s)
    dq = np.zeros_like(s)
    for k in range(len(coeffs), 0, -1):            # Horner in s = x², from the top
        q = q * s + coeffs[k - 1]
        dq = dq * s + (2 * k + 1) * coeffs[k - 1]
    p, dp = q * s, dq * s
    return x * (1.0 + p), 1.0 + dp


def first_fold(coeffs) -> float:
    """
    Return the fold of :func:`odd_poly`, the radius where it stops increasing.

    That is the smallest ``x > 0`` where ``f'(x) = 1 + Σ (2k+1) c_k x^(2k)`` vanishes,
    ``inf`` if it never does.
    """
    poly = [(2 * k + 1) * float(c) for k, c in reversed(list(enumerate(coeffs, start=1)))]
    poly.append(1.0)
    while poly and poly[0] == 0.0:
        poly.pop(0)
    if len(poly) < 2:
        return math.inf
    roots = np.roots(poly)                         # in s = x²
    real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.abs(roots)) & (roots.real > 0)]
    return math.sqrt(float(real.min())) if real.size else math.inf


@lru_cache(maxsize=64)
def _table(coeffs: tuple, top: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Tabulate ``x``, ``f(x)`` and ``f'(x)`` on ``[0, top]``.

    Uniform up to 1, geometric beyond: the radius of a wide field spans decades.
    """
    xg = (np.linspace(0.0, top, 257) if top <= 2.0 else
          np.concatenate([np.linspace(0.0, 1.0, 129)[:-1], np.geomspace(1.0, top, 129)]))
    return (xg, *odd_poly(coeffs, xg))


def solve_odd_poly(coeffs, t: np.ndarray, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Solve ``f(x) = t`` (:func:`odd_poly`) for ``x`` in ``[0, hi)``, where f increases.

    ``hi`` is at most the first fold (``inf`` if none). Returns ``(x, ok)``; ``ok`` is False
    where ``t`` is not finite, negative, or ≥ ``f(hi)`` (no solution in the increasing
    branch). Initial guess from a table of ``f`` on ``[0, hi]`` (``[0, 2ᵏ]`` with
    ``f(2ᵏ) ≥ max t`` if ``hi`` is infinite) by cubic Hermite interpolation of the inverse,
    then Newton steps kept inside the table interval that brackets the root (bisection when a
    step leaves it), on the points not yet converged.
    """
    t = np.asarray(t, dtype=float)
    ok = np.isfinite(t) & (t >= 0)
    t = np.where(ok, t, 0.0)
    coeffs = tuple(float(c) for c in coeffs)
    if not any(coeffs):
        return t, ok & (t < hi)
    top = hi
    if math.isinf(hi):                             # f → ∞: widen until f(top) ≥ max t
        tmax = float(t.max(initial=0.0))
        top = 2.0 ** math.ceil(math.log2(max(1.0, tmax)))
        while odd_poly(coeffs, np.array([top]))[0][0] < tmax:
            top *= 2.0
    xg, fg, dg = _table(coeffs, top)
    if math.isfinite(hi):
        ok &= t < fg[-1]
        t = np.where(ok, t, 0.0)
    j = np.clip(np.searchsorted(fg, t, side='right'), 1, len(xg) - 1)
    lo, up = xg[j - 1], xg[j]
    # x(t) on [f_j-1, f_j] by cubic Hermite (slopes 1/f'), clipped into the bracket
    h = fg[j] - fg[j - 1]
    s = (t - fg[j - 1]) / h
    m0, m1 = h / dg[j - 1], h / np.maximum(dg[j], 1e-300)
    x = (lo * (1 + 2 * s) * (1 - s) ** 2 + m0 * s * (1 - s) ** 2
         + up * s * s * (3 - 2 * s) + m1 * s * s * (s - 1))
    x = np.minimum(np.maximum(x, lo), up)
    live = None                                    # all points, until some converge
    for _ in range(60):
        xa, ta, la, ua = (x, t, lo, up) if live is None else (x[live], t[live], lo[live],
                                                              up[live])
        f, df = odd_poly(coeffs, xa)
        r = f - ta
        la = np.where(r < 0, xa, la)
        ua = np.where(r > 0, xa, ua)
        xn = xa - np.divide(r, df, out=np.full_like(r, np.inf), where=df > 0)
        xn = np.where((xn >= la) & (xn <= ua), xn, 0.5 * (la + ua))
        done = ((np.abs(xn - xa) <= 4 * _EPS * xa)     # converged, or f(x) = t to
                | (np.abs(r) <= 8 * _EPS * ta))        # rounding (f' ≈ 0 at a fold)
        if live is None:
            x, lo, up = xn, la, ua
            live = np.flatnonzero(~done)
        else:
            x[live], lo[live], up[live] = xn, la, ua
            live = live[~done]
        if not live.size:
            break
    else:
        ok[live] = False
    return x, ok


# --- radial-tangential distortion (plumb_bob; Mei's k1 k2 p1 p2 with k3 = 0) ----------------
def radtan(m: Points2, k1, k2, p1, p2, k3) -> tuple[Points2, np.ndarray]:
    """
    Distort normalized points ``m`` (N, 2); return ``m_d`` and the Jacobian ``∂m_d/∂m``.

    The radial-tangential model, in OpenCV's and ROS plumb_bob's order:
    ``m_d = m (1 + k1 r² + k2 r⁴ + k3 r⁶) + (2 p1 x y + p2 (r² + 2x²),
    p1 (r² + 2y²) + 2 p2 x y)``, ``r² = x² + y²``; the Jacobian is (N, 2, 2).
    """
    x, y = m[:, 0], m[:, 1]
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    L = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dL = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)      # dL/d(r²)
    md = np.empty_like(m)
    md[:, 0] = x * L + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    md[:, 1] = y * L + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    J = np.empty((len(m), 2, 2))
    J[:, 0, 0] = L + 2.0 * x2 * dL + 2.0 * p1 * y + 6.0 * p2 * x
    J[:, 0, 1] = J[:, 1, 0] = 2.0 * xy * dL + 2.0 * p1 * x + 2.0 * p2 * y
    J[:, 1, 1] = L + 2.0 * y2 * dL + 6.0 * p1 * y + 2.0 * p2 * x
    return md, J


def det2(J: np.ndarray) -> np.ndarray:
    """Return the determinants of (N, 2, 2) matrices."""
    return J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]


def undistort_radtan(md: Points2, coeffs, hi: float) -> tuple[Points2, np.ndarray]:
    """
    Invert :func:`radtan` (coeffs ``k1 k2 p1 p2 k3``) on its increasing branch ``r < hi``.

    The radial part exactly (:func:`solve_odd_poly`), then damped Newton on the tangential
    terms (from just inside ``hi`` where the tangential shift carries the point beyond the
    radial part's range). Returns ``(m, ok)``; ``ok`` is False where no such inverse exists
    or Newton did not converge to a point where the distortion is one-to-one
    (``det ∂m_d/∂m > 0``).
    """
    k1, k2, p1, p2, k3 = coeffs
    rd = np.hypot(md[:, 0], md[:, 1])
    r, ok = solve_odd_poly((k1, k2, k3), rd, hi)
    if p1 == 0.0 and p2 == 0.0:
        with np.errstate(divide='ignore', invalid='ignore'):
            return md * np.where(rd > 0, r / rd, 1.0)[:, None], ok
    if math.isfinite(hi):
        r = np.where(ok, r, (1.0 - 1e-3) * hi)
    ok = np.isfinite(rd)
    with np.errstate(divide='ignore', invalid='ignore'):
        m = np.where(ok[:, None], md * np.where(rd > 0, r / rd, 1.0)[:, None], 0.0)
    live = np.flatnonzero(ok)
    mm, tg = m[live], md[live]
    f, J = radtan(mm, *coeffs)
    res = f - tg
    err = np.hypot(res[:, 0], res[:, 1])
    for _ in range(40):
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            step = np.column_stack([J[:, 1, 1] * res[:, 0] - J[:, 0, 1] * res[:, 1],
                                    J[:, 0, 0] * res[:, 1] - J[:, 1, 0] * res[:, 0]])
            step /= det2(J)[:, None]
        step[~np.isfinite(step)] = 0.0
        mn = mm - step
        fn, Jn = radtan(mn, *coeffs)
        resn = fn - tg
        errn = np.hypot(resn[:, 0], resn[:, 1])
        for _ in range(12):                          # halve the steps that do not reduce |res|
            w = np.flatnonzero(errn > err)
            if not w.size:
                break
            step[w] *= 0.5
            mn[w] = mm[w] - step[w]
            fn[w], Jn[w] = radtan(mn[w], *coeffs)
            resn[w] = fn[w] - tg[w]
            errn[w] = np.hypot(resn[w, 0], resn[w, 1])
        done = ((np.hypot(step[:, 0], step[:, 1]) <= 8 * _EPS * (1.0 + np.hypot(*mn.T)))
                | (errn <= 2 * _EPS * (1.0 + np.hypot(*tg.T))))
        m[live] = mn
        keep = ~done
        live, mm, tg = live[keep], mn[keep], tg[keep]
        J, res, err = Jn[keep], resn[keep], errn[keep]
        if not live.size:
            break
    f, J = radtan(m, *coeffs)
    err = np.hypot(*(f - md).T)
    ok &= (err <= 1e-12 * (1.0 + rd)) & (det2(J) > 0) & (np.hypot(m[:, 0], m[:, 1]) < hi)
    return m, ok
