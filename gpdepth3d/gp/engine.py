"""What every engine shares: the `Engine` protocol, its options (`EngineConfig`) and what a call returns.

An engine (``exact``, ``kissgp``, ``fast``) computes the posterior of a `GridProblem` with
``engine.solve(problem, variance=True, extra_obs=())`` and returns a `Solution`; engines with
several routes also satisfy `RoutedEngine` (``plan``, ``factorize``, ``log_marginal_likelihood``).
See docs/architecture.md.
"""

from __future__ import annotations

import inspect
import re
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Iterator, Literal, Protocol, runtime_checkable

import numba as nb
import numpy as np

from ..checks import Choice, Int, check_fields, positive
from ..errors import InvalidInputError, ShapeError, describe

if TYPE_CHECKING:  # the model imports nothing from here; the annotation only
    from .model import GridProblem


@dataclass(frozen=True)
class EngineEntry:
    """How `gpdepth3d.gp.make_engine` builds one engine (its module is imported only then).

    Attributes:
        module: The module of `gpdepth3d.gp` that holds the engine's class.
        class_name: The class, whose constructor takes the keywords of ``fields``.
        fields: Constructor keyword -> the `EngineConfig` field that sets it.
    """

    module: str
    class_name: str
    fields: dict[str, str]


_FAST_FIELDS = ("device", "backend", "route", "threads", "max_dense_points", "max_memory_mb", "lattice")
ENGINES: dict[str, EngineEntry] = {
    "exact": EngineEntry("exact", "ExactEngine", {"max_points": "max_exact_points"}),
    "kissgp": EngineEntry("kissgp", "KissGPEngine", {"device": "device"}),
    "fast": EngineEntry("fast", "FastEngine", {f: f for f in _FAST_FIELDS}),
}
"""The engines `EngineConfig.name` chooses from; a new engine is one entry (and its name in `EngineName`)."""
ENGINE_NAMES = tuple(ENGINES)
EngineName = Literal["exact", "kissgp", "fast"]
FAST_BACKENDS = ("auto", "compiled", "torch")
FAST_ROUTES = ("auto", "grid", "woodbury", "neumann", "dense")
DEVICE_PATTERN = re.compile(r"(cpu|cuda|mps)(:[0-9]+)?")
"""Torch devices an engine accepts: "cpu", "cuda" or "mps", with an optional index ("cuda:1")."""


def device_name(device, argument: str = "device") -> str | None:
    """``device`` (None, a str or a torch.device) as a name matching `DEVICE_PATTERN`.

    Raises:
        InvalidInputError: another type, or a name torch does not run the engines on ("tpu").
    """
    if device is None:
        return None
    if not isinstance(device, str):
        if type(device).__name__ != "device":  # torch.device, without importing torch
            raise InvalidInputError(argument, "None, a str or a torch.device", describe(device))
        device = str(device)
    if DEVICE_PATTERN.fullmatch(device) is None:
        raise InvalidInputError(argument, "a torch device 'cpu', 'cuda', 'cuda:N' or 'mps'", repr(device))
    return device


def check_device_available(device, argument: str = "device") -> str | None:
    """`device_name` of ``device``, checked against the devices torch sees (imports torch unless CPU).

    Raises:
        InvalidInputError: a malformed device, or one torch does not see (``"cuda"`` on a CPU-only torch).
    """
    name = device_name(device, argument)
    if name is None or name == "cpu":
        return name
    import torch

    kind, _, index = name.partition(":")
    if kind == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise InvalidInputError(argument, "an available device (torch sees no CUDA GPU)", name)
        if index and int(index) >= count:
            raise InvalidInputError(argument, f"a CUDA device index below {count}", name)
    elif kind == "mps" and not torch.backends.mps.is_available():
        raise InvalidInputError(argument, "an available device (torch sees no MPS device)", name)
    return name


def check_engine_options(engine_class: type, options: dict, fixed: tuple = ()) -> dict:
    """``options`` checked against the keyword arguments of ``engine_class`` (those in ``fixed`` are set by fields).

    Raises:
        InvalidInputError: (argument ``options``) a key the constructor does not take, or one that an
            `EngineConfig` field sets.
    """
    params = inspect.signature(engine_class.__init__).parameters
    accepted = sorted(
        n
        for n, p in params.items()
        if n != "self" and n not in fixed and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    )
    for key in options:
        if key not in accepted:
            raise InvalidInputError(
                "options", f"keyword arguments of {engine_class.__name__} among {accepted}", repr(key)
            )
    return dict(options)


@dataclass(frozen=True)
class EngineConfig:
    """Options of the engine that computes a posterior (not of the model it computes).

    Attributes:
        name: "exact" (dense Cholesky, the reference), "kissgp" (GPyTorch, as the paper) or "fast"
            (grid-structured, the default); they compute the same posterior.
        device: Torch device of the ``fast`` engine's torch back-end and of ``kissgp`` ("cpu",
            "cuda", "cuda:1", "mps"; a torch.device is kept as its name); None: the CPU for
            ``fast``, CUDA when available for ``kissgp``. The engine refuses one torch does not see.
        backend: ``fast``: "auto" (compiled on the CPU, torch elsewhere), "compiled" or "torch".
        route: ``fast``: "auto" (the cheapest exact route by its cost model), "grid",
            "woodbury", "neumann" or "dense" (see `gpdepth3d.gp.fast.FastEngine`).
        lattice: ``fast`` grid route: "observed" (the default: the sub-grid spanning the
            observed pixels, the rest read out exactly by the Markov property) or "full" (the
            whole GP grid; for checks).
        threads: ``fast`` torch back-end: torch CPU threads during a call (None: unchanged).
        max_dense_points: ``fast``: most observed pixels of the dense route.
        max_memory_mb: ``fast``: memory budget of one call (MiB); None: 3/4 of the free memory.
        max_exact_points: ``exact``: most observed pixels (it refuses larger problems).
        lattice_stride: The default model (``log_residual``): GP-grid pixels per lattice node of its field,
            per side (1-16); None: automatic (`gpdepth3d.gp.model.LatticeConfig`); 1 is the exact model on
            every pixel.
        options: Further keyword arguments of the engine's constructor (e.g. ``kissgp``'s
            ``cg_tolerance``, ``fast``'s ``tile``); a key it does not take, or one a field above
            sets, is an `InvalidInputError` on ``options``.
    """

    name: EngineName = "fast"
    device: str | None = None
    backend: str = "auto"
    route: str = "auto"
    lattice: str = "observed"
    threads: int | None = 1
    max_dense_points: int = 6000
    max_memory_mb: float | None = None
    max_exact_points: int = 6000
    lattice_stride: int | None = None
    options: dict = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "device", device_name(self.device))  # a torch.device as its name
        check_fields(self, _RULES)
        if not isinstance(self.options, dict) or not all(isinstance(k, str) for k in self.options):
            raise InvalidInputError("options", "a dict of keyword arguments", describe(self.options))

    def replace(self, **changes) -> "EngineConfig":
        """A copy with some fields changed."""
        return replace(self, **changes)


_RULES = {
    "name": Choice(ENGINE_NAMES),
    "backend": Choice(FAST_BACKENDS),
    "route": Choice(FAST_ROUTES),
    "lattice": Choice(("observed", "full")),
    "threads": Int(1, optional=True),
    "max_dense_points": Int(0),
    "max_memory_mb": positive("MiB", optional=True),
    "max_exact_points": Int(1),
    "lattice_stride": Int(1, 16, optional=True),
}
"""`EngineConfig`'s fields and their rules (`gpdepth3d.checks`)."""


def _is_int(v, low: int) -> bool:
    return not isinstance(v, (bool, np.bool_)) and isinstance(v, (int, np.integer)) and v >= low


@dataclass(frozen=True)
class SolveInfo:
    """Facts of one `solve` call.

    Attributes:
        engine: The engine's name.
        route: How the posterior was computed (``fast``: "grid", "woodbury", "neumann" or
            "dense"; ``exact``: "dense"; ``kissgp``: "kissgp").
        seconds: Wall-clock seconds per stage (engine-specific keys; "total" always).
        details: Other facts of the call (``kissgp``: CG iterations and residuals; ``fast``:
            observed pixels, the lattice of the grid route).
    """

    engine: str
    route: str
    seconds: dict = field(default_factory=dict)
    details: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Solution:
    """Posterior of one `GridProblem` (what ``engine.solve`` returns).

    Attributes:
        mean: (Ho, Wo) posterior mean.
        variance: (Ho, Wo) posterior marginal variance, or None when not asked for.
        info: The facts of the call (`SolveInfo`).
        extra_means: One (Ho, Wo) posterior mean per observation vector of ``extra_obs``.

    It unpacks as the pair ``mean, var = engine.solve(problem)``; ``solution[0]`` and
    ``solution[1]`` work too.
    """

    mean: np.ndarray
    variance: np.ndarray | None
    info: SolveInfo
    extra_means: tuple = ()

    def __iter__(self) -> Iterator[Any]:
        yield self.mean
        yield self.variance

    def __len__(self) -> int:
        return 2

    def __getitem__(self, index):
        return (self.mean, self.variance)[index]


def check_extra_obs(problem, extra_obs) -> tuple[np.ndarray, ...]:
    """Validates ``extra_obs`` of a solve: (H, W) finite arrays (values matter where observed).

    Raises:
        ShapeError: not a sequence of arrays of the problem's grid shape.
        InvalidInputError: non-finite values at observed pixels.
    """
    if extra_obs is None:
        return ()
    if isinstance(extra_obs, np.ndarray) or not hasattr(extra_obs, "__iter__"):
        raise ShapeError("extra_obs", "a sequence of (H, W) observation arrays", describe(extra_obs))
    out = []
    prec = np.asarray(problem.precision, dtype=np.float64)
    for i, obs in enumerate(extra_obs):
        a = np.asarray(obs, dtype=np.float64)
        if a.shape != problem.shape:
            raise ShapeError(f"extra_obs[{i}]", f"shape {problem.shape}", describe(a))
        if any_outside_where_observed(prec, a, np.inf):
            raise InvalidInputError(f"extra_obs[{i}]", "finite values at the observed pixels", "non-finite values")
        out.append(a)
    return tuple(out)


def any_outside_where_observed(precision: np.ndarray, values: np.ndarray, limit: float) -> bool:
    """True when a value at an observed pixel (precision > 0) is not finite or beyond +-``limit``.

    One compiled pass over both (H, W) arrays, without the boolean masks and compressed copies of
    ``values[precision > 0]`` (a check that runs on every solve).
    """
    return bool(_any_outside(_flat(precision), _flat(values), float(limit)))


def _flat(a: np.ndarray) -> np.ndarray:
    """``a`` as a read-only contiguous 1-D float64 array (one compiled signature for every caller's array)."""
    out = np.ascontiguousarray(a, dtype=np.float64).reshape(-1).view()
    out.flags.writeable = False
    return out


@nb.njit(nogil=True, cache=True)
def _any_outside(precision, values, limit):
    """`any_outside_where_observed` over flat arrays."""
    for i in range(precision.size):
        if precision[i] > 0.0:
            v = abs(values[i])
            if not (v <= limit and v < np.inf):
                return True
    return False


@runtime_checkable
class Engine(Protocol):
    """What every engine provides: a name and `solve`, the posterior of one `GridProblem`.

    ``solve`` returns a `Solution`: mean (Ho, Wo) in metres, marginal variance (Ho, Wo) in m^2
    (None when ``variance`` is False), the means of ``extra_obs`` and the call's `SolveInfo`.
    It stores nothing about the call on the engine, so one engine can serve several callers.
    """

    name: str

    def solve(self, problem: "GridProblem", *, variance: bool = True, extra_obs=()) -> Solution:
        """Posterior of ``problem``; raises the typed errors of `gpdepth3d.errors`, never a wrong answer."""
        ...


@runtime_checkable
class RoutedEngine(Engine, Protocol):
    """An `Engine` that chooses among routes (``fast``): says which one beforehand, and gives the likelihood.

    ``plan`` returns the route name `solve` would take; ``factorize`` the grid route's factor;
    ``log_marginal_likelihood`` log p(y) of the observed pixels in nats (what fitting maximises).
    """

    def plan(self, problem: "GridProblem", *, variance: bool = True, extra: int = 0, lml: bool = False) -> str:
        """The route `solve` (or, with ``lml``, `log_marginal_likelihood`) takes for ``problem``."""
        ...

    def factorize(self, problem: "GridProblem"):
        """The factorisation of the posterior precision that `solve` would use."""
        ...

    def log_marginal_likelihood(self, problem: "GridProblem") -> float:
        """log p(y) of the observed pixels of ``problem`` (nats)."""
        ...
