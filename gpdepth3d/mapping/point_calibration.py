"""The points' sigma checked against each other, and what carrying a point between frames adds to it.

A frame's own points and the local map's points (triangulated by the last frames, placed in this
frame by their poses and its pose) often measure the same surface. Their difference over the sigma
both claim is a z-score that needs no ground truth: when the poses are worse than the triangulation's
pose prior says (a SLAM back-end's drift, a VIO's jitter), the z-scores spread wider than 1.
`SigmaCalibration` keeps the z-scores of the last frames and gives the factor every point's sigma is
multiplied by: their robust spread (1.4826 times the median absolute z), never below 1, so that exact
poses keep the triangulation's sigma and poorer poses widen it by what the points themselves show.
`misplacement_sigma` is what a point carried into a frame through inexact poses gets for landing beside
its pixel (the depth range around it), before the z-scores are taken.
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from ..errors import InvalidInputError
from ..measurements import SparseDepth
from .points.local_map import cell_ids
from .mde_check import MAD_TO_SIGMA


def paired_z_scores(own: SparseDepth, others: SparseDepth, cell: float) -> np.ndarray:
    """z-scores of ``own`` against ``others`` in the ``cell``-pixel cells that hold both.

    In each such cell the most certain point of each (smallest sigma / depth) is paired:
    ``z = (d_own - d_other) / sqrt(sigma_own^2 + sigma_other^2)``.

    Args:
        own: A frame's own measurements.
        others: Other measurements of the same image (e.g. the local map's).
        cell: Cell size, pixels (> 0).

    Returns:
        (M,) z-scores, one per shared cell (empty when none is shared).
    """
    if not np.isfinite(cell) or cell <= 0:
        raise InvalidInputError("cell", "a cell size > 0 (pixels)", cell)
    if not len(own) or not len(others):
        return np.zeros(0)
    best = []
    for sp in (own, others):
        ids = cell_ids(sp, cell)
        order = np.lexsort((sp.sigma / sp.depth, ids))
        first = np.ones(order.size, bool)
        first[1:] = ids[order][1:] != ids[order][:-1]
        best.append((ids[order][first], order[first]))
    common, ia, ib = np.intersect1d(best[0][0], best[1][0], return_indices=True)
    a, b = best[0][1][ia], best[1][1][ib]
    scale = np.hypot(own.sigma[a], others.sigma[b])
    ok = np.isfinite(scale) & (scale > 0)
    return (own.depth[a][ok] - others.depth[b][ok]) / scale[ok]


def misplacement_sigma(points: SparseDepth, depth_map: np.ndarray, radius: float) -> np.ndarray:
    """(N,) depth sigma, metres, of points that may lie up to ``radius`` pixels from where they are drawn.

    A point carried into a frame through poses that are off lands beside its pixel: its depth then stands
    for the surface some pixels away, and on a slope or across an edge that is another depth. The depth
    range of ``depth_map`` (e.g. the frame's MDE) in the square of half-side ``radius`` around each point,
    relative to its depth there, times the point's depth, is taken as +-2 sigma: sigma = d (max - min) / (4 m).

    Args:
        points: The points, pixels of their image.
        depth_map: (h, w) depth of the same image at any resolution, metres (<= 0 or NaN: none).
        radius: How far the points may lie from their pixels, pixels of the points' image (>= 0).

    Returns:
        The sigma of each point (0 where the map has no depth around it or ``radius`` is under half a map pixel).
    """
    if not np.isfinite(radius) or radius < 0:
        raise InvalidInputError("radius", "a distance >= 0 (pixels)", radius)
    depth_map = np.asarray(depth_map, dtype=np.float64)
    if depth_map.ndim != 2:
        raise InvalidInputError("depth_map", "an (h, w) depth map", depth_map.shape)
    h, w = depth_map.shape
    sx = w / points.image_size[1]
    half = int(np.floor(radius * sx + 0.5))
    if not len(points) or half < 1:
        return np.zeros(len(points))
    valid = np.isfinite(depth_map) & (depth_map > 0)
    square = np.ones((2 * half + 1, 2 * half + 1), np.uint8)  # OpenCV's max / min filters (van Herk: any size)
    hi = cv2.dilate(np.where(valid, depth_map, -np.inf), square, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(np.where(valid, depth_map, np.inf), square, borderType=cv2.BORDER_REPLICATE)
    iu = np.clip((points.u * sx).astype(np.int64), 0, w - 1)
    iv = np.clip((points.v * h / points.image_size[0]).astype(np.int64), 0, h - 1)
    hi, lo = hi[iv, iu], lo[iv, iu]
    with np.errstate(invalid="ignore", divide="ignore"):  # no depth around a point: inf - inf, NaN below
        centre = np.where(valid[iv, iu], depth_map[iv, iu], 0.5 * (hi + lo))
        rel = (hi - lo) / (4.0 * centre)
    return np.where(np.isfinite(rel) & (rel > 0), rel, 0.0) * points.depth


class SigmaCalibration:
    """The z-scores of the last ``frames`` frames and the sigma factor they call for.

    Args:
        frames: Frames whose z-scores are kept (oldest dropped first).
        min_pairs: Fewest z-scores kept before the factor departs from 1.
    """

    def __init__(self, frames: int, min_pairs: int = 30):
        if isinstance(frames, bool) or int(frames) != frames or frames < 1:
            raise InvalidInputError("frames", "an integer >= 1", frames)
        if isinstance(min_pairs, bool) or int(min_pairs) != min_pairs or min_pairs < 1:
            raise InvalidInputError("min_pairs", "an integer >= 1", min_pairs)
        self.min_pairs = int(min_pairs)
        self._z: deque[np.ndarray] = deque(maxlen=int(frames))

    def add(self, z: np.ndarray) -> None:
        """Remembers one frame's z-scores (`paired_z_scores`); non-finite ones are dropped."""
        z = np.asarray(z, dtype=np.float64).ravel()
        self._z.append(z[np.isfinite(z)])

    @property
    def factor(self) -> float:
        """The factor the points' sigma is multiplied by: the z-scores' robust spread, at least 1."""
        z = np.concatenate(list(self._z)) if self._z else np.zeros(0)
        if z.size < self.min_pairs:
            return 1.0
        return max(1.0, MAD_TO_SIGMA * float(np.median(np.abs(z))))
