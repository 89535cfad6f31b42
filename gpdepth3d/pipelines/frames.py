"""One frame's inputs on a GP grid: the MDE shrunk to the grid, the points split into input pool and ground truth.

The pieces every protocol builds its frames from (`gpdepth3d.evaluation.kitti_protocol`,
`gpdepth3d.pipelines.batch.HoldoutInputs`):

* `mde_to_grid`: a full-resolution MDE map on the 1/``factor`` grid, cropped to whole blocks and
  area-averaged (the blocks of `gpdepth3d.measurements.downsample_depth`).
* `holdout_lidar`: a full-resolution sparse depth map (projected LiDAR, SLAM points) shrunk to the
  grid keeping the closest point per block, then a seeded share of the grid's points held out as
  ground truth (`gpdepth3d.sampling.holdout_split`), at the grid and at full resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..depthmap import resize_map
from ..errors import EmptyInputError, InvalidInputError, ShapeError, describe
from ..measurements import SparseDepth, downsample_depth
from ..sampling import SeedLike, holdout_split


def _check_factor(factor) -> int:
    if isinstance(factor, (bool, np.bool_)) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise InvalidInputError("factor", "an integer >= 1", factor)
    return int(factor)


def mde_to_grid(mde_depth: np.ndarray, factor: int) -> np.ndarray:
    """An MDE map at the image resolution on the 1/``factor`` GP grid (area averaging per block).

    The map is cropped to whole ``factor`` x ``factor`` blocks first (trailing rows/columns dropped,
    as `gpdepth3d.measurements.downsample_depth` drops them), so grid pixel (i, j) is the mean of
    the block rows ``i*factor .. i*factor+factor-1``, columns likewise.

    Args:
        mde_depth: (H, W) MDE depth, metres.
        factor: Integer block size >= 1 (1 = a float64 copy of the map).

    Returns:
        (H // factor, W // factor) float64 map, metres.

    Raises:
        ShapeError: the map is not 2-D or smaller than one block.
        InvalidInputError: ``factor`` is not an integer >= 1.
    """
    factor = _check_factor(factor)
    d = np.asarray(mde_depth, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] < factor or d.shape[1] < factor:
        raise ShapeError("mde_depth", f"an (H, W) map of at least one {factor}x{factor} block", describe(d))
    h, w = d.shape[0] // factor, d.shape[1] // factor
    crop = np.ascontiguousarray(d[: h * factor, : w * factor])
    return crop.copy() if factor == 1 else resize_map(crop, (h, w), shrink="area", grow="area")


@dataclass(frozen=True)
class HoldoutLidar:
    """Sparse depth split into input pool and ground truth at two resolutions.

    Attributes:
        available: Points that may be given as input, on the (h, w) grid.
        gt_grid: (h, w) held-out depth on the grid, metres (0 = none).
        gt_full: (h * factor, w * factor) full-resolution depth inside held-out blocks (0 = none).
        n_grid: Number of points on the grid before the split.
    """

    available: SparseDepth
    gt_grid: np.ndarray
    gt_full: np.ndarray
    n_grid: int


def holdout_lidar(lidar_depth: np.ndarray, *, factor: int = 3, holdout: float = 0.2, rng: SeedLike = 0) -> HoldoutLidar:
    """Shrinks a sparse depth map (closest point per block) and holds out a share of it.

    Args:
        lidar_depth: (H, W) projected LiDAR (or any sparse) z-depth, metres (0/NaN = no point).
        factor: Block size; the grid is (H // factor, W // factor), trailing rows/columns dropped.
        holdout: Share of the grid's points held out, in (0, 1).
        rng: Seed or Generator of the split.

    Returns:
        `HoldoutLidar`; ``available`` and the held-out pixels are disjoint and together all grid
        pixels with a point; ``gt_full`` holds every full-resolution point of a held-out block.

    Raises:
        ShapeError: if ``lidar_depth`` is not 2-D or smaller than one block.
        EmptyInputError: if fewer than two grid pixels have a point.
    """
    d = np.asarray(lidar_depth, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError("lidar_depth", "an (H, W) depth map in metres", describe(d))
    grid = downsample_depth(d, factor)
    h, w = grid.shape
    available_all = SparseDepth.from_depth_map(grid)
    if len(available_all) < 2:
        raise EmptyInputError(
            "lidar_depth", "at least two LiDAR pixels on the grid to hold some out", len(available_all)
        )
    pool, held = holdout_split(available_all, holdout=holdout, rng=rng)
    gt_grid = np.zeros((h, w))
    gt_grid[held.v.astype(np.int64), held.u.astype(np.int64)] = held.depth
    full = d[: h * factor, : w * factor]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(full) & (full > 0)
    held_blocks = np.repeat(np.repeat(gt_grid > 0, factor, axis=0), factor, axis=1)
    gt_full = np.where(valid & held_blocks, full, 0.0)
    return HoldoutLidar(pool, gt_grid, gt_full, len(available_all))
