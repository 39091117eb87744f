"""
Typed refusals of values that come from outside (a message, a bag, a parameter); no ROS.

A check that fails raises an error class of the caller's layer (a
:class:`~sphere_servo.core.geometry.GeometryError` subclass: ``MeasurementError``,
``FeatureError``, ``ControlError``, ``CameraError``, ``TwistError``) carrying a
:class:`Violation`: the quantity, its value, which kind of bound it broke (:class:`Bound`)
and the bound itself, so a node can log ``str(error)`` and a test or a supervisor can
compare ``error.violation.bound`` with an enum, never with a message.

The helpers below are the elementary checks (shape, finite, range, whole number, unit
norm); the physical bounds they are given, and why, are documented where they are used
(``core/measurement.py``, ``core/features.py``, ``core/central.py``, ``sim/arm.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
import math
import numbers
from typing import NoReturn

import numpy as np

#: tolerance on the norm of a unit vector from outside: |‖b‖ − 1| ≤ UNIT_TOL. Our own unit
#: vectors are normalized in float64 (error ~1e-16); a message carries float64 too, so
#: anything farther from 1 was not normalized, or is corrupt.
UNIT_TOL = 1e-6


class Bound(str, Enum):
    """Which kind of bound a value broke (the value is the phrase of the message)."""

    SHAPE = 'is not the expected shape'
    FINITE = 'is not finite'
    RANGE = 'is outside its physical range'
    UNIT = 'is not a unit vector'
    FIELD = 'is outside the field of view'
    GEOMETRY = 'is geometrically impossible'
    MISMATCH = 'does not match'
    UNSUPPORTED = 'is not supported here'
    STATE = 'is refused in this state'
    MISSING = 'is missing'


def _text(value) -> str:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, float):  # numpy's float64 too, without its 'np.float64(…)'
        return repr(float(value))
    if isinstance(value, (list, tuple)) and all(isinstance(v, float) for v in value):
        return '[' + ', '.join(repr(float(v)) for v in value) + ']'
    return str(value)


@dataclass(frozen=True)
class Violation:
    """
    A refused value: ``quantity`` (its name), ``value``, the :class:`Bound` and the limit.

    ``limit`` states the bound with its numbers, e.g. ``'0 < r_delta < 1'``.
    """

    quantity: str
    value: object
    bound: Bound
    limit: str = ''

    def __str__(self) -> str:
        return (f'{self.quantity} = {_text(self.value)} {self.bound.value}'
                + (f': {self.limit}' if self.limit else ''))


def refuse(error: type, quantity: str, value, bound: Bound, limit: str = '') -> NoReturn:
    """Raise ``error(Violation(quantity, value, bound, limit))``."""
    raise error(Violation(quantity, value, bound, limit))


def check_array(error: type, quantity: str, value, shape: tuple) -> np.ndarray:
    """Return ``value`` as a finite float array of ``shape``, or refuse it (SHAPE, FINITE)."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        refuse(error, quantity, value, Bound.SHAPE, f'numbers of shape {shape}')
    if a.shape != shape:
        refuse(error, f'shape of {quantity}', a.shape, Bound.SHAPE, f'{shape}')
    if not np.all(np.isfinite(a)):
        refuse(error, quantity, a, Bound.FINITE, 'finite entries')
    return a


def check_number(error: type, quantity: str, value) -> float:
    """Return ``value`` as a finite float, or refuse it (SHAPE for a non-number, FINITE)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        refuse(error, quantity, value, Bound.SHAPE, 'a number')
    if not math.isfinite(x):
        refuse(error, quantity, x, Bound.FINITE, 'a finite number')
    return x


def check_range(error: type, quantity: str, value, lo: float = -math.inf,
                hi: float = math.inf, lo_open: bool = False, hi_open: bool = False) -> float:
    """
    Return ``value`` as a finite float in ``[lo, hi]``, or refuse it (RANGE).

    ``lo_open`` / ``hi_open`` make that end strict (``lo < value``, ``value < hi``).
    """
    x = check_number(error, quantity, value)
    low_ok = x > lo if lo_open else x >= lo
    high_ok = x < hi if hi_open else x <= hi
    if not (low_ok and high_ok):
        left = f'{lo:g} {"<" if lo_open else "≤"} ' if lo > -math.inf else ''
        right = f' {"<" if hi_open else "≤"} {hi:g}' if hi < math.inf else ''
        refuse(error, quantity, x, Bound.RANGE, f'{left}{quantity}{right}')
    return x


def check_whole(error: type, quantity: str, value, lo: float = -math.inf,
                hi: float = math.inf, limit: str = '') -> int:
    """
    Return ``value`` as an int in ``[lo, hi]``, or refuse it: a size, a count, an offset.

    A whole number is an int or a float equal to one, of any real type (numpy's too: a
    message's ``np.uint32``, a bag's ``480.0``, a 0-d array, a Fraction of any size; not a
    Decimal, which is no ``numbers.Real``). Refused: what is no real
    number, a bool (``True`` is no size of 1) and a str (SHAPE); inf, NaN (FINITE); a
    fraction, which ``int()`` would truncate (480.5 rows read as 480), and a value outside
    ``[lo, hi]`` (RANGE). ``limit`` replaces the refusal's statement of the bound
    (default: ``a whole number ≥ lo and ≤ hi``, either end left out when infinite).
    """
    if type(value) is int and lo <= value <= hi:  # the usual case, on every image: no text
        return value
    if not limit:
        ends = (f'≥ {lo:.15g}' if lo > -math.inf else '',
                f'≤ {hi:.15g}' if hi < math.inf else '')
        limit = ' '.join(['a whole number', ' and '.join(e for e in ends if e)]).rstrip()
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, (bool, np.bool_, np.timedelta64)) or \
            not isinstance(value, numbers.Real):  # a duration is no count either
        refuse(error, quantity, value, Bound.SHAPE, f'{limit}, not a {type(value).__name__}')
    # a ratio is finite (math.isfinite would convert 10**400 / 1 to a float: OverflowError);
    # numpy's own test for its floats (a long double of 1e4000 is finite, no float's inf)
    if not (isinstance(value, numbers.Rational) or (
            np.isfinite(value) if isinstance(value, np.floating) else math.isfinite(value))):
        refuse(error, quantity, value, Bound.FINITE, limit)
    n = int(value)
    if n != value or not lo <= n <= hi:
        refuse(error, quantity, value, Bound.RANGE, limit)
    return n


def check_unit(error: type, quantity: str, value, tol: float = UNIT_TOL) -> np.ndarray:
    """Return ``value`` as a finite (3,) array with ``|‖v‖ − 1| ≤ tol``, or refuse it (UNIT)."""
    v = check_array(error, quantity, value, (3,))
    n = math.hypot(*v)
    if not abs(n - 1.0) <= tol:
        refuse(error, f'‖{quantity}‖', n, Bound.UNIT, f'|‖{quantity}‖ − 1| ≤ {tol:g}')
    return v
