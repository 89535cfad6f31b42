"""The formulations of the depth model as strategies: one class each, one interface, chosen by the config.

* `LogResidual` (the default): a GP on log(depth / MDE) with the stages of docs/model.md.
* `Balanced` (the paper): MDE pixels and points are both observations of the depth field.
* `Residual`: the (aligned) MDE is the prior mean, the points the observations.

`formulation_of` picks the strategy that ``DepthGPConfig.formulation`` names (`FORMULATIONS`);
`gpdepth3d.completion.DepthCompleter` calls its `Formulation.posterior`. A new formulation is one class
here and its name in `DepthGPConfig`'s accepted values.
"""

from __future__ import annotations

import time
import warnings
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from ..depthmap import resize_map
from ..gp.model import DepthGPConfig
from ..measurements import SparseDepth
from .diagnostics import PosteriorWarning, gaussian_warnings
from .log_frame import log_frame
from .log_residual import log_residual_posterior
from .problem import _frame_inputs, build_problem, check_mde_depth


class Formulation(ABC):
    """One formulation of the depth model: how a frame's inputs become the posterior's fields."""

    name: ClassVar[str]

    @abstractmethod
    def posterior(
        self,
        completer: Any,
        mde_depth: np.ndarray,
        sparse: SparseDepth,
        output_shape: tuple[int, int] | None,
        variance: bool,
        frame: str | None,
    ) -> dict[str, Any]:
        """The keyword arguments of the frame's `DepthPosterior` (see `DepthCompleter.complete`).

        ``completer`` is the calling `DepthCompleter`: it holds the config, the engine and what the previous
        frame fitted (``fitted``), which a formulation updates. `PosteriorWarning`s are issued at the caller of
        `DepthCompleter.complete`.
        """


class LogResidual(Formulation):
    """The default model: a GP on the log ratio of depth to MDE, in named stages (docs/model.md)."""

    name = "log_residual"

    def posterior(self, completer, mde_depth, sparse, output_shape, variance, frame) -> dict[str, Any]:
        t0 = time.perf_counter()
        mde, valid, grid_sparse, out_shape = _frame_inputs(mde_depth, sparse, output_shape)
        inputs = log_frame(mde, valid, grid_sparse, out_shape, completer.config)
        t1 = time.perf_counter()
        result = log_residual_posterior(
            completer.engine,
            inputs,
            completer.config,
            variance=variance,
            name=f"frame {frame}: " if frame is not None else "",
            previous=completer._point_fit if completer.fitted is not None else None,
            stride=completer.engine_config.lattice_stride,
        )
        for message in result.warnings:
            warnings.warn(message, PosteriorWarning, stacklevel=3)
        completer.fitted, completer._point_fit = result.config, result.fit
        return dict(
            mean=result.mean,
            variance=result.variance,
            mde=mde_on_output(mde, valid, out_shape),
            sparse=grid_sparse,
            config=result.config,
            depth_scale=float(np.median(mde[valid])) if valid.any() else float(np.median(grid_sparse.depth)),
            alignment=result.alignment,
            timings={"setup": t1 - t0, **result.timings},
            rejected=result.rejected,
            warnings=result.warnings,
            solve=result.info,
            mde_slope=result.slope,
            stages=result.stages,
        )


class Gaussian(Formulation):
    """A Gaussian formulation on depth: one `GridProblem` for the engine, hyperparameters fitted by marginal
    likelihood when ``config.fit`` (`gpdepth3d.completion.marginal_fit`)."""

    def posterior(self, completer, mde_depth, sparse, output_shape, variance, frame) -> dict[str, Any]:
        t0 = time.perf_counter()
        config = self._frame_config(completer, mde_depth, sparse)
        tf = time.perf_counter()
        problem, grid_sparse, scale, alignment = build_problem(mde_depth, sparse, config, output_shape)
        t1 = time.perf_counter()
        solution = completer.engine.solve(problem, variance=variance)
        mean, var = solution.mean, solution.variance
        t2 = time.perf_counter()
        if var is None:
            var = np.full(mean.shape, np.nan)
        mde, valid = check_mde_depth(mde_depth)
        messages = gaussian_warnings(mean, mde, valid, grid_sparse, f"frame {frame}: " if frame is not None else "")
        for message in messages:
            warnings.warn(message, PosteriorWarning, stacklevel=3)
        return dict(
            mean=mean,
            variance=var,
            mde=mde_on_output(mde, valid, problem.out_shape),
            sparse=grid_sparse,
            config=config,
            depth_scale=scale,
            alignment=alignment,
            timings={"fit": tf - t0, "setup": t1 - tf, "solve": t2 - t1},
            warnings=messages,
            solve=solution.info,
        )

    @staticmethod
    def _frame_config(completer, mde_depth: np.ndarray, sparse: SparseDepth) -> DepthGPConfig:
        """The configuration of this frame: ``completer.config``, or fitted to the frame when ``config.fit``."""
        if not completer.config.fit:
            return completer.config
        from ..gp.fast import FastEngine
        from .marginal_fit import fit_hyperparameters

        if completer._fit_engine is None:
            engine = completer.engine
            completer._fit_engine = engine if isinstance(engine, FastEngine) else FastEngine()
        start = (completer.fitted or completer.config).replace(fit=False)
        fitted = fit_hyperparameters(mde_depth, sparse, start, engine=completer._fit_engine)
        completer.fitted = fitted
        return fitted.replace(fit=True)


class Balanced(Gaussian):
    """The paper's model: y = f(x) + noise for every MDE pixel (sigma_dl) and every point (sigma_meas)."""

    name = "balanced"


class Residual(Gaussian):
    """The aligned MDE is the prior mean; the GP models its correlated error, observed at the points."""

    name = "residual"


FORMULATIONS: dict[str, Formulation] = {f.name: f for f in (LogResidual(), Balanced(), Residual())}
"""Each formulation's strategy by the name ``DepthGPConfig.formulation`` holds."""


def mde_on_output(mde: np.ndarray, valid: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
    """The input MDE (H, W) on the output grid (Ho, Wo) (metres, 0 where it had no value)."""
    mde_out = resize_map(mde, out_shape)
    if tuple(out_shape) != mde.shape:
        mde_out = np.where(resize_map(valid.astype(np.float64), out_shape) > 0.999, mde_out, 0.0)
    return mde_out


def formulation_of(config: DepthGPConfig) -> Formulation:
    """The strategy of ``config.formulation`` (validated by `DepthGPConfig`)."""
    return FORMULATIONS[config.formulation]
