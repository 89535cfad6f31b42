"""Stage 7 of the default model: the variance at depth edges and its local calibration by the points (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, uint64

from ..gp.local_calibration import local_variance_factor
from ..gp.model import DepthGPConfig
from ..gp.points import loo_zscores
from .assemble import DepthMoments
from .log_frame import LogFrame
from .screen import Screened
from .mde_slope import Sloped
from .threads import single_threaded_blas


@dataclass(frozen=True)
class Calibrated:
    """The posterior variance after the calibration stage.

    Attributes:
        variance: (Ho, Wo) m^2, >= 0.
        factor: (Ho, Wo) the local calibration's factor on the model's variance (None when off).
    """

    variance: np.ndarray
    factor: np.ndarray | None


def calibrate(
    moments: DepthMoments, frame: LogFrame, sloped: Sloped, screened: Screened, config: DepthGPConfig
) -> Calibrated:
    """Adds the edge term (``assembly.edge_sigma`` x the MDE's local depth range, scaled by exp(b)) and multiplies by the
    local factor of the points' squared z-scores (`gpdepth3d.gp.local_calibration`; frames with fewer than
    ``calibration.min_points`` kept points keep the model's variance)."""
    factor = None
    keep = screened.keep
    if config.calibration.reach is not None and np.count_nonzero(keep) >= config.calibration.min_points:
        factor = frame.to_output(_local_factor(frame, sloped, screened, config))
    var = moments.variance  # the moments' array is left as it was
    if config.assembly.edge_sigma > 0:
        h, w = frame.shape
        half = int(np.ceil(max(frame.out_shape[0] / h, frame.out_shape[1] / w)))
        scale = config.assembly.edge_sigma * np.exp(screened.fit.log_scale)
        out = np.empty(var.shape)
        mde = np.ascontiguousarray(moments.mde, dtype=np.float64)
        use = factor is not None
        _edge_variance(var, mde, half, float(scale), factor if use else var, use, out)
        return Calibrated(out, factor)
    return Calibrated(var if factor is None else var * factor, factor)


def _local_factor(frame: LogFrame, sloped: Sloped, screened: Screened, config: DepthGPConfig) -> np.ndarray:
    """The local calibration's factor on the GP grid, from the kept points' z-scores (computed here when no screen
    ran)."""
    keep = screened.keep
    zscores, shares = screened.zscores, screened.shares
    if config.screen.outlier_threshold is None:  # no screen ran: the z-scores computed here
        with single_threaded_blas():
            zscores, shares = loo_zscores(
                frame.rows,
                frame.cols,
                sloped.resid,
                screened.noise,
                screened.fit,
                nu=config.nu,
                neighbours=config.screen.neighbours,
                stated=frame.stated,
            )
    return local_variance_factor(
        frame.shape,
        frame.rows[keep],
        frame.cols[keep],
        zscores[keep],
        reach=config.calibration.reach,
        prior_points=config.calibration.prior_points,
        zscore_cap=config.calibration.zscore_cap,
        noise_share=shares[keep],
    )


@njit(cache=True, nogil=True)
def _edge_variance(var, mde, half, scale, factor, use_factor, out):  # pragma: no cover - compiled
    """out = (var + (scale x edge range)^2) x factor in one pass over the rows (the factor only with ``use_factor``),
    the edge range being the MDE's max - min over the (2 half + 1)^2 window around each pixel (borders: the window
    cut at the map's edge): per row, each column's max and min over the window's rows, then over the window's
    columns, each step a loop over the row that vectorises."""
    h, w = mde.shape
    col_hi, col_lo, hi, lo = np.empty(w), np.empty(w), np.empty(w), np.empty(w)
    for i_ in range(h):
        i = uint64(i_)  # indices >= 0 as unsigned integers: no check for negative ones, so the loops vectorise
        r0, r1 = max(i_ - half, 0), min(i_ + half, h - 1)
        first = mde[uint64(r0)]
        for j in range(w):
            col_hi[j] = first[j]
            col_lo[j] = first[j]
        for r in range(r0 + 1, r1 + 1):
            row = mde[uint64(r)]
            for j in range(w):
                col_hi[j] = max(col_hi[j], row[j])
                col_lo[j] = min(col_lo[j], row[j])
        hi[:] = col_hi
        lo[:] = col_lo
        for d in range(1, half + 1):
            for j_ in range(w - d):
                j = uint64(j_)
                hi[j] = max(hi[j], col_hi[j + d])
                lo[j] = min(lo[j], col_lo[j + d])
            for j_ in range(d, w):
                j = uint64(j_)
                hi[j] = max(hi[j], col_hi[j - d])
                lo[j] = min(lo[j], col_lo[j - d])
        vi, fi, oi = var[i], factor[i], out[i]
        for j in range(w):
            e = (hi[j] - lo[j]) * scale
            v = vi[j] + e * e
            oi[j] = v * fi[j] if use_factor else v
