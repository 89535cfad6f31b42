"""Tests of the Woodbury route of the fast engine (gpdepth3d.gp.woodbury) against the exact GP."""

from __future__ import annotations

import dataclasses
import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter, build_problem
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp.exact import ExactEngine
from gpdepth3d.gp.fast import FastEngine
from gpdepth3d.gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates
from gpdepth3d.gp.multifrontal import inverse_from_cholesky
from gpdepth3d.gp.woodbury import WoodburyPosterior, woodbury_seconds
from gpdepth3d.measurements import SparseDepth

from test_fast import assert_thread_safe


def sparse_problem(rng, h, w, m, *, lengthscale=5.0, s=0.8, out_rows=None, out_cols=None, nu=0.5):
    """Residual-style GridProblem: m observed pixels with their own noise, random prior mean (metres)."""
    prior = rng.normal(3.0, 0.5, (h, w))
    prec = np.zeros((h, w))
    idx = rng.choice(h * w, m, replace=False)
    prec.ravel()[idx] = 1.0 / rng.uniform(0.005, 0.2, m) ** 2
    obs = prior + rng.normal(0.0, 0.6, (h, w))
    rows = np.arange(h, dtype=float) if out_rows is None else np.asarray(out_rows, float)
    cols = np.arange(w, dtype=float) if out_cols is None else np.asarray(out_cols, float)
    return GridProblem(
        prior, obs, prec, rows, cols, rng.normal(3.0, 0.5, (rows.size, cols.size)), Kernel(nu, lengthscale, s)
    )


class TestAgainstExact:
    @pytest.mark.parametrize("lengthscale", [0.4, 5.0, 300.0])
    def test_on_the_grid(self, lengthscale):
        problem = sparse_problem(np.random.default_rng(0), 23, 31, 80, lengthscale=lengthscale)
        m0, v0 = ExactEngine().solve(problem)
        post = WoodburyPosterior(problem)
        np.testing.assert_allclose(post.mean(), m0, atol=1e-10)
        # both sides cancel s^2 - (quadratic form): ~1e-16 x cond(A) of s^2 (large at l = 300)
        np.testing.assert_allclose(post.variance(), v0, rtol=1e-8, atol=1e-11 * problem.kernel.outputscale**2)

    @pytest.mark.parametrize("out", [(47, 63), (7, 9), (23, 31)])
    def test_output_grids(self, out):
        h, w = 23, 31
        problem = sparse_problem(
            np.random.default_rng(1),
            h,
            w,
            60,
            out_rows=output_coordinates(h, out[0]),
            out_cols=output_coordinates(w, out[1]),
        )
        m0, v0 = ExactEngine().solve(problem)
        m1, v1 = FastEngine(route="woodbury").solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-10)
        np.testing.assert_allclose(v1, v0, rtol=1e-8)

    @pytest.mark.parametrize("sort", [True, False])
    def test_means_read_out_every_right_hand_side_like_mean(self, sort):
        rng = np.random.default_rng(5)
        rows, cols = np.linspace(-2.0, 20.0, 15), np.linspace(-0.5, 29.5, 21)
        if not sort:
            rows, cols = rng.permutation(rows), rng.permutation(cols)
        problem = sparse_problem(rng, 18, 30, 35, out_rows=rows, out_cols=cols)
        extra = [rng.normal(0.0, 1.0, (18, 30)) for _ in range(2)]
        store: dict = {}
        for _ in range(2):  # the second call takes the first's buffers from the store
            post = WoodburyPosterior(problem, store)
            mean, extras = post.means(extra)
            np.testing.assert_array_equal(mean, post.mean())
            assert len(extras) == 2
            for e, m in zip(extra, extras):
                np.testing.assert_array_equal(m, post.mean(e))
                exact = ExactEngine().solve(dataclasses.replace(problem, obs=e), variance=False)[0]
                np.testing.assert_allclose(m, exact, atol=1e-10)

    def test_unsorted_and_outside_output_coordinates(self):
        rng = np.random.default_rng(2)
        rows = rng.permutation(np.linspace(-3.0, 20.0, 17))  # beyond the grid on both sides
        cols = rng.permutation(np.linspace(-0.5, 29.5, 12))
        problem = sparse_problem(rng, 18, 30, 40, out_rows=rows, out_cols=cols)
        m0, v0 = ExactEngine().solve(problem)
        post = WoodburyPosterior(problem)
        np.testing.assert_allclose(post.mean(), m0, atol=1e-10)
        np.testing.assert_allclose(post.variance(), v0, rtol=1e-8)

    def test_points_on_the_borders_and_corners(self):
        rng = np.random.default_rng(3)
        h, w = 12, 17
        prec = np.zeros((h, w))
        for r, c in [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1), (0, 5), (6, 0), (h - 1, 9), (4, w - 1), (5, 5)]:
            prec[r, c] = 1e3
        prior = np.full((h, w), 2.0)
        problem = GridProblem(
            prior,
            prior + rng.normal(0, 0.3, (h, w)),
            prec,
            output_coordinates(h, 2 * h),
            output_coordinates(w, 2 * w),
            np.full((2 * h, 2 * w), 2.0),
            Kernel(0.5, 3.0, 0.5),
        )
        m0, v0 = ExactEngine().solve(problem)
        post = WoodburyPosterior(problem)
        np.testing.assert_allclose(post.mean(), m0, atol=1e-11)
        np.testing.assert_allclose(post.variance(), v0, rtol=1e-9)

    def test_single_point_closed_form(self):
        h, w, s, l, sig = 9, 11, 0.7, 2.5, 0.1
        prec = np.zeros((h, w))
        prec[4, 6] = 1 / sig**2
        obs = np.zeros((h, w))
        obs[4, 6] = 1.0
        problem = GridProblem(
            np.zeros((h, w)),
            obs,
            prec,
            np.arange(h, dtype=float),
            np.arange(w, dtype=float),
            np.zeros((h, w)),
            Kernel(0.5, l, s),
        )
        r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        rho = np.exp(-(np.abs(r - 4) + np.abs(c - 6)) / l)
        gain = s**2 / (s**2 + sig**2)
        post = WoodburyPosterior(problem)
        np.testing.assert_allclose(post.mean(), rho * gain, atol=1e-14)
        np.testing.assert_allclose(post.variance(), s**2 * (1 - rho**2 * gain), rtol=1e-12)

    def test_no_points_gives_the_prior(self):
        rng = np.random.default_rng(4)
        problem = sparse_problem(rng, 6, 7, 0, out_rows=output_coordinates(6, 12), out_cols=output_coordinates(7, 3))
        post = WoodburyPosterior(problem)
        np.testing.assert_array_equal(post.mean(), problem.out_prior_mean)
        np.testing.assert_allclose(post.variance(), problem.kernel.outputscale**2)
        assert post.log_marginal_likelihood() == 0.0

    def test_log_marginal_likelihood_matches_dense_and_grid(self):
        problem = sparse_problem(np.random.default_rng(5), 14, 19, 30, lengthscale=3.0)
        obs = problem.precision > 0
        r, c = np.nonzero(obs)
        K = problem.kernel.matrix(r, c, r, c) + np.diag(1 / problem.precision[obs])
        y = problem.obs[obs] - problem.prior_mean[obs]
        dense = -0.5 * y @ np.linalg.solve(K, y) - 0.5 * np.linalg.slogdet(K)[1] - 0.5 * y.size * np.log(2 * np.pi)
        assert WoodburyPosterior(problem).log_marginal_likelihood() == pytest.approx(dense, rel=1e-10)
        grid = FastEngine(route="grid").log_marginal_likelihood(problem)
        assert FastEngine(route="woodbury").log_marginal_likelihood(problem) == pytest.approx(grid, rel=1e-9)

    def test_workspace_is_reused_and_results_repeat(self):
        rng = np.random.default_rng(6)
        engine = FastEngine(route="woodbury")
        a = sparse_problem(rng, 15, 20, 25)
        b = sparse_problem(rng, 15, 20, 40, out_rows=output_coordinates(15, 30), out_cols=output_coordinates(20, 40))
        first = engine.solve(a)
        engine.solve(b)  # another output shape
        again = engine.solve(a)  # buffers of a's shape are re-zeroed, not accumulated
        for x, y in zip(first, again):
            np.testing.assert_array_equal(x, y)


class TestRoute:
    def test_auto_takes_woodbury_for_sparse_points_and_the_grid_otherwise(self):
        rng = np.random.default_rng(7)
        engine = FastEngine()
        sparse = sparse_problem(rng, 120, 160, 150, lengthscale=20.0)
        mean, var = solution = engine.solve(sparse)
        assert solution.info.route == "woodbury"
        m_grid, v_grid = FastEngine(route="grid").solve(sparse)
        np.testing.assert_allclose(mean, m_grid, atol=1e-9)
        np.testing.assert_allclose(var, v_grid, rtol=1e-8)
        dense = sparse_problem(rng, 40, 50, 1500)  # most pixels observed
        assert engine.solve(dense).info.route == "grid"
        # nu = 1.5, few points: dense algebra over them
        assert engine.solve(sparse_problem(rng, 120, 160, 150, nu=1.5)).info.route == "dense"
        tiny_noise = sparse_problem(rng, 120, 160, 150, lengthscale=20.0)
        tiny_noise.precision[tiny_noise.precision > 0] = 1e12  # s^2 / noise ~ 6e11: cancellation
        assert engine.solve(tiny_noise).info.route == "grid"

    def test_cost_model_grows_with_points(self):
        assert (
            woodbury_seconds(100, 76800, True)
            < woodbury_seconds(1000, 76800, True)
            < woodbury_seconds(4000, 76800, True)
        )
        assert woodbury_seconds(500, 76800, False) < woodbury_seconds(500, 76800, True)

    def test_bad_route(self):
        with pytest.raises(InvalidInputError, match="route"):
            FastEngine(route="fastest")
        problem = sparse_problem(np.random.default_rng(8), 8, 9, 5, nu=1.5)
        with pytest.raises(InvalidInputError, match="route"):
            FastEngine(route="woodbury").solve(problem)


def test_inverse_from_cholesky_matches_numpy():
    rng = np.random.default_rng(9)
    for n in (1, 5, 33, 100):  # below, at and above the 32-column blocks
        X = rng.normal(size=(n, n))
        A = X @ X.T + n * np.eye(n)
        L = np.array(np.linalg.cholesky(A), order="F")
        inv = inverse_from_cholesky(L)
        np.testing.assert_allclose(np.tril(inv), np.tril(np.linalg.inv(A)), rtol=1e-10, atol=1e-14)


def test_real_frame_routes_agree(seven_scenes_frame):
    """7-Scenes Kinect depth at 120 x 160 with 200 points, residual model: both routes, the same posterior."""
    from gpdepth3d.measurements import downsample_depth

    depth = downsample_depth(seven_scenes_frame.depth, 4)
    rng = np.random.default_rng(10)
    r, c = np.nonzero(depth > 0)
    pick = rng.choice(r.size, 200, replace=False)
    sparse = SparseDepth.from_arrays(c[pick].astype(float), r[pick].astype(float), depth[r[pick], c[pick]], depth.shape)
    mde = np.where(depth > 0, depth, np.median(depth[depth > 0])) * 1.08
    config = DepthGPConfig.residual()
    grid = DepthCompleter(config, engine=EngineConfig(route="grid"))
    auto = DepthCompleter(config)
    a, g = auto(mde, sparse), grid(mde, sparse)
    assert auto.engine.plan(build_problem(mde, sparse, config)[0]) == "woodbury"
    np.testing.assert_allclose(a.mean, g.mean, atol=1e-9)
    np.testing.assert_allclose(a.std, g.std, rtol=1e-8)
    assert np.sqrt(np.mean((a.mean - depth) ** 2, where=depth > 0)) < np.sqrt(
        np.mean((mde - depth) ** 2, where=depth > 0)
    )


def test_concurrent_callers_share_an_engine():
    problems = [sparse_problem(np.random.default_rng(40 + k), 30, 37, 20 + 5 * k, lengthscale=4.0) for k in range(6)]
    assert_thread_safe(FastEngine(route="woodbury"), problems)


def test_failed_factorisation_is_a_typed_error(monkeypatch):
    """A LinAlgError of the Woodbury route's Cholesky reaches the caller as ConvergenceError naming the kernel."""
    import gpdepth3d.gp.fast as fast_module
    from gpdepth3d.errors import ConvergenceError

    def fail(*args, **kwargs):
        raise np.linalg.LinAlgError("the observed-pixel covariance is not positive definite (dpotrf info=3)")

    monkeypatch.setattr(fast_module, "WoodburyPosterior", fail)
    problem = sparse_problem(np.random.default_rng(11), 20, 25, 30)
    engine = FastEngine(route="woodbury")
    with pytest.raises(ConvergenceError, match=r"woodbury route.*nu=0.5, lengthscale=5 px"):
        engine.solve(problem)
    with pytest.raises(ConvergenceError, match="dpotrf"):
        engine.log_marginal_likelihood(problem)


class TestLongLengthscales:
    @pytest.mark.parametrize("lengthscale", [30.0, 100.0, 1000.0])
    def test_woodbury_and_grid_agree_with_exact(self, lengthscale):
        """nu = 0.5 stays exact at long length scales on both routes (the grid up to where its estimate allows)."""
        problem = sparse_problem(np.random.default_rng(12), 30, 40, 60, lengthscale=lengthscale)
        from gpdepth3d.gp.fast import IllConditionedError, grid_error_estimate

        m0, v0 = ExactEngine().solve(problem)
        for route in ("woodbury", "grid", "auto"):
            engine = FastEngine(route=route)
            if route == "grid" and grid_error_estimate(problem) > 1e-7:  # l = 1000 px on 30 x 40: refused, typed
                assert lengthscale == 1000.0
                with pytest.raises(IllConditionedError, match="lengthscale=1000 px"):
                    engine.solve(problem)
                continue
            m1, v1 = engine.solve(problem)
            np.testing.assert_allclose(m1, m0, atol=1e-8, err_msg=route)
            np.testing.assert_allclose(np.sqrt(v1), np.sqrt(v0), atol=1e-8, err_msg=route)


def test_near_noiseless_points_stay_on_the_grid_for_nu_15():
    """With s^2 / noise ~ 1e12 the dense route's s^2 (1 - q) would cancel like Woodbury's: auto keeps the grid
    whenever the grid can take the kernel, and the variance is right to 1e-6 relative at the points."""
    rng = np.random.default_rng(13)
    problem = sparse_problem(rng, 30, 40, 80, nu=1.5, lengthscale=2.0)
    problem.precision[problem.precision > 0] = 1e12
    engine = FastEngine()
    mean, var = solution = engine.solve(problem)
    assert solution.info.route == "grid"
    m0, v0 = ExactEngine().solve(problem)
    obs = problem.precision > 0
    np.testing.assert_allclose(mean, m0, atol=1e-8)
    np.testing.assert_allclose(var[obs], 1e-12, rtol=0.05)  # ~ the noise variance at the points
    np.testing.assert_allclose(var[~obs], v0[~obs], rtol=1e-6)
