"""
Small dense linear algebra for the control step, without NumPy's per-call Python checks.

``np.linalg.eigh`` on a 3×3 conic and ``np.linalg.solve`` on a 6×6 interaction matrix spend
more time in their Python wrappers (type checks, ``errstate`` context managers) than in
LAPACK; for a law that runs every frame that is most of its budget. These call the gufuncs
those wrappers call (NumPy is pinned in requirements.txt) and fall back to the public
functions if a NumPy release moves them. Results are identical (tested); a singular system
raises ``np.linalg.LinAlgError`` as ``np.linalg.solve`` does.
"""
from __future__ import annotations

import numpy as np

try:  # the gufuncs behind np.linalg.eigh / np.linalg.solve
    from numpy.linalg import _umath_linalg as _ul

    def eigh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eigenvalues (ascending) and eigenvectors (columns) of a symmetric matrix."""
        return _ul.eigh_lo(a, signature='d->dd')

    def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``a⁻¹ b`` for a square ``a`` and a vector ``b``; LinAlgError if singular."""
        with np.errstate(invalid='raise'):
            try:
                return _ul.solve1(a, b, signature='dd->d')
            except FloatingPointError:
                raise np.linalg.LinAlgError('Singular matrix') from None

    FAST = True
except (ImportError, AttributeError):  # pragma: no cover - a future NumPy layout
    eigh, solve, FAST = np.linalg.eigh, np.linalg.solve, False
