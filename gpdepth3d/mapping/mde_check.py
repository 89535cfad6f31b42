"""Is a frame's refinement better than its rescaled MDE? A held-out test, and the MDE fallback when it is not.

A frame's points can mislead the GP: poses off by more than their sigma says, tracks on moving or
specular surfaces, a local map placed by a wrong pose. The map must then not be worse than the
network's depth alone. `held_out_check` holds out a share of the frame's points, runs the GP on the
others, and compares how well the posterior median and the MDE rescaled by one median (fitted on the
same points) predict the held-out depths (median absolute log error: robust to the outliers that
such points contain). The held-out GP runs on a coarser output grid (`held_out_shape`): only its
values at the held-out points are read. Where the GP does not predict them better, `mde_fallback`
gives the rescaled MDE with the variance its residuals at all points show, and the `Mapper` fuses
that instead and says so (`FrameResult.mde_fallback`, a warning).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from ..measurements import SparseDepth
from .map_scale import fast_median

MAD_TO_SIGMA = 1.4826
"""The standard deviation of a normal distribution over its median absolute deviation."""

HELD_OUT_COARSENING = 2
"""Working-resolution pixels per side of one pixel of the held-out GP's output (`held_out_shape`).

The check reads that posterior only at the held-out points (each at the coarse pixel it falls in); a
coarser output skips most of the read-out and assembly of a full-size one and its sub-lattice detail
(the GP's lattice then follows `gpdepth3d.completion.lattice.lattice_stride`'s rule for such outputs),
while the fit and outlier screen of the kept points, which make most of the prediction, are unchanged.
"""


@dataclass(frozen=True)
class HeldOutCheck:
    """The held-out comparison of a frame's GP posterior with its rescaled MDE.

    Attributes:
        held_out: Points held out (0: not enough points to test; the GP is kept).
        gp_error: Median |log(posterior median / point depth)| at the held-out points (NaN untested).
        mde_error: The same for the rescaled MDE.
        mde_scale: The factor the MDE is multiplied by: median point depth / MDE depth at the points.
        mde_sigma: Relative depth sigma of the rescaled MDE: the robust spread (MAD) of
            log(point depth / rescaled MDE) at all points.
    """

    held_out: int
    gp_error: float
    mde_error: float
    mde_scale: float
    mde_sigma: float

    @property
    def gp_better(self) -> bool:
        """The GP predicted the held-out points better than the rescaled MDE (True when untested)."""
        return self.held_out == 0 or bool(self.gp_error < self.mde_error)

    def describe(self, kid: object) -> str:
        """One sentence for `FrameResult.warnings` when the frame falls back to the MDE."""
        return (
            f"frame {kid}: its points' GP predicts {self.held_out} held-out points worse than the MDE rescaled by "
            f"one median (median |log error| {self.gp_error:.3f} against {self.mde_error:.3f}): fused as the "
            f"rescaled MDE (x{self.mde_scale:.3f}, sigma {self.mde_sigma:.0%} of the depth)"
        )


def split_held_out(n: int, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(kept, held out) indices of ``n`` points: ``round(fraction * n)`` held out at random, seeded, both sorted."""
    if not 0 <= fraction < 1:
        raise InvalidInputError("fraction", "a share in [0, 1)", fraction)
    order = np.random.default_rng(abs(int(seed))).permutation(int(n))
    k = int(round(fraction * n))
    return np.sort(order[k:]), np.sort(order[:k])


def sample_at(image: np.ndarray, sparse: SparseDepth) -> np.ndarray:
    """``image`` (any resolution of the points' image) at each point's nearest pixel."""
    h, w = image.shape
    sy, sx = h / sparse.image_size[0], w / sparse.image_size[1]
    iu = np.clip(np.floor(sparse.u * sx).astype(np.int64), 0, w - 1)
    iv = np.clip(np.floor(sparse.v * sy).astype(np.int64), 0, h - 1)
    return image[iv, iu]


def _log_errors(prediction: np.ndarray, depth: np.ndarray) -> np.ndarray:
    ok = np.isfinite(prediction) & (prediction > 0) & np.isfinite(depth) & (depth > 0)
    return np.abs(np.log(prediction[ok] / depth[ok]))


def held_out_shape(shape: tuple[int, int], coarsening: int = HELD_OUT_COARSENING) -> tuple[int, int]:
    """The output shape of the held-out GP for a (h, w) working grid: each side divided by ``coarsening``
    (rounded up, at least 1 pixel)."""
    if int(coarsening) != coarsening or coarsening < 1:
        raise InvalidInputError("coarsening", "an integer >= 1", coarsening)
    c = int(coarsening)
    return max(1, -(-int(shape[0]) // c)), max(1, -(-int(shape[1]) // c))


def rescaled_mde(mde: np.ndarray, points: SparseDepth) -> tuple[float, float]:
    """(scale, relative sigma) of the MDE against the points: median ratio, and the MAD of the log ratios after it.

    Returns (1, NaN) when no point has an MDE depth.
    """
    at = sample_at(mde, points)
    ok = np.isfinite(at) & (at > 0) & (points.depth > 0)
    if not ok.any():
        return 1.0, float("nan")
    log_ratio = np.log(points.depth[ok] / at[ok])
    shift = fast_median(log_ratio)
    return float(np.exp(shift)), MAD_TO_SIGMA * fast_median(np.abs(log_ratio - shift))


def held_out_check(refine, mde: np.ndarray, points: SparseDepth, *, fraction: float, min_held_out: int, seed: int):
    """Holds out ``fraction`` of the points, refines with the others, and scores both predictors at them.

    Args:
        refine: ``(kept points) -> posterior median depth`` at any resolution of the points' image (the
            frame's GP; e.g. at `held_out_shape`), sampled at each held-out point's pixel (`sample_at`).
        mde: (h, w) MDE depth at the working resolution, metres (0: none).
        points: The frame's measurements (any resolution of the same image).
        fraction: Share of the points held out.
        min_held_out: Fewer held-out points than this: not tested (``held_out`` 0).
        seed: Seed of the held-out choice (the frame's id: repeatable).

    Returns:
        `HeldOutCheck`; the rescaled MDE's scale and sigma come from all points.
    """
    scale, sigma = rescaled_mde(mde, points)
    kept, held = split_held_out(len(points), fraction, seed)
    if held.size < min_held_out or kept.size < min_held_out:
        return HeldOutCheck(0, float("nan"), float("nan"), scale, sigma)
    test = points.subset(held)
    fit_scale, _ = rescaled_mde(mde, points.subset(kept))
    gp = _log_errors(sample_at(refine(points.subset(kept)), test), test.depth)
    md = _log_errors(fit_scale * sample_at(mde, test), test.depth)
    if gp.size < min_held_out or md.size < min_held_out:
        return HeldOutCheck(0, float("nan"), float("nan"), scale, sigma)
    return HeldOutCheck(int(held.size), fast_median(gp), fast_median(md), scale, sigma)


def mde_fallback(mde: np.ndarray, check: HeldOutCheck) -> tuple[np.ndarray, np.ndarray]:
    """The rescaled MDE and its variance, ``(mde_sigma * depth)^2`` (m^2), where the GP did not help.

    The depth is the median of the log-normal the rescaled MDE stands for; pixels without MDE depth stay 0.
    """
    depth = np.where(mde > 0, mde * check.mde_scale, 0.0)
    sigma = check.mde_sigma if np.isfinite(check.mde_sigma) else 0.0
    return depth, np.square(sigma * depth)
