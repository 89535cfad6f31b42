"""Stage 2 of the default model: the frame's scales fitted on its points and the outliers screened (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..gp.fit import PointFit
from ..gp.model import DepthGPConfig
from ..gp.points import screen_points
from .log_frame import LogFrame
from .mde_slope import Sloped
from .threads import single_threaded_blas


@dataclass(frozen=True)
class Screened:
    """The frame's scales and the points kept.

    Attributes:
        fit: l, s, tau, the global log scale b and its variance (`PointFit`).
        rejected: (N,) bool, the points rejected as outliers.
        zscores: (N,) their leave-one-out z-scores (0 when not screened).
        shares: (N,) the share of each point's predictive variance its stated noise makes.
        noise: (N,) the noise the points were judged with: theirs plus the edge term, log depth squared.
    """

    fit: PointFit
    rejected: np.ndarray
    zscores: np.ndarray
    shares: np.ndarray
    noise: np.ndarray

    @property
    def keep(self) -> np.ndarray:
        return ~self.rejected


def screen(frame: LogFrame, sloped: Sloped, config: DepthGPConfig, previous: PointFit | None = None) -> Screened:
    """Fits or raises the scales on the points and rejects those their neighbours contradict.

    A point at an MDE depth edge is judged with the edge's uncertainty (the same term the variance gets):
    there its neighbours may rightly disagree with it. ``previous`` (a `PointFit`) starts a fit's search.
    """
    n, resid = frame.n, sloped.resid
    noise = frame.noise
    if config.assembly.edge_sigma > 0:
        noise = frame.noise + (config.assembly.edge_sigma * (abs(sloped.a) * frame.edge)) ** 2
    s = config.outputscale
    b = float(np.median(resid)) if n else 0.0
    if config.fit and n < 3:  # too few to fit: the configured scales, the points' median as b
        fit = PointFit(config.lengthscale, s, config.nugget, b, s * s, n)
        return Screened(fit, np.zeros(n, dtype=bool), np.zeros(n), np.zeros(n), noise)
    start = None if config.fit else PointFit(config.lengthscale, s, config.nugget, b, s * s / max(n, 1), n)
    around = (previous.lengthscale, previous.eta) if previous is not None else None
    with single_threaded_blas():
        fit, rejected, zscores, shares = screen_points(
            frame.rows,
            frame.cols,
            resid,
            noise,
            threshold=config.screen.outlier_threshold,
            nu=config.nu,
            options=config.screen,
            start=start,
            around=around,
            raise_outputscale=start is not None and config.screen.raise_outputscale,
            stated=frame.stated,
        )
    return Screened(fit, rejected, zscores, shares, noise)


def follow_slope(screened: Screened, before: Sloped, after: Sloped, config: DepthGPConfig) -> Screened:
    """The global scale b after the slope's refit, by the statistic that set it: fixed scales, all points'
    median residual; fitted, moved by the kept points' median change."""
    if after is before:
        return screened
    if config.fit:
        b = screened.fit.log_scale + float(np.median((after.resid - before.resid)[screened.keep]))
    else:
        b = float(np.median(after.resid))
    return replace(screened, fit=replace(screened.fit, log_scale=b))
