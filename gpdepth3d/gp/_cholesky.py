"""A compiled in-place Cholesky factorisation for the small dense systems of the local kriging kernels
(`gpdepth3d.gp._loo`: a point's leave-one-out neighbourhood; `gpdepth3d.gp.sublattice`: a lattice cell's window)."""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True)
def cholesky_in_place(A, n):  # pragma: no cover - compiled
    """Lower Cholesky factor of A[:n, :n] in its lower triangle; False when not positive definite (NaN too).

    A column's entries below the diagonal are computed four rows at a time (four independent sums in flight); each
    entry's products are still subtracted one by one by ascending column, so the factor is that of the plain loop.
    """
    for a in range(n):
        s = A[a, a]
        for t in range(a):
            s -= A[a, t] * A[a, t]
        if not s > 0.0:
            return False
        s = math.sqrt(s)
        A[a, a] = s
        b = a + 1
        while b + 3 < n:
            u0 = A[b, a]
            u1 = A[b + 1, a]
            u2 = A[b + 2, a]
            u3 = A[b + 3, a]
            for t in range(a):
                x = A[a, t]
                u0 -= A[b, t] * x
                u1 -= A[b + 1, t] * x
                u2 -= A[b + 2, t] * x
                u3 -= A[b + 3, t] * x
            A[b, a] = u0 / s
            A[b + 1, a] = u1 / s
            A[b + 2, a] = u2 / s
            A[b + 3, a] = u3 / s
            b += 4
        while b < n:
            t2 = A[b, a]
            for t in range(a):
                t2 -= A[b, t] * A[a, t]
            A[b, a] = t2 / s
            b += 1
    return True
