"""Fitting the model's scales by marginal likelihood (arrays only; the library's one fitting module).

* Gaussian formulations: `maximise_log_marginal_likelihood` searches the logarithms of a
  `DepthGPConfig`'s free fields with SciPy's L-BFGS-B, given the log marginal likelihood as a function
  of the config (`gpdepth3d.completion.marginal_fit` builds it from a frame); `paired_log_likelihood` is the
  exact factor two observations on one pixel add once the engine has combined them.
* The default model: `fit_log_residual` profiles s and the global log scale b out in closed form
  (b by generalised least squares with a flat prior) over a small grid of (l, tau / s) on the frame's
  points; `raised_outputscale` raises a configured s to what the points show.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
import scipy.optimize

from ..errors import ConvergenceError, InvalidInputError
from .model import RANGES, DepthGPConfig, ScreenConfig, separable_correlation

LOG_SCALE_MAX = RANGES["log_outputscale"][1]
"""Largest fitted s and tau of the default model (log depth): the config's bound, so a fitted config is valid."""

FIT_BOUNDS: dict[str, tuple[float, float]] = {
    "lengthscale": (0.2, 500.0),
    "outputscale": (1e-4, 1e3),
    "sigma_dl": (1e-5, 1e2),
    "sigma_meas": (1e-6, 1e2),
}
"""Search interval of each fittable field (in the config's units; lengthscale in GP-grid pixels)."""


def fit_params(config: DepthGPConfig, params: Sequence[str] | None = None) -> tuple[str, ...]:
    """Checks the names of the fields to fit; None gives the formulation's default set.

    The defaults are lengthscale, outputscale and sigma_dl (balanced) or lengthscale and
    outputscale (residual).

    Raises:
        InvalidInputError: ``config`` is not a `DepthGPConfig`, its formulation is
            ``log_residual`` (fitted per frame on its points instead), a name is unknown or
            repeated, or sigma_dl is asked for in the residual formulation.
    """
    if not isinstance(config, DepthGPConfig):
        raise InvalidInputError("config", "a DepthGPConfig", type(config).__name__)
    if config.formulation == "log_residual":
        raise InvalidInputError(
            "config",
            "the 'balanced' or 'residual' formulation (log_residual is fitted per frame on its points by "
            "DepthCompleter, see gpdepth3d.gp.fit.fit_log_residual)",
            config.formulation,
        )
    if params is None:
        return (
            ("lengthscale", "outputscale", "sigma_dl")
            if config.formulation == "balanced"
            else ("lengthscale", "outputscale")
        )
    names = tuple(params)
    if not names or any(n not in FIT_BOUNDS for n in names) or len(set(names)) != len(names):
        raise InvalidInputError("params", f"distinct names from {sorted(FIT_BOUNDS)}", params)
    if config.formulation == "residual" and "sigma_dl" in names:
        raise InvalidInputError(
            "params", "no sigma_dl in the residual formulation (MDE pixels are not observed)", names
        )
    return names


def paired_log_likelihood(a: np.ndarray, b: np.ndarray, variance: np.ndarray) -> float:
    """Sum of log N(a - b; 0, variance) (nats): what two observations of one value add to the LML.

    Args:
        a: (n,) first observations (e.g. MDE depths at measured pixels).
        b: (n,) second observations of the same values (the measurements).
        variance: (n,) sum of the two observations' noise variances, > 0.
    """
    a, b, variance = (np.asarray(x, dtype=np.float64) for x in (a, b, variance))
    if not (a.shape == b.shape == variance.shape) or a.ndim != 1:
        raise InvalidInputError("a, b, variance", "three 1-D arrays of one length", (a.shape, b.shape, variance.shape))
    if not np.all(variance > 0):
        raise InvalidInputError("variance", "variances > 0", float(variance.min()))
    diff = a - b
    return float(np.sum(-0.5 * diff**2 / variance - 0.5 * np.log(2 * np.pi * variance)))


def maximise_log_marginal_likelihood(
    lml: Callable[[DepthGPConfig], float],
    config: DepthGPConfig,
    params: Sequence[str],
    *,
    max_iterations: int = 50,
    n_obs: int = 1,
) -> DepthGPConfig:
    """Maximises ``lml(config)`` over the fields ``params`` (L-BFGS-B on their logarithms).

    Args:
        lml: The log marginal likelihood (nats) of a configuration. A configuration for which it
            raises `numpy.linalg.LinAlgError` or `ConvergenceError`, or returns a non-finite
            value, counts as infinitely unlikely.
        config: Starting point and fixed settings.
        params: Names of the fitted fields (checked with `fit_params`).
        max_iterations: L-BFGS-B iteration limit.
        n_obs: Number of observations; the objective is the LML per observation, which keeps
            L-BFGS-B's first steps sensible.

    Returns:
        ``config`` with the fitted fields replaced, each within `FIT_BOUNDS`. The LML at the
        result is never lower than at ``config`` (clipped to the bounds).
    """
    names = fit_params(config, params)
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidInputError("max_iterations", "an integer >= 1", max_iterations)
    if isinstance(n_obs, bool) or not isinstance(n_obs, (int, np.integer)) or n_obs < 1:
        raise InvalidInputError("n_obs", "an integer >= 1", n_obs)
    x0 = np.log([getattr(config, n) for n in names])
    bounds = [tuple(np.log(FIT_BOUNDS[n])) for n in names]
    x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])

    def objective(x: np.ndarray) -> float:
        cfg = config.replace(**{n: float(np.exp(v)) for n, v in zip(names, x)})
        try:
            value = lml(cfg)
        except (np.linalg.LinAlgError, ConvergenceError):  # e.g. the grid route refused as ill-conditioned
            return 1e300
        return -value / n_obs if np.isfinite(value) else 1e300

    f0 = objective(x0)
    result = scipy.optimize.minimize(
        objective, x0, method="L-BFGS-B", bounds=bounds, options={"maxiter": max_iterations, "eps": 1e-6}
    )
    best = result.x if result.fun <= f0 else x0
    return config.replace(**{n: float(np.exp(v)) for n, v in zip(names, best)})


@dataclass(frozen=True)
class PointFit:
    """Hyperparameters of the log-residual GP fitted to one frame's points.

    Attributes:
        lengthscale: l, GP-grid pixels.
        outputscale: s, standard deviation of the correlated log-ratio field (dimensionless).
        nugget: tau = s * sqrt(eta), standard deviation of the white part of the MDE's log error.
        log_scale: b, the generalised-least-squares constant of the log ratio (exp(b) is the
            global scale that maps the MDE onto the points).
        log_scale_var: Variance of b (flat prior), from the fitted subset.
        n_used: Points the fit used.
    """

    lengthscale: float
    outputscale: float
    nugget: float
    log_scale: float
    log_scale_var: float
    n_used: int

    @property
    def eta(self) -> float:
        """Nugget share (tau / s)^2."""
        return (self.nugget / self.outputscale) ** 2 if self.outputscale > 0 else 0.0


def _profile(resid: np.ndarray, corr: np.ndarray, noise: np.ndarray, eta: float, s2_prev: float):
    """Profiled restricted likelihood for one (l, eta); returns (criterion, s2, b, var_b) or None."""
    n = resid.size
    # noise (measurement variance) is absolute; fold it in relative to the current s^2 estimate
    C = corr.copy()
    C[np.diag_indices(n)] += eta + noise / s2_prev
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return None
    from scipy.linalg import solve_triangular

    a1 = solve_triangular(L, np.ones(n), lower=True, check_finite=False)
    ar = solve_triangular(L, resid, lower=True, check_finite=False)
    q = float(a1 @ a1)
    b = float(a1 @ ar) / q
    a = ar - b * a1
    s2 = max(float(a @ a) / max(n - 1, 1), 1e-12)
    crit = 0.5 * (n - 1) * np.log(s2) + float(np.log(np.diag(L)).sum()) + 0.5 * np.log(q)
    return crit, s2, b, s2 / q


def _fit_subset(rows: np.ndarray, cols: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of a subset for the fit: random seed points, each with its nearest neighbour.

    A purely random subset of dense points (full LiDAR) has no close pairs, so the likelihood
    cannot see the short-range correlation and calls it nugget; pairing every seed with its
    nearest point keeps the points' own spacing in the subset.
    """
    from scipy.spatial import cKDTree

    n = rows.size
    seeds = rng.choice(n, size=size // 2, replace=False)
    xy = np.column_stack([rows, cols])
    _, nn = cKDTree(xy).query(xy[seeds], k=2, p=1)
    pick = np.unique(np.concatenate([seeds, nn[:, 1]]))
    if pick.size < size:  # duplicates: fill up with random other points
        rest = np.setdiff1d(np.arange(n), pick)
        pick = np.union1d(pick, rng.choice(rest, size=min(size - pick.size, rest.size), replace=False))
    return pick


def fit_log_residual(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    *,
    nu: float = 0.5,
    max_points: int = 150,
    lengthscales: tuple[float, ...] = ScreenConfig.fit_lengthscales,
    nuggets: tuple[float, ...] = ScreenConfig.fit_nuggets,
    rng: np.random.Generator | None = None,
    around: tuple[float, float] | None = None,
) -> PointFit:
    """Fits (l, s, tau, b) of the log-residual GP to the points by profiled marginal likelihood.

    Args:
        rows, cols: (N,) pixel coordinates of the points on the GP grid.
        resid: (N,) log(measured depth / MDE depth).
        noise: (N,) measurement variance in log units ((sigma / depth)^2).
        nu: Matern smoothness.
        max_points: Fit on a subset of at most this many points (cost max_points^3 per grid
            cell): half random seeds, half their nearest neighbours.
        lengthscales, nuggets: The grid searched (pixels; shares of s^2).
        rng: Generator of the subset (default seeded 0: the same frame gives the same fit).
        around: (l, eta) of a previous fit (the frame before in a sequence): instead of the
            whole grid, a pattern search starts at the grid cell nearest to it and moves to the
            best neighbouring cell until none is better (a few cells instead of all).

    Returns:
        The fit. With fewer than 3 points the length scale and nugget are the grid's middle
        values, s the spread of the residuals (at least 0.1) and b their median.
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    resid = np.asarray(resid, dtype=np.float64)
    noise = np.asarray(noise, dtype=np.float64)
    n = resid.size
    if not (rows.shape == cols.shape == resid.shape == noise.shape) or resid.ndim != 1:
        raise InvalidInputError(
            "rows, cols, resid, noise", "four (N,) arrays", (rows.shape, cols.shape, resid.shape, noise.shape)
        )
    if n < 3:
        b = float(np.median(resid)) if n else 0.0
        s = min(max(float(np.std(resid)) if n > 1 else 0.0, 0.1), LOG_SCALE_MAX)
        return PointFit(lengthscales[len(lengthscales) // 2], s, s * np.sqrt(nuggets[0]), b, s * s, n)
    if n > max_points:
        pick = _fit_subset(rows, cols, max_points, rng if rng is not None else np.random.default_rng(0))
        rows, cols, resid, noise = rows[pick], cols[pick], resid[pick], noise[pick]
        n = pick.size
    spread = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    s2_guess = max(spread * spread, float(np.median(noise)), 1e-6)
    corr_cache: dict[int, np.ndarray] = {}
    scores: dict[tuple[int, int], tuple | None] = {}

    def score(i: int, j: int):
        if (i, j) not in scores:
            if i not in corr_cache:
                corr_cache[i] = separable_correlation(
                    np.subtract.outer(rows, rows), np.subtract.outer(cols, cols), lengthscales[i], nu
                )
            scores[(i, j)] = _profile(resid, corr_cache[i], noise, nuggets[j], s2_guess)
        return scores[(i, j)]

    if around is None:
        cells = [(i, j) for i in range(len(lengthscales)) for j in range(len(nuggets))]
        for cell in cells:
            score(*cell)
    else:  # pattern search from the previous fit
        i = int(np.argmin(np.abs(np.log(np.asarray(lengthscales) / max(around[0], 1e-9)))))
        j = int(np.argmin(np.abs(np.log(np.asarray(nuggets) / max(around[1], 1e-9)))))
        while True:
            here = score(i, j)
            moves = [
                (a, b)
                for a in (i - 1, i, i + 1)
                for b in (j - 1, j, j + 1)
                if 0 <= a < len(lengthscales) and 0 <= b < len(nuggets) and (a, b) != (i, j)
            ]
            cand = [(score(a, b), (a, b)) for a, b in moves]
            cand = [(c[0], ab) for c, ab in cand if c is not None]
            if not cand or (here is not None and min(cand)[0] >= here[0]):
                break
            i, j = min(cand)[1]
    valid = [(out[0], lengthscales[i], nuggets[j], *out[1:]) for (i, j), out in scores.items() if out is not None]
    best = min(valid) if valid else None
    if best is None:  # every cell failed (duplicate points with no noise): fall back to a white model
        b = float(np.median(resid))
        s = min(np.sqrt(s2_guess), LOG_SCALE_MAX)
        return PointFit(lengthscales[0], s, s, b, s * s / n, n)
    _, lengthscale, eta, s2, b, var_b = best
    if s2 > LOG_SCALE_MAX**2:  # capped at the config's bound; Var[b] = s^2 / q follows
        var_b, s2 = var_b * LOG_SCALE_MAX**2 / s2, LOG_SCALE_MAX**2
    return PointFit(
        float(lengthscale), float(np.sqrt(s2)), float(min(np.sqrt(s2 * eta), LOG_SCALE_MAX)), b, float(var_b), n
    )


def raised_outputscale(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    start: PointFit,
    *,
    nu: float = 0.5,
    max_points: int = 150,
    use: np.ndarray | None = None,
) -> PointFit:
    """``start`` with its s raised to what the points show, never lowered.

    s is profiled by marginal likelihood (`fit_log_residual`, on at most ``max_points`` points
    evenly strided in their order) at ``start``'s length scale and nugget ratio
    eta = (tau / s)^2; when that s is larger than ``start``'s, it replaces it (and Var[b] =
    s^2 / N follows); l, tau and b stay ``start``'s. The configured s is then the least
    MDE error a frame is assumed to have: a network badly out of its range (FastDepth in a 20 m
    hall) gets a wider prior instead of a confident wrong mean.

    Args:
        rows, cols, resid, noise: (N,) as in `fit_log_residual`.
        start: The configured (floor) hyperparameters.
        nu: Matern smoothness.
        max_points: Subset size of the fit.
        use: (N,) bool, the points to fit on (default all): the same as passing those points alone, without
            gathering more of them than the subset.
    """
    n = np.asarray(resid).size if use is None else int(np.count_nonzero(use))
    if n < 3:
        return start
    eta = (start.nugget / start.outputscale) ** 2
    # l is not fitted, so no close pairs are needed: an evenly strided subset in the points' order
    # (as gp.slope's), not `fit_log_residual`'s k-d tree pairing (cheaper, and l is not fitted)
    take = np.linspace(0, n - 1, min(n, int(max_points))).round().astype(np.int64)
    if use is not None:
        take = np.flatnonzero(use)[take]
    fitted = fit_log_residual(
        np.asarray(rows)[take],
        np.asarray(cols)[take],
        np.asarray(resid)[take],
        np.asarray(noise)[take],
        nu=nu,
        max_points=take.size,
        lengthscales=(start.lengthscale,),
        nuggets=(eta,),
    )
    if fitted.outputscale <= start.outputscale:
        return start
    s = fitted.outputscale
    return replace(start, outputscale=s, log_scale_var=s * s / n)
