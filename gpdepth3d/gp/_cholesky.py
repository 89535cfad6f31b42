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


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def cholesky_dots_in_place(A, n):  # pragma: no cover - compiled
    """`cholesky_in_place` with each entry's products summed in any order (a dot product the compiler vectorises,
    fused multiply-adds): the factor agrees with it to rounding (a few units in the last place), not to the bit.

    Four rows of a column at a time share the loads of the column's own row. NaN still fails (no "nnan" flag).
    """
    for a in range(n):
        ra = A[a]
        s = 0.0
        for t in range(a):
            s += ra[t] * ra[t]
        s = A[a, a] - s
        if not s > 0.0:
            return False
        s = math.sqrt(s)
        A[a, a] = s
        b = a + 1
        while b + 3 < n:
            r0, r1, r2, r3 = A[b], A[b + 1], A[b + 2], A[b + 3]
            u0 = u1 = u2 = u3 = 0.0
            for t in range(a):
                x = ra[t]
                u0 += r0[t] * x
                u1 += r1[t] * x
                u2 += r2[t] * x
                u3 += r3[t] * x
            r0[a] = (r0[a] - u0) / s
            r1[a] = (r1[a] - u1) / s
            r2[a] = (r2[a] - u2) / s
            r3[a] = (r3[a] - u3) / s
            b += 4
        while b < n:
            rb = A[b]
            u = 0.0
            for t in range(a):
                u += rb[t] * ra[t]
            rb[a] = (rb[a] - u) / s
            b += 1
    return True
