"""The GP depth model and the engines that compute its posterior.

Every engine satisfies the `Engine` protocol: it takes a `GridProblem` and returns the same
posterior as a `Solution` (mean, marginal variance, the means of further observation vectors, and
`SolveInfo`: the route and stage times of that call; it unpacks as ``mean, variance``).
`make_engine` builds one from an `EngineConfig` (the engine's name, device, back-end, route,
limits; docs/engines.md). They differ only in how they compute it:

* ``exact``: dense Cholesky, the reference for small inputs.
* ``kissgp``: GPyTorch KISS-GP (``GridInterpolationKernel``), faithful to the paper.
* ``fast``: the cheapest exact route that fits (`gpdepth3d.gp.routes`); the default.
  Every engine validates the problem first (`gpdepth3d.gp.exact.check_problem`); where ``fast``
  cannot compute the exact posterior (a kernel whose precision form is too ill-conditioned, a
  problem beyond the memory budget) it takes another route (``dense`` over few observed pixels)
  or raises a typed error (`gpdepth3d.gp.fast.IllConditionedError`, a `ConvergenceError`;
  `ProblemTooLargeError`), never a wrong answer.
"""

from __future__ import annotations

import importlib

from .engine import Engine as Engine
from .engine import EngineConfig as EngineConfig
from .engine import RoutedEngine as RoutedEngine
from .engine import Solution as Solution
from .engine import SolveInfo as SolveInfo
from .model import AssemblyConfig as AssemblyConfig
from .model import CalibrationConfig as CalibrationConfig
from .model import DepthGPConfig as DepthGPConfig
from .model import LatticeConfig as LatticeConfig
from .model import ScreenConfig as ScreenConfig
from .model import SlopeConfig as SlopeConfig
from .model import GridProblem as GridProblem
from .kernels import MaternKernel as MaternKernel
from .model import Kernel as Kernel
from .model import matern_1d as matern_1d
from ..errors import InvalidInputError
from .engine import ENGINES, check_engine_options


def make_engine(options: EngineConfig | None = None) -> Engine:
    """Builds the engine an `EngineConfig` names, with its options (imports heavy back-ends lazily).

    Args:
        options: The engine and its options; None: the defaults (the ``fast`` engine).

    Returns:
        The engine of ``options.name`` in `gpdepth3d.gp.engine.ENGINES` (``ExactEngine``, ``KissGPEngine`` or
        ``FastEngine``).

    Raises:
        InvalidInputError: ``options`` of another type, an ``options.options`` key the engine does not
            take, or an option it rejects (e.g. a device torch does not see).
    """
    if options is None:
        options = EngineConfig()
    elif not isinstance(options, EngineConfig):
        raise InvalidInputError("options", "an EngineConfig or None", type(options).__name__)
    entry = ENGINES[options.name]  # EngineConfig admits only its names
    kind = getattr(importlib.import_module(f"{__name__}.{entry.module}"), entry.class_name)
    extra = check_engine_options(kind, options.options, tuple(entry.fields))
    return kind(**{keyword: getattr(options, name) for keyword, name in entry.fields.items()}, **extra)
