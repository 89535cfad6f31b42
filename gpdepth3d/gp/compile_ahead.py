"""Kernels compiled ahead, in a second process, while a first run compiles its own (a cold numba cache).

A first run compiles every kernel it calls (numba compiles on one core, and caches on disk). A run of the
default model calls the outlier screen's and the factorisation's kernels first, then the solve's and the
read-out's, the selected inverse's, and the sub-lattice detail's; the demo then runs the paper's model, whose
Neumann route has kernels of its own. `compile_ahead` starts a second Python process that compiles the later
groups (`GROUPS`) into the same cache on another core, through the same wrappers (so with the same signatures) on
a small problem, and reports each group as it is done; by the time the first process reaches them it loads them
from the cache. Before it calls a group's kernels, the first process waits (`gpdepth3d.gp.compile_wait.ready`)
until the second has reported the group: the wait is mostly shorter than compiling the group here would be (the
second process is at it on the other core, or done), and the two processes do not both compile a group. The
command line starts it when a command first compiles; a program, when its first `DepthCompleter` call does
(`on_cold_cache`); at most one per process.

    python -m gpdepth3d.gp.compile_ahead solve detail_serial detail neumann reuse
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys

import numpy as np

from . import compile_wait

ENV_SWITCH = "GPDEPTH3D_COMPILE_AHEAD"
"""Environment variable: "0" starts no process compiling ahead (a first run then compiles everything itself)."""

_WATCHED = False  # whether a completion call of this process has watched for a cold cache (`on_cold_cache`)

GROUPS = ("solve", "detail_serial", "detail", "neumann", "reuse")
"""The kernel groups this module compiles, in the order a run reaches them: the grid route's solve
(`gpdepth3d.gp.multifrontal`) with its read-out of means off the grid (`gpdepth3d.gp.readout.read_mean`), the
sub-lattice detail (`gpdepth3d.gp.sublattice`) of few points (serial) and of many (parallel; it shares the
serial kernel's per-row code, so it follows it), the Neumann route (`gpdepth3d.gp.neumann`), and the grid
route's reuse of the prior's factor from a resolution's second frame on."""

DEFAULT_MODEL_GROUPS = ("solve", "detail_serial", "detail", "reuse")
"""The groups a run of the default model reaches (the paper's model adds "neumann")."""


def _two_front_tree():
    """A `gpdepth3d.gp.multifrontal.FrontTree` of two fronts (four variables): the smallest the kernels run on."""
    from .multifrontal import FrontTree

    return FrontTree.build([0, 2], [2, 2], [1, -1], [[2], []], 4)


def _solve() -> None:
    """The grid route's solve (three right-hand sides) on a two-front tree, then the read-out of its means off the
    grid, as the default model calls them. The factor is left at zero: only the kernels' types matter here."""
    import scipy.sparse as sp

    from .multifrontal import FrontalFactor
    from .readout import Readout, read_mean

    tree = _two_front_tree()
    factor = FrontalFactor.__new__(FrontalFactor)  # no factorisation: its kernels are the first process's
    factor.tree, factor.scale2, factor.lbuf = tree, 1.0, np.zeros(tree.l_size)
    factor.solve(np.zeros((4, 3)))
    weights = sp.csr_matrix(np.ones((3, 2)))
    read_mean(Readout(weights, weights, None, None, None, None, None), np.zeros(4), np.arange(4).reshape(2, 2), 1,
              np.zeros((3, 3)))  # fmt: skip


def _reuse() -> None:
    """What the grid route's second frame of a resolution calls to reuse the prior's factor: the fronts that
    observations reach (`gpdepth3d.gp.multifrontal.FrontTree.touched_share`). No run waits for it: a second frame
    that comes before it compiles it itself."""
    _two_front_tree().touched_share(np.zeros(4))


def _detail(points: int) -> None:
    """The sub-lattice kriging of ``points`` points (its serial kernel below `sublattice.SERIAL_POINTS`, else its
    parallel one), as the default model calls it (three right-hand sides)."""
    from .sublattice import SERIAL_POINTS, sublattice_kriging

    h, w = 48, 2 * SERIAL_POINTS // 48 + 8
    rng = np.random.default_rng(0)
    pick = rng.choice(h * w, points, replace=False)
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


_COMPILE = {
    "solve": _solve,
    "detail_serial": lambda: _detail(16),
    "detail": lambda: _detail(2048),
    "neumann": _neumann,
    "reuse": _reuse,
}


def compile_groups(groups: list[str], *, report: bool = False) -> None:
    """Compiles ``groups`` (names of `GROUPS`) in this process, in order; with ``report``, writes each group's
    name on a line of the standard output once it is compiled (what `gpdepth3d.gp.compile_wait.ready` waits for)."""
    for name in groups:
        _COMPILE[name]()
        if report:
            try:
                os.write(1, f"{name}\n".encode())
            except OSError:  # the first process has ended: the cache is still worth filling
                pass


def compile_ahead(groups: tuple[str, ...] = GROUPS) -> subprocess.Popen | None:
    """Starts a process compiling ``groups`` into the numba cache; None on a one-core machine (no core to spare),
    when one was started already in this process, or with ``GPDEPTH3D_COMPILE_AHEAD=0`` in the environment.

    The process inherits the environment (the same ``NUMBA_CACHE_DIR`` and import path) and is left to finish on
    its own; until then `gpdepth3d.gp.compile_wait.ready` waits for its groups. It runs the interpreter that
    `multiprocessing` would start (``sys.executable`` unless an embedding application set another).
    """
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        from ..errors import InvalidInputError

        raise InvalidInputError("groups", f"names from {GROUPS}", unknown)
    if (os.cpu_count() or 1) < 2 or not groups or compile_wait.started() or os.environ.get(ENV_SWITCH) == "0":
        return None
    from multiprocessing import spawn

    proc = subprocess.Popen(
        [spawn.get_executable(), "-m", __name__, *groups],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    compile_wait.track(proc, groups)
    return proc


def on_cold_cache(groups: tuple[str, ...] = DEFAULT_MODEL_GROUPS) -> contextlib.AbstractContextManager:
    """A context around a completion call (`gpdepth3d.completion.DepthCompleter.complete`): the first numba compile
    of a package kernel inside it (a cold cache) starts `compile_ahead` of ``groups``. Only the first call of a
    process watches (the kernels a run calls first compile there); later calls get a context that does nothing.
    """
    global _WATCHED
    if _WATCHED:
        return contextlib.nullcontext()
    _WATCHED = True
    from .compile_notice import on_first_compile

    return on_first_compile(lambda _kernel: compile_ahead(groups))


if __name__ == "__main__":  # pragma: no cover - the process compile_ahead starts
    compile_groups(sys.argv[1:], report=True)
