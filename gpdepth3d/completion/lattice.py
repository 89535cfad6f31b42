"""Stage 3 of the default model: the lattice the field lives on and the points on it (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..gp.kernels import is_exponential
from ..gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates, separable_correlation
from .log_frame import LogFrame
from .screen import Screened
from .mde_slope import Sloped


@dataclass(frozen=True)
class Lattice:
    """The field's grid problem on a lattice of stride k, with the right-hand sides the read-out needs.

    Attributes:
        stride: k, GP-grid pixels per lattice node and side (1: every pixel).
        lengthscale: The field's length scale l in GP-grid pixels (the problem's kernel has l / k).
        problem: The `GridProblem` of the field g on the lattice (prior mean 0, log depth).
        extra: Further observation vectors of the same solve: ones (the kriging weights' sum) when the
            depth-aware factor, the scale term or the slope term needs it, then the centred log MDE.
        rows, cols: (M,) GP-grid pixels of the kept points.
        targets: (M,) their residuals minus b, then the extra vectors' values at them, as (M, 1 + E).
        white: (M,) their white variance, tau^2 + noise.
        centre: c, the log MDE depth the slope and the depth-aware factor are centred on.
        depth_aware, scale_term, slope_term: Which parts of the read-out apply (docs/model.md, "assemble").
    """

    stride: int
    lengthscale: float
    problem: GridProblem
    extra: tuple[np.ndarray, ...]
    rows: np.ndarray
    cols: np.ndarray
    targets: np.ndarray
    white: np.ndarray
    centre: float
    depth_aware: bool
    scale_term: bool
    slope_term: bool


@lru_cache(maxsize=8)
def _zeros(shape: tuple[int, int]) -> np.ndarray:
    """A read-only (H, W) map of zeros, one per shape: the field's prior mean on the lattice and on the output grid
    is the same every frame of a sequence, so it is made (and its pages touched) once, not per frame."""
    out = np.zeros(shape)
    out.setflags(write=False)
    return out


def lattice_stride(
    config: DepthGPConfig,
    h: int,
    w: int,
    n_points: int,
    lengthscale: float,
    output_shape: tuple[int, int] | None = None,
    stride: int | None = None,
) -> int:
    """Pixels of the GP grid per lattice node, per side: ``stride`` (`EngineConfig.lattice_stride`), else
    `LatticeConfig`'s rule.

    With the sub-lattice detail (nu = 0.5 and an output at least as fine as the grid, ``output_shape`` None:
    the grid): 2 up to ``detail_share`` of the pixels observed, ``dense_stride`` above; without it 2 up to
    ``sparse_share`` and 1 above; grids under ``min_side`` pixels and length scales under k / 2 x
    ``min_lengthscale`` take a finer stride. The rule's measured effect: see docs/results.md.
    """
    rule = config.lattice
    k = stride
    if k is None:
        detail = is_exponential(config.nu) and (output_shape is None or (output_shape[0] >= h and output_shape[1] >= w))
        if min(h, w) < rule.min_side:
            k = 1
        elif n_points <= (rule.detail_share if detail else rule.sparse_share) * h * w:
            k = 2
        else:
            k = rule.dense_stride if detail else 1
        while k > 1 and lengthscale < k / 2 * rule.min_lengthscale:
            k //= 2
    while k > 1 and (-(-h // k) < 2 or -(-w // k) < 2):
        k -= 1
    return k


def build_lattice(
    frame: LogFrame, sloped: Sloped, screened: Screened, config: DepthGPConfig, stride: int | None = None
) -> Lattice:
    """Each kept point enters at its lattice node with the field's variance between its pixel and the node added
    to its noise; points sharing a node enter as their precision-weighted mean (exact for them)."""
    h, w = frame.shape
    fit, keep = screened.fit, screened.keep
    r, c = frame.rows[keep], frame.cols[keep]
    k = lattice_stride(config, h, w, r.size, fit.lengthscale, frame.out_shape, stride)
    hl, wl = -(-h // k), -(-w // k)
    node_r, node_c = r // k, c // k
    off_r, off_c = r - (k * node_r + (k - 1) / 2), c - (k * node_c + (k - 1) / 2)
    between = (
        2 * fit.outputscale**2 * (1 - separable_correlation(off_r, off_c, fit.lengthscale, config.nu)) if k > 1 else 0.0
    )
    white = fit.nugget**2 + frame.noise[keep]
    precision_pt = 1.0 / (white + between)
    cell = node_r * wl + node_c
    precision = np.bincount(cell, precision_pt, hl * wl).astype(np.float64, copy=False).reshape(hl, wl)
    observed = precision > 0
    # the nodes' precision, 1 where none (their sums are 0 there): a plain division, not one masked by `observed`
    denominator = precision + ~observed

    def on_lattice(values):  # per-point values -> the precision-weighted mean at each node
        out = np.bincount(cell, precision_pt * values, hl * wl).astype(np.float64, copy=False).reshape(hl, wl)
        return np.divide(out, denominator, out=out)

    targets = [sloped.resid[keep] - fit.log_scale]
    depth_aware = config.assembly.depth_lengthscale is not None and r.size > 0
    scale_term = fit.log_scale_var > config.assembly.scale_var_share * fit.nugget**2
    slope_term = sloped.fit is not None and r.size > 0
    x_pts = frame.log_mde_at[keep]  # the raw (not re-sloped) log MDE at the points, read once per frame
    centre = sloped.fit.centre if sloped.fit is not None else (float(np.median(x_pts)) if r.size else 0.0)
    if depth_aware or scale_term or slope_term:
        targets.append(np.ones(r.size))
    if depth_aware or slope_term:
        targets.append(x_pts - centre)
    extra = (observed.astype(np.float64),) + tuple(on_lattice(t) for t in targets[2:]) if len(targets) > 1 else ()
    out_rows = (output_coordinates(h, frame.out_shape[0]) - (k - 1) / 2) / k
    out_cols = (output_coordinates(w, frame.out_shape[1]) - (k - 1) / 2) / k
    kernel = Kernel(config.nu, fit.lengthscale / k, fit.outputscale)
    problem = GridProblem(
        _zeros((hl, wl)), on_lattice(targets[0]), precision, out_rows, out_cols, _zeros(frame.out_shape), kernel
    )
    return Lattice(
        k,
        fit.lengthscale,
        problem,
        extra,
        r,
        c,
        np.stack(targets, 1),
        white,
        centre,
        depth_aware,
        scale_term,
        slope_term,
    )
