"""The default model (log_residual): point fit, leave-one-out screening, the posterior's formula,
robustness to gross outliers, warnings, and accuracy/calibration on real frames."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import AssemblyConfig, CalibrationConfig, ScreenConfig, SlopeConfig
from gpdepth3d.completion.complete import PosteriorWarning
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.model import matern_1d
from gpdepth3d.gp.fit import PointFit, fit_log_residual, raised_outputscale
from gpdepth3d.gp.points import loo_zscores, screen_points
from gpdepth3d.measurements import SparseDepth


def _kernel(rows, cols, l, nu=0.5):
    return matern_1d(np.subtract.outer(rows, rows), nu, l) * matern_1d(np.subtract.outer(cols, cols), nu, l)


def _field_sample(n, h, w, l, s, tau, b, seed):
    """n random pixels of an (h, w) grid with log residuals drawn from the model."""
    rng = np.random.default_rng(seed)
    flat = rng.choice(h * w, size=n, replace=False)
    rows, cols = (flat // w).astype(float), (flat % w).astype(float)
    K = s * s * _kernel(rows, cols, l) + tau * tau * np.eye(n)
    resid = b + np.linalg.cholesky(K + 1e-12 * np.eye(n)) @ rng.standard_normal(n)
    return rows, cols, resid


class TestFitLogResidual:
    def test_recovers_the_generating_scales(self):
        rows, cols, resid = _field_sample(400, 120, 160, l=16.0, s=0.25, tau=0.03, b=0.4, seed=0)
        fit = fit_log_residual(rows, cols, resid, np.full(400, 1e-6), max_points=400)
        assert 8.0 <= fit.lengthscale <= 32.0
        assert 0.15 <= fit.outputscale <= 0.4
        assert abs(fit.log_scale - 0.4) < 3 * np.sqrt(fit.log_scale_var) + 0.05
        assert fit.n_used == 400

    def test_short_and_long_fields_get_different_length_scales(self):
        a = fit_log_residual(*_field_sample(300, 120, 160, 4.0, 0.2, 0.01, 0.0, 1), np.full(300, 1e-6), max_points=300)
        b = fit_log_residual(*_field_sample(300, 120, 160, 64.0, 0.2, 0.01, 0.0, 1), np.full(300, 1e-6), max_points=300)
        assert a.lengthscale * 4 <= b.lengthscale

    def test_few_points_fall_back(self):
        fit = fit_log_residual(np.array([1.0]), np.array([2.0]), np.array([0.3]), np.array([1e-4]))
        assert fit.log_scale == pytest.approx(0.3) and fit.n_used == 1 and fit.outputscale >= 0.1

    def test_mismatched_lengths_raise(self):
        with pytest.raises(InvalidInputError, match="rows, cols, resid, noise"):
            fit_log_residual(np.zeros(3), np.zeros(3), np.zeros(4), np.zeros(3))


class TestLooZscores:
    def test_equals_exact_leave_one_out_when_every_point_is_a_neighbour(self):
        rows, cols, resid = _field_sample(12, 30, 40, 8.0, 0.3, 0.05, 0.1, 3)
        noise = np.full(12, 1e-4)
        fit = PointFit(8.0, 0.3, 0.05, 0.1, 0.0, 12)
        z = loo_zscores(rows, cols, resid, noise, fit, neighbours=11)
        K = 0.09 * _kernel(rows, cols, 8.0) + np.diag(0.0025 + noise)
        Ki = np.linalg.inv(K)
        r = resid - 0.1
        exact = (Ki @ r) / np.diag(Ki) / np.sqrt(1.0 / np.diag(Ki))
        np.testing.assert_allclose(z, exact, rtol=1e-8, atol=1e-10)

    def test_flags_a_planted_outlier(self):
        rows, cols, resid = _field_sample(300, 120, 160, 16.0, 0.2, 0.02, 0.0, 4)
        resid[17] += 1.5
        fit = fit_log_residual(rows, cols, resid, np.full(300, 1e-6))
        z = loo_zscores(rows, cols, resid, np.full(300, 1e-6), fit)
        assert np.argmax(np.abs(z)) == 17 and abs(z[17]) > 6


class TestScreenPoints:
    def test_rejects_gross_outliers_and_keeps_the_rest(self):
        rows, cols, resid = _field_sample(400, 120, 160, 16.0, 0.2, 0.02, 0.0, 5)
        rng = np.random.default_rng(5)
        bad = rng.choice(400, 20, replace=False)
        resid[bad] += np.log(rng.choice([0.15, 0.3, 2.5, 3.0], 20))
        fit, rejected, z, _ = screen_points(rows, cols, resid, np.full(400, 1e-6))
        assert np.count_nonzero(rejected[bad]) >= 19  # 20 planted, factors 0.15-3
        assert np.count_nonzero(np.abs(z[bad]) > 3.5) >= 19 and z.shape == (400,)
        assert rejected.sum() <= 20 + 4
        assert 0.1 <= fit.outputscale <= 0.35  # fitted without the outliers

    def test_threshold_none_keeps_all(self):
        rows, cols, resid = _field_sample(50, 30, 40, 8.0, 0.2, 0.02, 0.0, 6)
        resid[3] += 3.0
        _, rejected, z, _ = screen_points(rows, cols, resid, np.full(50, 1e-6), threshold=None)
        assert not z.any()
        assert not rejected.any()

    def test_raised_outputscale_follows_a_wider_field_and_never_lowers(self):
        start = PointFit(32.0, 0.2, 0.02, 0.0, 0.04 / 300, 300)
        wide = _field_sample(300, 120, 160, 32.0, 0.6, 0.06, 0.0, 11)
        raised = raised_outputscale(*wide, np.full(300, 1e-6), start)
        assert 0.4 <= raised.outputscale <= 0.9  # drawn with s = 0.6
        assert (raised.lengthscale, raised.nugget, raised.log_scale) == (32.0, 0.02, 0.0)
        assert raised.log_scale_var == pytest.approx(raised.outputscale**2 / 300)
        narrow = _field_sample(300, 120, 160, 32.0, 0.05, 0.005, 0.0, 12)
        assert raised_outputscale(*narrow, np.full(300, 1e-6), start) is start  # s = 0.05 < 0.2: kept
        assert raised_outputscale(np.zeros(2), np.arange(2.0), np.array([0.0, 3.0]), np.ones(2), start) is start

    def test_raised_outputscale_on_some_points_is_that_of_those_points(self):
        rng = np.random.default_rng(8)
        rows, cols = rng.integers(0, 40, 500).astype(float), rng.integers(0, 60, 500).astype(float)
        resid, noise = 0.4 * rng.standard_normal(500), rng.uniform(1e-6, 1e-3, 500)
        start = PointFit(10.0, 0.2, 0.02, 0.0, 1e-4, 500)
        for use in (rng.random(500) > 0.3, np.arange(500) < 2):
            got = raised_outputscale(rows, cols, resid, noise, start, use=use)
            assert got == raised_outputscale(rows[use], cols[use], resid[use], noise[use], start)
        assert raised_outputscale(rows, cols, resid, noise, start, use=rng.random(500) > 0.3) is not start

    def test_raise_outputscale_screens_a_wide_field_without_losing_its_points(self):
        """A field far wider than the configured s, with 15 gross outliers: a fixed s = 0.2 flags good
        points too; with the floor raised by the points the outliers go and the good points stay."""
        rows, cols, resid = _field_sample(400, 120, 160, 32.0, 0.7, 0.07, 0.0, 13)
        rng = np.random.default_rng(13)
        bad = rng.choice(400, 15, replace=False)
        resid[bad] += np.log(rng.choice([0.05, 0.1, 10.0, 20.0], 15))
        start = PointFit(32.0, 0.2, 0.02, float(np.median(resid)), 0.04 / 400, 400)
        good = np.ones(400, dtype=bool)
        good[bad] = False
        fixed_fit, fixed, _, _ = screen_points(rows, cols, resid, np.full(400, 1e-6), start=start)
        fit, rejected, _, _ = screen_points(rows, cols, resid, np.full(400, 1e-6), start=start, raise_outputscale=True)
        assert fixed_fit is start and fit.outputscale > 0.45
        assert np.count_nonzero(rejected[bad]) >= 14
        assert np.count_nonzero(rejected[good]) < np.count_nonzero(fixed[good])
        assert np.count_nonzero(rejected[good]) <= 4

    @pytest.mark.parametrize("threshold", [0.0, -1.0, float("nan")])
    def test_bad_threshold_raises(self, threshold):
        with pytest.raises(InvalidInputError, match="threshold"):
            screen_points(np.zeros(5), np.arange(5.0), np.zeros(5), np.ones(5), threshold=threshold)


def _scene(h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:h, 0:w]
    truth = 2.0 + 0.5 * np.sin(rr / 6.0) + 0.3 * cc / w
    mde = truth * np.exp(0.15 * np.sin(cc / 9.0 + 1.0) + 0.05 * rng.standard_normal((h, w))) * 0.8
    return truth, mde


def _dense_log_posterior(mde, sp, *, l, s, tau, sigma, depth_factor=None):
    """Independent dense reference of the log-residual posterior with fixed hyperparameters and b = the
    points' median log ratio: (mu, v) of the log depth at every pixel (row-major), and b. ``depth_factor``
    (one value per pixel, row-major) multiplies each pixel's cross-covariance with the points."""
    h, w = mde.shape
    rows, cols, z = sp.v.astype(int), sp.u.astype(int), sp.depth
    r = np.log(z) - np.log(mde[rows, cols])
    b, n = np.median(r), len(z)
    K = s * s * _kernel(rows.astype(float), cols.astype(float), l) + (tau**2 + sigma**2) * np.eye(n)
    R, C = np.mgrid[0:h, 0:w]
    kx = s * s * matern_1d(R.ravel()[:, None] - rows[None], 0.5, l) * matern_1d(C.ravel()[:, None] - cols[None], 0.5, l)
    if depth_factor is not None:
        kx = kx * depth_factor[:, None]
    A = kx @ np.linalg.inv(K)
    v = s * s - np.sum(A * kx, 1) + tau**2 + (s * s / n) * (1 - A @ np.ones(n)) ** 2
    return np.log(mde.ravel()) + b + A @ (r - b), v, b


class TestLogResidualPosterior:
    def test_matches_a_dense_reference(self):
        """Fixed hyperparameters, no rejection, no edge term: the posterior is a closed form."""
        truth, mde = _scene()
        sp = g.sample_uniform(truth, n=40, rng=1)
        cfg = g.DepthGPConfig(
            fit=False,
            lengthscale=6.0,
            outputscale=0.3,
            nugget=0.04,
            sigma_meas=0.01,
            screen=ScreenConfig(outlier_threshold=None),
            calibration=CalibrationConfig(reach=None),
            assembly=AssemblyConfig(edge_sigma=0.0, depth_lengthscale=None),
            slope=SlopeConfig(prior_sigma=None),
        )
        post = g.complete(mde, sp, config=cfg)
        mu, v, b = _dense_log_posterior(mde, sp, l=6.0, s=0.3, tau=0.04, sigma=0.01)
        np.testing.assert_allclose(post.mean.ravel(), np.exp(mu + v / 2), rtol=1e-9)
        np.testing.assert_allclose(post.variance.ravel(), np.expm1(v) * np.exp(2 * mu + v), rtol=1e-8)
        assert post.n_rejected == 0 and post.alignment.scale == pytest.approx(np.exp(b))

    def test_depth_aware_correlation_matches_the_product_kernel(self):
        """Points sharing one MDE depth: the posterior is the product kernel's, s^2 M(du) M(dv) exp(-|dz| / l_z)."""
        h, w, lz = 24, 32, 0.7
        rr, cc = np.mgrid[0:h, 0:w]
        mde = np.where(rr >= 12, 2.0, 2.0 * np.exp(1.2 * np.sin(cc / 5.0) + 0.4 * rr / h))
        truth = mde * np.exp(0.2 + 0.1 * np.cos(cc / 7.0))
        sp = g.sample_uniform(np.where(rr >= 12, truth, 0.0), n=40, rng=3)
        cfg = g.DepthGPConfig(
            fit=False,
            lengthscale=6.0,
            outputscale=0.3,
            nugget=0.04,
            sigma_meas=0.01,
            screen=ScreenConfig(outlier_threshold=None),
            calibration=CalibrationConfig(reach=None),
            assembly=AssemblyConfig(edge_sigma=0.0, depth_lengthscale=lz),
            slope=SlopeConfig(prior_sigma=None),
        )
        post = g.complete(mde, sp, config=cfg)
        rho = np.exp(-np.abs(np.log(mde.ravel()) - np.log(2.0)) / lz)
        mu, v, b = _dense_log_posterior(mde, sp, l=6.0, s=0.3, tau=0.04, sigma=0.01, depth_factor=rho)
        np.testing.assert_allclose(post.mean.ravel(), np.exp(mu + v / 2), rtol=1e-9)
        np.testing.assert_allclose(post.variance.ravel(), np.expm1(v) * np.exp(2 * mu + v), rtol=1e-8)
        # right above the points but at another depth: the correction fades and the variance returns to the prior's
        off = np.abs(np.log(mde) - np.log(2.0)) > 1.0
        near = off & (rr >= 9) & (rr < 12)
        assert near.any()
        stationary = g.complete(mde, sp, config=cfg.replace(assembly={"depth_lengthscale": None}))

        def correction(p):  # E[g] at the pixels: log-normal median minus the scaled MDE
            v = np.log1p(p.variance[near] / p.mean[near] ** 2)
            return np.log(p.mean[near]) - v / 2 - np.log(mde[near]) - b

        assert np.all(np.abs(correction(post)) < 0.5 * np.abs(correction(stationary)))
        assert np.all(post.variance[near] > stationary.variance[near])

    def test_many_points_bound_the_scale_term(self):
        """With Var[b] <= 5 % of tau^2 the scale term is bounded by Var[b], not solved for: variance high by <= 5 %."""
        truth, mde = _scene()
        sp = g.sample_uniform(truth, n=600, rng=5)
        cfg = g.DepthGPConfig(
            fit=False,
            lengthscale=6.0,
            outputscale=0.3,
            nugget=0.06,
            sigma_meas=0.01,
            screen=ScreenConfig(outlier_threshold=None),
            calibration=CalibrationConfig(reach=None),
            assembly=AssemblyConfig(edge_sigma=0.0, depth_lengthscale=None),
            slope=SlopeConfig(prior_sigma=None),
        )
        post = g.complete(mde, sp, config=cfg)
        _, exact, _ = _dense_log_posterior(mde, sp, l=6.0, s=0.3, tau=0.06, sigma=0.01)
        got = np.log1p(post.variance.ravel() / post.mean.ravel() ** 2)  # log-normal: var / mean^2 = expm1(v)
        ratio = got / exact
        assert 0.09 / len(sp) <= 0.05 * 0.06**2 and ratio.min() > 1 - 1e-6 and ratio.max() < 1.05

    @pytest.mark.parametrize("fit", [False, True])
    def test_engines_agree(self, fit):
        truth, mde = _scene(seed=2)
        sp = g.sample_uniform(truth, n=60, rng=2)
        a = g.complete(mde, sp, config=g.DepthGPConfig(fit=fit))
        b = g.complete(mde, sp, config=g.DepthGPConfig(fit=fit), engine=EngineConfig(name="exact"))
        np.testing.assert_allclose(a.mean, b.mean, rtol=1e-9)
        np.testing.assert_allclose(a.variance, b.variance, rtol=1e-7)
        assert a.config.lengthscale == b.config.lengthscale  # fitted, reported on the posterior

    def test_upsampled_output(self):
        truth, mde = _scene(seed=3)
        sp = g.sample_uniform(truth, n=80, rng=3)
        post = g.complete(mde, sp, output_shape=(48, 64))
        assert post.mean.shape == (48, 64) and np.all(post.mean > 0) and np.all(post.variance > 0)
        small = g.complete(mde, sp)
        assert abs(np.median(post.mean) - np.median(small.mean)) < 0.02

    def test_wrong_point_far_too_close_is_rejected_and_mean_stays_positive(self):
        """The mapping crash: one point at 0.15 m where the surface is at 1.85 m, sigma 2 mm."""
        truth, mde = _scene(seed=4)
        sp = g.sample_uniform(truth, n=120, rng=4)
        depth = sp.depth.copy()
        depth[0] = 0.08 * truth[int(sp.v[0]), int(sp.u[0])]
        bad = SparseDepth(sp.u, sp.v, depth, sp.image_size, np.full(len(depth), 0.002))
        post = g.complete(mde, bad)
        assert post.rejected[np.flatnonzero((post.sparse.u == sp.u[0]) & (post.sparse.v == sp.v[0]))[0]]
        assert np.all(post.mean > 0)
        clean = g.complete(mde, SparseDepth(sp.u, sp.v, sp.depth, sp.image_size, np.full(len(depth), 0.002)))
        assert np.sqrt(np.mean((post.mean - truth) ** 2)) < 1.1 * np.sqrt(np.mean((clean.mean - truth) ** 2)) + 1e-3

    def test_no_points_gives_the_mde_with_the_prior_variance(self):
        truth, mde = _scene(seed=5)
        empty = SparseDepth(np.zeros(0), np.zeros(0), np.zeros(0), (24, 32))
        with pytest.warns(PosteriorWarning, match="only 0 usable points"):
            post = g.complete(mde, empty)
        s = g.DepthGPConfig().outputscale
        np.testing.assert_allclose(np.log(post.mean), np.log(mde) + 0.5 * (s * s + 0.02**2 + s * s), rtol=1e-6)
        assert post.warnings and post.n_rejected == 0

    def test_scale_disagreement_warns_and_is_corrected(self):
        truth, mde = _scene(seed=6)
        sp = g.sample_uniform(truth * 7.0, n=100, rng=6)
        with pytest.warns(PosteriorWarning, match="factor of"):
            post = g.complete(mde, sp, frame="000042")
        assert "frame 000042" in post.warnings[0]
        assert abs(np.median(post.mean) / np.median(truth * 7.0) - 1) < 0.1

    def test_points_in_a_corner_warn_and_variance_grows_away_from_them(self):
        rr, cc = np.mgrid[0:60, 0:80]
        truth = 3.0 + 0.2 * np.sin(rr / 7.0)
        mde = truth * np.exp(0.2 * np.sin(cc / 3.0) * np.cos(rr / 4.0))
        corner = np.where((rr < 12) & (cc < 16), truth, 0.0)
        sp = g.sample_uniform(corner, n=60, rng=7)
        with pytest.warns(PosteriorWarning, match="cover little of the image"):
            post = g.complete(mde, sp, config=g.DepthGPConfig(assembly=AssemblyConfig(edge_sigma=0.0)))
        assert post.std[55, 75] > 3 * post.std[5, 5]

    def test_points_wider_than_the_prior_raise_s_and_warn(self):
        """An MDE whose log error (a smooth field, sd 0.7) is far wider than s = 0.2: the points raise s,
        the posterior says so, and its variance is wider than with s fixed."""
        import cv2

        rng = np.random.default_rng(21)
        rr, cc = np.mgrid[0:60, 0:80]
        truth = np.exp(3.0 * rr / 60 + 0.2 * np.sin(cc / 7.0))
        f = cv2.GaussianBlur(rng.standard_normal((60, 80)), (0, 0), 10)
        mde = truth * np.exp(0.7 * f / f.std())
        sp = g.sample_uniform(truth, n=150, rng=21)
        # the local calibration off: it too widens the variance of a model whose s is too small (from the
        # points' z-scores), and would hide which of the two did it
        local_off = g.DepthGPConfig(calibration=CalibrationConfig(reach=None))
        with pytest.warns(PosteriorWarning, match="points has s = 0.2[5-9], above the configured 0.20"):
            post = g.complete(mde, sp, frame="7", config=local_off)
        assert post.config.outputscale > 0.25 and "frame 7" in post.warnings[0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PosteriorWarning)
            fixed = g.complete(mde, sp, config=local_off.replace(screen={"raise_outputscale": False}))
        assert fixed.config.outputscale == 0.2 and not any("above the configured" in w for w in fixed.warnings)
        assert np.median(post.std) > 1.1 * np.median(fixed.std)

    def test_clean_frame_gives_no_warning(self):
        truth, mde = _scene(seed=8)
        sp = g.sample_uniform(truth, n=150, rng=8)
        with warnings.catch_warnings():
            warnings.simplefilter("error", PosteriorWarning)
            post = g.complete(mde, sp)
        assert post.warnings == ()

    def test_build_problem_refuses_log_residual(self):
        from gpdepth3d.completion.complete import build_problem

        truth, mde = _scene()
        with pytest.raises(InvalidInputError, match="log_residual"):
            build_problem(mde, g.sample_uniform(truth, n=5, rng=0), g.DepthGPConfig())

    @pytest.mark.parametrize(
        "field, value",
        [
            ("nugget", -1.0),
            ("assembly.edge_sigma", float("nan")),
            ("screen.outlier_threshold", 0.0),
            ("assembly.depth_lengthscale", 0.0),
            ("assembly.depth_lengthscale", "1"),
            ("screen.raise_outputscale", "yes"),
        ],
    )
    def test_config_validation(self, field, value):
        section, _, name = field.rpartition(".")
        with pytest.raises(InvalidInputError, match=name):
            g.DepthGPConfig().replace(**({section: {name: value}} if section else {name: value}))

    def test_paper_preset_is_the_paper(self):
        p = g.DepthGPConfig.paper()
        assert (p.formulation, p.nu, p.lengthscale, p.outputscale, p.sigma_dl, p.sigma_meas, p.fit) == (
            "balanced",
            0.5,
            1.5,
            1.0,
            0.05,
            0.001,
            False,
        )


def _max_minus_min(depth: np.ndarray, window: int) -> np.ndarray:
    """The reference local depth range: SciPy's maximum_filter - minimum_filter over window x window pixels."""
    from scipy.ndimage import maximum_filter, minimum_filter

    return maximum_filter(depth, window) - minimum_filter(depth, window)


def test_edge_range_at_points_equals_the_filtered_map():
    """The screening's edge term, computed at the points only, is the 3 x 3 max - min filter's value there (borders too)."""
    from gpdepth3d.completion.log_frame import edge_range_at as _edge_range_at

    depth = np.random.default_rng(0).uniform(0.5, 20.0, (17, 23))
    rows, cols = np.divmod(np.arange(17 * 23), 23)
    np.testing.assert_array_equal(_edge_range_at(depth, rows, cols), _max_minus_min(depth, 3)[rows, cols])


def test_edge_variance_pass_equals_the_morphology_formula():
    """The calibration's one compiled pass gives (var + (scale x edge range)^2) x factor bit for bit, borders included
    (the edge range: SciPy's max - min filter, windows of 3 to 9 pixels, maps smaller than the window too)."""
    from gpdepth3d.completion.calibrate import _edge_variance

    rng = np.random.default_rng(2)
    for shape, half in (((17, 23), 1), ((40, 61), 3), ((5, 4), 4), ((2, 2), 1)):
        mde, var, factor = rng.uniform(0.5, 20.0, shape), rng.uniform(0.0, 3.0, shape), rng.uniform(0.2, 4.0, shape)
        edge = _max_minus_min(mde, 2 * half + 1) * 0.37
        for use in (False, True):
            out = np.empty(shape)
            _edge_variance(var, mde, half, 0.37, factor if use else var, use, out)
            expected = var + edge**2
            np.testing.assert_array_equal(out, expected * factor if use else expected)


class TestLattice:
    """The field's lattice: every pixel, 2nd or 4th (`lattice_stride`)."""

    def test_stride_rule(self):
        from gpdepth3d.completion.lattice import lattice_stride

        cfg = g.DepthGPConfig()
        assert lattice_stride(cfg, 125, 414, 3158, 32.0) == 2  # KITTI 1/3, 1/4 of the LiDAR: 6.1 % of the pixels
        assert lattice_stride(cfg, 125, 414, 5175, 32.0) == 2  # 1 point per 10 pixels
        assert lattice_stride(cfg, 125, 414, 5200, 32.0) == 4  # denser: every 4th pixel, 10 x 10 windows
        assert lattice_stride(cfg, 125, 414, 125 * 414, 32.0) == 4  # a point on every pixel
        assert lattice_stride(cfg, 125, 414, 5200, 32.0, (125, 414)) == 4
        assert lattice_stride(cfg, 125, 414, 5200, 32.0, (375, 1242)) == 4  # a finer output: the detail is kriged
        # a coarser output reads no detail: sparse only up to 1 point per 32 pixels, denser every pixel
        assert lattice_stride(cfg, 125, 414, 1617, 32.0, (62, 207)) == 2
        assert lattice_stride(cfg, 125, 414, 1700, 32.0, (62, 207)) == 1
        assert lattice_stride(cfg, 125, 414, 5200, 32.0, (124, 414)) == 1
        smooth = cfg.replace(nu=1.5)  # no sub-lattice kriging: the same
        assert lattice_stride(smooth, 125, 414, 1617, 32.0) == 2 and lattice_stride(smooth, 125, 414, 1700, 32.0) == 1
        assert lattice_stride(smooth, 125, 414, 10**4, 32.0) == 1
        assert lattice_stride(cfg, 125, 414, 790, 4.0) == 1  # length scale too short for a coarse lattice
        assert lattice_stride(cfg, 125, 414, 5200, 12.0) == 2  # long enough for stride 2 (8 px), not 4 (16 px)
        assert lattice_stride(cfg, 125, 414, 5200, 16.0) == 4
        assert lattice_stride(cfg, 12, 414, 5, 32.0) == 1  # too few rows
        assert lattice_stride(cfg, 125, 414, 10, 32.0, stride=1) == 1
        assert lattice_stride(cfg, 125, 414, 10**5, 32.0, stride=4) == 4
        assert lattice_stride(cfg, 3, 414, 10, 32.0, stride=8) == 2  # 2 nodes per side at least

    @pytest.mark.parametrize("bad", [0, 17, 1.5, True, "2", np.nan])
    def test_invalid_stride_is_refused_by_name(self, bad):
        with pytest.raises(InvalidInputError, match="lattice_stride"):
            EngineConfig(lattice_stride=bad)

    @pytest.mark.parametrize("shape", [(64, 96), (63, 97)])
    def test_coarse_lattice_agrees_with_every_pixel_when_points_are_sparse(self, shape):
        truth, mde = _scene(*shape, seed=11)
        sp = g.sample_uniform(truth, n=120, rng=11)
        fine = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1))
        coarse = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=2))
        auto = g.complete(mde, sp)  # 120 points on ~6000 pixels: sparse, so the default takes stride 2
        np.testing.assert_array_equal(auto.mean, coarse.mean)
        assert not np.array_equal(fine.mean, coarse.mean)  # the lattice is really coarser
        gap = np.abs(np.log(coarse.mean / fine.mean))
        assert np.median(gap) < 0.01 and np.max(gap) < 0.06  # largest next to the points
        spread = np.log(coarse.std / fine.std)
        # about the same sd, never much surer; wider at the points' own pixels (they inform a node beside them)
        assert (
            np.median(np.abs(spread)) < 0.05
            and np.percentile(spread, 1) > -0.1
            and np.min(spread) > -0.2
            and np.max(spread) < 0.5
        )
        rmse = lambda p: np.sqrt(np.mean((p.mean - truth) ** 2))  # noqa: E731
        assert rmse(coarse) < 1.05 * rmse(fine)
        # any output resolution, as on the pixel lattice
        big = (2 * shape[0], 2 * shape[1])
        up = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=2), output_shape=big)
        fine_up = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1), output_shape=big)
        assert up.mean.shape == big and np.all(np.isfinite(up.variance))
        assert np.median(np.abs(np.log(up.mean / fine_up.mean))) < 0.01

    def test_detail_below_the_lattice_is_kriged_back(self):
        """At the points' own pixels the coarse lattice alone stays ~1 % off every pixel's mean and ~12 % wider
        (a point informs the node beside it); with its detail kriged back (gp.sublattice) 0.2 % and 2 %."""
        truth, mde = _scene(64, 96, seed=14)
        sp = g.sample_uniform(truth, n=500, rng=14)  # 8 % of the pixels: stride 2 by default
        fine = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1))
        coarse = g.complete(mde, sp)
        r, c = sp.v.astype(int), sp.u.astype(int)
        assert np.median(np.abs(np.log(coarse.mean[r, c] / fine.mean[r, c]))) < 0.005
        assert np.median(coarse.std[r, c] / fine.std[r, c]) < 1.06
        assert np.sqrt(np.mean((coarse.mean - truth) ** 2)) < 1.05 * np.sqrt(np.mean((fine.mean - truth) ** 2))
        # upsampled 3x: every 3rd output pixel is a grid pixel, and gets the same posterior there
        big = g.complete(mde, sp, output_shape=(192, 288))
        np.testing.assert_allclose(big.mean[1::3, 1::3], coarse.mean, rtol=1e-6)
        np.testing.assert_allclose(big.variance[1::3, 1::3], coarse.variance, rtol=1e-5)
        # a coarser output keeps the lattice's own posterior (no detail is read there), close to every pixel's
        small = g.complete(mde, sp, output_shape=(32, 48))
        small_fine = g.complete(
            mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1), output_shape=(32, 48)
        )
        assert np.all(np.isfinite(small.variance)) and np.all(small.variance > 0)
        assert np.median(np.abs(np.log(small.mean / small_fine.mean))) < 0.02

    def test_dense_points_take_every_4th_pixel_with_their_detail(self):
        """Points on ~11 % of the pixels: stride 4 with the detail kriged from 10 x 10 windows, close to every pixel;
        an output coarser than the grid reads no detail and keeps every pixel."""
        truth, mde = _scene(64, 96, seed=12)
        sp = g.sample_uniform(truth, n=700, rng=12)
        fine = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1))
        auto = g.complete(mde, sp)
        np.testing.assert_array_equal(
            auto.mean, g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=4)).mean
        )
        assert not np.array_equal(auto.mean, fine.mean)
        r, c = sp.v.astype(int), sp.u.astype(int)
        assert np.median(np.abs(np.log(auto.mean[r, c] / fine.mean[r, c]))) < 0.005
        assert np.median(auto.std[r, c] / fine.std[r, c]) < 1.05
        rmse = lambda p: np.sqrt(np.mean((p.mean - truth) ** 2))  # noqa: E731
        assert rmse(auto) < 1.05 * rmse(fine)
        np.testing.assert_array_equal(
            g.complete(mde, sp, output_shape=(32, 48)).mean,
            g.complete(
                mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1), output_shape=(32, 48)
            ).mean,
        )
        # finer outputs, also by non-integer factors and in one axis only: the detail resized from the grid's pixels
        for out in [(100, 150), (64, 150), (130, 96)]:
            a = g.complete(mde, sp, output_shape=out)
            f = g.complete(mde, sp, config=g.DepthGPConfig(), engine=EngineConfig(lattice_stride=1), output_shape=out)
            assert a.mean.shape == out and np.all(np.isfinite(a.variance)) and np.all(a.variance > 0)
            assert np.median(np.abs(np.log(a.mean / f.mean))) < 0.012 and np.median(a.std / f.std) < 1.03

    def test_points_sharing_a_node_count_as_their_precision_weighted_mean(self):
        """Two points in one 2 x 2 cell with the same residual inform the node as one point with both precisions."""
        truth, mde = _scene(32, 32, seed=13)
        stride2 = EngineConfig(lattice_stride=2)
        cfg = g.DepthGPConfig(
            screen=ScreenConfig(outlier_threshold=None),
            slope=SlopeConfig(prior_sigma=None),
            assembly=AssemblyConfig(edge_sigma=0.0, depth_lengthscale=None),
        )
        u, v = np.array([10.0, 11.0, 25.0]), np.array([8.0, 9.0, 20.0])  # pixel centres (10, 8), (11, 9): one cell
        depth = mde[v.astype(int), u.astype(int)] * 1.3
        two = g.complete(mde, SparseDepth(u, v, depth, (32, 32), np.full(3, 0.01 * depth)), config=cfg, engine=stride2)
        one = g.complete(
            mde,
            SparseDepth(u[1:], v[1:], depth[1:], (32, 32), np.full(2, 0.01 * depth[1:])),
            config=cfg,
            engine=stride2,
        )
        # the shared node is better known with both points: the posterior there pulls harder towards 1.3 x MDE
        ratio_two, ratio_one = two.mean[8, 10] / mde[8, 10], one.mean[8, 10] / mde[8, 10]
        assert abs(ratio_two - 1.3) <= abs(ratio_one - 1.3) + 1e-12
        assert two.variance[8, 10] < one.variance[8, 10]
