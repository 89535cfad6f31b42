"""The GP depth model and the engines that compute its posterior.

All engines take a `GridProblem` and return the same posterior (mean, marginal variance);
they differ only in how they compute it:

* ``exact``: dense Cholesky, the reference for small inputs.
* ``kissgp``: GPyTorch KISS-GP (``GridInterpolationKernel``), faithful to the paper.
* ``fast``: exploits the pixel grid (sparse precision, or Woodbury over few points); the default.
  Every engine validates the problem first (`gpdepth3d.gp.exact.check_problem`); where ``fast``
  cannot compute the exact posterior (a kernel whose precision form is too ill-conditioned, a
  problem beyond the memory budget) it takes another route (``dense`` over few observed pixels)
  or raises a typed error (`gpdepth3d.gp.fast.IllConditionedError`, a `ConvergenceError`;
  `ProblemTooLargeError`), never a wrong answer.
"""

from __future__ import annotations

from .model import DepthGPConfig as DepthGPConfig
from .model import GridProblem as GridProblem
from .model import Kernel as Kernel
from .model import matern_1d as matern_1d
from ..errors import InvalidInputError


def make_engine(config: DepthGPConfig):
    """Builds the engine named by ``config.engine`` (imports heavy back-ends lazily)."""
    if config.engine == "exact":
        from .exact import ExactEngine

        return ExactEngine(max_points=config.max_exact_points)
    if config.engine == "kissgp":
        from .kissgp import KissGPEngine

        return KissGPEngine()
    if config.engine == "fast":
        from .fast import FastEngine

        return FastEngine()
    raise InvalidInputError("engine", "'exact', 'kissgp' or 'fast'", config.engine)
