"""The ``fast`` engine's routes as strategies: each says whether it fits a problem and what it costs.

Every route computes the same exact posterior; `choose_route` takes a forced one or the cheapest
that fits by `gpdepth3d.gp.cost_model`, else raises a typed error naming sizes and limits.
See `gpdepth3d.gp.fast.FastEngine` for what each route does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import NoReturn, Protocol, runtime_checkable

import numpy as np

from ..errors import ConvergenceError, InvalidInputError, ProblemTooLargeError
from .cost_model import (
    GRID_MAX_ERROR,
    NEUMANN_BYTES_PER_PIXEL,
    NEUMANN_MIN_OBSERVED,
    WOODBURY_MAX_SNR,
    dense_seconds,
    grid_bytes,
    grid_error_estimate,
    grid_seconds,
    woodbury_bytes,
    woodbury_seconds,
)
from .exact import dense_bytes
from .model import GridProblem
from .neumann import NEUMANN_MEAN_TOL, NeumannPosterior


class IllConditionedError(ConvergenceError):
    """The grid route's precision form is too ill-conditioned for float64 with this kernel (and no
    other route of the engine can take the problem)."""


@dataclass
class RouteQuery:
    """One call's facts that the routes judge (built by the engine per call).

    Attributes:
        problem: The problem as given.
        lattice: The grid route's problem: ``problem`` on the sub-grid spanning its observed
            pixels (`gpdepth3d.gp.observed_lattice`), or ``problem`` itself.
        variance: The call computes marginal variances.
        extra: Further right-hand sides (``extra_obs``) of the call.
        lml: The call is a log marginal likelihood (no Neumann series: it gives no determinant).
        forced: The route was named by the caller: held only to what it needs to be exact.
        backend: "compiled" or "torch"; ``auto`` takes Woodbury and Neumann on "compiled" only.
        budget: Memory budget of the call (bytes).
        max_dense_points: Most observed pixels of the dense route.
        grid_buffers_held: The engine already holds the grid route's buffers (it allocates none).
        neumann_buffers: The engine's workspace of the Neumann series.
        scratch: Objects a route's `fits` built for its `seconds` and for the solve (the series).
    """

    problem: GridProblem
    lattice: GridProblem
    variance: bool
    extra: int
    lml: bool
    forced: bool
    backend: str
    budget: int
    max_dense_points: int
    grid_buffers_held: bool = False
    neumann_buffers: dict | None = None
    scratch: dict = field(default_factory=dict)

    @cached_property
    def observed(self) -> int:
        """Observed pixels of the problem."""
        return int(np.count_nonzero(np.asarray(self.problem.precision) > 0))

    @cached_property
    def out_pixels(self) -> int:
        """Output pixels of the problem."""
        ho, wo = self.problem.out_shape
        return ho * wo

    @cached_property
    def near_noiseless(self) -> bool:
        """Some observation's noise is tiny against the outputscale (`WOODBURY_MAX_SNR`)."""
        prec = np.asarray(self.problem.precision, dtype=np.float64)
        return bool(
            prec.size
            and prec.max() > 0
            and float(prec.max()) * float(self.problem.kernel.outputscale) ** 2 > WOODBURY_MAX_SNR
        )


@dataclass(frozen=True)
class Refusal:
    """Why a route does not take a problem.

    Attributes:
        kind: "applicability" (the route cannot compute this problem: a forced one is an
            `InvalidInputError` on ``route``), "conditioning" (float64 cannot hold it),
            "memory" (over the budget) or "limit" (another limit of the route).
        text: The reason, with the sizes and limits involved.
        expected: For "applicability": what ``route`` should have been instead.
        got: For "applicability": what came (default: the route's name).
    """

    kind: str
    text: str
    expected: str = ""
    got: str = ""


@dataclass(frozen=True)
class RouteCost:
    """What a route costs on a problem by the cost model: wall-clock seconds and peak bytes."""

    seconds: float
    bytes: int


def _memory(needed: int, budget: int) -> Refusal | None:
    if needed > budget:
        return Refusal("memory", f"it needs ~{needed / 2**30:.3g} GiB (limit {budget / 2**30:.3g} GiB)")
    return None


@runtime_checkable
class Route(Protocol):
    """A way to compute the exact posterior: whether it fits a problem, and what it costs there.

    Capability flags state what a route needs of the kernel (`gpdepth3d.gp.kernels.MaternKernel`):
    ``needs_exponential``, the exponential kernel's first-order Markov form (nu = 1/2).
    """

    name: str
    needs_exponential: bool

    def fits(self, query: RouteQuery) -> Refusal | None:
        """None when the route can take the problem, else why not."""
        ...

    def cost(self, query: RouteQuery) -> RouteCost:
        """Seconds and bytes of the route on the problem (called only when it fits)."""
        ...

    def yields_to(self, query: RouteQuery) -> tuple[str, ...]:
        """Routes that ``auto`` prefers to this one whenever they fit (more accurate or the same algebra)."""
        ...


class GridRoute:
    """Sparse precision over the pixel lattice, multifrontal Cholesky and selected inverse (any nu)."""

    name = "grid"
    needs_exponential = False

    def fits(self, q: RouteQuery) -> Refusal | None:
        k = q.lattice.kernel
        err = grid_error_estimate(q.lattice)
        if err > GRID_MAX_ERROR:
            return Refusal(
                "conditioning",
                (
                    f"its precision form is too ill-conditioned for the Matern kernel nu={k.nu}, "
                    f"lengthscale={k.lengthscale:g} px (estimated error {err:.2g} x outputscale > {GRID_MAX_ERROR:g})"
                ),
            )
        return _memory(self._bytes(q), q.budget)

    @staticmethod
    def _bytes(q: RouteQuery) -> int:
        return 0 if q.grid_buffers_held else grid_bytes(q.lattice.shape, q.lattice.kernel.nu)

    def cost(self, q: RouteQuery) -> RouteCost:
        h, w = q.lattice.shape
        seconds = grid_seconds(h, w, q.problem.kernel.nu, q.variance, q.out_pixels, q.extra, q.lattice is not q.problem)
        return RouteCost(seconds, self._bytes(q))

    def yields_to(self, q: RouteQuery) -> tuple[str, ...]:
        return ()


class DenseRoute:
    """Dense algebra over the observed pixels (`gpdepth3d.gp.exact.dense_posterior`; any nu, few points)."""

    name = "dense"
    needs_exponential = False

    def fits(self, q: RouteQuery) -> Refusal | None:
        m = q.observed
        if m > q.max_dense_points:
            return Refusal("limit", f"{m} observed pixels exceed its limit of {q.max_dense_points}")
        return _memory(self._bytes(q), q.budget)

    def _bytes(self, q: RouteQuery) -> int:
        return dense_bytes(q.observed, q.out_pixels, variance=q.variance)

    def cost(self, q: RouteQuery) -> RouteCost:
        return RouteCost(dense_seconds(q.observed, q.out_pixels, q.variance, q.extra), self._bytes(q))

    def yields_to(self, q: RouteQuery) -> tuple[str, ...]:
        # Woodbury is the same algebra with an O(m^2 + n) variance; the grid is the torch back-end's
        # device route, and does not cancel near near-noiseless points.
        return ("woodbury", "grid") if q.backend == "torch" or q.near_noiseless else ("woodbury",)


def _kernel_refusal(route: Route, kernel) -> Refusal | None:
    """Why ``route`` cannot take ``kernel`` by its capability flags, or None."""
    if route.needs_exponential and not kernel.exponential:
        return Refusal(
            "applicability",
            "it needs nu = 0.5",
            f"'auto', 'grid' or 'dense' for nu = {kernel.nu} ('{route.name}' needs nu = 0.5)",
        )
    return None


class WoodburyRoute:
    """nu = 0.5: Woodbury over the observed pixels with recursive filtering (`gpdepth3d.gp.woodbury`)."""

    name = "woodbury"
    needs_exponential = True  # capability flag: its recursive filter is the exponential kernel's Markov chain

    def fits(self, q: RouteQuery) -> Refusal | None:
        refusal = _kernel_refusal(self, q.problem.kernel)
        if refusal is not None:
            return refusal
        if not q.forced and q.backend != "compiled":
            return Refusal("limit", "auto takes it with the compiled back-end only")
        if not q.forced and q.observed and q.near_noiseless:
            return Refusal("limit", "an observation's noise is too small against the outputscale")
        return _memory(woodbury_bytes(q.observed, q.out_pixels), q.budget)

    def cost(self, q: RouteQuery) -> RouteCost:
        return RouteCost(
            woodbury_seconds(q.observed, q.out_pixels, q.variance, q.extra), woodbury_bytes(q.observed, q.out_pixels)
        )

    def yields_to(self, q: RouteQuery) -> tuple[str, ...]:
        return ()


class NeumannRoute:
    """nu = 0.5, every pixel observed strongly: the certified Neumann series (`gpdepth3d.gp.neumann`).

    Its `fits` builds the series (whose convergence decides) and keeps it in ``query.scratch``.
    """

    name = "neumann"
    needs_exponential = True  # capability flag: its diagonal dominance is the exponential kernel's precision

    def _cheap_refusal(self, q: RouteQuery) -> Refusal | None:
        h, w = q.lattice.shape
        refusal = _kernel_refusal(self, q.problem.kernel)
        if refusal is not None:
            return refusal
        if not q.problem.output_is_input:
            return Refusal(
                "applicability",
                "it needs the output grid to be the input grid",
                "'auto', 'grid' or 'woodbury' for an output grid other than the input",
            )
        if not q.forced and (q.backend != "compiled" or q.lml):
            return Refusal("limit", "auto takes it with the compiled back-end, and not for the likelihood")
        if not q.forced and q.observed < NEUMANN_MIN_OBSERVED * h * w:
            return Refusal("limit", f"fewer than {NEUMANN_MIN_OBSERVED:.0%} of the pixels are observed")
        return _memory(NEUMANN_BYTES_PER_PIXEL * h * w, q.budget)

    def fits(self, q: RouteQuery) -> Refusal | None:
        why = self._cheap_refusal(q)
        if why is not None:
            return why
        series = NeumannPosterior(q.problem, q.neumann_buffers)
        if q.forced:
            ok = series.terms(NEUMANN_MEAN_TOL) is not None and not (q.variance and series.seconds(True) is None)
        else:
            ok = series.seconds(q.variance) is not None
        if not ok:
            series.release()
            return Refusal(
                "applicability" if q.forced else "limit",
                f"the series converges too slowly (rho = {series.rho:.3g})",
                "'auto' or 'grid': the precision is not diagonally dominant enough for 'neumann'",
                f"rho = {series.rho:.3g}",
            )
        q.scratch[self.name] = series
        return None

    def cost(self, q: RouteQuery) -> RouteCost:
        h, w = q.lattice.shape
        return RouteCost(q.scratch[self.name].seconds(q.variance), NEUMANN_BYTES_PER_PIXEL * h * w)

    def yields_to(self, q: RouteQuery) -> tuple[str, ...]:
        return ()


ROUTES: tuple[Route, ...] = (GridRoute(), DenseRoute(), WoodburyRoute(), NeumannRoute())
"""The routes, in the order ``auto`` breaks ties of equal cost."""


@dataclass
class RouteChoice:
    """The route `choose_route` took, its series (Neumann) or None, and what each route cost or why it was refused."""

    name: str
    payload: NeumannPosterior | None
    costs: dict
    refusals: dict

    def release(self) -> None:
        """Hands back the buffers of a payload that will not be used."""
        if self.payload is not None:
            self.payload.release()
            self.payload = None


def choose_route(query: RouteQuery, route: str) -> RouteChoice:
    """The forced ``route``, or with "auto" the cheapest route that fits (ties: `ROUTES` order).

    Raises:
        InvalidInputError: A forced route that cannot compute this problem (names ``route``).
        IllConditionedError: The grid route is too ill-conditioned and no other route fits.
        ProblemTooLargeError: No route (or not the forced one) fits in the memory and size limits.
    """
    if route != "auto":
        chosen = next(r for r in ROUTES if r.name == route)
        why = chosen.fits(query)
        if why is not None and why.kind == "applicability":
            raise InvalidInputError("route", why.expected, why.got or route)
        if why is not None:
            refuse({route: why}, query.problem)
        return RouteChoice(route, query.scratch.pop(route, None), {}, {})
    costs, refusals = {}, {}
    for r in ROUTES:
        why = r.fits(query)
        if why is None:
            costs[r.name] = r.cost(query)
        else:
            refusals[r.name] = why
    for r in ROUTES:
        if r.name in costs and any(other in costs for other in r.yields_to(query)):
            del costs[r.name]
    if not costs:
        refuse(refusals, query.problem)
    name = min(costs, key=lambda n: costs[n].seconds)
    choice = RouteChoice(name, query.scratch.pop(name, None), costs, refusals)
    for series in query.scratch.values():
        series.release()
    query.scratch.clear()
    return choice


def refuse(refusals: dict, problem: GridProblem) -> NoReturn:
    """Raises the typed error saying why no route (or not the forced one) takes ``problem``.

    `IllConditionedError` when a route was refused for conditioning and none for memory, else
    `ProblemTooLargeError`; the message names the grid, the observed pixels, the kernel and each
    route's sizes and limits.
    """
    k = problem.kernel
    text = "; ".join(f"the {r} route is refused: {why.text}" for r, why in refusals.items())
    msg = (
        f"fast engine: no route for a {problem.shape[0]} x {problem.shape[1]} grid with "
        f"{int(np.count_nonzero(np.asarray(problem.precision) > 0))} observed pixels, Matern nu={k.nu}, "
        f"lengthscale={k.lengthscale:g} px: {text}"
    )
    kinds = {why.kind for why in refusals.values()}
    if "conditioning" in kinds and "memory" not in kinds:
        raise IllConditionedError(msg + "; use a smaller lengthscale or nu, or fewer observed pixels")
    raise ProblemTooLargeError(msg + "; use a smaller grid or output, or fewer observed pixels")
