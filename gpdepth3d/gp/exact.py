"""The ``exact`` engine: dense Cholesky of the observed-pixel kernel matrix (the reference).

Cost O(n^3) in the number n of observed pixels and O(n m) memory for m output pixels, so it is
meant for small crops and for checking the other engines. It refuses larger problems with
`ProblemTooLargeError` instead of exhausting memory. The same algebra (`dense_posterior`) is the
``fast`` engine's ``dense`` route for few observed pixels with nu > 0.5.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg

from ..errors import ConvergenceError, InvalidDepthError, InvalidInputError, ProblemTooLargeError, ShapeError
from .engine import Solution, SolveInfo, check_extra_obs
from .model import GridProblem

# Ranges every engine accepts (metres): beyond them s^2, 1/s^2 or the products of the algebra
# overflow or underflow float64 (an MDE of 1e300 gave OverflowError, 1e-300 NaN or a division by zero).
MAX_ABS_DEPTH = 1e8
OUTPUTSCALE_RANGE = (1e-9, 1e8)
MAX_PRECISION_RATIO = 1e30  # largest observation precision x s^2 (noise variance >= 1e-30 s^2)


def check_problem(problem: GridProblem) -> None:
    """Validates a `GridProblem` before any engine computes with it.

    Raises:
        InvalidInputError: Not a GridProblem, a non-finite or out-of-range kernel parameter,
            or precisions that are negative, non-finite or beyond 1e30 / s^2.
        ShapeError: Arrays whose shapes do not fit the grid.
        InvalidDepthError: Non-finite depths, or depths beyond +-1e8 m, where they are used.
    """
    if not isinstance(problem, GridProblem):
        raise InvalidInputError("problem", "a GridProblem", type(problem).__name__)
    h, w = np.shape(problem.prior_mean) if np.ndim(problem.prior_mean) == 2 else (0, 0)
    if h < 1 or w < 1:
        raise ShapeError("problem.prior_mean", "a 2-D (H, W) array", np.shape(problem.prior_mean))
    for name in ("obs", "precision"):
        if np.shape(getattr(problem, name)) != (h, w):
            raise ShapeError(f"problem.{name}", f"shape {(h, w)}", np.shape(getattr(problem, name)))
    if np.shape(problem.out_prior_mean) != problem.out_shape:
        raise ShapeError("problem.out_prior_mean", f"shape {problem.out_shape}", np.shape(problem.out_prior_mean))
    k = problem.kernel
    lo, hi = OUTPUTSCALE_RANGE
    if not (lo <= float(k.outputscale) <= hi):
        raise InvalidInputError("problem.kernel.outputscale", f"a prior std in [{lo:g}, {hi:g}] m", k.outputscale)
    if not (np.isfinite(k.lengthscale) and 0 < float(k.lengthscale) <= 1e8):
        raise InvalidInputError("problem.kernel.lengthscale", "a length scale in (0, 1e8] px", k.lengthscale)
    prec = np.asarray(problem.precision, dtype=np.float64)
    if not np.all(np.isfinite(prec)) or np.any(prec < 0):
        raise InvalidInputError("problem.precision", "finite values >= 0", "negative or non-finite values")
    pmax = float(prec.max(initial=0.0))
    if pmax * float(k.outputscale) ** 2 > MAX_PRECISION_RATIO:
        raise InvalidInputError(
            "problem.precision",
            f"observation precisions <= {MAX_PRECISION_RATIO:g} / outputscale^2 "
            f"(noise std >= 1e-15 x {float(k.outputscale):g} m)",
            f"max {pmax:g} 1/m^2",
        )
    for name in ("out_rows", "out_cols"):
        if not np.all(np.isfinite(np.asarray(getattr(problem, name), dtype=np.float64))):
            raise InvalidInputError(f"problem.{name}", "finite output coordinates", "non-finite values")
    observed = prec > 0
    for name, values in (
        ("prior_mean", np.asarray(problem.prior_mean, np.float64)[observed]),
        ("obs", np.asarray(problem.obs, np.float64)[observed]),
        ("out_prior_mean", np.asarray(problem.out_prior_mean, np.float64)),
    ):
        if np.abs(values).max(initial=0.0) <= MAX_ABS_DEPTH:  # NaN fails the comparison
            continue
        bad = ~np.isfinite(values) | (np.abs(values) > MAX_ABS_DEPTH)
        if np.any(bad):
            raise InvalidDepthError(
                f"problem.{name}",
                f"finite depths within +-{MAX_ABS_DEPTH:g} m",
                f"{int(bad.sum())} values outside, e.g. {float(values[bad][0]):g}",
            )


def _factor(problem: GridProblem):
    """(rows, cols, Cholesky factor of the correlation + noise ratio matrix, residuals) of the observed pixels."""
    rows, cols = np.nonzero(problem.precision > 0)
    k = problem.kernel
    s2 = float(k.outputscale) ** 2
    noise = 1.0 / np.asarray(problem.precision, np.float64)[rows, cols]
    resid = np.asarray(problem.obs, np.float64)[rows, cols] - np.asarray(problem.prior_mean, np.float64)[rows, cols]
    # Work in units of s so that the matrix is a correlation plus noise ratio.
    A = k.factor(rows, rows) * k.factor(cols, cols)
    A[np.diag_indices(rows.shape[0])] += noise / s2
    try:
        chol = scipy.linalg.cho_factor(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError as err:
        raise ConvergenceError(
            f"dense Cholesky failed for the Matern kernel nu={k.nu}, lengthscale={k.lengthscale:g} px, "
            f"outputscale={k.outputscale:g} m on {rows.shape[0]} observed pixels: the kernel matrix plus noise "
            f"(smallest noise/s^2 = {float(noise.min()) / s2:.3g}) is not numerically positive definite ({err})"
        ) from None
    return rows, cols, chol, resid


def dense_posterior(
    problem: GridProblem, *, variance: bool = True, max_cross_entries: int = 60_000_000
) -> tuple[np.ndarray, np.ndarray | None]:
    """Posterior mean (Ho, Wo) and marginal variance (Ho, Wo) (or None) by dense algebra over the observed pixels.

    mean = m* + K*o (Koo + D)^-1 (y - m), var = k** - diag(K*o (Koo + D)^-1 Ko*). The cross
    covariances of the separable kernel are products of two 1-D tables (output rows x observed
    rows, output columns x observed columns), so no kernel is evaluated per (output, observed) pair.

    Args:
        problem: The grid problem (either formulation, any output grid).
        variance: Also compute the marginal variances (m^2).
        max_cross_entries: Output pixels x observed pixels handled per block (bounds the memory).
    """
    mean, var, _ = dense_solve(problem, variance=variance, max_cross_entries=max_cross_entries)
    return mean, var


def dense_solve(
    problem: GridProblem, *, variance: bool = True, extra_obs: tuple = (), max_cross_entries: int = 60_000_000
) -> tuple[np.ndarray, np.ndarray | None, tuple]:
    """`dense_posterior` with further observation vectors sharing the factorisation.

    Args:
        problem: The grid problem.
        variance: Also compute the marginal variances.
        extra_obs: (H, W) observation arrays; for each, the posterior mean with ``problem``'s
            prior mean, precision and kernel.
        max_cross_entries: As in `dense_posterior`.

    Returns:
        (mean, variance or None, one mean per ``extra_obs``).
    """
    k = problem.kernel
    s2 = float(k.outputscale) ** 2
    ho, wo = problem.out_shape
    m = ho * wo
    out_prior = np.asarray(problem.out_prior_mean, np.float64)
    if not np.any(problem.precision > 0):
        return (
            out_prior.copy(),
            (np.full((ho, wo), s2) if variance else None),
            tuple(out_prior.copy() for _ in extra_obs),
        )
    rows, cols, chol, resid = _factor(problem)
    n = rows.shape[0]
    prior_obs = np.asarray(problem.prior_mean, np.float64)[rows, cols]
    rhs = np.stack([resid] + [np.asarray(e, np.float64)[rows, cols] - prior_obs for e in extra_obs], axis=1)
    alpha = scipy.linalg.cho_solve(chol, rhs, check_finite=False)  # (n, 1 + extras)
    kr = k.factor(problem.out_rows, rows)  # (Ho, n)
    kc = k.factor(problem.out_cols, cols)  # (Wo, n)
    means = np.empty((m, alpha.shape[1]))
    var = np.empty(m) if variance else None
    rows_per_block = max(1, max_cross_entries // max(n * wo, 1) // 4)
    for r0 in range(0, ho, rows_per_block):
        r1 = min(ho, r0 + rows_per_block)
        cross = (kr[r0:r1, None, :] * kc[None, :, :]).reshape(-1, n)  # (b, n) correlations
        sl = slice(r0 * wo, r1 * wo)
        means[sl] = cross @ alpha
        if var is not None:
            half = scipy.linalg.solve_triangular(chol[0], cross.T, lower=True, check_finite=False)
            var[sl] = s2 * np.maximum(1.0 - np.einsum("ij,ij->j", half, half), 0.0)
    means = out_prior.reshape(-1, 1) + means
    extras = tuple(means[:, j].reshape(ho, wo) for j in range(1, means.shape[1]))
    return means[:, 0].reshape(ho, wo), (var.reshape(ho, wo) if var is not None else None), extras


def dense_log_marginal_likelihood(problem: GridProblem) -> float:
    """log N(y; m, Koo + D) of the observed pixels of ``problem`` (nats), by dense Cholesky."""
    if not np.any(problem.precision > 0):
        return 0.0
    rows, cols, chol, resid = _factor(problem)
    s2 = float(problem.kernel.outputscale) ** 2
    n = rows.shape[0]
    alpha = scipy.linalg.cho_solve(chol, resid, check_finite=False)
    logdet = 2.0 * float(np.sum(np.log(np.diag(chol[0])))) + n * np.log(s2)
    return -0.5 * float(resid @ alpha) / s2 - 0.5 * logdet - 0.5 * n * np.log(2.0 * np.pi)


def dense_bytes(n_observed: int, n_out: int, *, variance: bool = True, max_cross_entries: int = 60_000_000) -> int:
    """Peak memory (bytes) of `dense_posterior`: the n x n factor, the 1-D tables and one block."""
    n = int(n_observed)
    block = min(int(n_out) * n, max(n, max_cross_entries // 4))
    return 8 * (2 * n * n + block * (2 if variance else 1) + 4 * n_out)


class ExactEngine:
    """Dense GP posterior: mean = m* + K*o (Koo + D)^-1 (y - m), var = k** - diag(K*o (Koo + D)^-1 Ko*)."""

    name = "exact"

    def __init__(self, max_points: int = 6000, max_cross_entries: int = 60_000_000):
        for name, value in (("max_points", max_points), ("max_cross_entries", max_cross_entries)):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InvalidInputError(name, "an integer >= 1", value)
        self.max_points = max_points
        self.max_cross_entries = max_cross_entries

    def solve(self, problem: GridProblem, *, variance: bool = True, extra_obs=()) -> Solution:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None).

        Args:
            problem: The grid problem.
            variance: Also compute the marginal variances.
            extra_obs: Further (H, W) observation arrays; their posterior means share the
                factorisation (`Solution.extra_means`).

        Returns:
            A `Solution` (unpacks as ``mean, variance``); its route is "dense".

        Raises:
            ProblemTooLargeError: More observed pixels or cross entries than the limits.
            ConvergenceError: The kernel matrix plus noise is not numerically positive definite.
            InvalidInputError: A malformed problem (see `check_problem`).
        """
        t0 = time.perf_counter()
        check_problem(problem)
        extra = check_extra_obs(problem, extra_obs)
        n = int(np.count_nonzero(problem.precision > 0))
        ho, wo = problem.out_shape
        m = ho * wo
        if n > self.max_points or n * m > self.max_cross_entries:
            raise ProblemTooLargeError(
                f"exact engine: {n} observed pixels x {m} output pixels exceeds its limit "
                f"({self.max_points} observed pixels, {self.max_cross_entries} cross entries); "
                "use engine='fast' or a smaller crop"
            )
        mean, var, extras = dense_solve(
            problem, variance=variance, extra_obs=extra, max_cross_entries=self.max_cross_entries
        )
        info = SolveInfo("exact", "dense", {"total": time.perf_counter() - t0}, {"observed": n})
        return Solution(mean, var, info, extras)
