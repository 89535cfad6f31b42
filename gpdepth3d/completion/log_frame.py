"""A frame in the default model's terms: the MDE's log depth and the points' log depths and noise (docs/model.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from ..depthmap import fill_nearest, resize_map
from ..gp.model import DepthGPConfig
from ..measurements import SparseDepth


@dataclass(frozen=True)
class LogFrame:
    """One frame's inputs of the log-residual model, on the GP grid.

    Attributes:
        base: (H, W) the MDE depth with its holes filled by the nearest valid pixel, metres.
        log_mde: (H, W) log of ``base``.
        rows, cols: (N,) int64 GP-grid pixels of the points.
        log_z: (N,) log of the points' depths.
        noise: (N,) the points' noise variance in log depth, (sigma / z)^2 (``sigma_meas`` where none is given).
        stated: (N,) the part of ``noise`` the points' own sigmas state (0 where ``sigma_meas`` stands in).
        edge: (N,) the MDE's log-depth range over 3 x 3 pixels around each point (0 when ``assembly.edge_sigma`` is 0).
        out_shape: (Ho, Wo) of the output.
    """

    base: np.ndarray
    log_mde: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    log_z: np.ndarray
    noise: np.ndarray
    stated: np.ndarray
    edge: np.ndarray
    out_shape: tuple[int, int]

    @property
    def shape(self) -> tuple[int, int]:
        return self.base.shape  # type: ignore[return-value]

    @cached_property
    def log_mde_at(self) -> np.ndarray:
        """(N,) ``log_mde`` at the points (computed when first asked for: the slope's fits share it)."""
        return self.log_mde[self.rows, self.cols]

    @property
    def n(self) -> int:
        return int(self.rows.size)

    @property
    def same_grid(self) -> bool:
        """True when the output is the GP grid itself."""
        return tuple(self.out_shape) == self.shape

    def to_output(self, field: np.ndarray) -> np.ndarray:
        """An (H, W) map on the output grid (itself when the grids are the same)."""
        return field if self.same_grid else resize_map(field, self.out_shape)


def log_frame(
    mde: np.ndarray, valid: np.ndarray, grid_sparse: SparseDepth, out_shape: tuple[int, int], config: DepthGPConfig
) -> LogFrame:
    """The `LogFrame` of validated inputs (`gpdepth3d.completion.problem._frame_inputs`)."""
    h, w = mde.shape
    base = fill_nearest(mde, valid) if valid.any() else np.full((h, w), float(np.median(grid_sparse.depth)))
    rows, cols = grid_sparse.v.astype(np.int64), grid_sparse.u.astype(np.int64)
    z, sig = grid_sparse.depth, grid_sparse.sigma
    unit = 1.0 if config.units == "metres" else z
    given, relative = np.isfinite(sig), sig / z
    noise = np.where(given, relative, config.sigma_meas * unit / z) ** 2
    stated = np.where(given, relative, 0.0) ** 2
    log_mde = np.log(base)
    edge = edge_range_at(log_mde, rows, cols) if config.assembly.edge_sigma > 0 else np.zeros(rows.size)
    return LogFrame(base, log_mde, rows, cols, np.log(z), noise, stated, edge, tuple(out_shape))


def edge_range_at(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N,) max - min of ``depth`` over the 3 x 3 pixels around (rows, cols) (borders: the edge pixel repeated)."""
    out = np.empty(rows.size)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    _edge_range_at(depth, np.asarray(rows, np.int64), np.asarray(cols, np.int64), out)
    return out


@njit(cache=True, nogil=True)
def _edge_range_at(depth, rows, cols, out):  # pragma: no cover - compiled
    """One pass over the points: the nine neighbours of each read where they lie (one compiled loop, not nine gathers
    of the whole point set)."""
    h, w = depth.shape
    for k in range(rows.size):
        hi, lo = -math.inf, math.inf
        for dr in range(-1, 2):
            i = min(max(rows[k] + dr, 0), h - 1)
            for dc in range(-1, 2):
                x = depth[i, min(max(cols[k] + dc, 0), w - 1)]
                hi, lo = max(hi, x), min(lo, x)
        out[k] = hi - lo
