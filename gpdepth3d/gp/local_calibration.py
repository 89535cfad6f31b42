"""Local calibration of the posterior variance from the points' leave-one-out z-scores (docs/model.md).

A stationary GP gives every region of a frame the same prior variance, but an MDE's error is not
stationary: flat walls and road are off by a smooth scale the points pin down, depth edges and objects the
network blurs by much more. A point's leave-one-out z-score z_i (`gpdepth3d.gp.points.loo_zscores`) has
E[z_i^2] = 1 where the model's variance is right, less where the field is smoother than the model says,
more where it is rougher. The variance at a pixel x is multiplied by

    f(x) = (sum_i w_i(x) q_i + w_0) / (sum_i w_i(x) + w_0),   w_i(x) = exp(-|x - x_i|^2 / (2 r^2)),

r = reach x the points' mean spacing sqrt(A / N) (A: the points' bounding box), q_i = min(z_i^2, cap), and
w_0 the weight of ``prior_points`` pseudo-points at q = 1: far from the points f returns to 1. A point with
a sigma of its own (triangulated SLAM points) enters with q_i at least its noise share (the part of its
predictive variance its stated noise makes): with independent errors of the stated size E[z_i^2] is at
least that share, so a z^2 far below it says the error is shared with the neighbours, not that the pixels
between them are certain. The effect is measured (see docs/results.md).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..errors import InvalidInputError, describe
from .model import CalibrationConfig


def local_variance_factor(
    shape: tuple[int, int],
    rows: np.ndarray,
    cols: np.ndarray,
    zscores: np.ndarray,
    *,
    reach: float = 1.5,
    prior_points: float = CalibrationConfig.prior_points,
    zscore_cap: float = CalibrationConfig.zscore_cap,
    noise_share: np.ndarray | None = None,
) -> np.ndarray:
    """The factor f(x) on the posterior variance at every pixel of a grid (see the module).

    Args:
        shape: (H, W) of the grid the points' pixels index.
        rows, cols: (N,) integer pixel coordinates of the points (row, column).
        zscores: (N,) their leave-one-out z-scores (finite).
        reach: Gaussian radius in mean point spacings, sqrt(A / N) pixels with A the area of the
            points' bounding box.
        prior_points: Pseudo-points at f = 1 (the weight of the model's own variance).
        zscore_cap: Squared z-scores enter capped at this (one point must not set a region's variance alone).
        noise_share: (N,) the points' noise shares q_i in [0, 1] (`gpdepth3d.gp.points.loo_zscores`):
            each squared z-score enters as max(z_i^2, q_i) (see the module). None: no floor.

    Returns:
        (H, W) float64 factor, > 0; all ones when there are no points.

    Raises:
        InvalidInputError: arrays of different lengths, pixels outside the grid, non-finite
            z-scores, or reach / prior_points not > 0.
    """
    h, w = int(shape[0]), int(shape[1])
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    z = np.asarray(zscores, dtype=np.float64)
    if not (rows.shape == cols.shape == z.shape and z.ndim == 1):
        raise InvalidInputError(
            "rows, cols, zscores", "three (N,) arrays", f"shapes {rows.shape}, {cols.shape}, {z.shape}"
        )
    for name, value in (("reach", reach), ("prior_points", prior_points), ("zscore_cap", zscore_cap)):
        if not np.isfinite(value) or value <= 0:
            raise InvalidInputError(name, "a finite number > 0", value)
    if not np.all(np.isfinite(z)):
        raise InvalidInputError("zscores", "finite z-scores", f"{int(np.count_nonzero(~np.isfinite(z)))} non-finite")
    if noise_share is not None:
        share = np.asarray(noise_share, dtype=np.float64)
        if share.shape != z.shape or not np.all((share >= 0) & (share <= 1)):
            raise InvalidInputError("noise_share", f"({z.size},) values in [0, 1]", describe(share))
    if z.size == 0:
        return np.ones((h, w))
    rows = rows.astype(np.int64)
    cols = cols.astype(np.int64)
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= h or cols.max() >= w:
        raise InvalidInputError(
            "rows, cols",
            f"pixels inside a {h} x {w} grid",
            f"rows {rows.min()}..{rows.max()}, cols {cols.min()}..{cols.max()}",
        )
    import cv2

    # the points' mean spacing where they are: over their bounding box, not the whole grid (points in
    # one half of the image would otherwise carry their factor ~1.4x too far into the other half)
    area = float((rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1))
    radius = reach * math.sqrt(area / z.size)
    # the sums on bins of ~radius / 3 pixels, each point splatted bilinearly onto the 4 bin centres
    # around it (bin centres on the pixel centres of the c-fold grid, so resizing bilinearly by
    # exactly c and cropping puts them back): the blur is then >= 3 bins wide whatever the density
    # (an approximation of the direct sum: tests/gp/test_local_calibration.py bounds its error)
    c = max(1, int(radius // 3))
    hb, wb = -(-h // c), -(-w // c)
    q = np.minimum(z * z if noise_share is None else np.maximum(z * z, share), zscore_cap)
    if c == 1:  # the points' own pixels
        cell = rows * w + cols
        sums, weights = np.bincount(cell, q, h * w), np.bincount(cell, None, h * w).astype(np.float64)
    else:
        sums, weights = np.zeros(hb * wb), np.zeros(hb * wb)
        _splat(rows, cols, q, c, hb, wb, sums, weights, np.zeros(hb * wb), np.zeros(hb * wb))
    sums, weights = sums.reshape(hb, wb), weights.reshape(hb, wb)
    sigma = radius / c
    size = 2 * int(math.ceil(3 * sigma)) + 1
    sums = cv2.GaussianBlur(sums, (size, size), sigma, borderType=cv2.BORDER_CONSTANT)
    weights = cv2.GaussianBlur(weights, (size, size), sigma, borderType=cv2.BORDER_CONSTANT)
    w0 = prior_points / (2 * math.pi * sigma * sigma)  # a point's own weight under the blur
    factor = np.maximum(sums, 0.0, out=sums)  # the blurred maps are this function's own: the factor made in place
    factor += w0
    factor /= np.add(np.maximum(weights, 0.0, out=weights), w0, out=weights)
    if c > 1:
        factor = cv2.resize(factor, (wb * c, hb * c), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return np.ascontiguousarray(factor)


@njit(cache=True, nogil=True)
def _splat(rows, cols, q, c, hb, wb, sums, weights, part, part_w):  # pragma: no cover - compiled
    """sums, weights += each point's q and 1 splatted bilinearly onto the 4 bin centres around it (bins of c pixels,
    hb x wb, flat; clipped at the borders), corner by corner: a corner's sums over the points by bin first (in
    ``part``, ``part_w``: zeros in, zeros out), then added, so each bin's sum is that of one np.bincount per corner
    added in turn; a bin is touched only where a point lands (no pass over all bins per corner)."""
    half = (c - 1) / 2
    for di in range(2):
        for dj in range(2):
            for p in range(rows.size):
                b = _corner(rows[p], cols[p], half, c, di, dj, hb, wb)
                y, x = (rows[p] - half) / c, (cols[p] - half) / c
                fy, fx = y - math.floor(y), x - math.floor(x)
                share = (fy if di else 1 - fy) * (fx if dj else 1 - fx)
                part[b] += share * q[p]
                part_w[b] += share
            for p in range(rows.size):  # each bin's corner sum added once (a bin added again adds its zero)
                b = _corner(rows[p], cols[p], half, c, di, dj, hb, wb)
                sums[b] += part[b]
                weights[b] += part_w[b]
                part[b] = 0.0
                part_w[b] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _corner(r, col, half, c, di, dj, hb, wb):  # pragma: no cover - compiled
    """The flat bin of corner (di, dj) of the bilinear splat of pixel (r, col) (`_splat`)."""
    i = min(max(math.floor((r - half) / c) + di, 0), hb - 1)
    j = min(max(math.floor((col - half) / c) + dj, 0), wb - 1)
    return i * wb + j
