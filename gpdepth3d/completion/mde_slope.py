"""Stage 1 of the default model: the MDE's log-depth slope a of this frame (`gpdepth3d.gp.slope`, docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..gp.model import DepthGPConfig, Kernel
from ..gp.slope import SlopeFit, fit_mde_slope
from .log_frame import LogFrame
from .threads import single_threaded_blas


@dataclass(frozen=True)
class Sloped:
    """The MDE re-sloped by the frame's fitted slope.

    Attributes:
        fit: The slope fit (`SlopeFit`), None when the slope is fixed at 1.
        raw_log_mde: (H, W) the frame's log MDE depth, before the slope.
        resid: (N,) the points' log residuals against the re-sloped one, log z - log MDE'.
    """

    fit: SlopeFit | None
    raw_log_mde: np.ndarray
    resid: np.ndarray

    @cached_property
    def log_mde(self) -> np.ndarray:
        """(H, W) the re-sloped log MDE depth, c + a (log MDE - c), computed when first asked for (a slope that
        is fitted again never needs its own)."""
        return self.raw_log_mde if self.fit is None else self.fit.apply(self.raw_log_mde)

    @property
    def a(self) -> float:
        """The slope (1 when not fitted)."""
        return self.fit.slope if self.fit is not None else 1.0


def fit_slope(frame: LogFrame, config: DepthGPConfig, use: np.ndarray | None = None) -> Sloped:
    """Fits the slope on the points ``use`` (default all) with the edge term added to their noise."""
    at = frame.log_mde_at
    if config.slope.prior_sigma is None or frame.n < config.slope.min_points:
        return Sloped(None, frame.log_mde, frame.log_z - at)
    noise = (
        frame.noise + (config.assembly.edge_sigma * frame.edge) ** 2 if config.assembly.edge_sigma > 0 else frame.noise
    )
    points = (frame.rows, frame.cols, frame.log_z, at, noise)
    kernel = Kernel(config.nu, config.lengthscale, config.outputscale)
    with single_threaded_blas():
        fit = fit_mde_slope(
            *points,
            kernel,
            config.nugget,
            prior_sigma=config.slope.prior_sigma,
            max_points=config.slope.max_points,
            huber=config.slope.huber,
            iterations=config.slope.iterations,
            use=use,
        )
    return Sloped(fit, frame.log_mde, frame.log_z - fit.apply(at))


def refit_slope(frame: LogFrame, sloped: Sloped, rejected: np.ndarray, config: DepthGPConfig) -> Sloped:
    """The slope fitted again without the points the screen rejected (one point at a tenth of its depth can
    still tilt a robust fit); ``sloped`` itself when nothing was rejected or too few points are left."""
    keep = ~rejected
    if sloped.fit is None or keep.all() or np.count_nonzero(keep) < config.slope.min_points:
        return sloped
    return fit_slope(frame, config, keep)
