"""The ``fast`` engine's cost model: seconds, bytes and rounding error of each route, from which it picks one.

Its constants were fitted to single-thread float64 timings on the project's 2-core x86-64 CI machine;
the routes they rank are measured in docs/engines.md and docs/results.md.
"""

from __future__ import annotations

import os
import time

import numpy as np

from .markov import state_dim
from .model import GridProblem

GRID_FLOPS_PER_S = 14e9
"""Sustained flop rate of the grid route's fronts (flop/s): nested dissection of an n-pixel grid
takes ~22 n^1.5 flops to factorise and ~60 n^1.5 more for the selected inverse (dense-front counts
over the trees of `gpdepth3d.gp.elimination_tree`)."""
GRID_SOLVE_S = 2.5e-8
"""Seconds per n log2 n (n lattice nodes) of one forward and backward solve over the factor."""
READOUT_MEAN_S = 1e-8
"""Seconds per output pixel and right-hand side of the mean's Markov read-out."""
READOUT_VAR_S = 1e-8
"""Seconds per output pixel and state of the variance's Markov read-out."""
WOODBURY_MAX_SNR = 1e8
"""Largest s^2 x observation precision ``auto`` gives Woodbury or the dense route: their
s^2 (1 - quadratic form) cancels near a point whose noise is tiny against s (error ~1e-16 s^2 x that
ratio), the grid's factorisation does not."""
GRID_MAX_ERROR = 1e-7
"""Largest `grid_error_estimate` (relative to s) at which the grid route is taken: calibrated
against the dense engine (nu = 1.5, 2.5; l = 1.5-100 px; both formulations) in tests/gp/test_fast.py."""
GRID_BYTES = 80.0
"""Bytes per ds^2 n log2 n of the grid route's numeric phase (factor, update stack, covariance
fronts, symbolic structure), an upper bound checked in tests/gp/test_fast.py."""
NEUMANN_BYTES_PER_PIXEL = 200
"""Bytes per grid pixel of the Neumann route (coefficient images and work arrays)."""
NEUMANN_MIN_OBSERVED = 0.9
"""``auto`` considers the Neumann series only when at least this share of the pixels is observed."""


def grid_error_estimate(problem: GridProblem) -> float:
    """Estimated rounding error of the grid route relative to the prior std s (dimensionless).

    eps ||Qv|| ||Qu|| min(||Cv|| ||Cu||, 1 / (s^2 min w)): the prior precision's conditioning,
    bounded by the observations when every pixel is observed (`gpdepth3d.gp.markov.chain_conditioning`).
    """
    from .markov import chain_conditioning

    h, w = problem.shape
    k = problem.kernel
    qv, cv = chain_conditioning(h, float(k.nu), float(k.lengthscale))
    qu, cu = chain_conditioning(w, float(k.nu), float(k.lengthscale))
    cov = cv * cu
    wmin = float(np.min(problem.precision))
    if wmin > 0:
        cov = min(cov, 1.0 / (wmin * float(k.outputscale) ** 2))
    return float(np.finfo(np.float64).eps * qv * qu * cov)


def grid_bytes(shape: tuple[int, int], nu: float) -> int:
    """Peak memory (bytes) of the grid route on an (H, W) grid: `GRID_BYTES` ds^2 n log2 n."""
    n = float(shape[0]) * float(shape[1])
    ds = state_dim(nu) ** 2
    return int(GRID_BYTES * ds * ds * n * max(np.log2(n), 1.0))


def grid_seconds(
    h: int, w: int, nu: float, variance: bool, n_out: int = 0, extra: int = 0, readout: bool = False
) -> float:
    """Seconds of the grid route on an h x w lattice with ``extra`` further right-hand sides.

    Fronts are ds = d^2 times larger for nu > 0.5; with ``readout`` the n_out output pixels are
    read out through the Markov weights (`gpdepth3d.gp.readout`).
    """
    ds = state_dim(nu) ** 2
    n = float(h * w)
    t = (22.0 + (60.0 if variance else 0.0)) * n**1.5 * ds**3 / GRID_FLOPS_PER_S
    t += extra * GRID_SOLVE_S * n * np.log2(max(n, 2.0))
    if readout:
        t += n_out * (1 + extra) * READOUT_MEAN_S + (n_out * READOUT_VAR_S * ds if variance else 0.0)
    return t


def dense_seconds(m: int, n_out: int, variance: bool, extra: int = 0) -> float:
    """Seconds of the dense route: Cholesky m^3 / 3, cross tables n_out m per right-hand side, solves n_out m^2."""
    t = (m**3 / 3.0) / 10e9 + n_out * m * 3e-9 * (1 + extra)
    if variance:
        t += n_out * float(m) ** 2 / 4e9
    return t


def woodbury_seconds(m: int, n_out: int, variance: bool, extra: int = 0) -> float:
    """Seconds of `gpdepth3d.gp.woodbury.WoodburyPosterior` with m observed and n_out output pixels.

    Cholesky m^3 / 3 flops, for the variance the inverse 2 m^3 / 3 and a splat per pair of
    points, and a recursive filter per output pixel (rates fitted as in the module docstring).
    """
    t = m**3 / 3 / 15e9 + (1 + extra) * n_out * 10e-9 + extra * 2 * m * m / 5e9
    if variance:
        t += 2 * m**3 / 3 / 25e9 + m * (m + 1) / 2 * 40e-9 + n_out * 25e-9
    return t


def woodbury_bytes(m: int, n_out: int) -> int:
    """Peak memory (bytes) of the Woodbury route: three m x m matrices and twelve output images."""
    return 8 * (3 * m * m + 12 * n_out)


KISSGP_BYTES_PER_PIXEL = 6_000
"""Upper bound of the KISS-GP engine's working memory per grid and output pixel (bytes): GPyTorch's
interpolation indices, CG vectors and variance columns, from the peak resident memory of solves
at 300x400 and 600x800 pixels on the 2-core CI machine."""

KISSGP_BASE_BYTES = 1 << 30
"""The KISS-GP engine's memory beyond its per-pixel share (torch and GPyTorch themselves), bytes."""


def kissgp_bytes(shape: tuple[int, int], out_shape: tuple[int, int]) -> int:
    """Bytes a KISS-GP solve on a grid of ``shape`` with outputs ``out_shape`` may need (an upper bound)."""
    return KISSGP_BASE_BYTES + KISSGP_BYTES_PER_PIXEL * (shape[0] * shape[1] + out_shape[0] * out_shape[1])


MEMORY_READING_S = 0.5
"""Seconds one reading of the available memory serves `memory_budget`: a frame's route choices, and the
frames of a sequence at camera rate, share a reading instead of each parsing the system's memory table."""

_reading: tuple[float, int] = (-np.inf, 0)  # (time.monotonic() of the last reading, bytes available then)


def memory_budget() -> int:
    """Default memory budget of one solve (bytes): three quarters of the memory available now (read at most
    once per `MEMORY_READING_S`)."""
    global _reading
    now = time.monotonic()
    if now - _reading[0] > MEMORY_READING_S:
        try:
            import psutil

            avail = int(psutil.virtual_memory().available)
        except Exception:  # pragma: no cover - psutil missing or no /proc
            avail = int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        _reading = (now, avail)
    return _reading[1] * 3 // 4
