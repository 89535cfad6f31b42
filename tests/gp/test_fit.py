"""Tests of hyperparameter fitting: gpdepth3d.completion.marginal_fit on data sampled from the model, gpdepth3d.gp.fit alone."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.completion.complete import build_problem
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.completion.marginal_fit import fit_hyperparameters, log_marginal_likelihood
from gpdepth3d.gp.model import DepthGPConfig, matern_1d
from gpdepth3d.measurements import SparseDepth

H, W = 32, 40


def sample_field(rng, lengthscale, s, nu=0.5, mean=10.0):
    """One draw of the separable Matern field on the (H, W) grid (dense Kronecker Cholesky)."""
    Lv = np.linalg.cholesky(
        matern_1d(np.subtract.outer(np.arange(H), np.arange(H)), nu, lengthscale) + 1e-10 * np.eye(H)
    )
    Lu = np.linalg.cholesky(
        matern_1d(np.subtract.outer(np.arange(W), np.arange(W)), nu, lengthscale) + 1e-10 * np.eye(W)
    )
    return mean + s * Lv @ rng.standard_normal((H, W)) @ Lu.T


def balanced_frame(rng, lengthscale=3.0, s=1.0, sdl=0.3, smeas=0.02, n_points=300):
    f = sample_field(rng, lengthscale, s)
    mde = f + rng.normal(0, sdl, f.shape)
    idx = rng.choice(H * W, n_points, replace=False)
    r, c = np.divmod(idx, W)
    sparse = SparseDepth.from_arrays(c.astype(float), r.astype(float), f[r, c] + rng.normal(0, smeas, n_points), (H, W))
    return mde, sparse


def dense_balanced_lml(mde, sparse, cfg):
    """Dense reference: one row per observation (MDE pixels and points separately)."""
    rr, cc = np.nonzero(mde > 0)
    rows = np.concatenate([rr, sparse.v.astype(int)])
    cols = np.concatenate([cc, sparse.u.astype(int)])
    y = np.concatenate([mde[rr, cc], sparse.depth]) - mde[rr, cc].mean()
    noise = np.concatenate([np.full(rr.size, cfg.sigma_dl**2), np.full(len(sparse), cfg.sigma_meas**2)])
    K = cfg.outputscale**2 * matern_1d(np.subtract.outer(rows, rows), cfg.nu, cfg.lengthscale) * matern_1d(
        np.subtract.outer(cols, cols), cfg.nu, cfg.lengthscale
    ) + np.diag(noise)
    sign, logdet = np.linalg.slogdet(K)
    return -0.5 * y @ np.linalg.solve(K, y) - 0.5 * logdet - 0.5 * y.size * np.log(2 * np.pi)


class TestLogMarginalLikelihood:
    def test_balanced_matches_dense_with_double_observations(self):
        rng = np.random.default_rng(0)
        small = (12, 14)
        f = 10 + rng.normal(0, 1, small)
        mde = f + rng.normal(0, 0.3, small)
        r, c = np.divmod(rng.choice(small[0] * small[1], 20, replace=False), small[1])
        sparse = SparseDepth.from_arrays(c.astype(float), r.astype(float), f[r, c], small)
        cfg = DepthGPConfig.paper(units="metres", lengthscale=2.0, outputscale=1.2, sigma_dl=0.3, sigma_meas=0.05)
        assert log_marginal_likelihood(mde, sparse, cfg) == pytest.approx(
            dense_balanced_lml(mde, sparse, cfg), rel=1e-9
        )

    def test_residual_matches_dense(self):
        rng = np.random.default_rng(1)
        mde = 10 + rng.normal(0, 1, (10, 12))
        r, c = np.divmod(rng.choice(120, 30, replace=False), 12)
        sparse = SparseDepth.from_arrays(c.astype(float), r.astype(float), mde[r, c] + rng.normal(0, 0.5, 30), (10, 12))
        cfg = DepthGPConfig.residual(units="metres", align="none", outputscale=0.7, lengthscale=3.0, sigma_meas=0.1)
        problem, *_ = build_problem(mde, sparse, cfg)
        K = 0.49 * matern_1d(np.subtract.outer(r, r), 0.5, 3.0) * matern_1d(np.subtract.outer(c, c), 0.5, 3.0)
        K += 0.01 * np.eye(30)
        y = sparse.depth - mde[r, c]
        dense = -0.5 * y @ np.linalg.solve(K, y) - 0.5 * np.linalg.slogdet(K)[1] - 15 * np.log(2 * np.pi)
        assert log_marginal_likelihood(mde, sparse, cfg) == pytest.approx(dense, rel=1e-9)


class TestFitHyperparameters:
    def test_recovers_balanced_parameters_and_improves_lml(self):
        rng = np.random.default_rng(2)
        mde, sparse = balanced_frame(rng, lengthscale=3.0, s=1.0, sdl=0.3, smeas=0.02)
        start = DepthGPConfig.paper(units="metres", lengthscale=1.0, outputscale=0.3, sigma_dl=0.05, sigma_meas=0.02)
        fitted = fit_hyperparameters(mde, sparse, start, max_iterations=30)
        assert fitted.lengthscale == pytest.approx(3.0, rel=0.4)
        assert fitted.outputscale == pytest.approx(1.0, rel=0.4)
        assert fitted.sigma_dl == pytest.approx(0.3, rel=0.15)
        assert fitted.sigma_meas == start.sigma_meas and fitted.formulation == "balanced"
        assert log_marginal_likelihood(mde, sparse, fitted) > log_marginal_likelihood(mde, sparse, start) + 10

    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_residual_fit_improves_lml(self):
        rng = np.random.default_rng(3)
        err = sample_field(rng, 6.0, 0.8, mean=0.0)
        truth = 10 + rng.normal(0, 1, (H, W))
        mde = truth - err
        r, c = np.divmod(rng.choice(H * W, 800, replace=False), W)
        sparse = SparseDepth.from_arrays(c.astype(float), r.astype(float), truth[r, c], (H, W), sigma=0.01)
        start = DepthGPConfig.residual(units="metres", align="none", lengthscale=1.0, outputscale=0.1)
        fitted = fit_hyperparameters(mde, sparse, start, max_iterations=30)
        assert fitted.lengthscale == pytest.approx(6.0, rel=0.5)
        assert fitted.outputscale == pytest.approx(0.8, rel=0.5)
        assert log_marginal_likelihood(mde, sparse, fitted) > log_marginal_likelihood(mde, sparse, start)

    def test_bad_arguments(self):
        mde, sparse = balanced_frame(np.random.default_rng(4), n_points=10)
        with pytest.raises(InvalidInputError):
            fit_hyperparameters(mde, sparse, DepthGPConfig.paper(), params=("bogus",))
        with pytest.raises(InvalidInputError):
            fit_hyperparameters(mde, sparse, DepthGPConfig.residual(), params=("sigma_dl",))
        with pytest.raises(InvalidInputError):
            fit_hyperparameters(mde, sparse, DepthGPConfig.paper(), max_iterations=0)
        with pytest.raises(InvalidInputError):
            fit_hyperparameters(mde, sparse, "config")


class TestFitOption:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_config_fit_fits_each_frame_warm_started(self, monkeypatch):
        from gpdepth3d.completion.complete import DepthCompleter
        import gpdepth3d.completion.marginal_fit as fitmod

        rng = np.random.default_rng(5)
        start = DepthGPConfig.paper(
            units="metres", lengthscale=1.0, outputscale=0.3, sigma_dl=0.05, sigma_meas=0.02, fit=True
        )
        completer = DepthCompleter(start)
        starts = []
        real = fitmod.fit_hyperparameters

        def spy(mde, sparse, config, **kw):
            starts.append(config)
            return real(mde, sparse, config, **kw)

        monkeypatch.setattr(fitmod, "fit_hyperparameters", spy)
        frames = [balanced_frame(rng, lengthscale=3.0, s=1.0, sdl=0.3) for _ in range(2)]
        posts = [completer(mde, sparse) for mde, sparse in frames]
        # frame 1 starts from the config, frame 2 from frame 1's fit
        assert starts[0].lengthscale == 1.0 and not starts[0].fit
        assert starts[1].lengthscale == posts[0].config.lengthscale != 1.0
        for (mde, sparse), post in zip(frames, posts):
            assert post.config.fit and post.config.sigma_dl == pytest.approx(0.3, rel=0.2)
            assert log_marginal_likelihood(mde, sparse, post.config) > log_marginal_likelihood(mde, sparse, start) + 10
            assert post.timings["fit"] > 0
        # the posterior is the one of the fitted model
        ref = DepthCompleter(posts[1].config.replace(fit=False))(*frames[1])
        np.testing.assert_allclose(posts[1].mean, ref.mean, atol=1e-9)

    def test_fit_flag_is_validated(self):
        with pytest.raises(InvalidInputError, match="fit"):
            DepthGPConfig(fit="yes")


class TestFitParams:
    def test_defaults_per_formulation_and_checks(self):
        from gpdepth3d.gp.fit import fit_params

        assert fit_params(DepthGPConfig.paper()) == ("lengthscale", "outputscale", "sigma_dl")
        assert fit_params(DepthGPConfig.residual()) == ("lengthscale", "outputscale")
        assert fit_params(DepthGPConfig.paper(), ["sigma_meas"]) == ("sigma_meas",)
        for bad in ([], ["nu"], ["lengthscale", "lengthscale"]):
            with pytest.raises(InvalidInputError, match="params"):
                fit_params(DepthGPConfig.paper(), bad)
        with pytest.raises(InvalidInputError, match="sigma_dl"):
            fit_params(DepthGPConfig.residual(), ["sigma_dl"])
        with pytest.raises(InvalidInputError, match="log_residual"):
            fit_params(DepthGPConfig())
        with pytest.raises(InvalidInputError, match="config"):
            fit_params({"lengthscale": 1.0})


class TestPairedLogLikelihood:
    def test_matches_scipy_normal(self):
        from scipy.stats import norm

        from gpdepth3d.gp.fit import paired_log_likelihood

        rng = np.random.default_rng(0)
        a, b, var = rng.normal(5, 1, 20), rng.normal(5, 1, 20), rng.uniform(0.01, 2.0, 20)
        expected = norm.logpdf(a - b, scale=np.sqrt(var)).sum()
        assert paired_log_likelihood(a, b, var) == pytest.approx(expected, rel=1e-12)
        assert paired_log_likelihood(np.zeros(0), np.zeros(0), np.zeros(0)) == 0.0

    def test_bad_arguments(self):
        from gpdepth3d.gp.fit import paired_log_likelihood

        with pytest.raises(InvalidInputError, match="a, b, variance"):
            paired_log_likelihood(np.zeros(3), np.zeros(2), np.ones(3))
        with pytest.raises(InvalidInputError, match="variance"):
            paired_log_likelihood(np.zeros(2), np.zeros(2), np.array([1.0, 0.0]))


class TestMaximiseLogMarginalLikelihood:
    """The optimiser alone, on arrays: a known likelihood surface in the config's fields."""

    def test_finds_the_maximum_and_stays_in_bounds(self):
        from gpdepth3d.gp.fit import FIT_BOUNDS, maximise_log_marginal_likelihood

        start = DepthGPConfig.paper(lengthscale=1.0, outputscale=0.5)

        def lml(cfg):  # peak at lengthscale 7, outputscale 2000 (beyond its upper bound 1e3)
            return -50 * (np.log(cfg.lengthscale) - np.log(7.0)) ** 2 - (np.log(cfg.outputscale) - np.log(2000.0)) ** 2

        fitted = maximise_log_marginal_likelihood(lml, start, ["lengthscale", "outputscale"], n_obs=3)
        assert fitted.lengthscale == pytest.approx(7.0, rel=1e-3)
        assert fitted.outputscale == pytest.approx(FIT_BOUNDS["outputscale"][1], rel=1e-6)
        assert fitted.sigma_dl == start.sigma_dl and fitted.formulation == start.formulation

    def test_failing_configs_count_as_unlikely_and_the_start_is_kept(self):
        from gpdepth3d.errors import ConvergenceError
        from gpdepth3d.gp.fit import maximise_log_marginal_likelihood

        start = DepthGPConfig.paper(lengthscale=3.0)

        def lml(cfg):
            if cfg.lengthscale != start.lengthscale:
                raise (np.linalg.LinAlgError if cfg.lengthscale > 3.0 else ConvergenceError)("refused")
            return -1.0

        fitted = maximise_log_marginal_likelihood(lml, start, ["lengthscale"])
        assert fitted.lengthscale == pytest.approx(3.0, rel=1e-12)
        # a likelihood worse everywhere than at the start: the start is returned
        fitted = maximise_log_marginal_likelihood(
            lambda cfg: 0.0 if cfg.lengthscale == 3.0 else float("nan"), start, ["lengthscale"]
        )
        assert fitted.lengthscale == pytest.approx(3.0, rel=1e-12)

    def test_bad_arguments(self):
        from gpdepth3d.gp.fit import maximise_log_marginal_likelihood

        cfg = DepthGPConfig.paper()
        with pytest.raises(InvalidInputError, match="max_iterations"):
            maximise_log_marginal_likelihood(lambda c: 0.0, cfg, ["lengthscale"], max_iterations=0)
        with pytest.raises(InvalidInputError, match="n_obs"):
            maximise_log_marginal_likelihood(lambda c: 0.0, cfg, ["lengthscale"], n_obs=0)
        with pytest.raises(InvalidInputError, match="params"):
            maximise_log_marginal_likelihood(lambda c: 0.0, cfg, ["nu"])
