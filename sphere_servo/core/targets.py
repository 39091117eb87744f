"""
Target models (no ROS): the special sphere, the CC target and the "balloon".

All positions are in the target frame ``o`` (origin at the sphere centre O), in metres.

- special sphere: two marks P1, P2 glued on the surface. Paper §IV.A.1:
  ``OP1 = r(0, 1/2, −√3/2)``, ``OP2 = r(1/2, 0, −√3/2)``.
- CC target: mark P1 on the surface and the tip P3 of a tangent vector at P1
  (``OP1 ⟂ P1P3``); P3 is off the surface.
- balloon: an ellipsoid with semi-axes ``axes`` (a non-spherical body) carrying two surface
  marks; it is servoed as a special sphere with an approximate radius r̂.

A camera looking along the target's +z axis from ``(0, 0, −d)`` (``cMo = (I, (0, 0, d))``)
sees both default marks, which sit on the −z cap.

The marks' look is part of the description, shared by the renderer and the detector:
``colors`` (rgb8 of the body, P1 and the second mark — under 'P2' for both kinds, the CC
tip being coloured like P2) and ``mark_radius``, the angular radius of a painted cap as
seen from O. The factories take them as keywords (``mark_radius_deg`` in degrees for a
configuration file).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from sphere_servo.core.geometry import normalize

SPECIAL = 'special'
CC = 'cc'
KINDS = (SPECIAL, CC)
#: the two marks the features use, by target kind: the second is P2 on a special sphere,
#: the tangent tip P3 on a CC target
MARK_NAMES = {SPECIAL: ('P1', 'P2'), CC: ('P1', 'P3')}
#: the default look: an off-white body, a red P1 and a blue second mark (rgb8)
DEFAULT_COLORS = {'body': (235, 235, 225), 'P1': (220, 30, 30), 'P2': (30, 60, 220)}
#: the default angular radius of a painted cap (rad)
DEFAULT_MARK_RADIUS = math.radians(9.0)
#: the largest cap radius accepted (rad): a cap is a small mark, not a hemisphere
MAX_MARK_RADIUS = math.radians(30.0)


def mark_names(kind: str) -> tuple[str, str]:
    """('P1', 'P2') for a special sphere, ('P1', 'P3') for a CC target."""
    try:
        return MARK_NAMES[kind]
    except KeyError:
        raise ValueError(f'target kind must be one of {KINDS}, got {kind!r}') from None


@dataclass(frozen=True)
class Target:
    """
    A marked sphere (or ellipsoid, if ``axes`` is given).

    kind     'special' (marks P1, P2 on the surface) or 'cc' (P1 on the surface, P3 the tip
             of a tangent vector at P1).
    radius   sphere radius r (m); for a balloon, the radius of a sphere of equal volume.
    oP1      (3,) first mark in the target frame.
    oP2      (3,) second mark: P2 (special) or the tangent tip P3 (cc), target frame.
    axes     (3,) ellipsoid semi-axes (m) for a non-spherical body, or None for a sphere.
    colors   rgb8 colours: 'body', 'P1' and the second mark's under 'P2' (special: P2;
             cc: the tip P3).
    mark_radius  angular radius (rad) of a painted surface mark, as seen from O, in
             (0, 30°]; two surface caps must not overlap.
    """

    kind: str
    radius: float
    oP1: np.ndarray
    oP2: np.ndarray
    axes: np.ndarray | None = None
    colors: dict = field(default_factory=lambda: dict(DEFAULT_COLORS))
    mark_radius: float = DEFAULT_MARK_RADIUS

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f'target kind must be one of {KINDS}, got {self.kind!r}')
        if not np.isfinite(self.radius) or self.radius <= 0:
            raise ValueError(f'target radius must be a finite number > 0, got {self.radius}')
        object.__setattr__(self, 'oP1', np.asarray(self.oP1, dtype=float))
        object.__setattr__(self, 'oP2', np.asarray(self.oP2, dtype=float))
        if self.axes is not None:
            axes = np.asarray(self.axes, dtype=float)
            if axes.shape != (3,) or np.any(~np.isfinite(axes)) or np.any(axes <= 0):
                raise ValueError(f'ellipsoid semi-axes must be 3 numbers > 0, got {self.axes}')
            object.__setattr__(self, 'axes', axes)
        object.__setattr__(self, 'colors', _check_colors(self.colors))
        rho = self.mark_radius
        if not (isinstance(rho, (int, float, np.floating)) and math.isfinite(rho)
                and 0 < rho <= MAX_MARK_RADIUS):
            raise ValueError(f'mark radius must be in (0, {math.degrees(MAX_MARK_RADIUS):.0f}°]'
                             f', got {rho!r} rad')
        object.__setattr__(self, 'mark_radius', float(rho))
        if self.kind == SPECIAL:
            n1, n2 = self.surface_normal(self.oP1), self.surface_normal(self.oP2)
            apart = math.acos(max(-1.0, min(1.0, float(n1 @ n2))))
            if apart <= 2 * rho:
                raise ValueError(f'caps of radius {math.degrees(rho):.1f}° overlap: the marks '
                                 f'are {math.degrees(apart):.1f}° apart')

    @property
    def mark_names(self) -> tuple[str, str]:
        """('P1', 'P2') for a special sphere, ('P1', 'P3') for a CC target."""
        return mark_names(self.kind)

    @property
    def is_sphere(self) -> bool:
        return self.axes is None

    def marks(self) -> dict[str, np.ndarray]:
        """Mark positions in the target frame, by name."""
        a, b = self.mark_names
        return {a: self.oP1, b: self.oP2}

    def surface_normal(self, oP: np.ndarray) -> np.ndarray:
        """Outward unit normal at a surface point (target frame)."""
        if self.axes is None:
            return normalize(oP)
        return normalize(oP / self.axes ** 2)


def _check_colors(colors) -> dict:
    """Return ``colors`` as {'body', 'P1', 'P2': (r, g, b) ints in 0..255}, or raise."""
    if not isinstance(colors, dict):
        raise ValueError(f'target colors must be a dict, got {type(colors).__name__}')
    out = dict(colors)
    if 'P2' not in out and 'P3' in out:
        out['P2'] = out.pop('P3')               # the CC tip's colour, under either name
    for key in ('body', 'P1', 'P2'):
        if key not in out:
            raise ValueError(f"target colors lack {key!r}: give 'body', 'P1' and 'P2'")
        c = out[key]
        try:
            rgb = tuple(float(x) for x in c)
        except (TypeError, ValueError):
            raise ValueError(f'target color {key!r} must be 3 numbers, got {c!r}') from None
        if len(rgb) != 3 or not all(math.isfinite(x) and 0 <= x <= 255 for x in rgb):
            raise ValueError(f'target color {key!r} must be 3 numbers in 0..255, got {c!r}')
        out[key] = tuple(int(round(x)) for x in rgb)
    return out


def _look(kw: dict) -> dict:
    """Turn ``mark_radius_deg`` (degrees, for a config file) into ``mark_radius`` (rad)."""
    deg = kw.pop('mark_radius_deg', None)
    if deg is not None:
        if 'mark_radius' in kw:
            raise ValueError('give mark_radius (rad) or mark_radius_deg, not both')
        try:
            kw['mark_radius'] = math.radians(float(deg))
        except (TypeError, ValueError):
            raise ValueError(f'mark_radius_deg must be a number, got {deg!r}') from None
    return kw


def special_sphere(radius: float = 0.05, **kw) -> Target:
    """Build the paper's special sphere: ``OP1 = r(0, 1/2, −√3/2)``, ``OP2 = r(1/2, 0, −√3/2)``."""
    s3 = np.sqrt(3.0) / 2.0
    return Target(SPECIAL, radius, radius * np.array([0.0, 0.5, -s3]),
                  radius * np.array([0.5, 0.0, -s3]), **_look(kw))


def cc_target(radius: float = 0.05, stick_length: float | None = None, **kw) -> Target:
    """
    Build a CC target: P1 at the paper's position, P3 = P1 + ℓ·t the tip of a tangent stick.

    t is the unit tangent at P1 pointing towards the paper's P2 (so ``OP1 ⟂ P1P3``); ℓ = r
    by default.
    """
    ref = special_sphere(radius)
    ell = radius if stick_length is None else float(stick_length)
    if not np.isfinite(ell) or ell <= 0:
        raise ValueError(f'stick length must be > 0, got {stick_length}')
    n1 = normalize(ref.oP1)
    d = ref.oP2 - ref.oP1
    t = normalize(d - (d @ n1) * n1)
    return Target(CC, radius, ref.oP1, ref.oP1 + ell * t, **_look(kw))


def balloon(axes=(0.06, 0.055, 0.045), **kw) -> Target:
    """
    Build a non-spherical body: an ellipsoid with semi-axes ``axes`` and two surface marks.

    The marks lie in the paper's directions (projected radially onto the ellipsoid).
    ``radius`` is that of the sphere of equal volume.
    """
    axes = np.asarray(axes, dtype=float)
    r_eq = float(np.prod(axes) ** (1.0 / 3.0))
    s3 = np.sqrt(3.0) / 2.0
    dirs = [np.array([0.0, 0.5, -s3]), np.array([0.5, 0.0, -s3])]
    # radial projection onto x²/a² + y²/b² + z²/c² = 1
    pts = [d / np.sqrt(np.sum((d / axes) ** 2)) for d in dirs]
    return Target(SPECIAL, r_eq, pts[0], pts[1], axes=axes, **_look(kw))


def make_target(kind: str, radius: float = 0.05, **kw) -> Target:
    """
    Build a target by name: 'special', 'cc' or 'balloon'.

    Keywords of the factory, and the look: ``colors``, ``mark_radius`` (rad) or
    ``mark_radius_deg``.
    """
    if kind == SPECIAL:
        return special_sphere(radius, **kw)
    if kind == CC:
        return cc_target(radius, **kw)
    if kind == 'balloon':
        return balloon(**kw)
    raise ValueError(f"unknown target kind {kind!r}: use 'special', 'cc' or 'balloon'")
