"""One metric row: a prediction's depth metrics and the calibration of its variance against ground truth."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..errors import InvalidInputError
from ..metrics import METRIC_NAMES, calibration_metrics, depth_metrics

CALIBRATION_NAMES: tuple[str, ...] = ("nll", "coverage_1sigma", "coverage_2sigma", "z_rms")
"""The calibration keys of a row (`gpdepth3d.metrics.calibration_metrics` without its count ``n``)."""


def metric_row(
    mean: np.ndarray,
    variance: np.ndarray | None,
    gt: np.ndarray,
    *,
    depth_keys: Sequence[str] = METRIC_NAMES,
    calibration_keys: Sequence[str] = CALIBRATION_NAMES,
) -> dict[str, float]:
    """The metrics of one prediction: `depth_metrics` then `calibration_metrics` values, by key.

    Args:
        mean: (H, W) predicted depth, metres.
        variance: (H, W) predicted variance, m^2, or None for a method without one.
        gt: (H, W) ground-truth depth, metres (0 = none).
        depth_keys: Keys of `depth_metrics` to keep (``"n"`` = the number of ground-truth pixels).
        calibration_keys: Keys of `calibration_metrics` to keep; NaN each when ``variance`` is
            None or not finite everywhere.

    Returns:
        {key: value} in the order depth_keys, calibration_keys.

    Raises:
        InvalidInputError: a key that the metric functions do not compute.
    """
    depth = depth_metrics(mean, gt)
    unknown = [k for k in depth_keys if k not in depth]
    if unknown:
        raise InvalidInputError("depth_keys", f"keys of depth_metrics {tuple(depth)}", unknown)
    allowed_cal = CALIBRATION_NAMES + ("n",)
    unknown = [k for k in calibration_keys if k not in allowed_cal]
    if unknown:
        raise InvalidInputError("calibration_keys", f"keys of calibration_metrics {allowed_cal}", unknown)
    row = {k: depth[k] for k in depth_keys}
    if variance is not None and np.all(np.isfinite(variance)):
        cal = calibration_metrics(mean, variance, gt)
        row.update({k: cal[k] for k in calibration_keys})
    else:
        row.update({k: math.nan for k in calibration_keys})
    return row
