"""Stage 4 of the default model: the engine's posterior of the field on the lattice (docs/model.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..gp.engine import SolveInfo
from .lattice import Lattice


@dataclass(frozen=True)
class FieldPosterior:
    """The stationary posterior of the field g at the output pixels (log depth).

    Attributes:
        mean: (Ho, Wo) E0[g].
        variance: (Ho, Wo) Var0[g].
        extra: One (Ho, Wo) read-out per extra observation vector of the lattice: the kriging weights'
            sum w1 = k(x)' (K + N)^-1 1, then the weighted centred log MDE wx = k(x)' (K + N)^-1 (x - c).
        info: The engine's facts of the call.
    """

    mean: np.ndarray
    variance: np.ndarray
    extra: tuple[np.ndarray, ...]
    info: SolveInfo


def solve_field(engine, lattice: Lattice) -> FieldPosterior:
    """One engine call for the mean, the variance and the extra right-hand sides (one factorisation).

    The variance is always computed: the log-normal mean needs it, so a posterior without variance keeps
    the same mean.
    """
    solution = engine.solve(lattice.problem, variance=True, extra_obs=lattice.extra)
    return FieldPosterior(solution.mean, solution.variance, tuple(solution.extra_means), solution.info)
