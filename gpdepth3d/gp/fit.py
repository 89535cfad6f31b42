"""Marginal-likelihood maximisation over a `DepthGPConfig`'s hyperparameters (arrays only).

The optimiser knows nothing about images or measurements: it is given the log marginal
likelihood as a function of the configuration (`gpdepth3d.completion.fit` builds that function
from an MDE map and measurements) and searches the logarithms of the free parameters with
SciPy's L-BFGS-B and finite-difference gradients. `paired_log_likelihood` is the exact factor
that two observations on one pixel add to the LML once the engine has combined them into one
precision-weighted observation.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import scipy.optimize

from ..errors import ConvergenceError, InvalidInputError
from .model import DepthGPConfig

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
            "DepthCompleter, see gpdepth3d.gp.points)",
            config.formulation,
        )
    if params is None:
        return ("lengthscale", "outputscale", "sigma_dl") if config.formulation == "balanced" else ("lengthscale", "outputscale")
    names = tuple(params)
    if not names or any(n not in FIT_BOUNDS for n in names) or len(set(names)) != len(names):
        raise InvalidInputError("params", f"distinct names from {sorted(FIT_BOUNDS)}", params)
    if config.formulation == "residual" and "sigma_dl" in names:
        raise InvalidInputError("params", "no sigma_dl in the residual formulation (MDE pixels are not observed)", names)
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
        objective, x0, method="L-BFGS-B", bounds=bounds,
        options={"maxiter": max_iterations, "eps": 1e-6},
    )
    best = result.x if result.fun <= f0 else x0
    return config.replace(**{n: float(np.exp(v)) for n, v in zip(names, best)})
