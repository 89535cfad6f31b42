"""Stage 2 of the default model: the frame's scales fitted on its points and the outliers screened (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..gp.fit import PointFit
from ..gp.model import DepthGPConfig
from ..gp.points import screen_points, start_screen_search
from .log_frame import LogFrame
from .mde_slope import Sloped
from .threads import single_threaded_blas

if TYPE_CHECKING:
    from ..gp._loo import SharedSearch


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


def screen(
    frame: LogFrame,
    sloped: Sloped,
    config: DepthGPConfig,
    previous: PointFit | None = None,
    search: SharedSearch | None = None,
) -> Screened:
    """Fits or raises the scales on the points and rejects those their neighbours contradict.

    A point at an MDE depth edge is judged with the edge's uncertainty (the same term the variance gets):
    there its neighbours may rightly disagree with it. ``previous`` (a `PointFit`) starts a fit's search;
    ``search``: the first round's neighbour search started before (`start_search`), None: searched here.
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
            search=search,
        )
    return Screened(fit, rejected, zscores, shares, noise)


def start_search(frame: LogFrame, config: DepthGPConfig) -> SharedSearch | None:
    """The screen's first neighbour search on the frame's points, started on a second thread (it needs only their
    positions) to run while the slope is fitted (`gpdepth3d.gp.points.start_screen_search`); None where it does not
    pay or the screen does not search."""
    if config.fit and frame.n < 3:  # `screen` fits nothing and screens nothing
        return None
    return start_screen_search(frame.rows, frame.cols, config.screen)


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
