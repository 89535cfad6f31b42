"""The sub-grid spanning the observed pixels, which the grid route factorises instead of the whole grid.

The separable Matern field is Markov along each axis, so the posterior there is the whole grid's
and the pixels outside are read out exactly (`gpdepth3d.gp.readout`).
"""

from __future__ import annotations

import numpy as np


LATTICE_QUANTUM = 8
"""The observed lattice's bounds are rounded outwards to multiples of this many pixels (clipped to
the grid), so that the frames of a sequence share its elimination structure."""


def observed_lattice(precision: np.ndarray, quantum: int = LATTICE_QUANTUM) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1): the sub-grid [r0, r1) x [c0, c1) spanning the observed pixels, or None for the whole grid.

    The separable Matern field is Markov along each axis, so the posterior on this sub-grid
    given the observations (all inside it) is the posterior of the whole grid there, and every
    other pixel is read out exactly from the sub-grid's states next to it (as an output grid
    other than the input grid is, `markov.readout_weights`). The bounds are rounded outwards
    to multiples of ``quantum`` and the sub-grid has at least 2 x 2 pixels.

    Args:
        precision: (H, W) observation precisions (0 = unobserved).
        quantum: Rounding of the bounds (pixels, >= 1).

    Returns:
        The bounds, or None when there is no observation or the sub-grid is the whole grid.
    """
    obs = np.asarray(precision) > 0
    h, w = obs.shape
    rows = np.flatnonzero(obs.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(obs.any(axis=0))
    q = max(int(quantum), 1)

    def bounds(lo: int, hi: int, n: int) -> tuple[int, int]:
        lo, hi = (lo // q) * q, min(n, -(-hi // q) * q)
        if hi - lo < 2:  # the grid route needs two nodes per axis (n >= 2 is checked)
            lo = min(lo, n - 2)
            hi = lo + 2
        return lo, hi

    r0, r1 = bounds(int(rows[0]), int(rows[-1]) + 1, h)
    c0, c1 = bounds(int(cols[0]), int(cols[-1]) + 1, w)
    if (r0, r1, c0, c1) == (0, h, 0, w):
        return None
    return r0, r1, c0, c1
