"""The fast engine's routes as strategies (gpdepth3d.gp.routes): fits, cost, the cheapest choice, typed refusals."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, ProblemTooLargeError
from gpdepth3d.gp.cost_model import dense_seconds, grid_seconds, woodbury_seconds
from gpdepth3d.gp.model import GridProblem, Kernel
from gpdepth3d.gp.routes import ROUTES, IllConditionedError, Refusal, Route, RouteCost, RouteQuery, choose_route


def problem(h=30, w=40, points=20, *, nu=0.5, lengthscale=5.0, every=False, noise=0.05):
    rng = np.random.default_rng(0)
    prec = np.full((h, w), 1.0 / 0.04**2) if every else np.zeros((h, w))
    idx = rng.choice(h * w, points, replace=False)
    prec.ravel()[idx] += 1.0 / noise**2
    prior = np.full((h, w), 3.0)
    return GridProblem(
        prior,
        prior + rng.normal(0, 0.1, (h, w)),
        prec,
        np.arange(h, dtype=float),
        np.arange(w, dtype=float),
        prior,
        Kernel(nu, lengthscale, 0.5),
    )


def query(p, *, route="auto", backend="compiled", budget=2**34, max_dense_points=6000, variance=True, lml=False):
    return RouteQuery(p, p, variance, 0, lml, route != "auto", backend, budget, max_dense_points, neumann_buffers={})


def test_every_route_is_a_route_with_a_name():
    assert [r.name for r in ROUTES] == ["grid", "dense", "woodbury", "neumann"]
    assert all(isinstance(r, Route) for r in ROUTES)


class TestFitsAndCost:
    def test_costs_come_from_the_cost_model(self):
        p = problem()
        q = query(p)
        costs = {r.name: r.cost(q) for r in ROUTES[:3] if r.fits(q) is None}
        assert costs["grid"].seconds == pytest.approx(grid_seconds(30, 40, 0.5, True))
        assert costs["dense"].seconds == pytest.approx(dense_seconds(20, 1200, True))
        assert costs["woodbury"].seconds == pytest.approx(woodbury_seconds(20, 1200, True))
        assert all(isinstance(c, RouteCost) and c.bytes > 0 for c in costs.values())

    def test_reasons_name_sizes_and_limits(self):
        p = problem(points=50)
        why = {r.name: r.fits(query(p, budget=1000, max_dense_points=10)) for r in ROUTES}
        assert why["dense"] == Refusal("limit", "50 observed pixels exceed its limit of 10")
        assert why["grid"].kind == "memory" and "GiB (limit 9.31e-07 GiB)" in why["grid"].text
        assert why["neumann"].kind == "limit" and "90%" in why["neumann"].text

    def test_applicability(self):
        p = problem(nu=1.5)
        for r in ROUTES[2:]:
            why = r.fits(query(p, route=r.name))
            assert why.kind == "applicability" and "nu = 0.5" in why.expected


class TestChoice:
    def test_cheapest_that_fits(self):
        q = query(problem(points=20))
        choice = choose_route(q, "auto")
        assert choice.name == min(choice.costs, key=lambda n: choice.costs[n].seconds) == "woodbury"
        assert "dense" not in choice.costs  # it yields to Woodbury, the same algebra
        assert choose_route(query(problem(points=20), backend="torch"), "auto").name == "grid"

    def test_neumann_when_every_pixel_is_observed(self):
        choice = choose_route(query(problem(120, 160, every=True, lengthscale=1.5)), "auto")
        assert choice.name == "neumann" and choice.payload is not None
        choice.release()
        assert choice.payload is None

    def test_refusal_is_typed_and_names_sizes(self):
        p = problem(points=50)
        with pytest.raises(ProblemTooLargeError, match=r"30 x 40 grid with 50 observed pixels.*limit of 10"):
            choose_route(query(p, budget=1000, max_dense_points=10), "auto")
        with pytest.raises(ProblemTooLargeError, match="the dense route is refused"):
            choose_route(query(p, route="dense", max_dense_points=10), "dense")

    def test_ill_conditioned_only_when_no_memory_refusal(self):
        p = problem(nu=2.5, lengthscale=100.0, every=True)
        with pytest.raises(IllConditionedError, match="ill-conditioned"):
            choose_route(query(p, max_dense_points=10), "auto")

    def test_forced_route_that_cannot_compute_it(self):
        with pytest.raises(InvalidInputError, match="route.*needs nu = 0.5"):
            choose_route(query(problem(nu=1.5), route="woodbury"), "woodbury")
        with pytest.raises(InvalidInputError, match="diagonally dominant"):
            choose_route(query(problem(points=20), route="neumann"), "neumann")
