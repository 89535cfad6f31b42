"""Stage 7 of the default model: the variance at depth edges and its local calibration by the points (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    var = moments.variance
    h, w = frame.shape
    if config.assembly.edge_sigma > 0:
        window = 2 * int(np.ceil(max(frame.out_shape[0] / h, frame.out_shape[1] / w))) + 1
        edge = edge_range(moments.mde, window)  # its own array: scaled and squared in place
        edge *= config.assembly.edge_sigma * np.exp(screened.fit.log_scale)
        var = var + np.square(edge, out=edge)
    keep = screened.keep
    if config.calibration.reach is None or np.count_nonzero(keep) < config.calibration.min_points:
        return Calibrated(var, None)
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
    factor = local_variance_factor(
        frame.shape,
        frame.rows[keep],
        frame.cols[keep],
        zscores[keep],
        reach=config.calibration.reach,
        prior_points=config.calibration.prior_points,
        zscore_cap=config.calibration.zscore_cap,
        noise_share=shares[keep],
    )
    factor = frame.to_output(factor)
    if var is moments.variance:  # the moments' array is left as it was
        return Calibrated(var * factor, factor)
    var *= factor
    return Calibrated(var, factor)


def edge_range(depth: np.ndarray, window: int) -> np.ndarray:
    """Local depth range (max - min) over a window x window neighbourhood (OpenCV's dilate and erode), metres."""
    import cv2

    kernel = np.ones((window, window), np.uint8)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    return cv2.dilate(depth, kernel) - cv2.erode(depth, kernel)
