"""Tests of the fast engine (gpdepth3d.gp.fast) and its Markov helpers against the exact GP."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter, build_problem
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.errors import ConvergenceError, InvalidInputError, ShapeError
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
        prior,
        obs,
        prec,
        output_coordinates(h, ho),
        output_coordinates(w, wo),
        rng.normal(10.0, 1.0, (ho, wo)),
        Kernel(nu, lengthscale, s),
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
        m2, v2 = solution = engine.solve(problem)
        assert route == "auto" or solution.info.route == "grid"
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
        fast = DepthCompleter(base, engine=EngineConfig(name="fast"))(mde, sparse, output_shape=(48, 128))
        exact = DepthCompleter(base, engine=EngineConfig(name="exact"))(mde, sparse, output_shape=(48, 128))
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
        bad = GridProblem(
            problem.prior_mean,
            problem.obs,
            -problem.precision - 1,
            problem.out_rows,
            problem.out_cols,
            problem.out_prior_mean,
            problem.kernel,
        )
        with pytest.raises(InvalidInputError, match="precision"):
            FastEngine().solve(bad)
        tiny = GridProblem(
            np.zeros((1, 5)),
            np.zeros((1, 5)),
            np.zeros((1, 5)),
            np.arange(1.0),
            np.arange(5.0),
            np.zeros((1, 5)),
            problem.kernel,
        )
        with pytest.raises(ShapeError):
            FastEngine().solve(tiny)
        with pytest.raises(InvalidInputError):
            FastEngine().solve("not a problem")

    def test_default_engine_is_fast(self):
        from gpdepth3d.gp import make_engine

        assert isinstance(make_engine(EngineConfig(name="fast")), FastEngine)


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


# ----------------------------------------------------------------------------- every kernel x every route

NUS = [0.5, 1.5, 2.5]
LENGTHSCALES = [1.5, 30.0, 100.0]
ROUTES = ["grid", "woodbury", "neumann", "dense", "auto"]


def naive_posterior(problem: GridProblem) -> tuple[np.ndarray, np.ndarray]:
    """Independent dense reference: the GP equations with numpy.linalg.solve (LU, no Cholesky)."""
    k = problem.kernel
    s2 = k.outputscale**2
    r, c = np.nonzero(problem.precision > 0)
    orr, occ = np.meshgrid(problem.out_rows, problem.out_cols, indexing="ij")
    orr, occ = orr.ravel(), occ.ravel()
    K = (
        s2
        * matern_1d(np.subtract.outer(r, r), k.nu, k.lengthscale)
        * matern_1d(np.subtract.outer(c, c), k.nu, k.lengthscale)
    )
    K += np.diag(1.0 / problem.precision[r, c])
    Kx = (
        s2
        * matern_1d(np.subtract.outer(orr, r), k.nu, k.lengthscale)
        * matern_1d(np.subtract.outer(occ, c), k.nu, k.lengthscale)
    )
    y = problem.obs[r, c] - problem.prior_mean[r, c]
    mean = problem.out_prior_mean.ravel() + Kx @ np.linalg.solve(K, y)
    var = s2 - np.einsum("ij,ji->i", Kx, np.linalg.solve(K, Kx.T))
    return mean.reshape(problem.out_shape), np.maximum(var, 0.0).reshape(problem.out_shape)


def formulation_problem(rng, h, w, *, nu, lengthscale, balanced, s=0.8, points=25, out=None):
    """Residual: `points` pixels observed (sigma 5-20 cm); balanced: every pixel (sigma_DL = 4 cm) plus points (2 mm)."""
    prior = 3.0 + np.cumsum(rng.normal(0.0, 0.05, (h, w)), axis=1)
    prec = np.full((h, w), 1.0 / 0.04**2) if balanced else np.zeros((h, w))
    idx = rng.choice(h * w, points, replace=False)
    prec.ravel()[idx] += 1.0 / (0.002**2 if balanced else rng.uniform(0.05, 0.2, points) ** 2)
    obs = prior + 0.4 * np.sin(np.arange(w) / 5.0)[None, :] + rng.normal(0.0, 0.05, (h, w))
    ho, wo = out or (h, w)
    return GridProblem(
        prior,
        obs,
        prec,
        output_coordinates(h, ho),
        output_coordinates(w, wo),
        rng.normal(3.0, 0.1, (ho, wo)),
        Kernel(nu, lengthscale, s),
    )


def check_route(problem, route, reference):
    """Solves with ``route``; returns "match" (and asserts agreement with ``reference``), or the typed refusal."""
    from gpdepth3d.errors import ConvergenceError
    from gpdepth3d.gp.fast import IllConditionedError, grid_error_estimate

    engine = FastEngine(route=route)
    k = problem.kernel
    if route in ("woodbury", "neumann") and k.nu != 0.5:
        with pytest.raises(InvalidInputError, match="route"):
            engine.solve(problem)
        return "refused"
    if route == "grid" and grid_error_estimate(problem) > 1e-7:
        with pytest.raises(IllConditionedError, match=f"nu={k.nu}") as info:
            engine.solve(problem)
        assert isinstance(info.value, ConvergenceError)
        return "refused"
    try:
        mean, var = solution = engine.solve(problem)
    except InvalidInputError as err:
        assert route == "neumann" and "diagonally dominant" in str(err)
        return "refused"
    m0, v0 = reference
    s = k.outputscale
    np.testing.assert_allclose(mean, m0, rtol=0, atol=1e-7 * s, err_msg=f"mean, route {route} -> {solution.info.route}")
    np.testing.assert_allclose(np.sqrt(var), np.sqrt(v0), rtol=0, atol=1e-7 * s, err_msg=f"std, route {route}")
    assert route == "auto" or solution.info.route == route
    return "match"


class TestEveryKernelAndRoute:
    """nu in {0.5, 1.5, 2.5} x l in {1.5, 30, 100} px x every route x both formulations against a numpy GP:
    the engine matches it or refuses with a typed error, never a wrong answer."""

    @pytest.mark.parametrize("balanced", [False, True], ids=["residual", "balanced"])
    @pytest.mark.parametrize("nu", NUS)
    def test_synthetic(self, nu, balanced):
        outcomes = {}
        for lengthscale in LENGTHSCALES:
            problem = formulation_problem(
                np.random.default_rng(int(nu * 10 + lengthscale)),
                12,
                16,
                nu=nu,
                lengthscale=lengthscale,
                balanced=balanced,
            )
            reference = naive_posterior(problem)
            for route in ROUTES:
                outcomes[lengthscale, route] = check_route(problem, route, reference)
        assert all(outcomes[lengthscale, r] == "match" for lengthscale in LENGTHSCALES for r in ("auto", "dense"))
        assert outcomes[1.5, "grid"] == "match"  # short length scales stay on the grid route
        if nu == 0.5:
            assert all(
                outcomes[lengthscale, r] == "match" for lengthscale in LENGTHSCALES for r in ("grid", "woodbury")
            )
            assert outcomes[1.5, "neumann"] == ("match" if balanced else "refused")
        if nu == 2.5:
            assert outcomes[100.0, "grid"] == "refused"  # the precision form cannot hold this kernel in float64

    @pytest.mark.parametrize("nu", [1.5, 2.5])
    def test_other_output_grid(self, nu):
        problem = formulation_problem(
            np.random.default_rng(3), 10, 13, nu=nu, lengthscale=30.0, balanced=False, out=(19, 7)
        )
        reference = naive_posterior(problem)
        assert check_route(problem, "auto", reference) == "match"
        assert check_route(problem, "dense", reference) == "match"

    def test_grid_route_long_lengthscale_where_accepted(self):
        """nu = 1.5, l = 30 on a small fully observed grid: accepted by the estimate and exact to 1e-7 s."""
        from gpdepth3d.gp.fast import grid_error_estimate

        problem = formulation_problem(np.random.default_rng(4), 12, 16, nu=1.5, lengthscale=30.0, balanced=True)
        assert grid_error_estimate(problem) <= 1e-7
        assert check_route(problem, "grid", naive_posterior(problem)) == "match"

    @pytest.mark.parametrize("balanced", [False, True], ids=["residual", "balanced"])
    def test_real_7scenes_crop(self, seven_scenes_frame, balanced):
        """A crop of 7-Scenes at 1/4 resolution (30 x 40 residual, 20 x 24 balanced: every pixel observed), every nu
        and length scale, through `DepthCompleter`."""
        from scipy.ndimage import gaussian_filter

        from gpdepth3d.measurements import downsample_depth

        depth = downsample_depth(seven_scenes_frame.depth, 4)
        depth = depth[45:65, 70:94] if balanced else depth[40:70, 60:100]
        valid = depth > 0
        assert valid.sum() > 0.8 * depth.size
        rng = np.random.default_rng(5)
        r, c = np.nonzero(valid)
        pick = rng.choice(r.size, 30, replace=False)
        sparse = SparseDepth.from_arrays(
            c[pick].astype(float), r[pick].astype(float), depth[r[pick], c[pick]], depth.shape
        )
        mde = gaussian_filter(np.where(valid, depth, np.median(depth[valid])), 2.0) * 1.08  # smooth, biased
        engine = FastEngine()  # one engine for all kernels, as a DepthCompleter keeps it
        base = DepthGPConfig.paper() if balanced else DepthGPConfig.residual()
        for nu in NUS:
            for lengthscale in LENGTHSCALES:
                cfg = base.replace(nu=nu, lengthscale=lengthscale)
                exact = DepthCompleter(cfg, engine=EngineConfig(name="exact"))(mde, sparse)
                fast = DepthCompleter(cfg, engine=EngineConfig(name="fast"))
                fast.engine = engine  # the same engine object for every kernel (its caches)
                post = fast(mde, sparse)
                route = engine.plan(build_problem(mde, sparse, cfg)[0])
                scale = float(np.median(mde)) * cfg.outputscale  # s in metres (relative units)
                np.testing.assert_allclose(
                    post.mean, exact.mean, rtol=0, atol=1e-7 * scale, err_msg=f"nu={nu} l={lengthscale} route {route}"
                )
                np.testing.assert_allclose(post.std, exact.std, rtol=0, atol=1e-7 * scale)


class TestRefusals:
    def test_no_bare_linalg_error_from_the_grid_route(self):
        """nu = 2.5, l = 100 with many observed pixels: no route can take it -> IllConditionedError, not LinAlgError."""
        from gpdepth3d.errors import ConvergenceError
        from gpdepth3d.gp.fast import IllConditionedError

        problem = formulation_problem(np.random.default_rng(6), 30, 40, nu=2.5, lengthscale=100.0, balanced=True)
        for engine in (FastEngine(route="grid"), FastEngine(max_dense_points=100)):
            with pytest.raises(IllConditionedError, match=r"nu=2.5.*lengthscale=100") as info:
                engine.solve(problem)
            assert isinstance(info.value, ConvergenceError) and "estimated error" in str(info.value)

    def test_factorisation_failure_is_typed(self, monkeypatch):
        """Should the factorisation still fail, the LinAlgError is mapped to IllConditionedError naming the kernel."""
        import gpdepth3d.gp.fast as fast_module

        def fail(*args, **kwargs):
            raise np.linalg.LinAlgError("posterior precision not positive definite")

        monkeypatch.setattr(fast_module, "FrontalFactor", fail)
        problem = random_problem(np.random.default_rng(7), 8, 9, nu=1.5)
        with pytest.raises(fast_module.IllConditionedError, match=r"nu=1.5.*not numerically positive definite"):
            FastEngine(route="grid").solve(problem)

    def test_memory_budget_refuses_up_front(self):
        from gpdepth3d.errors import ProblemTooLargeError
        from gpdepth3d.gp.fast import grid_bytes

        rng = np.random.default_rng(8)
        h, w = 600, 800  # every pixel observed but a hole of 200 x 200 (an MDE with a NaN block)
        prec = np.full((h, w), 400.0)
        prec[200:400, 300:500] = 0.0
        prior = np.full((h, w), 3.0)
        problem = GridProblem(
            prior, prior + rng.normal(0, 0.1, (h, w)), prec, np.arange(h), np.arange(w), prior, Kernel(0.5, 1.5, 1.0)
        )
        assert grid_bytes((h, w), 0.5) > 300 * 2**20
        with pytest.raises(ProblemTooLargeError, match=r"GiB \(limit 0.293 GiB\)"):
            FastEngine(max_memory_mb=300).solve(problem)
        with pytest.raises(ProblemTooLargeError, match="grid route is refused"):
            FastEngine(route="grid", max_memory_mb=300).solve(problem)
        with pytest.raises(InvalidInputError, match="max_memory_mb"):
            FastEngine(max_memory_mb=-1)
        with pytest.raises(InvalidInputError, match="max_dense_points"):
            FastEngine(max_dense_points="many")

    def test_buffers_already_held_are_not_counted_again(self, monkeypatch):
        """A second frame of a resolution reuses the grid buffers of the first: a budget that has shrunk since
        (the first frame's buffers are part of what is no longer free) must not refuse it."""
        import gpdepth3d.gp.fast as fast_module
        from gpdepth3d.errors import ProblemTooLargeError

        problem = formulation_problem(np.random.default_rng(12), 40, 48, nu=0.5, lengthscale=1.5, balanced=True)
        need = fast_module.grid_bytes((40, 48), 0.5)
        engine = FastEngine(route="grid")
        monkeypatch.setattr(fast_module, "memory_budget", lambda: 2 * need)
        m0, _ = engine.solve(problem)
        monkeypatch.setattr(fast_module, "memory_budget", lambda: need // 2)
        m1, _ = engine.solve(problem)
        np.testing.assert_array_equal(m1, m0)
        with pytest.raises(ProblemTooLargeError, match="grid route is refused"):
            FastEngine(route="grid").solve(problem)  # a fresh engine must allocate them

    def test_grid_bytes_estimate_bounds_the_buffers(self):
        """The estimate is an upper bound of the numeric buffers, within 2x, for nu = 0.5 and 1.5."""
        from gpdepth3d.gp.elimination_tree import front_tree as _front_tree
        from gpdepth3d.gp.fast import grid_bytes

        engine = FastEngine()
        for (h, w), nu in (((60, 80), 0.5), ((120, 160), 0.5), ((60, 80), 1.5)):
            ds = state_dim(nu) ** 2
            fronts = _front_tree(engine._tree(h, w, ds))
            used = 8 * (fronts.l_size + fronts.stack_size + fronts.sig_size + 2 * fronts.work_size)
            assert used <= grid_bytes((h, w), nu) <= 2 * used


class TestConditioningHelpers:
    def test_process_noise_accurate_for_short_steps(self):
        """Q(h) ~ G h^(2d - 1) / ((d - 1)!^2 (2d - 1)) for the first state: P - A P A^T loses it, quadrature does not."""
        from math import factorial

        from gpdepth3d.gp.markov import _step, _unit_sde

        for d in (2, 3):
            G = _unit_sde(d)[2][d - 1, d - 1]
            for h in (1e-3, 1e-2):
                Q = _step(d, h)[1]
                lead = G * h ** (2 * d - 1) / (factorial(d - 1) ** 2 * (2 * d - 1))
                assert Q[0, 0] == pytest.approx(lead, rel=5 * d * h)
                assert np.all(np.linalg.eigvalsh(Q) > 0)

    def test_chain_precision_long_lengthscales(self):
        """Scaled states keep the 1-D chain accurate at l = 30-100 px (was 1.4e-4 off at nu = 2.5, l = 100)."""
        x = np.arange(40, dtype=float)
        for nu, lengthscale, tol in ((1.5, 100.0, 1e-10), (2.5, 30.0, 1e-7)):
            Q, _ = chain_precision(x, nu, lengthscale)
            d = state_dim(nu)
            S = np.linalg.inv(Q.toarray())
            np.testing.assert_allclose(S[::d, ::d], matern_1d(np.subtract.outer(x, x), nu, lengthscale), atol=tol)

    def test_chain_conditioning_bounds_the_condition_number(self):
        from gpdepth3d.gp.markov import chain_conditioning

        for nu in NUS:
            for lengthscale in (1.5, 10.0):
                q, c = chain_conditioning(30, nu, lengthscale)
                Q, _ = chain_precision(np.arange(30, dtype=float), nu, lengthscale)
                assert np.linalg.cond(Q.toarray()) <= q * c
        grow = [np.prod(chain_conditioning(100, 2.5, lengthscale)) for lengthscale in (1.5, 10.0, 30.0)]
        assert grow[0] < grow[1] < grow[2]
        with pytest.raises(InvalidInputError, match="n"):
            chain_conditioning(0, 0.5, 1.0)

    def test_fit_treats_a_refused_kernel_as_infeasible(self):
        """fit_hyperparameters meets IllConditionedError (nu = 2.5, l = 30, every pixel observed, no dense route):
        the objective treats it as infeasible instead of letting it escape."""
        from gpdepth3d.completion.marginal_fit import fit_hyperparameters

        rng = np.random.default_rng(9)
        mde = 3.0 + np.cumsum(rng.normal(0, 0.02, (16, 20)), axis=1)
        sparse = SparseDepth.from_arrays(
            rng.uniform(0, 19, 15), rng.uniform(0, 15, 15), rng.uniform(2.5, 3.5, 15), (16, 20)
        )
        engine = FastEngine(max_dense_points=0)
        config = DepthGPConfig.paper(nu=2.5, lengthscale=30.0)
        with pytest.raises(ConvergenceError):
            engine.solve(build_problem(mde, sparse, config)[0])
        fitted = fit_hyperparameters(mde, sparse, config, params=("lengthscale",), max_iterations=3, engine=engine)
        assert isinstance(fitted, DepthGPConfig) and np.isfinite(fitted.lengthscale)

    def test_memory_budget_is_a_share_of_available_memory(self):
        psutil = pytest.importorskip("psutil")  # installed with dask.distributed

        from gpdepth3d.gp.fast import memory_budget

        avail = psutil.virtual_memory().available
        assert 0.5 * avail < memory_budget() <= 0.8 * avail

    def test_memory_budget_reads_the_memory_once_per_interval(self, monkeypatch):
        psutil = pytest.importorskip("psutil")
        from types import SimpleNamespace

        import gpdepth3d.gp.cost_model as cost_model

        reads, clock = [], [1000.0]
        monkeypatch.setattr(cost_model, "_reading", (-np.inf, 0))
        monkeypatch.setattr(cost_model, "time", SimpleNamespace(monotonic=lambda: clock[0]))
        monkeypatch.setattr(psutil, "virtual_memory", lambda: reads.append(1) or type("M", (), {"available": 4000})())
        assert cost_model.memory_budget() == 3000 and len(reads) == 1
        clock[0] += 0.5 * cost_model.MEMORY_READING_S
        assert cost_model.memory_budget() == 3000 and len(reads) == 1  # the same reading
        clock[0] += cost_model.MEMORY_READING_S
        assert cost_model.memory_budget() == 3000 and len(reads) == 2  # read again


class TestPropertySweep:
    """Bounded property test: on small random problems every engine route returns a typed error or a finite
    posterior that matches the independent numpy GP."""

    @pytest.mark.slow  # ~9 s (40 examples); 400 examples found no failure (grid, dense, woodbury matches; typed refusals)
    def test_typed_error_or_exact(self):
        from hypothesis import HealthCheck, given, settings
        from hypothesis import strategies as st

        from gpdepth3d.errors import GPDepthError

        @settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
        @given(
            h=st.integers(2, 7),
            w=st.integers(2, 8),
            nu=st.sampled_from(NUS),
            log_l=st.floats(-0.5, 3.0),
            log_s=st.floats(-2.0, 3.0),
            log_noise=st.floats(-4.0, 1.0),
            frac=st.floats(0.0, 1.0),
            depth=st.floats(0.5, 1e4),
            seed=st.integers(0, 2**16),
            route=st.sampled_from(ROUTES),
            out=st.sampled_from([None, (5, 3), (9, 11)]),
        )
        def check(h, w, nu, log_l, log_s, log_noise, frac, depth, seed, route, out):
            rng = np.random.default_rng(seed)
            s = 10.0**log_s
            prior = depth * (1 + 0.1 * rng.random((h, w)))
            prec = np.where(rng.random((h, w)) < frac, 10.0 ** (-2 * log_noise) * rng.uniform(0.5, 2, (h, w)), 0.0)
            ho, wo = out or (h, w)
            problem = GridProblem(
                prior,
                prior + s * rng.normal(size=(h, w)),
                prec,
                output_coordinates(h, ho),
                output_coordinates(w, wo),
                depth * np.ones((ho, wo)),
                Kernel(nu, 10.0**log_l, s),
            )
            try:
                mean, var = FastEngine(route=route).solve(problem)
            except GPDepthError:
                return
            assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)
            m0, v0 = naive_posterior(problem)
            # The numpy reference is itself only as good as cond(K + D) allows: compare where it is reliable.
            r, c = np.nonzero(prec > 0)
            if r.size:
                K = matern_1d(np.subtract.outer(r, r), nu, 10.0**log_l) * matern_1d(
                    np.subtract.outer(c, c), nu, 10.0**log_l
                )
                K += np.diag(1.0 / (prec[r, c] * s * s))
                if np.linalg.cond(K) > 1e8:
                    return
            np.testing.assert_allclose(mean, m0, rtol=0, atol=1e-6 * s + 1e-9 * depth)
            np.testing.assert_allclose(np.sqrt(var), np.sqrt(v0), rtol=0, atol=1e-6 * s)

        check()


def test_single_state_and_between_pixel_outputs_in_one_readout():
    """Outputs on grid pixels (and beyond the grid's edge) read one state and take the selected inverse's
    diagonal; outputs between pixels read 2 x 2 states from covariance fronts: mixed in one output grid,
    both match the dense GP equations."""
    from gpdepth3d.gp.readout import frontal_readout as _frontal_readout
    from gpdepth3d.gp.multifrontal import FrontalFactor

    rng = np.random.default_rng(11)
    h, w = 17, 23
    base = random_problem(rng, h, w, lengthscale=6.0, frac=0.15)
    out_rows = np.array([-2.0, 0.0, 0.5, 3.0, 7.25, 16.0, 18.5])
    out_cols = np.array([0.0, 1.0, 4.5, 11.0, 22.0, 23.75])
    problem = GridProblem(
        base.prior_mean,
        base.obs,
        base.precision,
        out_rows,
        out_cols,
        rng.normal(10.0, 1.0, (out_rows.size, out_cols.size)),
        base.kernel,
    )
    engine = FastEngine(route="grid", lattice="full")
    mean, var = engine.solve(problem)
    ref_mean, ref_var = naive_posterior(problem)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(var, ref_var, rtol=1e-8, atol=1e-10)
    factor, tree, _, _ = engine.factorize(problem)
    assert isinstance(factor, FrontalFactor)
    (ptr, outs, _, _, n_out), (single, _, _) = _frontal_readout(factor.tree, engine._readout(tree, problem))
    assert 0 < single.size < n_out and outs.size == n_out - single.size  # both kinds present
