"""What a frame's input cannot support, as one sentence each (`DepthPosterior.warnings`).

The thresholds below only decide when to warn; none of them changes a posterior.
"""

from __future__ import annotations

import numpy as np

from ..gp.distance import taxicab_transform
from ..gp.model import DepthGPConfig
from ..measurements import SparseDepth
from .log_frame import LogFrame
from .screen import Screened
from .mde_slope import Sloped


class PosteriorWarning(UserWarning):
    """The input of a frame cannot support a confident posterior (see `DepthPosterior.warnings`)."""


SCALE_WARN_FACTOR = 2.0
"""The MDE's scale disagrees with the points beyond this factor (either way)."""
FEW_POINTS = 10
"""Fewer kept points than this: the posterior is mostly the MDE with the prior's variance."""
COVERAGE_WARN = 0.5
"""Warn when more than this share of the image is far from every point..."""
COVERAGE_REACH = 6.0
"""...far meaning beyond max(H, W) / this many pixels (taxicab)."""
REJECTED_WARN = 0.2
"""Warn when more than this share of the points is rejected."""
SLOPE_WARN = 0.2
"""A fitted MDE slope below this: the MDE's shape is barely used (disparity passed as depth?)."""
OUTPUTSCALE_WARN = 1.25
"""The points raised s above this factor of the configured s."""


def log_residual_warnings(
    frame: LogFrame, sloped: Sloped, screened: Screened, config: DepthGPConfig, name: str
) -> tuple[str, ...]:
    """The default model's warnings of one frame (``name``: "frame X: " or "")."""
    fit, rejected = screened.fit, screened.rejected
    n_kept = int(np.count_nonzero(~rejected))
    scale = float(np.exp(fit.log_scale))
    messages = []
    if frame.n and not 1.0 / SCALE_WARN_FACTOR <= scale <= SCALE_WARN_FACTOR:
        messages.append(scale_message(name, scale, float(np.median(frame.base))))
    if n_kept < FEW_POINTS:
        messages.append(
            f"{name}only {n_kept} usable points: the posterior is the MDE with the prior's variance "
            f"(s = {fit.outputscale:.2f} in log depth) away from them"
        )
    elif (far := _far_share(frame, ~rejected)) > COVERAGE_WARN:
        reach = max(frame.shape) / COVERAGE_REACH
        messages.append(
            f"{name}the points cover little of the image: {far:.0%} of it is "
            f"farther than {reach:.0f} px from any point (the variance grows there)"
        )
    if sloped.fit is not None and sloped.a < SLOPE_WARN:
        messages.append(
            f"{name}the points follow the MDE's depth differences only weakly (slope {sloped.a:.2f} in log "
            f"depth; 1 = fully): its shape is barely used, check that it is depth (not disparity) of this image"
        )
    if not config.fit and fit.outputscale > OUTPUTSCALE_WARN * config.outputscale:
        messages.append(
            f"{name}the MDE's log-depth error at the points has s = {fit.outputscale:.2f}, above the "
            f"configured {config.outputscale:.2f}: the variance is widened to match (is the MDE out of its "
            f"range here?)"
        )
    if frame.n and rejected.mean() > REJECTED_WARN:
        messages.append(f"{name}{int(rejected.sum())} of {frame.n} points ({rejected.mean():.0%}) rejected as outliers")
    return tuple(messages)


def _far_share(frame: LogFrame, keep: np.ndarray) -> float:
    """Share of the GP grid farther than max(H, W) / COVERAGE_REACH pixels (taxicab) from every kept point."""
    far = taxicab_transform(frame.shape, frame.rows[keep], frame.cols[keep]) > max(frame.shape) / COVERAGE_REACH
    return float(np.mean(far))


def scale_message(name: str, factor: float, median_mde: float) -> str:
    """The warning for an MDE whose scale disagrees with the points by more than SCALE_WARN_FACTOR."""
    return (
        f"{name}the MDE's scale disagrees with the points by a factor of {factor:.2f} "
        f"(median MDE depth {median_mde:.2f} m): check the MDE's units or model"
    )


def gaussian_warnings(
    mean: np.ndarray, mde: np.ndarray, valid: np.ndarray, grid_sparse: SparseDepth, name: str
) -> tuple[str, ...]:
    """What a posterior of the Gaussian formulations (``balanced``, ``residual``) cannot support.

    These models are Gaussian in metres (the paper's model as the paper states it), so nothing keeps their
    mean positive: pixels at or below 0 m are counted, not clipped. The MDE's scale is checked as for the
    default model.
    """
    messages = []
    rows, cols = grid_sparse.v.astype(np.int64), grid_sparse.u.astype(np.int64)
    seen = valid[rows, cols]
    if seen.any():
        ratio = float(np.median(grid_sparse.depth[seen] / mde[rows[seen], cols[seen]]))
        if not 1.0 / SCALE_WARN_FACTOR <= ratio <= SCALE_WARN_FACTOR:
            messages.append(scale_message(name, ratio, float(np.median(mde[valid]))))
    low = int(np.count_nonzero(~(mean > 0)))
    if low:
        messages.append(
            f"{name}{low} pixels ({low / mean.size:.1%}) have a posterior mean <= 0 m or not finite (a Gaussian model "
            f"in metres; the default log_residual model keeps depths positive): mask them before use"
        )
    return tuple(messages)
