"""Kernels compiled ahead, in a second process, while a first run compiles its own (a cold numba cache).

A first run compiles every kernel it calls (numba compiles on one core, and caches on disk). A run of the
default model calls the outlier screen's, the factorisation's, the solve's and the selected inverse's kernels
first, and the sub-lattice detail's after them; the demo then runs the paper's model, whose Neumann route has
kernels of its own. `compile_ahead` starts a second Python process that compiles those later kernels into the same
cache on another core, through the same wrappers (so with the same signatures) on a small problem; by the time the
first process reaches them it loads them from the cache. When it gets there first, both compile them, and
nothing is lost but the other core's time.

    python -m gpdepth3d.gp.compile_ahead detail neumann
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

GROUPS = ("detail", "neumann")
"""The kernel groups this module compiles: the grid route's read-out of means (`gpdepth3d.gp.readout.read_mean`)
with the sub-lattice detail (`gpdepth3d.gp.sublattice`), and the Neumann route (`gpdepth3d.gp.neumann`)."""


def _detail() -> None:
    """The read-out of the grid route's means off the grid, then the sub-lattice kriging's parallel kernel, as
    the default model calls them (three right-hand sides)."""
    import scipy.sparse as sp

    from .readout import Readout, read_mean
    from .sublattice import SERIAL_POINTS, sublattice_kriging

    weights = sp.csr_matrix(np.ones((3, 2)))
    read_mean(Readout(weights, weights, None, None, None, None, None), np.zeros(4), np.arange(4).reshape(2, 2), 1,
              np.zeros((3, 3)))  # fmt: skip

    h, w = 48, 2 * SERIAL_POINTS // 48 + 8
    rng = np.random.default_rng(0)
    pick = rng.choice(h * w, SERIAL_POINTS + 16, replace=False)
    rows, cols = pick // w, pick % w
    sublattice_kriging(
        np.arange(h, dtype=np.float64),
        np.arange(w, dtype=np.float64),
        rows,
        cols,
        rng.standard_normal((rows.size, 3)),
        np.full(rows.size, 1e-3),
        (h, w),
        stride=4,
        lengthscale=8.0,
        outputscale=0.2,
    )


def _neumann() -> None:
    """The Neumann route's coefficients, mean and variance series on a small grid (nu = 0.5)."""
    from .model import GridProblem, Kernel
    from .neumann import MAX_VARIANCE_TERMS, NeumannPosterior

    h, w = 12, 16
    prec = np.full((h, w), 400.0)
    problem = GridProblem(
        np.ones((h, w)), np.ones((h, w)), prec, np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64),
        np.ones((h, w)), Kernel(0.5, 1.5, 0.05),
    )  # fmt: skip
    post = NeumannPosterior(problem)
    post.mean(3)
    post.variance(min(4, MAX_VARIANCE_TERMS))


def compile_groups(groups: list[str]) -> None:
    """Compiles ``groups`` (names of `GROUPS`) in this process, in order."""
    for name in groups:
        {"detail": _detail, "neumann": _neumann}[name]()


def compile_ahead(groups: tuple[str, ...] = GROUPS) -> subprocess.Popen | None:
    """Starts a process compiling ``groups`` into the numba cache; None on a one-core machine (no core to spare).

    The process inherits the environment (the same ``NUMBA_CACHE_DIR`` and import path), prints nothing and is
    left to finish on its own.
    """
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        from ..errors import InvalidInputError

        raise InvalidInputError("groups", f"names from {GROUPS}", unknown)
    if (os.cpu_count() or 1) < 2 or not groups:
        return None
    return subprocess.Popen(
        [sys.executable, "-m", __name__, *groups],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


if __name__ == "__main__":  # pragma: no cover - the process compile_ahead starts
    compile_groups(sys.argv[1:])
