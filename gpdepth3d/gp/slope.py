"""The MDE's log depth as a covariate of the default model: its slope a per frame (docs/model.md, "slope").

How much of an MDE's depth variation is real differs by network and scene, so the coefficient of its
centred log depth is fitted on each frame's points by generalised least squares (regression kriging
with the MDE as covariate)::

    log z_j = c + a (log MDE(x_j) - c) + b + g(x_j) + w_j + e_j,   a ~ N(1, sigma_a^2), b flat

with c the points' median log MDE depth (b and a are then nearly uncorrelated), g the stationary GP and
w + e the white noise. The prior keeps a frame with few points near a = 1; Huber re-weighting keeps gross
outliers from tilting the slope. Above ``max_points`` points an evenly strided subset is used (the fit is
one scalar and an offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from ..errors import InvalidInputError, ShapeError, describe
from .model import Kernel


@dataclass(frozen=True)
class SlopeFit:
    """The MDE coefficient of one frame.

    Attributes:
        slope: a, the coefficient of the MDE's centred log depth (1: the plain log-residual model).
        slope_var: Its posterior variance (prior and points).
        centre: c, the points' median log MDE depth the covariate is centred on.
        n_used: Points the fit used.
    """

    slope: float
    slope_var: float
    centre: float
    n_used: int

    def apply(self, log_mde: np.ndarray) -> np.ndarray:
        """The re-sloped log MDE depth ``c + a (log MDE - c)``."""
        return self.centre + self.slope * (np.asarray(log_mde, dtype=np.float64) - self.centre)


def fit_mde_slope(
    rows: np.ndarray,
    cols: np.ndarray,
    log_z: np.ndarray,
    log_mde: np.ndarray,
    noise: np.ndarray,
    kernel: Kernel,
    nugget: float,
    *,
    prior_sigma: float,
    max_points: int = 150,
    huber: float = 2.0,
    iterations: int = 3,
    use: np.ndarray | None = None,
) -> SlopeFit:
    """Fits the MDE's log-depth coefficient of one frame by robust generalised least squares.

    Args:
        rows, cols: (N,) grid coordinates of the points (GP-grid pixels).
        log_z: (N,) log measured depths.
        log_mde: (N,) log MDE depths at the points.
        noise: (N,) measurement variances in log depth ((sigma / z)^2).
        kernel: The GP's kernel on the grid (its length scale in grid pixels, outputscale in log depth).
        nugget: tau, the white part of the MDE's log error.
        prior_sigma: Standard deviation of the Gaussian prior of the slope around 1 (> 0).
        max_points: Largest number of points the dense fit uses (an evenly strided subset above).
        huber: Huber threshold on the standardised residuals (re-weighting of outliers).
        iterations: Re-weighting rounds.
        use: (N,) bool, the points to fit on (default all): the same as passing those points alone, without
            gathering more of them than the fit uses.

    Returns:
        `SlopeFit`; with no points the prior (slope 1, variance prior_sigma^2).

    Raises:
        ShapeError: inputs of different lengths.
        InvalidInputError: prior_sigma not > 0, max_points < 2.
    """
    arrays = [np.asarray(a).ravel() for a in (rows, cols)]  # as float64 once the subset is taken
    arrays += [np.asarray(a, dtype=np.float64).ravel() for a in (log_z, log_mde, noise)]
    n = arrays[0].size
    for name, a in zip(("rows", "cols", "log_z", "log_mde", "noise"), arrays):
        if a.size != n:
            raise ShapeError(name, f"{n} values, one per point", describe(a))
    if not np.isfinite(prior_sigma) or prior_sigma <= 0:
        raise InvalidInputError("prior_sigma", "a standard deviation > 0", prior_sigma)
    if int(max_points) != max_points or max_points < 2:
        raise InvalidInputError("max_points", "an integer >= 2", max_points)
    if use is not None and np.shape(use) != (n,):
        raise ShapeError("use", f"{n} flags, one per point", describe(np.asarray(use)))
    r, c, y, x, e = arrays
    ok = np.isfinite(y) & np.isfinite(x) & np.isfinite(e)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    pick = None if ok.all() else np.flatnonzero(ok)  # the points fitted on (None: all); the others gathered last
    if pick is not None:
        x = x[pick]  # all of them for the median
    n = x.size
    if n == 0:
        return SlopeFit(1.0, float(prior_sigma) ** 2, 0.0, 0)
    centre = float(np.median(x))
    if n > max_points:
        take = np.linspace(0, n - 1, int(max_points)).round().astype(np.int64)
        x, pick = x[take], take if pick is None else pick[take]
    if pick is not None:
        r, c, y, e = r[pick], c[pick], y[pick], e[pick]
    r, c = r.astype(np.float64), c.astype(np.float64)
    xc = x - centre
    yc = y - centre - xc  # the log ratio under a = 1; its slope on xc is a - 1
    H = np.column_stack([np.ones_like(xc), xc])
    K = kernel.matrix(r, c, r, c)
    white = nugget**2 + e
    prior_prec = np.diag([0.0, 1.0 / prior_sigma**2])  # offset flat, slope - 1 ~ N(0, prior_sigma^2)
    weights = np.ones_like(yc)
    marginal = np.sqrt(kernel.outputscale**2 + white)
    beta = np.zeros(2)
    M = prior_prec
    rhs = np.column_stack([H, yc])
    work = np.empty_like(K, order="F")  # the factor, in LAPACK's order (no copy of the matrix per round)
    for it in range(max(1, int(iterations))):
        Z = _cholesky_solve(K, white / weights, rhs, work)  # (K + diag(white / weights))^-1 [H, y]
        M = H.T @ Z[:, :2] + prior_prec
        beta = np.linalg.solve(M, H.T @ Z[:, 2])
        if it + 1 < iterations:
            t = np.abs(yc - H @ beta) / marginal
            new = np.where(t <= huber, 1.0, huber / np.maximum(t, 1e-300))
            if np.all(np.abs(new - weights) <= 1e-8 + 1e-5 * weights):  # np.allclose of the (positive) weights
                break
            weights = new
    cov = np.linalg.inv(M)
    return SlopeFit(float(1.0 + beta[1]), float(cov[1, 1]), centre, int(len(yc)))


def _cholesky_solve(K: np.ndarray, diag: np.ndarray, rhs: np.ndarray, work: np.ndarray) -> np.ndarray:
    """S^-1 rhs, S = K + diag(diag), by LAPACK's Cholesky factorisation and solve (potrf, potrs: those scipy's
    cho_factor and cho_solve call, without their checks on a matrix built here); a matrix that is not numerically
    positive definite gets a jitter of 1e-10 times its mean diagonal.

    ``work``: an (n, n) Fortran-ordered buffer S is built and factorised in (LAPACK's order: no copy of it).

    Raises:
        numpy.linalg.LinAlgError: not positive definite even with the jitter.
    """
    n = len(K)
    on_diagonal = np.arange(n)

    def build_s() -> None:  # S into work (again after a failed factorisation, which overwrote it)
        np.copyto(work, K)
        work[on_diagonal, on_diagonal] += diag

    build_s()
    factor, info = lapack.dpotrf(work, lower=1, clean=0, overwrite_a=1)
    if info > 0:
        build_s()
        work[on_diagonal, on_diagonal] += 1e-10 * np.trace(work) / n  # the jitter
        factor, info = lapack.dpotrf(work, lower=1, clean=0, overwrite_a=1)
        if info > 0:
            raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    return lapack.dpotrs(factor, rhs, lower=1)[0]
