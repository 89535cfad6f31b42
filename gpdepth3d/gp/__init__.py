"""The GP depth model and the engines that compute its posterior.

Every engine satisfies the `Engine` protocol: it takes a `GridProblem` and returns the same
posterior as a `Solution` (mean, marginal variance, the means of further observation vectors, and
`SolveInfo`: the route and stage times of that call; it unpacks as ``mean, variance``).
`make_engine` builds one from the model config and an `EngineConfig` (device, back-end, route,
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
from .model import Kernel as Kernel
from .model import matern_1d as matern_1d
from ..errors import InvalidInputError
from .engine import check_engine_options


def make_engine(config: DepthGPConfig | EngineConfig | None = None, options: EngineConfig | None = None) -> Engine:
    """Builds the engine of a model config with the engine options (imports heavy back-ends lazily).

    Args:
        config: The model's `DepthGPConfig` (its ``engine`` names the engine unless
            ``options.name`` does, its ``max_exact_points`` bounds ``exact``), or an
            `EngineConfig` alone (then ``options`` must be None), or None (the ``fast`` engine).
        options: The engine's options (`EngineConfig`); None: the defaults.

    Returns:
        An ``ExactEngine``, ``KissGPEngine`` or ``FastEngine``.

    Raises:
        InvalidInputError: ``config`` or ``options`` of another type, an ``options.options`` key
            the engine does not take, or an option it rejects (e.g. a device torch does not see).
    """
    if isinstance(config, EngineConfig):
        if options is not None:
            raise InvalidInputError("options", "None when config is an EngineConfig", type(options).__name__)
        config, options = None, config
    if config is not None and not isinstance(config, DepthGPConfig):
        raise InvalidInputError("config", "a DepthGPConfig, an EngineConfig or None", type(config).__name__)
    if options is None:
        options = EngineConfig()
    elif not isinstance(options, EngineConfig):
        raise InvalidInputError("options", "an EngineConfig or None", type(options).__name__)
    name = options.name or (config.engine if config is not None else "fast")
    if name == "exact":
        from .exact import ExactEngine

        extra = check_engine_options(ExactEngine, options.options, ("max_points",))
        limit = options.max_exact_points or (config.max_exact_points if config is not None else 6000)
        return ExactEngine(max_points=limit, **extra)
    if name == "kissgp":
        from .kissgp import KissGPEngine

        extra = check_engine_options(KissGPEngine, options.options, ("device",))
        return KissGPEngine(device=options.device, **extra)
    if name == "fast":
        from .fast import FastEngine

        fields = ("device", "backend", "route", "threads", "max_dense_points", "max_memory_mb", "lattice")
        extra = check_engine_options(FastEngine, options.options, fields)
        return FastEngine(
            device=options.device,
            backend=options.backend,
            route=options.route,
            threads=options.threads,
            max_dense_points=options.max_dense_points,
            max_memory_mb=options.max_memory_mb,
            lattice=options.lattice,
            **extra,
        )
    raise InvalidInputError("engine", "'exact', 'kissgp' or 'fast'", name)
