"""The GP problem of one frame: validated inputs (MDE map, measurements, output size) to a `GridProblem`."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..depthmap import fill_nearest, resize_map
from ..errors import EmptyInputError, InvalidDepthError, InvalidInputError, ShapeError, describe
from ..gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates
from ..limits import check_completion_size
from ..mde.align import AlignmentResult, align_depth
from ..measurements import SparseDepth

MAX_UPSAMPLING = 16
"""Largest ratio of an output side to the MDE's side (`check_output_shape`)."""
MAX_OUTPUT_PIXELS = 2**27
"""Largest number of output pixels (each output array of float64 then takes up to 1 GiB)."""


def check_output_shape(output_shape, input_shape: tuple[int, int]) -> tuple[int, int]:
    """Validates ``output_shape``: None (the input shape) or two integers (Ho, Wo) >= 1.

    Each side may be at most `MAX_UPSAMPLING` times the input's and the output at most
    `MAX_OUTPUT_PIXELS` pixels; every size, the default one included, goes through the memory
    guard (`gpdepth3d.limits.check_completion_size`).

    Raises:
        ShapeError: for anything else (a string, NaN, floats, 1 or 3 sizes, zero, too large).
        ProblemTooLargeError: a completion beyond `gpdepth3d.limits.memory_limit`.
    """
    if output_shape is None:  # the MDE's own size: still within the memory limit
        h, w = int(input_shape[0]), int(input_shape[1])
        check_completion_size((h, w), (h, w))
        return (h, w)
    expected = "None or (Ho, Wo): two integers >= 1"
    if isinstance(output_shape, (str, bytes)) or not hasattr(output_shape, "__len__") or len(output_shape) != 2:
        raise ShapeError("output_shape", expected, describe(output_shape))
    sizes = []
    for s in output_shape:
        if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) or s < 1:
            raise ShapeError("output_shape", expected, describe(output_shape))
        sizes.append(int(s))
    ho, wo = sizes
    h, w = input_shape
    if ho > MAX_UPSAMPLING * h or wo > MAX_UPSAMPLING * w or ho * wo > MAX_OUTPUT_PIXELS:
        raise ShapeError(
            "output_shape",
            f"at most {MAX_UPSAMPLING}x the MDE size {h}x{w} per side and {MAX_OUTPUT_PIXELS} pixels",
            (ho, wo),
        )
    check_completion_size((h, w), (ho, wo))  # ProblemTooLargeError before any output array is allocated
    return (ho, wo)


def check_mde_depth(mde_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validates an MDE depth map; returns it as float64 with invalid pixels at 0, and the valid mask."""
    d = np.ma.filled(mde_depth, 0.0) if np.ma.isMaskedArray(mde_depth) else np.asarray(mde_depth)  # masked: no MDE
    if d.ndim != 2 or d.shape[0] < 2 or d.shape[1] < 2:
        raise ShapeError("mde_depth", "a 2-D (H, W) depth map with H, W >= 2", describe(d))
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise ShapeError("mde_depth", "a real-valued depth map", describe(d))
    d = np.asarray(d, dtype=np.float64)
    out = np.empty(d.shape)
    valid = np.empty(d.shape, dtype=bool)
    negative, outside, first = _valid_depth(d, out, valid)
    if negative:
        raise InvalidDepthError("mde_depth", "z-depths >= 0 in metres (0/NaN/inf = no depth)", f"{negative} negative")
    if outside:  # beyond any camera: the GP's scales would under/overflow
        raise InvalidDepthError(
            "mde_depth", "z-depths in [1e-6, 1e6] m (0/NaN/inf = no depth)", f"{outside} outside, e.g. {first:g}"
        )
    return out, valid


@njit(cache=True, nogil=True)
def _valid_depth(d, out, valid):  # pragma: no cover - compiled
    """One pass over the map d: valid = finite and > 0, out = d there and 0 elsewhere; returns the counts of finite
    negative depths and of valid ones outside [1e-6, 1e6], and the first of those in row-major order.

    The pass has no branches (comparisons as 0/1 counts, NaN failing each), so it vectorises; the first depth
    outside the range is looked for only when there is one."""
    negative, outside = 0, 0
    for i in range(d.shape[0]):
        row, o, v = d[i], out[i], valid[i]
        for j in range(row.shape[0]):
            x = row[j]
            ok = (x > 0.0) & (x < math.inf)
            negative += (x < 0.0) & (x > -math.inf)
            outside += ((x > 0.0) & (x < 1e-6)) | ((x > 1e6) & (x < math.inf))
            v[j] = ok
            o[j] = x if ok else 0.0
    first = 0.0
    if outside:
        for x in d.ravel():
            if (x > 0.0 and x < 1e-6) or (x > 1e6 and x < math.inf):
                first = x
                break
    return negative, outside, first


def _frame_inputs(
    mde_depth: np.ndarray, sparse: SparseDepth, output_shape
) -> tuple[np.ndarray, np.ndarray, SparseDepth, tuple[int, int]]:
    """Validates one frame's inputs: (MDE with invalid = 0, valid mask, points on the MDE grid, output shape)."""
    mde, valid = check_mde_depth(mde_depth)
    if not isinstance(sparse, SparseDepth):
        raise ShapeError("sparse", "a SparseDepth", type(sparse).__name__)
    h, w = mde.shape
    sh, sw = sparse.image_size
    if abs((sw / sh) / (w / h) - 1.0) > 0.01:
        raise ShapeError(
            "sparse", f"measurements of an image with the aspect ratio of mde_depth {w}x{h}", f"image size {sw}x{sh}"
        )
    grid_sparse = sparse.rasterize((h, w))
    if not valid.any() and len(grid_sparse) == 0:
        raise EmptyInputError("mde_depth, sparse", "at least one valid MDE pixel or measurement", "none")
    return mde, valid, grid_sparse, check_output_shape(output_shape, (h, w))


def build_problem(
    mde_depth: np.ndarray, sparse: SparseDepth, config: DepthGPConfig, output_shape: tuple[int, int] | None = None
) -> tuple[GridProblem, SparseDepth, float, AlignmentResult]:
    """Turns an MDE map and measurements into the `GridProblem` of ``config``'s formulation.

    Returns:
        The problem, the measurements on the GP grid, the depth scale (metres) and the alignment.
    """
    if config.formulation == "log_residual":
        raise InvalidInputError(
            "config", "the 'balanced' or 'residual' formulation (log_residual: use DepthCompleter)", config.formulation
        )
    mde, valid, grid_sparse, out_shape = _frame_inputs(mde_depth, sparse, output_shape)
    h, w = mde.shape
    scale = float(np.median(mde[valid])) if valid.any() else float(np.median(grid_sparse.depth))
    unit = scale if config.units == "relative" else 1.0
    s, sdl, smeas = config.outputscale * unit, config.sigma_dl * unit, config.sigma_meas * unit

    rows = grid_sparse.v.astype(np.int64)
    cols = grid_sparse.u.astype(np.int64)
    sig = np.where(np.isfinite(grid_sparse.sigma), grid_sparse.sigma, smeas)
    meas_prec = np.zeros((h, w))
    meas_val = np.zeros((h, w))
    meas_prec[rows, cols] = 1.0 / sig**2
    meas_val[rows, cols] = grid_sparse.depth

    alignment = AlignmentResult(1.0, 0.0, 0)
    if config.formulation == "balanced":
        c = float(np.mean(mde[valid])) if valid.any() else float(np.mean(grid_sparse.depth))
        prior = np.full((h, w), c)
        mde_prec = np.where(valid, 1.0 / sdl**2, 0.0)
        precision = mde_prec + meas_prec
        with np.errstate(invalid="ignore", divide="ignore"):
            obs = np.where(precision > 0, (mde_prec * mde + meas_prec * meas_val) / precision, 0.0)
        out_prior = np.full(out_shape, c)
    else:
        if len(grid_sparse):
            alignment = align_depth(mde[rows, cols], grid_sparse.depth, config.align)
        base = fill_nearest(mde, valid) if valid.any() else np.full((h, w), float(np.median(grid_sparse.depth)))
        prior = alignment.apply(base)
        precision, obs = meas_prec, meas_val
        out_prior = resize_map(prior, out_shape)
    problem = GridProblem(
        prior_mean=prior,
        obs=obs,
        precision=precision,
        out_rows=output_coordinates(h, out_shape[0]),
        out_cols=output_coordinates(w, out_shape[1]),
        out_prior_mean=out_prior,
        kernel=Kernel(config.nu, config.lengthscale, s),
    )
    return problem, grid_sparse, scale, alignment
