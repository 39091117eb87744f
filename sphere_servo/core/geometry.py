"""
Small SO(3)/SE(3) helpers on ndarrays (no ROS).

Conventions (DESIGN.md §1): frames are named in variables, ``aMb`` is the pose of frame b in
frame a (a ``pin.SE3``), ``aRb`` its rotation (3×3 ndarray). ``θu = log(R)`` is the
axis-angle vector. A camera twist ``v_c = (v, ω)`` (shape (6,)) is expressed in the current
camera frame; integrating it for ``dt`` moves the camera as ``wMc ← wMc · exp6(v_c dt)``.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from sphere_servo.core.types import Mat3, Twist, Vec3
from sphere_servo.core.validation import Bound, Violation


class GeometryError(ValueError):
    """
    A geometric quantity is undefined (degenerate input, NaN, point at infinity).

    Built from a message or from a :class:`~sphere_servo.core.validation.Violation`, kept
    as ``violation`` (None for a message): the typed reason of a refused value.
    """

    def __init__(self, what: str | Violation = ''):
        self.violation = what if isinstance(what, Violation) else None
        super().__init__(str(what))


def skew(a: Vec3) -> Mat3:
    """Return ``[a]×``, the 3×3 matrix with ``[a]× b = a × b``."""
    return np.array([[0.0, -a[2], a[1]],
                     [a[2], 0.0, -a[0]],
                     [-a[1], a[0], 0.0]])


def cross3(a: Vec3, b: Vec3) -> Vec3:
    """Return ``a × b`` for 3-vectors (several times faster than ``np.cross`` on one pair)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def normalize(a: np.ndarray, what: str = 'vector') -> np.ndarray:
    """Return ``a / ‖a‖``; raise :class:`GeometryError` on a zero or non-finite ``a``."""
    n = math.sqrt(float(a @ a))
    if not math.isfinite(n) or n < 1e-12:
        raise GeometryError(f'cannot normalize {what}: norm is {n}')
    return a / n


def require_finite(a, what: str) -> np.ndarray:
    """Return ``a`` as a float ndarray; raise :class:`GeometryError` if an entry is NaN or inf."""
    arr = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f'{what} contains NaN or inf: {arr!r}')
    return arr


def sinc(x: float) -> float:
    """
    ``sin(x)/x`` with the removable singularity at 0.

    Raises :class:`GeometryError` on ±inf (where ``math.sin`` would raise a bare
    ``ValueError: math domain error``) and NaN.
    """
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0
    if not abs(x) < math.inf:  # inf, and NaN (which compares False)
        raise GeometryError(Violation('sinc argument', x, Bound.FINITE, 'a finite angle'))
    return math.sin(x) / x


def log3(R: Mat3) -> Vec3:
    """``θu = log(R)`` (Pinocchio's ``log3``), θ ∈ [0, π]."""
    return np.asarray(pin.log3(np.asarray(R, dtype=float)))


def exp3(thetau: Vec3) -> Mat3:
    """``R = exp([θu]×)`` (Pinocchio's ``exp3``)."""
    return np.asarray(pin.exp3(np.asarray(thetau, dtype=float)))


def L_omega(thetau: Vec3, sign: float = +1.0) -> Mat3:
    """
    ``I + sign·(θ/2)[u]× + (1 − sinc θ / sinc²(θ/2)) [u]×²`` (DESIGN.md §3).

    ``sign = +1``: interaction matrix of ``θu = log(ᶜ*R_c)`` w.r.t. ω of the current camera
    (rotation multiplied on the right; the paper's eq. (7) prints ``−``, which is wrong for
    this convention). ``sign = −1``: a rotation multiplied on the left (the ζ rows of s_cc).
    Equals Pinocchio's ``Jlog3`` for ``sign = +1``.

    Raises :class:`GeometryError` when θ is not finite (an entry ±inf or NaN, or so large
    that θ² overflows, ‖θu‖ ≳ 1e154): no matrix of such a θu exists.
    """
    x, y, z = (float(v) for v in thetau)
    theta = math.sqrt(x * x + y * y + z * z)
    if theta < 1e-12:  # NaN compares False: falls through to the finite check
        return np.eye(3)
    if not theta < math.inf:
        raise GeometryError(Violation('θ = ‖θu‖', theta, Bound.FINITE,
                                      'finite θu entries with a finite norm'))
    x, y, z = x / theta, y / theta, z / theta
    # [u]×² = u uᵀ − I for a unit u:  L = (1 − c) I + c u uᵀ + a [u]×
    a = sign * theta / 2.0
    c = 1.0 - sinc(theta) / sinc(theta / 2.0) ** 2
    d = 1.0 - c
    return np.array([[d + c * x * x, c * x * y - a * z, c * x * z + a * y],
                     [c * x * y + a * z, d + c * y * y, c * y * z - a * x],
                     [c * x * z - a * y, c * y * z + a * x, d + c * z * z]])


def integrate_camera(wMc: pin.SE3, v_c: Twist, dt: float) -> pin.SE3:
    """Exact integration of a constant camera twist: ``wMc · exp6(v_c dt)``."""
    return wMc * pin.exp6(pin.Motion(np.asarray(v_c, dtype=float) * dt))


def se3(R: Mat3 | None = None, t=None) -> pin.SE3:
    """Build a ``pin.SE3`` from a rotation and a translation (identity / zero by default)."""
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    t = np.zeros(3) if t is None else np.asarray(t, dtype=float)
    return pin.SE3(R, t)


def rotation_angle_deg(aRb: Mat3) -> float:
    """Angle of a rotation in degrees."""
    return float(np.degrees(np.linalg.norm(log3(aRb))))


def look_at(eye: Vec3, target: Vec3, up: Vec3 = (0.0, 0.0, 1.0)) -> pin.SE3:
    """
    Return the pose ``wMc`` of a camera at ``eye`` looking at ``target``.

    Optical frame: z forward, x right, y down; the image 'up' direction is as close as
    possible to ``up``.
    """
    eye = np.asarray(eye, dtype=float)
    z = normalize(np.asarray(target, dtype=float) - eye, 'viewing direction')
    x = np.cross(z, -np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = normalize(x)
    y = np.cross(z, x)
    return pin.SE3(np.column_stack([x, y, z]), eye)
