"""Alignment of an MDE depth map to sparse metric measurements (scale, or scale and shift).

Robust: a few wrong measurements (a LiDAR point seen through glass, a mismatched SLAM feature)
must not drag the whole map. Both fits minimise a Huber loss by iteratively reweighted least
squares, started from the median ratio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import InvalidInputError


@dataclass(frozen=True)
class AlignmentResult:
    """depth_aligned = scale * depth + shift (metres); ``n_used`` points supported the fit."""

    scale: float
    shift: float
    n_used: int

    def apply(self, depth: np.ndarray) -> np.ndarray:
        """Applies the fit to a depth map, keeping invalid (<= 0) pixels at 0."""
        d = np.asarray(depth, dtype=np.float64)
        out = self.scale * d + self.shift
        return np.where(d > 0, np.maximum(out, 1e-6), 0.0)


def align_depth(
    mde_values: np.ndarray,
    measured: np.ndarray,
    mode: Literal["none", "scale", "scale_shift"] = "scale",
    *,
    huber: float = 0.05,
    iterations: int = 10,
) -> AlignmentResult:
    """Fits ``measured ~ scale * mde + shift`` robustly.

    Args:
        mde_values: (N,) MDE depths at the measured pixels, metres (or relative units).
        measured: (N,) metric depths, metres.
        mode: "none" (identity), "scale" or "scale_shift".
        huber: Huber threshold as a fraction of the measured depth.
        iterations: IRLS iterations.

    Returns:
        The fit; the identity when fewer than 1 (scale) or 3 (scale_shift) usable points exist.
    """
    x = np.asarray(mde_values, dtype=np.float64).ravel()
    y = np.asarray(measured, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise InvalidInputError("mde_values, measured", "arrays of one length", (x.shape, y.shape))
    if mode not in ("none", "scale", "scale_shift"):
        raise InvalidInputError("mode", "'none', 'scale' or 'scale_shift'", mode)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    x, y = x[ok], y[ok]
    if mode == "none" or x.size == 0 or (mode == "scale_shift" and x.size < 3):
        return AlignmentResult(1.0, 0.0, 0)
    scale, shift = float(np.median(y / x)), 0.0
    for _ in range(iterations):
        r = y - (scale * x + shift)
        c = huber * y
        w = np.where(np.abs(r) <= c, 1.0, c / np.maximum(np.abs(r), 1e-12)) / y**2  # relative error
        if mode == "scale":
            scale = float(np.sum(w * x * y) / np.sum(w * x * x))
        else:
            A = np.stack([x, np.ones_like(x)], axis=1)
            sol, *_ = np.linalg.lstsq(A * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)
            scale, shift = float(sol[0]), float(sol[1])
    if not np.isfinite(scale) or scale <= 0:
        scale, shift = float(np.median(y / x)), 0.0
    return AlignmentResult(scale, shift, int(x.size))
