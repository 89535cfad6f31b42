"""The ``exact`` engine: dense Cholesky of the observed-pixel kernel matrix (the reference).

Cost O(n^3) in the number n of observed pixels and O(n m) memory for m output pixels, so it is
meant for small crops and for checking the other engines. It refuses larger problems with
`ProblemTooLargeError` instead of exhausting memory.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ..errors import ProblemTooLargeError
from .model import GridProblem


class ExactEngine:
    """Dense GP posterior: mean = m* + K*o (Koo + D)^-1 (y - m), var = k** - diag(K*o (Koo + D)^-1 Ko*)."""

    name = "exact"

    def __init__(self, max_points: int = 6000, max_cross_entries: int = 60_000_000):
        self.max_points = max_points
        self.max_cross_entries = max_cross_entries

    def solve(self, problem: GridProblem, *, variance: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None)."""
        rows, cols = np.nonzero(problem.precision > 0)
        n = rows.shape[0]
        ho, wo = problem.out_shape
        m = ho * wo
        if n > self.max_points or n * m > self.max_cross_entries:
            raise ProblemTooLargeError(
                f"exact engine: {n} observed pixels x {m} output pixels exceeds its limit "
                f"({self.max_points} observed pixels, {self.max_cross_entries} cross entries); "
                "use engine='fast' or a smaller crop"
            )
        k = problem.kernel
        s2 = k.outputscale**2
        if n == 0:
            mean = problem.out_prior_mean.astype(np.float64).copy()
            return mean, (np.full((ho, wo), s2) if variance else None)
        noise = 1.0 / problem.precision[rows, cols]
        resid = problem.obs[rows, cols] - problem.prior_mean[rows, cols]
        # Work in units of s so that the matrix is a correlation plus noise ratio.
        A = k.factor(rows, rows) * k.factor(cols, cols)
        A[np.diag_indices(n)] += noise / s2
        chol = scipy.linalg.cho_factor(A, lower=True, check_finite=False)
        alpha = scipy.linalg.cho_solve(chol, resid, check_finite=False)
        out_r, out_c = np.meshgrid(problem.out_rows, problem.out_cols, indexing="ij")
        out_r, out_c = out_r.ravel(), out_c.ravel()
        mean = np.empty(m)
        var = np.empty(m) if variance else None
        block = max(1, self.max_cross_entries // max(n, 1) // 4)
        for start in range(0, m, block):
            sl = slice(start, min(m, start + block))
            cross = k.factor(out_r[sl], rows) * k.factor(out_c[sl], cols)  # (b, n) correlations
            mean[sl] = cross @ alpha
            if var is not None:
                half = scipy.linalg.solve_triangular(chol[0], cross.T, lower=True, check_finite=False)
                var[sl] = s2 * np.maximum(1.0 - np.einsum("ij,ij->j", half, half), 0.0)
        mean = problem.out_prior_mean.ravel() + mean
        return mean.reshape(ho, wo), (var.reshape(ho, wo) if var is not None else None)
