"""Alignment of an MDE depth map to sparse metric measurements (scale, or scale and shift).

Robust: a few wrong measurements (a LiDAR point seen through glass, a mismatched SLAM feature)
must not drag the whole map. Both fits minimise a Huber loss by iteratively reweighted least
squares, started from the median ratio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from ..errors import InvalidInputError

if TYPE_CHECKING:
    from ..measurements import SparseDepth


@dataclass(frozen=True)
class AlignmentResult:
    """The fitted map; ``n_used`` points supported the fit.

    ``space="depth"``: depth_aligned = scale * depth + shift (metres).
    ``space="inverse"``: 1 / depth_aligned = scale / depth + shift (shift in 1/m), the natural
    fit for networks that predict affine-invariant inverse depth (disparity).
    """

    scale: float
    shift: float
    n_used: int
    space: Literal["depth", "inverse"] = "depth"

    def apply(self, depth: np.ndarray) -> np.ndarray:
        """Applies the fit to a depth map, keeping invalid (<= 0) pixels at 0."""
        d = np.asarray(depth, dtype=np.float64)
        if self.space == "inverse":
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = self.scale / np.where(d > 0, d, 1.0) + self.shift
                out = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0)
            return np.where((d > 0) & (inv > 0), out, 0.0)
        out = self.scale * d + self.shift
        return np.where(d > 0, np.maximum(out, 1e-6), 0.0)


def align_depth(
    mde_values: np.ndarray,
    measured: np.ndarray,
    mode: Literal["none", "scale", "scale_shift"] = "scale",
    *,
    huber: float = 0.05,
    iterations: int = 10,
    space: Literal["depth", "inverse"] = "depth",
) -> AlignmentResult:
    """Fits ``measured ~ scale * mde + shift`` robustly.

    Args:
        mde_values: (N,) MDE depths at the measured pixels, metres (or relative units).
        measured: (N,) metric depths, metres.
        mode: "none" (identity), "scale" or "scale_shift".
        huber: Huber threshold as a fraction of the measured depth.
        iterations: IRLS iterations.
        space: "depth" fits depths; "inverse" fits inverse depths (1/measured ~ scale / mde +
            shift), for relative inverse-depth networks. Residuals are relative in both.

    Returns:
        The fit; the identity when fewer than 1 (scale) or 3 (scale_shift) usable points exist.
    """
    x = np.asarray(mde_values, dtype=np.float64).ravel()
    y = np.asarray(measured, dtype=np.float64).ravel()
    if space not in ("depth", "inverse"):
        raise InvalidInputError("space", "'depth' or 'inverse'", space)
    if x.shape != y.shape:
        raise InvalidInputError("mde_values, measured", "arrays of one length", (x.shape, y.shape))
    if mode not in ("none", "scale", "scale_shift"):
        raise InvalidInputError("mode", "'none', 'scale' or 'scale_shift'", mode)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    x, y = x[ok], y[ok]
    if mode == "none" or x.size == 0 or (mode == "scale_shift" and x.size < 3):
        return AlignmentResult(1.0, 0.0, 0, space)
    if space == "inverse":
        x, y = 1.0 / x, 1.0 / y
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
    return AlignmentResult(scale, shift, int(x.size), space)


def align_to_sparse(
    depth: np.ndarray,
    sparse: "SparseDepth",
    *,
    mode: Literal["none", "scale", "scale_shift"] = "scale",
    space: Literal["depth", "inverse"] = "depth",
    huber: float = 0.05,
) -> tuple[np.ndarray, AlignmentResult]:
    """Aligns a dense (relative) depth map to sparse metric measurements.

    Args:
        depth: (H, W) depth map (metres or relative units; 0 = none).
        sparse: Measurements of the same image (any resolution with the same aspect).
        mode: "none", "scale" or "scale_shift".
        space: Fit in "depth" or "inverse" depth (see `align_depth`).
        huber: Huber threshold (fraction of the measured depth).

    Returns:
        The (H, W) aligned depth in metres (0 where ``depth`` is 0) and the fit.
    """
    from ..errors import ShapeError, describe
    from ..measurements import SparseDepth

    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError("depth", "a 2-D (H, W) depth map", describe(d))
    if not isinstance(sparse, SparseDepth):
        raise InvalidInputError("sparse", "a SparseDepth", type(sparse).__name__)
    d = np.where(np.isfinite(d), d, 0.0)
    g = sparse.rasterize(d.shape)
    vals = d[g.v.astype(np.int64), g.u.astype(np.int64)]
    fit = align_depth(vals, g.depth, mode, huber=huber, space=space)
    return fit.apply(d), fit
