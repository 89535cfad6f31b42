"""Tests of the Neumann-series route of the fast engine (gpdepth3d.gp.neumann)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter, build_problem
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp.exact import ExactEngine
from gpdepth3d.gp.fast import FastEngine
from gpdepth3d.gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates
from gpdepth3d.gp.neumann import NEUMANN_MEAN_TOL, NEUMANN_VAR_TOL, NeumannPosterior
from gpdepth3d.measurements import SparseDepth

from test_fast import assert_thread_safe


def balanced_problem(rng, h, w, *, lengthscale=1.5, s=1.0, sigma_dl=0.05, points=60, holes=0, hole=0, out=None):
    """The paper's balanced set-up in relative units: every pixel an MDE observation, some precise points.

    ``holes`` scattered pixels and a ``hole`` x ``hole`` block have no observation (MDE holes).
    """
    prec = np.full((h, w), 1.0 / sigma_dl**2)
    prec.ravel()[rng.choice(h * w, points, replace=False)] += 1.0 / 0.001**2
    prec.ravel()[rng.choice(h * w, holes, replace=False)] = 0.0
    prec[2 : 2 + hole, 3 : 3 + hole] = 0.0
    obs = 1.0 + 0.1 * rng.standard_normal((h, w))
    prior = np.full((h, w), 1.0)
    ho, wo = out or (h, w)
    rows = np.arange(h, dtype=float) if out is None else output_coordinates(h, ho)
    cols = np.arange(w, dtype=float) if out is None else output_coordinates(w, wo)
    return GridProblem(prior, obs, prec, rows, cols, np.full((ho, wo), 1.0), Kernel(0.5, lengthscale, s))


class TestSeries:
    def test_matches_the_grid_route_and_exact(self):
        problem = balanced_problem(np.random.default_rng(0), 17, 23)
        post = NeumannPosterior(problem)
        assert 0.0 < post.rho < 0.05
        mean, var = post.mean(post.terms(NEUMANN_MEAN_TOL)), post.variance(post.terms(NEUMANN_VAR_TOL))
        m_grid, v_grid = FastEngine(route="grid").solve(problem)
        np.testing.assert_allclose(mean, m_grid, atol=1e-13)
        np.testing.assert_allclose(var, v_grid, rtol=1e-10)
        m_exact, v_exact = ExactEngine().solve(problem)
        np.testing.assert_allclose(mean, m_exact, atol=1e-12)
        np.testing.assert_allclose(var, v_exact, rtol=1e-8)  # the dense reference cancels to ~1e-9 here

    @pytest.mark.parametrize("lengthscale,sigma_dl", [(1.5, 0.05), (3.0, 0.2), (0.7, 0.5)])
    def test_truncation_stays_within_the_certified_bound(self, lengthscale, sigma_dl):
        problem = balanced_problem(np.random.default_rng(1), 14, 19, lengthscale=lengthscale, sigma_dl=sigma_dl)
        post = NeumannPosterior(problem)
        assert post.rho < 1.0
        m_ref, v_ref = FastEngine(route="grid").solve(problem)
        c = problem.precision * (problem.obs - problem.prior_mean) / np.sqrt(post.M)
        for k in range(0, 8):
            bound = post.rho ** (k + 1) / (1 - post.rho)
            assert np.max(np.abs(post.variance(k) - v_ref) / v_ref) <= bound * (1 + 1e-6) + 1e-13
            err_z = np.abs(post.mean(k) - m_ref) * np.sqrt(post.M)  # error of z = M^1/2 (mean - prior)
            assert err_z.max() <= bound * np.abs(c).max() * (1 + 1e-6) + 1e-12
        rel_err = [np.max(np.abs(post.variance(k) - v_ref) / v_ref) for k in (1, 7)]
        assert rel_err[1] < 0.5 * rel_err[0]  # more terms, smaller error: the series is the posterior

    def test_terms(self):
        post = NeumannPosterior(balanced_problem(np.random.default_rng(2), 6, 7, points=10))
        k = post.terms(1e-10)
        assert post.rho ** (k + 1) / (1 - post.rho) <= 1e-10 < post.rho**k / (1 - post.rho)
        post.rho = 1.2
        assert post.terms(1e-10) is None
        post.rho = 0.0
        assert post.terms(1e-10) == 0

    def test_scattered_holes_converge_a_large_hole_does_not(self):
        rng = np.random.default_rng(3)
        scattered = balanced_problem(rng, 10, 12, holes=3)
        post = NeumannPosterior(scattered)
        assert post.rho < 0.5  # an unobserved pixel among observed ones is still dominated
        m_grid, v_grid = FastEngine(route="grid").solve(scattered)
        np.testing.assert_allclose(post.variance(post.terms(NEUMANN_VAR_TOL)), v_grid, rtol=1e-10)
        np.testing.assert_allclose(post.mean(post.terms(NEUMANN_MEAN_TOL)), m_grid, atol=1e-12)
        block = NeumannPosterior(balanced_problem(rng, 10, 12, hole=4))
        assert block.rho > 1.0 and block.terms(1e-10) is None


class TestRoute:
    def test_auto_takes_neumann_for_the_papers_set_up(self):
        problem = balanced_problem(np.random.default_rng(4), 60, 90)
        engine = FastEngine()
        mean, var = solution = engine.solve(problem)
        assert solution.info.route == "neumann"
        m_grid, v_grid = FastEngine(route="grid").solve(problem)
        np.testing.assert_allclose(mean, m_grid, atol=1e-12)
        np.testing.assert_allclose(var, v_grid, rtol=1e-10)
        mean_only, none = solution = engine.solve(problem, variance=False)
        assert none is None and solution.info.route == "neumann"
        np.testing.assert_array_equal(mean_only, mean)

    def test_auto_falls_back_to_the_grid(self):
        rng = np.random.default_rng(5)
        engine = FastEngine()
        assert engine.solve(balanced_problem(rng, 60, 90, hole=6)).info.route == "grid"  # a block without MDE
        assert engine.solve(balanced_problem(rng, 60, 90, out=(120, 180))).info.route == "grid"  # another output grid
        # strong smoothing: slow series
        assert engine.solve(balanced_problem(rng, 60, 90, lengthscale=40.0, s=3.0)).info.route == "grid"
        problem = balanced_problem(rng, 60, 90)
        assert engine.plan(problem, lml=True) == "grid"

    def test_forced_route_errors(self):
        rng = np.random.default_rng(6)
        with pytest.raises(InvalidInputError, match="route"):
            FastEngine(route="neumann").solve(balanced_problem(rng, 10, 12, hole=4))
        with pytest.raises(InvalidInputError, match="route"):
            FastEngine(route="neumann").solve(balanced_problem(rng, 10, 12, out=(20, 24)))
        forced = FastEngine(route="neumann")
        problem = balanced_problem(rng, 10, 12)
        assert forced.log_marginal_likelihood(problem) == pytest.approx(
            FastEngine(route="grid").log_marginal_likelihood(problem), rel=1e-12
        )
        assert forced.plan(problem, lml=True) == "grid"  # the series has no log-determinant
        nu15 = balanced_problem(rng, 10, 12)
        nu15 = GridProblem(
            nu15.prior_mean,
            nu15.obs,
            nu15.precision,
            nu15.out_rows,
            nu15.out_cols,
            nu15.out_prior_mean,
            Kernel(1.5, 1.5, 1.0),
        )
        with pytest.raises(InvalidInputError, match="route"):
            FastEngine(route="neumann").solve(nu15)


def test_real_kitti_frame_routes_agree(shared_data):
    """KITTI LiDAR at 1/3 resolution with a simulated MDE, the paper's set-up: Neumann vs grid."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    from gpdepth3d.measurements import downsample_depth

    lidar = np.load(shared_data / "kitti_tiny" / "velodyne_02" / "0000000000.npz")["velodyne_depth"].astype(float)
    lidar = downsample_depth(lidar[lidar.shape[0] - 352 :, :1216], 3)
    _, (ri, ci) = distance_transform_edt(lidar <= 0, return_indices=True)
    mde = gaussian_filter(lidar[ri, ci], 4.0) * 1.05
    sparse = SparseDepth.from_depth_map(lidar)
    auto = DepthCompleter(DepthGPConfig.paper())
    grid = DepthCompleter(DepthGPConfig.paper(), engine=EngineConfig(route="grid"))
    a, g = auto(mde, sparse), grid(mde, sparse)
    assert auto.engine.plan(build_problem(mde, sparse, DepthGPConfig.paper())[0]) == "neumann"
    depth_range = float(np.ptp(lidar[lidar > 0]))
    assert np.max(np.abs(a.mean - g.mean)) < 1e-10 * depth_range
    np.testing.assert_allclose(a.std, g.std, rtol=1e-10)


def test_concurrent_callers_share_an_engine():
    problems = [balanced_problem(np.random.default_rng(60 + k), 50 + 10 * (k % 2), 70) for k in range(6)]
    assert_thread_safe(FastEngine(route="neumann"), problems)
