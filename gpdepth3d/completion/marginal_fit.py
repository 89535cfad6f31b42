"""Hyperparameter fitting by maximising the exact log marginal likelihood of one frame.

The log marginal likelihood (LML) of the model is computed exactly from the sparse precision of
the `fast` engine (no subsampling, no stochastic trace estimates)::

    log p(y) = log N(y; f*, W^-1) + log N(f*; m, Q^-1) - log N(f*; f*, P^-1)

at the posterior mean f* (any f would do; f* is numerically best), with log det P from the
multifrontal Cholesky factor and log det Q from the 1-D chains. In the balanced formulation a
pixel with an MDE depth and a measurement holds two observations; the engine combines them into
one precision-weighted observation, so the LML adds the exact factor
N(y_mde - y_meas; 0, sigma_dl^2 + sigma_meas^2) of each such pixel (it depends on sigma_dl).

The optimiser (`gpdepth3d.gp.fit.maximise_log_marginal_likelihood`) is SciPy's L-BFGS-B on the
logarithms of the free parameters with finite-difference gradients (each evaluation is one sparse
factorisation); this module builds the frame's problem for it. Cost: about 20-60 factorisations, so
fit on a crop of a large frame (e.g. 1/3 KITTI resolution) and reuse the values for the
sequence.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..gp.fit import fit_params, maximise_log_marginal_likelihood, paired_log_likelihood
from ..gp.model import DepthGPConfig
from ..measurements import SparseDepth
from .problem import build_problem, check_mde_depth


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
    from ..gp.fast import FastEngine

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
        lml += paired_log_likelihood(mde[r[both], c[both]], grid_sparse.depth[both], var)
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
    from ..gp.fast import FastEngine

    names = fit_params(config, params)
    engine = engine or FastEngine()
    # per-observation scale keeps L-BFGS-B's first steps sensible
    n_obs = max(1, int(check_mde_depth(mde_depth)[1].sum()) * (config.formulation == "balanced") + len(sparse))
    return maximise_log_marginal_likelihood(
        lambda cfg: log_marginal_likelihood(mde_depth, sparse, cfg, engine=engine),
        config,
        names,
        max_iterations=max_iterations,
        n_obs=n_obs,
    )
