"""A compiled in-place Cholesky factorisation for the small dense systems of the local kriging kernels
(`gpdepth3d.gp._loo`: a point's leave-one-out neighbourhood; `gpdepth3d.gp.sublattice`: a lattice cell's window)."""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True)
def cholesky_in_place(A, n):  # pragma: no cover - compiled
    """Lower Cholesky factor of A[:n, :n] in its lower triangle; False when not positive definite (NaN too)."""
    for a in range(n):
        s = A[a, a]
        for t in range(a):
            s -= A[a, t] * A[a, t]
        if not s > 0.0:
            return False
        s = math.sqrt(s)
        A[a, a] = s
        for b in range(a + 1, n):
            t2 = A[b, a]
            for t in range(a):
                t2 -= A[b, t] * A[a, t]
            A[b, a] = t2 / s
    return True
