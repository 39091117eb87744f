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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sphere_servo.core.geometry import normalize

SPECIAL = 'special'
CC = 'cc'
KINDS = (SPECIAL, CC)
#: the two marks the features use, by target kind: the second is P2 on a special sphere,
#: the tangent tip P3 on a CC target
MARK_NAMES = {SPECIAL: ('P1', 'P2'), CC: ('P1', 'P3')}


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
    colors   rgb8 colours of the sphere body, of P1 and of the second mark.
    mark_radius  angular radius (rad) of a painted surface mark, as seen from O.
    """

    kind: str
    radius: float
    oP1: np.ndarray
    oP2: np.ndarray
    axes: np.ndarray | None = None
    colors: dict = field(default_factory=lambda: {
        'body': (235, 235, 225), 'P1': (220, 30, 30), 'P2': (30, 60, 220)})
    mark_radius: float = np.radians(9.0)

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


def special_sphere(radius: float = 0.05, **kw) -> Target:
    """Build the paper's special sphere: ``OP1 = r(0, 1/2, −√3/2)``, ``OP2 = r(1/2, 0, −√3/2)``."""
    s3 = np.sqrt(3.0) / 2.0
    return Target(SPECIAL, radius, radius * np.array([0.0, 0.5, -s3]),
                  radius * np.array([0.5, 0.0, -s3]), **kw)


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
    return Target(CC, radius, ref.oP1, ref.oP1 + ell * t, **kw)


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
    return Target(SPECIAL, r_eq, pts[0], pts[1], axes=axes, **kw)


def make_target(kind: str, radius: float = 0.05, **kw) -> Target:
    """Build a target by name: 'special', 'cc' or 'balloon'."""
    if kind == SPECIAL:
        return special_sphere(radius, **kw)
    if kind == CC:
        return cc_target(radius, **kw)
    if kind == 'balloon':
        return balloon(**kw)
    raise ValueError(f"unknown target kind {kind!r}: use 'special', 'cc' or 'balloon'")
