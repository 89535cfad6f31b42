"""Tests of the fast engine (gpdepth3d.gp.fast) and its Markov helpers against the exact GP."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.complete import DepthCompleter
from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.gp.exact import ExactEngine
from gpdepth3d.gp.fast import FastEngine
from gpdepth3d.gp.markov import chain_precision, readout_weights, state_dim
from gpdepth3d.gp.model import DepthGPConfig, GridProblem, Kernel, matern_1d, output_coordinates
from gpdepth3d.measurements import SparseDepth


def random_problem(rng, h, w, *, nu=0.5, lengthscale=2.0, s=1.3, frac=0.3, out=None, balanced=False):
    """A GridProblem with random prior mean, observations and precisions (metres)."""
    prior = rng.normal(10.0, 1.0, (h, w))
    if balanced:
        prec = np.full((h, w), 1.0 / 0.5**2)
        prec[rng.random((h, w)) < frac] += 1.0 / 0.01**2
    else:
        prec = np.where(rng.random((h, w)) < frac, rng.uniform(1.0, 1e4, (h, w)), 0.0)
    obs = prior + rng.normal(0.0, 1.0, (h, w))
    ho, wo = out or (h, w)
    return GridProblem(
        prior, obs, prec, output_coordinates(h, ho), output_coordinates(w, wo),
        rng.normal(10.0, 1.0, (ho, wo)), Kernel(nu, lengthscale, s),
    )


def assert_thread_safe(engine, problems):
    """Solving ``problems`` on one engine from 4 threads at once gives the serial answers."""
    from concurrent.futures import ThreadPoolExecutor

    serial = [engine.solve(p) for p in problems]
    with ThreadPoolExecutor(4) as pool:
        parallel = list(pool.map(engine.solve, problems))
    for (m0, v0), (m1, v1) in zip(serial, parallel):
        np.testing.assert_allclose(m1, m0, atol=1e-12)
        np.testing.assert_allclose(v1, v0, rtol=1e-12)


class TestMarkov:
    @pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
    def test_chain_precision_inverts_matern(self, nu):
        x = np.array([0.0, 1.0, 2.0, 3.5, 4.0, 7.0, 7.2])
        Q, logdet = chain_precision(x, nu, 1.7)
        d = state_dim(nu)
        S = np.linalg.inv(Q.toarray())
        np.testing.assert_allclose(S[::d, ::d], matern_1d(np.subtract.outer(x, x), nu, 1.7), atol=1e-10)
        assert logdet == pytest.approx(np.linalg.slogdet(Q.toarray())[1], abs=1e-8)
        if nu == 0.5:  # OU: tridiagonal
            assert np.count_nonzero(np.triu(Q.toarray(), 2)) == 0

    @pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
    def test_readout_weights_match_full_kriging(self, nu):
        x = np.arange(6, dtype=float)
        t = np.array([-1.3, 0.0, 0.4, 2.5, 5.0, 6.2])
        first, wts, resid = readout_weights(x, t, nu, 1.3)
        d = state_dim(nu)
        # Kriging of f(t) on f at a dense grid approaches the state read-out for nu = 0.5 exactly.
        if nu == 0.5:
            K = matern_1d(np.subtract.outer(x, x), nu, 1.3)
            for j, tj in enumerate(t):
                w_full = np.linalg.solve(K, matern_1d(tj - x, nu, 1.3))
                w_ours = np.zeros(6)
                w_ours[first[j] : first[j] + 2] = wts[j, :, 0]
                np.testing.assert_allclose(w_ours, w_full, atol=1e-12)
                assert resid[j] == pytest.approx(1 - matern_1d(tj - x, nu, 1.3) @ w_full, abs=1e-12)
        assert wts.shape == (6, 2, d)
        assert resid[1] == 0.0 and resid[4] == 0.0  # on grid nodes
        assert np.all(resid >= 0)

    def test_bad_inputs(self):
        with pytest.raises(InvalidInputError):
            chain_precision(np.array([0.0, 0.0, 1.0]), 0.5, 1.0)
        with pytest.raises(InvalidInputError):
            state_dim(1.0)
        with pytest.raises(InvalidInputError):
            readout_weights(np.array([0.0]), np.array([0.5]), 0.5, 1.0)


class TestFastEngineAgainstExact:
    @pytest.mark.parametrize("nu,route", [(0.5, "grid"), (0.5, "woodbury"), (1.5, "auto"), (2.5, "auto")])
    @pytest.mark.parametrize("out", [None, (25, 31), (5, 7)])
    def test_random_problems(self, nu, route, out):
        rng = np.random.default_rng(1)
        problem = random_problem(rng, 12, 15, nu=nu, out=out)
        m1, v1 = ExactEngine().solve(problem)
        m2, v2 = FastEngine(route=route).solve(problem)
        tol = 1e-9 if nu < 2.5 else 1e-7
        np.testing.assert_allclose(m2, m1, atol=tol * 10)
        np.testing.assert_allclose(v2, v1, atol=tol * v1.max())

    @pytest.mark.parametrize("balanced,route", [(True, "grid"), (True, "auto"), (False, "grid")])
    def test_64x64_with_2k_points(self, balanced, route):
        rng = np.random.default_rng(2)
        h, w = (40, 48) if balanced else (64, 64)  # balanced: every pixel is observed
        prior = np.full((h, w), 15.0)
        prec = np.full((h, w), 1 / 0.75**2) if balanced else np.zeros((h, w))
        idx = rng.choice(h * w, 2000 if not balanced else 500, replace=False)
        prec.ravel()[idx] += 1.0 / 0.015**2
        obs = prior + np.cumsum(rng.normal(0, 0.3, (h, w)), axis=1)
        problem = GridProblem(prior, obs, prec, np.arange(h), np.arange(w), prior, Kernel(0.5, 1.5, 15.0))
        m1, v1 = ExactEngine().solve(problem)
        engine = FastEngine(route=route)
        m2, v2 = engine.solve(problem)
        assert route == "auto" or engine.last_route == "grid"
        depth_range = np.ptp(m1)
        assert np.sqrt(np.mean((m1 - m2) ** 2)) < 1e-8 * depth_range
        np.testing.assert_allclose(np.sqrt(v2), np.sqrt(v1), rtol=1e-7)

    def test_no_observations_gives_prior(self):
        rng = np.random.default_rng(3)
        problem = random_problem(rng, 8, 9, frac=0.0, out=(16, 18))
        mean, var = FastEngine().solve(problem)
        np.testing.assert_allclose(mean, problem.out_prior_mean, atol=1e-12)
        np.testing.assert_allclose(var, problem.kernel.outputscale**2, rtol=1e-10)

    def test_variance_false(self):
        problem = random_problem(np.random.default_rng(4), 6, 7)
        mean, var = FastEngine().solve(problem, variance=False)
        assert var is None and mean.shape == (6, 7)

    @pytest.mark.parametrize("formulation", ["balanced", "residual"])
    def test_real_kitti_crop_through_completer(self, shared_data, formulation):
        lidar = np.load(shared_data / "kitti_tiny" / "velodyne_02" / "0000000000.npz")["velodyne_depth"]
        crop = lidar[214:238, 400:464]  # 24 x 64 pixels with LiDAR
        sparse = SparseDepth.from_depth_map(crop)
        assert len(sparse) > 50
        from scipy.ndimage import gaussian_filter

        filled = np.where(crop > 0, crop, np.median(crop[crop > 0]))
        mde = gaussian_filter(filled, 3.0) * 1.1  # simulated MDE: smoothed, scaled
        base = DepthGPConfig.paper() if formulation == "balanced" else DepthGPConfig.residual()
        fast = DepthCompleter(base.replace(engine="fast"))(mde, sparse, output_shape=(48, 128))
        exact = DepthCompleter(base.replace(engine="exact"))(mde, sparse, output_shape=(48, 128))
        depth_range = float(np.ptp(crop[crop > 0]))
        assert np.sqrt(np.mean((fast.mean - exact.mean) ** 2)) < 1e-6 * depth_range
        np.testing.assert_allclose(fast.std, exact.std, rtol=1e-6)


class TestFastEngineBehaviour:
    def test_caches_setup_per_resolution(self):
        engine = FastEngine()
        rng = np.random.default_rng(5)
        p1 = random_problem(rng, 10, 12)
        m1, _ = engine.solve(p1)
        tree = engine._tree(10, 12, 1)
        assert tree.ntiles >= 1
        engine.solve(random_problem(rng, 10, 12))
        assert engine._tree(10, 12, 1) is tree
        m1b, _ = engine.solve(p1)
        np.testing.assert_array_equal(m1, m1b)
        for i in range(6):  # the cache stays bounded
            engine.solve(random_problem(rng, 6 + i, 7))
        assert len(engine._trees) <= engine.cache_size

    @pytest.mark.parametrize("leaf", [1, 7, 1000])
    def test_leaf_size_does_not_change_result(self, leaf):
        problem = random_problem(np.random.default_rng(6), 11, 14, out=(22, 28))
        m0, v0 = ExactEngine().solve(problem)
        m, v = FastEngine(leaf_pixels=leaf).solve(problem)
        np.testing.assert_allclose(m, m0, atol=1e-9)
        np.testing.assert_allclose(v, v0, rtol=1e-8)

    def test_log_marginal_likelihood_matches_dense(self):
        rng = np.random.default_rng(7)
        problem = random_problem(rng, 9, 11, nu=1.5)
        obs = problem.precision > 0
        r, c = np.nonzero(obs)
        k = problem.kernel
        K = k.matrix(r, c, r, c) + np.diag(1 / problem.precision[obs])
        y = problem.obs[obs] - problem.prior_mean[obs]
        dense = -0.5 * y @ np.linalg.solve(K, y) - 0.5 * np.linalg.slogdet(K)[1] - 0.5 * y.size * np.log(2 * np.pi)
        assert FastEngine().log_marginal_likelihood(problem) == pytest.approx(dense, rel=1e-9)

    def test_bad_inputs(self):
        with pytest.raises(InvalidInputError):
            FastEngine(leaf_pixels=0)
        with pytest.raises(InvalidInputError):
            FastEngine(cache_size=0)
        with pytest.raises(InvalidInputError):
            FastEngine(threads=0)
        with pytest.raises(InvalidInputError):
            FastEngine(tile=-3)
        problem = random_problem(np.random.default_rng(8), 5, 5)
        bad = GridProblem(problem.prior_mean, problem.obs, -problem.precision - 1, problem.out_rows,
                          problem.out_cols, problem.out_prior_mean, problem.kernel)
        with pytest.raises(InvalidInputError, match="precision"):
            FastEngine().solve(bad)
        tiny = GridProblem(np.zeros((1, 5)), np.zeros((1, 5)), np.zeros((1, 5)), np.arange(1.0), np.arange(5.0),
                           np.zeros((1, 5)), problem.kernel)
        with pytest.raises(ShapeError):
            FastEngine().solve(tiny)
        with pytest.raises(InvalidInputError):
            FastEngine().solve("not a problem")

    def test_default_engine_is_fast(self):
        from gpdepth3d.gp import make_engine

        assert isinstance(make_engine(DepthGPConfig(engine="fast")), FastEngine)


class TestDevices:
    def test_explicit_torch_cpu_device_matches_default(self):
        problem = random_problem(np.random.default_rng(9), 9, 13, out=(18, 26))
        m0, v0 = FastEngine().solve(problem)
        m1, v1 = FastEngine(device="cpu").solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-12)
        np.testing.assert_allclose(v1, v0, rtol=1e-12)

    def test_cuda_matches_exact(self):
        torch = pytest.importorskip("torch")
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device")
        problem = random_problem(np.random.default_rng(10), 20, 30, out=(40, 60))
        m0, v0 = ExactEngine().solve(problem)
        m1, v1 = FastEngine(device="cuda").solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-8)

    def test_padding_and_tiling_exact_on_odd_sizes(self):
        # sizes that need padding to the tile lattice, several tiles per axis
        problem = random_problem(np.random.default_rng(11), 23, 37, out=(23, 37))
        m0, v0 = ExactEngine().solve(problem)
        m1, v1 = FastEngine(tile=5, leaf_pixels=6).solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-9)
