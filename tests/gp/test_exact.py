"""Tests of the exact engine (gpdepth3d.gp.exact) against a naive dense GP written here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from gpdepth3d.completion.complete import build_problem, complete
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.errors import ProblemTooLargeError
from gpdepth3d.gp.exact import ExactEngine
from gpdepth3d.gp.model import DepthGPConfig, GridProblem, Kernel
from gpdepth3d.measurements import SparseDepth

H, W = 6, 7


def matern(d, nu, l):
    """Matern correlation written out independently of gpdepth3d."""
    r = np.abs(d) / l
    if nu == 0.5:
        return np.exp(-r)
    if nu == 1.5:
        return (1 + np.sqrt(3) * r) * np.exp(-np.sqrt(3) * r)
    return (1 + np.sqrt(5) * r + 5 * r**2 / 3) * np.exp(-np.sqrt(5) * r)


def k(ra, ca, rb, cb, s, nu, l):
    return s**2 * matern(np.subtract.outer(ra, rb), nu, l) * matern(np.subtract.outer(ca, cb), nu, l)


def naive_posterior(mde, sparse, cfg, out_shape):
    """Dense GP with one row per observation (an MDE pixel and a point on it are two rows)."""
    valid = np.isfinite(mde) & (mde > 0)
    scale = np.median(mde[valid])
    unit = scale if cfg.units == "relative" else 1.0
    s, sdl, sm = cfg.outputscale * unit, cfg.sigma_dl * unit, cfg.sigma_meas * unit
    pr, pc, pd = sparse.v, sparse.u, sparse.depth
    psig = np.where(np.isfinite(sparse.sigma), sparse.sigma, sm)
    ho, wo = out_shape
    orr = (np.arange(ho) + 0.5) * H / ho - 0.5
    occ = (np.arange(wo) + 0.5) * W / wo - 0.5
    oR, oC = [a.ravel() for a in np.meshgrid(orr, occ, indexing="ij")]
    if cfg.formulation == "balanced":
        mr, mc = np.nonzero(valid)
        rows = np.concatenate([mr, pr])
        cols = np.concatenate([mc, pc])
        y = np.concatenate([mde[valid], pd])
        noise = np.concatenate([np.full(mr.size, sdl**2), psig**2])
        c = mde[valid].mean()
        m_obs = np.full(y.size, c)
        m_out = np.full(oR.size, c)
    else:
        assert valid.all()
        rows, cols, y, noise = pr, pc, pd, psig**2
        m_obs = mde[pr.astype(int), pc.astype(int)]
        m_out = map_coordinates(mde, [oR, oC], order=1, mode="nearest")  # bilinear, pixel centres
    Koo = k(rows, cols, rows, cols, s, cfg.nu, cfg.lengthscale) + np.diag(noise)
    Kso = k(oR, oC, rows, cols, s, cfg.nu, cfg.lengthscale)
    mean = m_out + Kso @ np.linalg.solve(Koo, y - m_obs)
    var = s**2 - np.einsum("ij,ji->i", Kso, np.linalg.solve(Koo, Kso.T))
    return mean.reshape(out_shape), var.reshape(out_shape)


def inputs(seed=0):
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:H, 0:W]
    mde = 3.0 + 0.3 * r + 0.1 * c + 0.2 * rng.normal(size=(H, W))
    pts = [(1, 2), (4, 5), (2, 6), (5, 0)]
    v = np.array([p[0] for p in pts], float)
    u = np.array([p[1] for p in pts], float)
    d = mde[v.astype(int), u.astype(int)] * 1.1 + rng.normal(0, 0.05, size=len(pts))
    sigma = np.array([np.nan, 0.02, np.nan, np.nan])  # one point carries its own sigma (metres)
    return mde, SparseDepth(u, v, d, (H, W), sigma)


EXACT = EngineConfig(name="exact")
CONFIGS = [
    DepthGPConfig.paper(nu=0.5, lengthscale=1.5),
    DepthGPConfig.paper(nu=1.5, lengthscale=2.0, sigma_dl=0.1, sigma_meas=0.01),
    DepthGPConfig.paper(nu=2.5, lengthscale=1.0, outputscale=0.5, units="metres"),
    DepthGPConfig.residual(align="none", lengthscale=3.0),
    DepthGPConfig.residual(align="none", nu=2.5, lengthscale=2.0, units="metres"),
]


class TestExactEngineVsNaiveGP:
    @pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: f"{c.formulation}-nu{c.nu}-{c.units}")
    @pytest.mark.parametrize("out_shape", [(H, W), (12, 14), (9, 10)])
    def test_posterior_matches(self, cfg, out_shape):
        mde, sparse = inputs()
        if cfg.formulation == "balanced":
            mde[3, 3] = np.nan  # an invalid MDE pixel is not an observation
        post = complete(mde, sparse, config=cfg, engine=EXACT, output_shape=out_shape)
        mean, var = naive_posterior(mde, sparse, cfg, out_shape)
        assert post.mean.shape == post.variance.shape == out_shape
        np.testing.assert_allclose(post.mean, mean, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(post.variance, var, rtol=1e-6, atol=1e-10)

    def test_measurement_on_an_invalid_mde_pixel(self):
        mde, _ = inputs()
        mde[2, 2] = 0.0
        sparse = SparseDepth(np.array([2.0]), np.array([2.0]), np.array([7.0]), (H, W))
        cfg = CONFIGS[0]
        post = complete(mde, sparse, config=cfg, engine=EXACT)
        mean, var = naive_posterior(mde, sparse, cfg, (H, W))
        np.testing.assert_allclose(post.mean, mean, rtol=1e-8)
        np.testing.assert_allclose(post.variance, var, rtol=1e-6)


def grid_problem(n_obs=5, shape=(H, W), seed=1, s=0.7):
    rng = np.random.default_rng(seed)
    precision = np.zeros(shape)
    idx = rng.choice(shape[0] * shape[1], n_obs, replace=False)
    precision.flat[idx] = 1.0 / 0.1**2
    obs = rng.uniform(2.0, 4.0, size=shape)
    return GridProblem(
        prior_mean=np.full(shape, 3.0),
        obs=obs,
        precision=precision,
        out_rows=np.arange(shape[0], dtype=float),
        out_cols=np.arange(shape[1], dtype=float),
        out_prior_mean=np.full(shape, 3.0),
        kernel=Kernel(1.5, 2.0, s),
    )


class TestExactEngineSolve:
    def test_variance_flag(self):
        p = grid_problem()
        mean, var = ExactEngine().solve(p)
        mean2, none = ExactEngine().solve(p, variance=False)
        assert none is None and var.shape == mean.shape == (H, W)
        np.testing.assert_array_equal(mean, mean2)
        assert np.all(var > 0) and np.all(var <= 0.7**2 + 1e-12)

    def test_no_observations_gives_the_prior(self):
        p = grid_problem(n_obs=0)
        mean, var = ExactEngine().solve(p)
        np.testing.assert_array_equal(mean, p.out_prior_mean)
        np.testing.assert_allclose(var, 0.49)

    def test_small_noise_interpolates(self):
        p = grid_problem(n_obs=4)
        p = GridProblem(
            p.prior_mean,
            p.obs,
            np.where(p.precision > 0, 1e10, 0.0),
            p.out_rows,
            p.out_cols,
            p.out_prior_mean,
            p.kernel,
        )
        mean, var = ExactEngine().solve(p)
        at = p.precision > 0
        np.testing.assert_allclose(mean[at], p.obs[at], atol=1e-4)
        assert np.all(var[at] < 1e-8) and np.all(var[~at] > 1e-4)

    def test_blocked_output_equals_single_block(self):
        p = grid_problem(n_obs=10, shape=(20, 30))
        a = ExactEngine().solve(p)
        b = ExactEngine(max_cross_entries=10 * 600).solve(p)  # 4 output blocks of 150 pixels
        np.testing.assert_allclose(a[0], b[0], rtol=1e-12)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-10)

    def test_too_large_is_refused(self):
        p = grid_problem(n_obs=10)
        with pytest.raises(ProblemTooLargeError, match="exact engine"):
            ExactEngine(max_points=9).solve(p)
        with pytest.raises(ProblemTooLargeError):
            ExactEngine(max_cross_entries=10 * H * W - 1).solve(p)
        with pytest.raises(ProblemTooLargeError):
            complete(*inputs(), config=DepthGPConfig.paper(), engine=EngineConfig(name="exact", max_exact_points=10))

    def test_build_problem_feeds_the_engine(self):
        mde, sparse = inputs()
        problem, grid_sparse, scale, _ = build_problem(mde, sparse, CONFIGS[0])
        assert problem.output_is_input and scale == pytest.approx(np.median(mde))
        assert np.count_nonzero(problem.precision) == H * W and len(grid_sparse) == 4


def with_changes(problem: GridProblem, **changes) -> GridProblem:
    from dataclasses import replace

    return replace(problem, **changes)


def _bad_problems():
    p = grid_problem(n_obs=6)
    obs_pixel = tuple(np.argwhere(p.precision > 0)[0])
    huge_obs = p.obs.copy()
    huge_obs[obs_pixel] = 1e300
    nan_obs = p.obs.copy()
    nan_obs[obs_pixel] = np.nan
    huge_prec = p.precision.copy()
    huge_prec[obs_pixel] = 1e300
    return {
        "outputscale 1e300": (with_changes(p, kernel=Kernel(0.5, 1.5, 1e300)), "outputscale"),
        "outputscale 1e-300": (with_changes(p, kernel=Kernel(1.5, 1.5, 1e-300)), "outputscale"),
        "lengthscale inf": (with_changes(p, kernel=Kernel(0.5, np.inf, 1.0)), "lengthscale"),
        "observed depth 1e300": (with_changes(p, obs=huge_obs), "problem.obs"),
        "observed depth NaN": (with_changes(p, obs=nan_obs), "problem.obs"),
        "prior mean 1e300": (with_changes(p, prior_mean=np.full(p.shape, 1e300)), "problem.prior_mean"),
        "output prior mean inf": (with_changes(p, out_prior_mean=np.full(p.out_shape, np.inf)), "out_prior_mean"),
        "precision 1e300": (with_changes(p, precision=huge_prec), "problem.precision"),
        "precision NaN": (with_changes(p, precision=np.where(p.precision > 0, np.nan, 0.0)), "problem.precision"),
        "output rows NaN": (with_changes(p, out_rows=np.full(p.out_shape[0], np.nan)), "out_rows"),
        "precision of another shape": (with_changes(p, precision=p.precision[:, :-1]), "problem.precision"),
    }


class TestExtremeValues:
    """Out-of-range numbers give a typed error naming the argument on every engine, never an OverflowError,
    a ZeroDivisionError, NaN or inf."""

    @pytest.mark.parametrize("case", list(_bad_problems()))
    @pytest.mark.parametrize("engine", ["exact", "fast", "fast-dense", "fast-woodbury"])
    def test_bad_problem_is_refused(self, case, engine):
        from gpdepth3d.errors import InvalidInputError
        from gpdepth3d.gp.fast import FastEngine

        problem, argument = _bad_problems()[case]
        solver = (
            ExactEngine() if engine == "exact" else FastEngine(route=engine.split("-")[1] if "-" in engine else "auto")
        )
        with pytest.raises(InvalidInputError, match=argument):
            solver.solve(problem)

    def test_limits_are_inclusive_of_sane_values(self):
        """Depths of 1e5 m with s = 1e4 m and noise 1 m: accepted and finite (both engines agree). (With noise
        1e-3 m, s^2 / noise = 1e14, the dense reference's s^2 (1 - q) cancels: its std is 1 % off at the points.)"""
        from gpdepth3d.gp.fast import FastEngine

        p = grid_problem(n_obs=6)
        big = with_changes(
            p,
            prior_mean=p.prior_mean * 3e4,
            obs=p.obs * 3e4,
            out_prior_mean=p.out_prior_mean * 3e4,
            precision=np.where(p.precision > 0, 1.0, 0.0),
            kernel=Kernel(0.5, 1.5, 1e4),
        )
        m0, v0 = ExactEngine().solve(big)
        m1, v1 = FastEngine().solve(big)
        assert np.all(np.isfinite(m0)) and np.all(np.isfinite(v0))
        np.testing.assert_allclose(m1, m0, rtol=1e-9)
        np.testing.assert_allclose(np.sqrt(v1), np.sqrt(v0), rtol=1e-7)

    @pytest.mark.parametrize("value", [1e300, 1e-300, 1e7, 1e-7])
    @pytest.mark.parametrize(
        "cfg, engine",
        [(DepthGPConfig.paper(), None), (DepthGPConfig.residual(), None), (DepthGPConfig.residual(), EXACT)],
        ids=["paper", "residual", "residual-exact"],
    )
    def test_mde_out_of_range_through_complete(self, value, cfg, engine):
        from gpdepth3d.errors import InvalidDepthError

        mde, sparse = inputs()
        with pytest.raises(InvalidDepthError, match=r"mde_depth.*\[1e-6, 1e6\] m"):
            complete(np.full_like(mde, value), sparse, config=cfg, engine=engine)
        mde[2, 3] = value  # one pixel is enough
        with pytest.raises(InvalidDepthError, match="1 outside"):
            complete(mde, sparse, config=cfg, engine=engine)

    @pytest.mark.parametrize("value", [1e300, 1e-300, 1e7])
    @pytest.mark.parametrize(
        "cfg, engine",
        [(DepthGPConfig.paper(), None), (DepthGPConfig.residual(), None), (DepthGPConfig.residual(), EXACT)],
        ids=["paper", "residual", "residual-exact"],
    )
    def test_one_extreme_sparse_depth(self, value, cfg, engine):
        """One measurement of 1e300 / 1e-300 / 1e7 m: a typed error or a finite posterior, never inf or NaN."""
        from gpdepth3d.errors import GPDepthError

        mde, sparse = inputs()
        depth = sparse.depth.copy()
        depth[0] = value
        try:
            bad = SparseDepth(sparse.u, sparse.v, depth, sparse.image_size, sparse.sigma)
            post = complete(mde, bad, config=cfg, engine=engine)
        except GPDepthError:
            return
        assert np.all(np.isfinite(post.mean)) and np.all(np.isfinite(post.std))


class TestDenseAlgebra:
    def test_log_marginal_likelihood_matches_naive(self):
        from gpdepth3d.gp.exact import dense_log_marginal_likelihood

        p = grid_problem(n_obs=9, shape=(8, 9))
        obs = p.precision > 0
        r, c = np.nonzero(obs)
        K = k(r, c, r, c, p.kernel.outputscale, p.kernel.nu, p.kernel.lengthscale) + np.diag(1 / p.precision[obs])
        y = p.obs[obs] - p.prior_mean[obs]
        naive = -0.5 * y @ np.linalg.solve(K, y) - 0.5 * np.linalg.slogdet(K)[1] - 0.5 * y.size * np.log(2 * np.pi)
        assert dense_log_marginal_likelihood(p) == pytest.approx(naive, rel=1e-12)
        empty = with_changes(p, precision=np.zeros(p.shape))
        assert dense_log_marginal_likelihood(empty) == 0.0

    def test_fast_engine_lml_on_the_dense_route_matches(self):
        from gpdepth3d.gp.exact import dense_log_marginal_likelihood
        from gpdepth3d.gp.fast import FastEngine

        p = with_changes(grid_problem(n_obs=9, shape=(8, 9)), kernel=Kernel(2.5, 30.0, 0.7))
        engine = FastEngine()
        assert engine.log_marginal_likelihood(p) == pytest.approx(dense_log_marginal_likelihood(p), rel=1e-12)
        assert engine.plan(p, lml=True) == "dense"

    def test_dense_bytes_grows_with_points_and_outputs(self):
        from gpdepth3d.gp.exact import dense_bytes

        assert dense_bytes(100, 1000) < dense_bytes(1000, 1000) < dense_bytes(1000, 100000)
        assert dense_bytes(500, 76800, variance=False) < dense_bytes(500, 76800)
        assert dense_bytes(2000, 10) >= 8 * 2000**2

    def test_failed_cholesky_is_a_typed_error(self, monkeypatch):
        """Should the kernel matrix plus noise not be numerically positive definite, the LinAlgError becomes a
        ConvergenceError naming the kernel and the smallest noise ratio."""
        import scipy.linalg

        from gpdepth3d.errors import ConvergenceError

        def fail(*args, **kwargs):
            raise np.linalg.LinAlgError("2-th leading minor not positive definite")

        monkeypatch.setattr(scipy.linalg, "cho_factor", fail)
        p = with_changes(grid_problem(n_obs=20, shape=(8, 9)), kernel=Kernel(2.5, 1e6, 1.0))
        with pytest.raises(ConvergenceError, match=r"nu=2.5, lengthscale=1e\+06 px.*noise/s\^2 = 0.01"):
            ExactEngine().solve(p)


@pytest.mark.parametrize(
    "field, value, error, match",
    [
        ("precision", np.nan, "InvalidInputError", "problem.precision"),
        ("precision", -1.0, "InvalidInputError", "problem.precision"),
        ("precision", np.inf, "InvalidInputError", "problem.precision"),
        ("prior_mean", np.nan, "InvalidDepthError", "problem.prior_mean.*1 values outside"),
        ("obs", 2e8, "InvalidDepthError", "problem.obs.*1 values outside, e.g. 2e"),
        ("obs", -np.inf, "InvalidDepthError", "problem.obs"),
        ("out_prior_mean", np.nan, "InvalidDepthError", "problem.out_prior_mean"),
        ("out_prior_mean", -3e8, "InvalidDepthError", "problem.out_prior_mean.*e.g. -3e"),
    ],
)
def test_check_problem_rejects_bad_values(field, value, error, match):
    from gpdepth3d import errors
    from gpdepth3d.gp.exact import check_problem

    p = grid_problem(n_obs=6)
    check_problem(p)
    arr = np.array(getattr(p, field), dtype=np.float64)
    r, c = np.argwhere(p.precision > 0)[0]
    arr[r, c] = value  # an observed pixel
    with pytest.raises(getattr(errors, error), match=match):
        check_problem(with_changes(p, **{field: arr}))
    if field in ("prior_mean", "obs"):  # where nothing is observed a value is not used, and not checked
        arr = np.array(getattr(p, field), dtype=np.float64)
        r, c = np.argwhere(p.precision == 0)[0]
        arr[r, c] = value
        check_problem(with_changes(p, **{field: arr}))
