"""The default model (``log_residual``) as a pipeline of named stages (docs/model.md).

fit slope (`slope`) -> screen points (`screen`) -> lattice (`lattice`) -> solve (`solve`) -> sub-lattice
detail (`detail`) -> assemble (`assemble`) -> calibrate (`calibrate`); each stage a function returning a
small dataclass.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..gp.engine import SolveInfo
from ..gp.fit import PointFit
from ..gp.model import DepthGPConfig
from ..mde.align import AlignmentResult
from .assemble import assemble_depth
from .calibrate import calibrate
from .detail import add_detail
from .diagnostics import log_residual_warnings
from .lattice import build_lattice
from .log_frame import LogFrame
from .screen import follow_slope, screen, start_search
from .mde_slope import fit_slope, refit_slope
from .solve import solve_field
from .threads import single_threaded_blas


@dataclass(frozen=True)
class LogResidualPosterior:
    """The default model's posterior of one frame and how it was reached.

    Attributes:
        mean: (Ho, Wo) posterior mean depth, metres.
        variance: (Ho, Wo) its variance, m^2 (NaN when not asked for).
        fit: The frame's scales and global log scale (`PointFit`).
        config: The config with the frame's l, s and tau.
        rejected: (N,) bool, the points rejected as outliers.
        warnings: What the input cannot support, one sentence each.
        alignment: exp(b) as the MDE's scale.
        timings: Seconds of "fit" (slope and screen) and "solve" (the other stages).
        stages: Seconds of the stages inside "solve": "lattice", "engine" (the engine's call), "detail",
            "assemble", "calibrate".
        info: The engine's facts of the call.
        slope: The MDE's fitted log-depth slope a.
    """

    mean: np.ndarray
    variance: np.ndarray
    fit: PointFit
    config: DepthGPConfig
    rejected: np.ndarray
    warnings: tuple[str, ...]
    alignment: AlignmentResult
    timings: dict
    info: SolveInfo
    slope: float
    stages: dict


def log_residual_posterior(
    engine,
    frame: LogFrame,
    config: DepthGPConfig,
    *,
    variance: bool = True,
    name: str = "",
    previous: PointFit | None = None,
    stride: int | None = None,
) -> LogResidualPosterior:
    """Runs the default model's stages on one frame; ``previous`` starts the scales' search (sequences),
    ``stride`` fixes the lattice's (`gpdepth3d.gp.EngineConfig.lattice_stride`; None: automatic)."""
    t0 = time.perf_counter()
    # One block for the frame: every stage's small dense algebra and the engine's numeric sections run with one
    # BLAS thread, and the blocks inside it are then free (each outermost block sets and restores every library).
    with single_threaded_blas():
        search = start_search(frame, config)  # on a second thread while the slope is fitted
        first = fit_slope(frame, config)
        screened = screen(frame, first, config, previous, search)
        sloped = refit_slope(frame, first, screened.rejected, config)
        screened = follow_slope(screened, first, sloped, config)
        t1 = time.perf_counter()
        lattice = build_lattice(frame, sloped, screened, config, stride)
        ta = time.perf_counter()
        field = solve_field(engine, lattice)
        tb = time.perf_counter()
        field = add_detail(field, lattice, frame, config)
        tc = time.perf_counter()
        moments = assemble_depth(frame, sloped, screened, lattice, field, config)
        td = time.perf_counter()
        var = (
            calibrate(moments, frame, sloped, screened, config).variance
            if variance
            else np.full(frame.out_shape, np.nan)
        )
        t2 = time.perf_counter()
    stages = {"lattice": ta - t1, "engine": tb - ta, "detail": tc - tb, "assemble": td - tc, "calibrate": t2 - td}
    fit = screened.fit
    return LogResidualPosterior(
        mean=moments.mean,
        variance=var,
        fit=fit,
        config=config.replace(lengthscale=fit.lengthscale, outputscale=fit.outputscale, nugget=fit.nugget),
        rejected=screened.rejected,
        warnings=log_residual_warnings(frame, sloped, screened, config, name),
        alignment=AlignmentResult(float(np.exp(fit.log_scale)), 0.0, int(np.count_nonzero(screened.keep))),
        timings={"fit": t1 - t0, "solve": t2 - t1},
        stages=stages,
        info=field.info,
        slope=sloped.a,
    )
