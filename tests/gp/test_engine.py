"""The engine protocol: EngineConfig / make_engine, Solution and SolveInfo, extra right-hand sides, the observed lattice."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.gp import Engine, EngineConfig, RoutedEngine, Solution, SolveInfo, make_engine
from gpdepth3d.gp.exact import ExactEngine, dense_posterior, dense_solve
from gpdepth3d.gp.fast import LATTICE_QUANTUM, FastEngine, observed_lattice
from gpdepth3d.gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates


def problem_with_points(rng, h, w, points, *, nu=0.5, lengthscale=8.0, s=0.5, out=None, box=None, noise=0.05):
    """Residual-style problem: ``points`` observed pixels (inside ``box`` = (r0, r1, c0, c1) if given)."""
    r0, r1, c0, c1 = box or (0, h, 0, w)
    prec = np.zeros((h, w))
    cells = rng.choice((r1 - r0) * (c1 - c0), points, replace=False)
    rr, cc = np.divmod(cells, c1 - c0)
    prec[rr + r0, cc + c0] = 1.0 / (noise * rng.uniform(0.5, 2.0, points)) ** 2
    prior = rng.normal(5.0, 0.2, (h, w))
    obs = prior + rng.normal(0.0, s, (h, w))
    ho, wo = out or (h, w)
    return GridProblem(
        prior,
        obs,
        prec,
        output_coordinates(h, ho),
        output_coordinates(w, wo),
        rng.normal(5.0, 0.2, (ho, wo)),
        Kernel(nu, lengthscale, s),
    )


class TestEngineConfig:
    def test_defaults(self):
        c = EngineConfig()
        assert (c.name, c.device, c.backend, c.route, c.lattice) == ("fast", None, "auto", "auto", "observed")
        assert (c.max_exact_points, c.lattice_stride) == (6000, None)
        assert c.replace(route="grid").route == "grid" and c.route == "auto"

    @pytest.mark.parametrize(
        "field,value",
        [
            ("name", "fastest"),
            ("backend", "gpu"),
            ("route", "quick"),
            ("lattice", "half"),
            ("options", ["tile"]),
            ("max_exact_points", 0),
            ("max_exact_points", True),
            ("max_exact_points", None),
            ("name", None),
            ("lattice_stride", 0),
            ("lattice_stride", 17),
            ("lattice_stride", 2.0),
        ],
    )
    def test_bad_values_name_the_field(self, field, value):
        with pytest.raises(InvalidInputError, match=field):
            EngineConfig(**{field: value})

    def test_hashable_and_comparable(self):
        assert EngineConfig(route="grid") == EngineConfig(route="grid")
        assert len({EngineConfig(), EngineConfig(options={"tile": 16})}) >= 1  # options do not enter the hash


def keyword_only(method, names):
    """True when ``method`` takes ``names`` as keyword-only parameters (as the protocol states them)."""
    import inspect

    params = inspect.signature(method).parameters
    return all(n in params and params[n].kind is inspect.Parameter.KEYWORD_ONLY for n in names)


class TestEngineProtocol:
    @pytest.mark.parametrize("name", ["exact", "kissgp", "fast"])
    def test_every_engine_satisfies_the_protocol(self, name):
        if name == "kissgp":
            pytest.importorskip("gpytorch")
        engine = make_engine(EngineConfig(name=name, device="cpu" if name == "kissgp" else None))
        assert isinstance(engine, Engine) and engine.name == name
        assert keyword_only(engine.solve, ("variance", "extra_obs"))
        solution = engine.solve(problem_with_points(np.random.default_rng(20), 8, 9, 6), variance=False)
        assert isinstance(solution, Solution) and isinstance(solution.info, SolveInfo)
        assert solution.info.engine == name and solution.variance is None and solution.mean.shape == (8, 9)

    def test_routed_engines(self):
        fast = make_engine(EngineConfig(name="fast"))
        assert isinstance(fast, RoutedEngine)
        assert keyword_only(fast.plan, ("variance", "extra", "lml"))
        problem = problem_with_points(np.random.default_rng(21), 8, 9, 6)
        assert fast.plan(problem) in ("grid", "woodbury", "neumann", "dense")
        assert np.isfinite(fast.log_marginal_likelihood(problem))
        assert not isinstance(ExactEngine(), RoutedEngine)  # one route: no plan

    def test_objects_without_solve_are_not_engines(self):
        class NoSolve:
            name = "none"

        class NoName:
            def solve(self, problem, *, variance=True, extra_obs=()):
                return None

        assert not isinstance(NoSolve(), Engine) and not isinstance(NoName(), Engine)


class TestMakeEngine:
    def test_the_options_set_the_engine_up(self):
        engine = make_engine(
            EngineConfig(route="grid", lattice="full", max_dense_points=7, max_memory_mb=512, options={"tile": 16})
        )
        assert isinstance(engine, FastEngine)
        assert (engine.route, engine.lattice, engine.max_dense_points, engine.max_memory_mb, engine.tile) == (
            "grid",
            "full",
            7,
            512.0,
            16,
        )

    def test_the_config_names_the_engine_and_bounds_exact(self):
        engine = make_engine(EngineConfig(name="exact", max_exact_points=77))
        assert isinstance(engine, ExactEngine) and engine.max_points == 77
        assert make_engine(EngineConfig(name="exact")).max_points == 6000

    def test_engine_config_alone_and_none(self):
        assert isinstance(make_engine(EngineConfig(name="exact")), ExactEngine)
        assert isinstance(make_engine(), FastEngine)

    def test_bad_arguments(self):
        with pytest.raises(InvalidInputError, match="options"):
            make_engine("fast")
        with pytest.raises(InvalidInputError, match="options"):
            make_engine(DepthGPConfig())
        with pytest.raises(InvalidInputError, match="options"):
            make_engine({"route": "grid"})
        with pytest.raises(InvalidInputError, match="options"):
            make_engine(EngineConfig(options={"no_such_option": 1}))

    def test_completer_takes_the_engine_options(self):
        with pytest.raises(InvalidInputError, match="engine"):
            DepthCompleter(DepthGPConfig.residual(), engine="exact")
        completer = DepthCompleter(DepthGPConfig.residual(), engine=EngineConfig(route="grid"))
        assert isinstance(completer.engine, FastEngine) and completer.engine.route == "grid"


class TestSolution:
    def test_unpacks_and_indexes_as_the_old_pair(self):
        problem = problem_with_points(np.random.default_rng(0), 8, 9, 6)
        solution = ExactEngine().solve(problem)
        mean, var = solution
        assert isinstance(solution, Solution) and len(solution) == 2
        assert solution[0] is mean is solution.mean and solution[1] is var is solution.variance
        assert solution.extra_means == ()

    @pytest.mark.parametrize("route", ["grid", "woodbury", "dense"])
    def test_fast_info_says_what_the_call_did(self, route):
        problem = problem_with_points(np.random.default_rng(1), 20, 24, 12, box=(8, 16, 4, 20))
        solution = FastEngine(route=route).solve(problem)
        info = solution.info
        assert isinstance(info, SolveInfo) and info.engine == "fast" and info.route == route
        assert info.details["observed"] == 12
        assert info.seconds["total"] >= max(v for k, v in info.seconds.items() if k != "total") >= 0
        if route == "grid":
            r0, r1, c0, c1 = info.details["lattice"]
            assert r0 % LATTICE_QUANTUM == 0 and c0 % LATTICE_QUANTUM == 0 and (r1 - r0, c1 - c0) != (20, 24)

    def test_no_per_call_state_on_the_engines(self):
        engine = FastEngine()
        engine.solve(problem_with_points(np.random.default_rng(2), 10, 12, 5))
        assert not hasattr(engine, "last_route") and not hasattr(ExactEngine(), "last_route")

    def test_plan_matches_the_route_taken(self):
        rng = np.random.default_rng(3)
        engine = FastEngine()
        for problem in (
            problem_with_points(rng, 30, 40, 10),
            problem_with_points(rng, 30, 40, 900),
            problem_with_points(rng, 12, 14, 10, nu=1.5),
        ):
            assert engine.plan(problem) == engine.solve(problem).info.route


def engines_and_routes():
    return [
        ("exact", {}),
        ("fast", {"route": "grid"}),
        ("fast", {"route": "grid", "lattice": "full"}),
        ("fast", {"route": "woodbury"}),
        ("fast", {"route": "dense"}),
        ("fast", {"route": "auto"}),
    ]


class TestExtraObservations:
    @pytest.mark.parametrize("name,kwargs", engines_and_routes())
    @pytest.mark.parametrize("out", [None, (31, 17)])
    def test_extra_means_equal_separate_solves(self, name, kwargs, out):
        rng = np.random.default_rng(4)
        problem = problem_with_points(rng, 14, 11, 20, out=out, box=(2, 12, 0, 9))
        ones = np.where(problem.precision > 0, 1.0, 0.0)
        other = rng.normal(4.0, 1.0, problem.shape)
        engine = make_engine(EngineConfig(name=name, **kwargs))
        solution = engine.solve(problem, extra_obs=(ones, other))
        alone = engine.solve(problem)
        # (route "auto" may take another route with the extra right-hand sides: equal to rounding)
        np.testing.assert_allclose(solution.mean, alone.mean, rtol=1e-10)
        np.testing.assert_allclose(solution.variance, alone.variance, rtol=1e-10)
        for obs, got in zip((ones, other), solution.extra_means):
            ref, _ = dense_posterior(dataclasses.replace(problem, obs=obs), variance=False)
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * float(np.max(np.abs(ref))))

    def test_neumann_extra_mean(self):
        rng = np.random.default_rng(5)
        h, w = 16, 20
        prec = np.full((h, w), 1 / 0.05**2)
        prior = np.full((h, w), 10.0)
        problem = GridProblem(
            prior,
            prior + rng.normal(0, 0.1, (h, w)),
            prec,
            np.arange(h) * 1.0,
            np.arange(w) * 1.0,
            prior,
            Kernel(0.5, 1.5, 1.0),
        )
        other = prior + rng.normal(0, 0.3, (h, w))
        solution = FastEngine().solve(problem, extra_obs=(other,))
        assert solution.info.route == "neumann"
        ref, _ = dense_posterior(dataclasses.replace(problem, obs=other), variance=False)
        np.testing.assert_allclose(solution.extra_means[0], ref, atol=1e-9)

    def test_dense_solve_without_observations(self):
        problem = problem_with_points(np.random.default_rng(6), 6, 7, 0)
        mean, var, extras = dense_solve(problem, extra_obs=(np.ones((6, 7)),))
        np.testing.assert_array_equal(mean, problem.out_prior_mean)
        np.testing.assert_array_equal(extras[0], problem.out_prior_mean)

    @pytest.mark.parametrize("name", ["exact", "fast"])
    def test_bad_extra_obs(self, name):
        problem = problem_with_points(np.random.default_rng(7), 6, 7, 5)
        engine = make_engine(EngineConfig(name=name))
        with pytest.raises(ShapeError, match="extra_obs"):
            engine.solve(problem, extra_obs=(np.ones((7, 6)),))
        with pytest.raises(ShapeError, match="extra_obs"):
            engine.solve(problem, extra_obs=np.ones((6, 7)))  # one array, not a sequence of them
        bad = np.ones((6, 7))
        bad[problem.precision > 0] = np.nan
        with pytest.raises(InvalidInputError, match="extra_obs"):
            engine.solve(problem, extra_obs=(bad,))


class TestObservedLattice:
    def test_bounds_round_outwards_and_stay_inside(self):
        prec = np.zeros((40, 50))
        prec[13, 21] = prec[29, 30] = 1.0
        assert observed_lattice(prec) == (8, 32, 16, 32)
        assert observed_lattice(prec, quantum=1) == (13, 30, 21, 31)
        prec[39, 49] = 1.0
        assert observed_lattice(prec) == (8, 40, 16, 50)

    def test_whole_grid_or_nothing_observed_gives_none(self):
        prec = np.zeros((20, 30))
        assert observed_lattice(prec) is None
        prec[0, 0] = prec[19, 29] = 1.0
        assert observed_lattice(prec) is None

    def test_one_point_gives_two_by_two_at_least(self):
        prec = np.zeros((20, 30))
        prec[19, 29] = 1.0
        r0, r1, c0, c1 = observed_lattice(prec, quantum=1)
        assert (r1 - r0, c1 - c0) == (2, 2) and r1 == 20 and c1 == 30

    @pytest.mark.parametrize("nu,lengthscale", [(0.5, 6.0), (0.5, 40.0), (1.5, 3.0)])
    @pytest.mark.parametrize("out", [None, (53, 71), (9, 13)])
    def test_lattice_equals_whole_grid_and_exact(self, nu, lengthscale, out):
        """Points in one corner: the pixels outside the lattice (above, left, right, below) are read out exactly."""
        rng = np.random.default_rng(8)
        problem = problem_with_points(rng, 26, 35, 40, nu=nu, lengthscale=lengthscale, out=out, box=(9, 19, 12, 27))
        sub = FastEngine(route="grid").solve(problem)
        assert sub.info.details["lattice"] != (0, 26, 0, 35)
        whole = FastEngine(route="grid", lattice="full").solve(problem)
        exact = ExactEngine().solve(problem)
        s = problem.kernel.outputscale
        for got in (sub, whole):
            np.testing.assert_allclose(got.mean, exact.mean, rtol=0, atol=1e-9 * s)
            np.testing.assert_allclose(np.sqrt(got.variance), np.sqrt(exact.variance), rtol=0, atol=1e-9 * s)

    def test_log_marginal_likelihood_on_the_lattice(self):
        from gpdepth3d.gp.exact import dense_log_marginal_likelihood

        problem = problem_with_points(np.random.default_rng(9), 30, 40, 60, box=(5, 15, 20, 38))
        for lattice in ("observed", "full"):
            lml = FastEngine(route="grid", lattice=lattice).log_marginal_likelihood(problem)
            assert lml == pytest.approx(dense_log_marginal_likelihood(problem), rel=1e-10)

    def test_bad_lattice(self):
        with pytest.raises(InvalidInputError, match="lattice"):
            FastEngine(lattice="sparse")


def test_cuda_torch_back_end_on_the_lattice_with_extra_obs():
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    rng = np.random.default_rng(10)
    problem = problem_with_points(rng, 40, 60, 150, out=(80, 120), box=(10, 35, 5, 50))
    ones = np.where(problem.precision > 0, 1.0, 0.0)
    gpu = make_engine(EngineConfig(device="cuda")).solve(problem, extra_obs=(ones,))
    cpu = FastEngine(route="grid").solve(problem, extra_obs=(ones,))
    assert gpu.info.route == "grid"
    np.testing.assert_allclose(gpu.mean, cpu.mean, rtol=1e-10)
    np.testing.assert_allclose(gpu.variance, cpu.variance, rtol=1e-9)
    np.testing.assert_allclose(gpu.extra_means[0], cpu.extra_means[0], rtol=1e-10, atol=1e-12)


# (engine options, the argument the typed error must name, a phrase of what was expected)
BAD_OPTIONS = [
    ({"device": "tpu"}, "device", "'cpu', 'cuda'"),
    ({"device": "cuda:x"}, "device", "'cpu', 'cuda'"),
    ({"device": 3}, "device", "torch.device"),
    ({"device": "cuda"}, "device", "no CUDA GPU"),  # torch is made CPU-only below
    ({"device": "cuda:1"}, "device", "no CUDA GPU"),
    ({"name": "kissgp", "device": "cuda"}, "device", "no CUDA GPU"),
    ({"name": "kissgp", "device": "tpu"}, "device", "'cpu', 'cuda'"),
    ({"threads": 0}, "threads", "integer >= 1"),
    ({"threads": "two"}, "threads", "integer >= 1"),
    ({"max_dense_points": -1}, "max_dense_points", "integer >= 0"),
    ({"max_dense_points": 1.5}, "max_dense_points", "integer >= 0"),
    ({"max_memory_mb": "lots"}, "max_memory_mb", "finite number > 0"),
    ({"max_memory_mb": float("inf")}, "max_memory_mb", "finite number > 0"),
    ({"options": {"bogus": 1}}, "options", "keyword arguments of FastEngine"),
    ({"options": {"device": "cpu"}}, "options", "keyword arguments of FastEngine"),  # a field's job
    ({"name": "exact", "options": {"bogus": 1}}, "options", "keyword arguments of ExactEngine"),
    ({"name": "kissgp", "options": {"bogus": 1}}, "options", "keyword arguments of KissGPEngine"),
    ({"options": {"tile": 0}}, "tile", "integer >= 1"),
    ({"options": {"cache_size": True}}, "cache_size", "integer >= 1"),
    ({"name": "exact", "options": {"max_cross_entries": 0}}, "max_cross_entries", "integer >= 1"),
    ({"name": "kissgp", "options": {"cg_tolerance": "tight"}}, "cg_tolerance", "(0, 1)"),
    ({"name": "kissgp", "options": {"pad": 1}}, "pad", "integer >= 2"),
]


class TestEngineOptionsAtTheBoundary:
    @pytest.mark.parametrize("options,argument,expected", BAD_OPTIONS, ids=[str(c[0]) for c in BAD_OPTIONS])
    def test_typed_error_names_argument_expected_and_got(self, monkeypatch, options, argument, expected):
        torch = pytest.importorskip("torch")
        if options.get("name") == "kissgp":
            pytest.importorskip("gpytorch")
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # a CPU-only torch, on any machine
        with pytest.raises(InvalidInputError) as info:
            make_engine(EngineConfig(**options))
        err = info.value
        assert err.argument == argument and expected in err.expected and str(err.got)
        assert not isinstance(err, (AssertionError, TypeError, RuntimeError))

    @pytest.mark.parametrize("device", [None, "cpu"])
    def test_good_devices(self, device):
        import torch

        assert make_engine(EngineConfig(device=device)).device == device
        assert EngineConfig(device=torch.device("cpu")).device == "cpu"


ENGINE_MODULES = (
    "engine",
    "fast",
    "elimination_tree",
    "grid_prior",
    "readout",
    "torch_factor",
    "observed_lattice",
    "routes",
    "cost_model",
    "exact",
    "kissgp",
    "woodbury",
    "multifrontal",
    "markov",
    "neumann",
)


@pytest.mark.parametrize("module", ENGINE_MODULES)
def test_engine_functions_fit_in_100_lines(module):
    """Every function of the engine modules, docstring and decorators included, is at most 100 lines."""
    import ast
    from pathlib import Path

    import gpdepth3d.gp

    path = Path(gpdepth3d.gp.__file__).parent / f"{module}.py"
    tree = ast.parse(path.read_text())
    long = [
        (node.name, node.end_lineno - node.lineno + 1 + len(node.decorator_list))
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
    ]
    assert [f for f in long if f[1] > 100] == []


def test_any_outside_where_observed():
    from gpdepth3d.gp.engine import any_outside_where_observed

    prec = np.array([[0.0, 1.0], [2.0, 0.0]])
    ok = np.array([[np.nan, 3.0], [-4.0, np.inf]])  # the unobserved pixels' values do not count
    assert not any_outside_where_observed(prec, ok, 5.0)
    assert any_outside_where_observed(prec, ok, 3.5)  # |-4| > 3.5
    for bad in (np.nan, np.inf, -np.inf):
        v = ok.copy()
        v[0, 1] = bad
        assert any_outside_where_observed(prec, v, np.inf)
    assert not any_outside_where_observed(prec, ok[:, ::-1][:, ::-1].astype(np.float32), 5.0)  # any layout, dtype
