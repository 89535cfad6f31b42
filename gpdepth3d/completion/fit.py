"""Hyperparameter fitting by maximising the exact log marginal likelihood of one frame.

The log marginal likelihood (LML) of the model is computed exactly from the sparse precision of
the `fast` engine (no subsampling, no stochastic trace estimates)::

    log p(y) = log N(y; f*, W^-1) + log N(f*; m, Q^-1) - log N(f*; f*, P^-1)

at the posterior mean f* (any f would do; f* is numerically best), with log det P from the
multifrontal Cholesky factor and log det Q from the 1-D chains. In the balanced formulation a
pixel with an MDE depth and a measurement holds two observations; the engine combines them into
one precision-weighted observation, so the LML adds the exact factor
N(y_mde - y_meas; 0, sigma_dl^2 + sigma_meas^2) of each such pixel (it depends on sigma_dl).

The optimiser is SciPy's L-BFGS-B on the logarithms of the free parameters with finite-difference
gradients (each evaluation is one sparse factorisation). Cost: about 20-60 factorisations, so
fit on a crop of a large frame (e.g. 1/3 KITTI resolution) and reuse the values for the
sequence.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.optimize

from ..errors import ConvergenceError, InvalidInputError
from ..measurements import SparseDepth
from .model import DepthGPConfig

_BOUNDS = {
    "lengthscale": (0.2, 500.0),
    "outputscale": (1e-4, 1e3),
    "sigma_dl": (1e-5, 1e2),
    "sigma_meas": (1e-6, 1e2),
}


def _default_params(config: DepthGPConfig) -> tuple[str, ...]:
    if config.formulation == "balanced":
        return ("lengthscale", "outputscale", "sigma_dl")
    return ("lengthscale", "outputscale")


def log_marginal_likelihood(mde_depth: np.ndarray, sparse: SparseDepth, config: DepthGPConfig, *, engine=None) -> float:
    """Exact log marginal likelihood (nats) of a frame's observations under ``config``.

    In the balanced formulation the observations are every valid MDE pixel and every
    measurement (two observations on one pixel count as two); in the residual formulation the
    measurements, given the (aligned) MDE as prior mean.

    Args:
        mde_depth: (H, W) MDE depth, metres (0/NaN/inf = none).
        sparse: Measurements (any resolution of the same image).
        config: The model; its ``engine`` is ignored (the fast engine computes the LML).
        engine: Optional `FastEngine` to reuse (its caches make repeated calls cheaper).
    """
    from ..complete import build_problem, check_mde_depth
    from .fast import FastEngine

    engine = engine or FastEngine()
    problem, grid_sparse, scale, _ = build_problem(mde_depth, sparse, config)
    lml = engine.log_marginal_likelihood(problem)
    if config.formulation == "balanced" and len(grid_sparse):
        mde, valid = check_mde_depth(mde_depth)
        r = grid_sparse.v.astype(np.int64)
        c = grid_sparse.u.astype(np.int64)
        unit = scale if config.units == "relative" else 1.0
        smeas = np.where(np.isfinite(grid_sparse.sigma), grid_sparse.sigma, config.sigma_meas * unit)
        both = valid[r, c]
        var = (config.sigma_dl * unit) ** 2 + smeas[both] ** 2
        diff = mde[r[both], c[both]] - grid_sparse.depth[both]
        lml += float(np.sum(-0.5 * diff**2 / var - 0.5 * np.log(2 * np.pi * var)))
    return float(lml)


def fit_hyperparameters(
    mde_depth: np.ndarray,
    sparse: SparseDepth,
    config: DepthGPConfig,
    *,
    params: Sequence[str] | None = None,
    max_iterations: int = 50,
    engine=None,
) -> DepthGPConfig:
    """Fits the model's hyperparameters to one frame by maximising the exact marginal likelihood.

    Args:
        mde_depth: (H, W) MDE depth, metres (0/NaN/inf = none).
        sparse: Measurements (any resolution of the same image).
        config: Starting point and fixed settings (formulation, nu, units, align).
        params: Names of the fitted fields; default lengthscale, outputscale and sigma_dl
            (balanced) or lengthscale and outputscale (residual). Allowed: lengthscale,
            outputscale, sigma_dl, sigma_meas.
        max_iterations: L-BFGS-B iteration limit.
        engine: Optional `FastEngine` to reuse.

    Returns:
        ``config`` with the fitted fields replaced (in ``config.units``; lengthscale in
        GP-grid pixels). The LML at the result is never lower than at ``config``.
    """
    from .fast import FastEngine

    if not isinstance(config, DepthGPConfig):
        raise InvalidInputError("config", "a DepthGPConfig", type(config).__name__)
    names = tuple(params) if params is not None else _default_params(config)
    if not names or any(n not in _BOUNDS for n in names) or len(set(names)) != len(names):
        raise InvalidInputError("params", f"distinct names from {sorted(_BOUNDS)}", params)
    if config.formulation == "log_residual":
        raise InvalidInputError(
            "config",
            "the 'balanced' or 'residual' formulation (log_residual is fitted per frame on its points by "
            "DepthCompleter, see gpdepth3d.gp.points)",
            config.formulation,
        )
    if config.formulation == "residual" and "sigma_dl" in names:
        raise InvalidInputError("params", "no sigma_dl in the residual formulation (MDE pixels are not observed)", names)
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidInputError("max_iterations", "an integer >= 1", max_iterations)
    engine = engine or FastEngine()
    x0 = np.log([getattr(config, n) for n in names])
    bounds = [tuple(np.log(_BOUNDS[n])) for n in names]
    x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])

    from ..complete import check_mde_depth

    # per-observation scale keeps L-BFGS-B's first steps sensible
    n_obs = max(1, int(check_mde_depth(mde_depth)[1].sum()) * (config.formulation == "balanced") + len(sparse))

    def objective(x: np.ndarray) -> float:
        cfg = config.replace(**{n: float(np.exp(v)) for n, v in zip(names, x)})
        try:
            value = log_marginal_likelihood(mde_depth, sparse, cfg, engine=engine)
        except (np.linalg.LinAlgError, ConvergenceError):  # e.g. the grid route refused as ill-conditioned
            return 1e300
        return -value / n_obs if np.isfinite(value) else 1e300

    f0 = objective(x0)
    result = scipy.optimize.minimize(
        objective, x0, method="L-BFGS-B", bounds=bounds,
        options={"maxiter": max_iterations, "eps": 1e-6},
    )
    best = result.x if result.fun <= f0 else x0
    return config.replace(**{n: float(np.exp(v)) for n, v in zip(names, best)})
