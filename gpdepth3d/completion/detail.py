"""Stage 5 of the default model: the field's detail below the lattice, kriged back from the points (docs/model.md)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..gp.kernels import is_exponential
from ..gp.model import DepthGPConfig
from ..gp.sublattice import sublattice_kriging
from .lattice import Lattice
from .log_frame import LogFrame
from .solve import FieldPosterior


def add_detail(field: FieldPosterior, lattice: Lattice, frame: LogFrame, config: DepthGPConfig) -> FieldPosterior:
    """The field with its sub-lattice detail (`gpdepth3d.gp.sublattice`) in the mean, variance and extra read-outs.

    Only for a lattice coarser than the grid, nu = 0.5, and outputs at least as fine as the grid. The detail
    is kriged at the GP grid's pixels (where the points are) and resized to a finer output.
    """
    h, w = frame.shape
    ho, wo = frame.out_shape
    if lattice.stride == 1 or not is_exponential(config.nu) or not lattice.rows.size or ho < h or wo < w:
        return field
    fields = (field.mean, *field.extra)
    at = _at_points(fields, lattice.rows, lattice.cols, (h, w))
    kernel = lattice.problem.kernel
    corr, reduction = sublattice_kriging(
        np.arange(h, dtype=np.float64),
        np.arange(w, dtype=np.float64),
        lattice.rows,
        lattice.cols,
        lattice.targets - at.T,
        lattice.white,
        (h, w),
        stride=lattice.stride,
        lengthscale=lattice.lengthscale,
        outputscale=kernel.outputscale,
        max_window_points=config.lattice.max_window_points,
    )
    if not frame.same_grid:
        corr = np.stack([frame.to_output(f) for f in corr])
        reduction = frame.to_output(reduction)
    for f, c in zip(fields, corr):  # the corrections' own (fresh) arrays take the sums
        c += f
    variance = np.subtract(field.variance, reduction, out=reduction)
    np.maximum(variance, 0.0, out=variance)
    return replace(field, mean=corr[0], variance=variance, extra=tuple(corr[1:]))


def _at_points(fields: tuple[np.ndarray, ...], rows: np.ndarray, cols: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(m, n) values of m (Ho, Wo) output fields at the GP-grid pixels (rows, cols); output >= grid.

    The output's own pixels where they coincide with the grid's, else bilinear between output pixels.
    """
    ho, wo = fields[0].shape
    h, w = grid
    if (ho, wo) == (h, w):  # one flat index for all the fields
        flat = rows * w + cols
        return np.stack([f.ravel().take(flat) for f in fields])
    from scipy.ndimage import map_coordinates

    y = (rows + 0.5) * ho / h - 0.5  # the inverse of output_coordinates
    x = (cols + 0.5) * wo / w - 0.5
    return np.stack([map_coordinates(f, [y, x], order=1, mode="nearest") for f in fields])
