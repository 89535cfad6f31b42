"""The MDE's log-depth coefficient (gp.slope) and its place in the default posterior."""

from __future__ import annotations

import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.gp.model import AssemblyConfig, CalibrationConfig, ScreenConfig, SlopeConfig
from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.gp.model import Kernel, matern_1d
from gpdepth3d.gp.slope import SlopeFit, fit_mde_slope
from gpdepth3d.measurements import SparseDepth

KERNEL = Kernel(0.5, 8.0, 0.2)


def _draw(n, slope, *, seed=0, h=60, w=80, outputscale=0.2, nugget=0.02):
    """Points drawn from the model: log z = c + a (x - c) + b + g + w, x a varied log MDE depth."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, h, n).astype(float)
    cols = rng.integers(0, w, n).astype(float)
    x = np.log(2.0) + 0.6 * np.sin(cols / 9.0) + 0.4 * np.cos(rows / 7.0) + 0.2 * rng.standard_normal(n)
    K = Kernel(0.5, KERNEL.lengthscale, outputscale).matrix(rows, cols, rows, cols)
    gfield = np.linalg.cholesky(K + 1e-9 * np.eye(n)) @ rng.standard_normal(n)
    c = np.median(x)
    log_z = c + slope * (x - c) + 0.1 + gfield + nugget * rng.standard_normal(n)
    return rows, cols, log_z, x, np.full(n, 1e-4)


def _closed_form(rows, cols, log_z, x, noise, kernel, nugget, prior_sigma):
    """Generalised least squares written out: (H' S^-1 H + P)^-1 (H' S^-1 y + P m)."""
    c = np.median(x)
    H = np.column_stack([np.ones_like(x), x - c])
    S = kernel.matrix(rows, cols, rows, cols) + np.diag(nugget**2 + noise)
    Si = np.linalg.inv(S)
    P = np.diag([0.0, prior_sigma**-2])
    M = H.T @ Si @ H + P
    beta = np.linalg.solve(M, H.T @ Si @ (log_z - c) + P @ np.array([0.0, 1.0]))
    return beta[1], np.linalg.inv(M)[1, 1]


class TestFitMdeSlope:
    def test_matches_the_closed_form_without_outliers(self):
        rows, cols, y, x, e = _draw(150, 0.6, seed=1)
        fit = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5, huber=50.0)
        a, var = _closed_form(rows, cols, y, x, e, KERNEL, 0.02, 0.5)
        assert fit.slope == pytest.approx(a, rel=1e-9) and fit.slope_var == pytest.approx(var, rel=1e-9)
        assert fit.centre == pytest.approx(np.median(x)) and fit.n_used == 150

    @pytest.mark.parametrize("slope", [0.4, 1.0, 1.3])
    def test_recovers_the_slope_of_the_model(self, slope):
        rows, cols, y, x, e = _draw(400, slope, seed=2)
        fit = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5)
        assert abs(fit.slope - slope) < 3 * np.sqrt(fit.slope_var) + 0.02
        assert np.sqrt(fit.slope_var) < 0.1

    def test_points_with_a_non_finite_value_are_left_out(self):
        rows, cols, y, x, e = _draw(300, 0.7, seed=4)
        bad = np.zeros(300, dtype=bool)
        bad[[3, 50, 120, 299]] = True
        y2, x2, e2 = y.copy(), x.copy(), e.copy()
        y2[3], x2[50], e2[120], y2[299] = np.nan, np.inf, np.nan, -np.inf
        got = fit_mde_slope(rows.astype(np.int64), cols.astype(np.int64), y2, x2, e2, KERNEL, 0.02, prior_sigma=0.5)
        keep = ~bad
        ref = fit_mde_slope(rows[keep], cols[keep], y[keep], x[keep], e[keep], KERNEL, 0.02, prior_sigma=0.5)
        assert got == ref and got.n_used == 150

    def test_use_is_the_fit_of_those_points_alone(self):
        rows, cols, y, x, e = _draw(500, 0.7, seed=6)
        x = x.copy()
        x[7] = np.nan
        rng = np.random.default_rng(6)
        for use in (rng.random(500) > 0.3, rng.random(500) > 0.9, np.zeros(500, dtype=bool)):
            got = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5, use=use)
            ref = fit_mde_slope(rows[use], cols[use], y[use], x[use], e[use], KERNEL, 0.02, prior_sigma=0.5)
            assert got == ref
        with pytest.raises(ShapeError, match="use"):
            fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5, use=np.ones(3, dtype=bool))

    def test_few_points_stay_near_the_prior(self):
        rows, cols, y, x, e = _draw(3, 0.3, seed=3)
        fit = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.1)
        assert abs(fit.slope - 1.0) < 0.2 and fit.slope_var > 0.5 * 0.1**2
        none = fit_mde_slope([], [], [], [], [], KERNEL, 0.02, prior_sigma=0.5)
        assert none == SlopeFit(1.0, 0.25, 0.0, 0)

    def test_gross_outliers_do_not_tilt_it(self):
        rows, cols, y, x, e = _draw(300, 0.5, seed=4)
        clean = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5)
        rng = np.random.default_rng(4)
        bad = rng.choice(300, 15, replace=False)
        y2 = y.copy()
        y2[bad] += np.log(rng.uniform(0.1, 3.0, 15))
        robust = fit_mde_slope(rows, cols, y2, x, e, KERNEL, 0.02, prior_sigma=0.5)
        assert abs(robust.slope - clean.slope) < 0.05

    def test_subset_above_max_points(self):
        rows, cols, y, x, e = _draw(900, 0.7, seed=5)
        fit = fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.5, max_points=300)
        assert fit.n_used == 300 and abs(fit.slope - 0.7) < 0.15

    def test_apply(self):
        fit = SlopeFit(0.5, 0.01, np.log(2.0), 10)
        np.testing.assert_allclose(np.exp(fit.apply(np.log([2.0, 8.0]))), [2.0, 4.0])

    def test_bad_input(self):
        rows, cols, y, x, e = _draw(10, 1.0)
        with pytest.raises(ShapeError, match="log_mde"):
            fit_mde_slope(rows, cols, y, x[:5], e, KERNEL, 0.02, prior_sigma=0.5)
        with pytest.raises(InvalidInputError, match="prior_sigma"):
            fit_mde_slope(rows, cols, y, x, e, KERNEL, 0.02, prior_sigma=0.0)
        with pytest.raises(InvalidInputError, match="prior_sigma"):
            g.DepthGPConfig(slope=SlopeConfig(prior_sigma=-1.0))


def _scene(h=30, w=40):
    rr, cc = np.mgrid[0:h, 0:w]
    mde = 2.0 * np.exp(0.8 * np.sin(cc / 6.0) + 0.5 * rr / h)
    truth = 2.2 * (mde / 2.0) ** 0.5 * np.exp(0.05 * np.cos(rr / 5.0))  # the MDE over-states depth variation
    return truth, mde


def test_posterior_matches_a_dense_reference_with_the_slope():
    """Fixed hyperparameters, no rejection, no edge or depth term: the posterior with the fitted slope a
    is the re-sloped MDE's log-residual posterior plus Var[a] (x(x) - c - k(x)' (K + N)^-1 (x - c))^2."""
    truth, mde = _scene()
    sp = g.sample_uniform(truth, n=50, rng=1)
    l, s, tau, sig = 6.0, 0.3, 0.04, 0.01
    cfg = g.DepthGPConfig(
        fit=False,
        lengthscale=l,
        outputscale=s,
        nugget=tau,
        sigma_meas=sig,
        screen=ScreenConfig(outlier_threshold=None),
        calibration=CalibrationConfig(reach=None),
        assembly=AssemblyConfig(edge_sigma=0.0, depth_lengthscale=None),
        slope=SlopeConfig(prior_sigma=0.5),
    )
    post = g.complete(mde, sp, config=cfg)
    rows, cols, z = sp.v.astype(int), sp.u.astype(int), sp.depth
    x = np.log(mde[rows, cols])
    fit = fit_mde_slope(rows, cols, np.log(z), x, np.full(len(z), sig**2), Kernel(0.5, l, s), tau, prior_sigma=0.5)
    assert 0.3 < fit.slope < 0.75  # the truth's 0.5, found
    h, w = mde.shape
    xs = fit.apply(np.log(mde)).ravel()
    r = np.log(z) - fit.apply(x)
    b, n = np.median(r), len(z)
    K = s * s * matern_1d(rows[:, None] - rows[None], 0.5, l) * matern_1d(cols[:, None] - cols[None], 0.5, l)
    K = K + (tau**2 + sig**2) * np.eye(n)
    R, C = np.mgrid[0:h, 0:w]
    kx = s * s * matern_1d(R.ravel()[:, None] - rows[None], 0.5, l) * matern_1d(C.ravel()[:, None] - cols[None], 0.5, l)
    A = kx @ np.linalg.inv(K)
    mu = xs + b + A @ (r - b)
    v = s * s - np.sum(A * kx, 1) + tau**2 + (s * s / n) * (1 - A @ np.ones(n)) ** 2
    v = v + fit.slope_var * (np.log(mde.ravel()) - fit.centre - A @ (x - fit.centre)) ** 2
    np.testing.assert_allclose(post.mean.ravel(), np.exp(mu + v / 2), rtol=1e-8)
    np.testing.assert_allclose(post.variance.ravel(), np.expm1(v) * np.exp(2 * mu + v), rtol=1e-7)
    assert post.mde_slope == pytest.approx(fit.slope)


def test_the_slope_helps_where_the_mde_overstates_depth_variation():
    truth, mde = _scene()
    sp = g.sample_uniform(truth, n=60, rng=2)
    fixed = g.complete(mde, sp, config=g.DepthGPConfig(slope=SlopeConfig(prior_sigma=None)))
    fitted = g.complete(mde, sp)
    rmse = lambda p: np.sqrt(np.mean((p.mean - truth) ** 2))  # noqa: E731
    assert rmse(fitted) < 0.7 * rmse(fixed) and fixed.mde_slope == 1.0 and fitted.mde_slope < 0.8
    assert np.mean(np.abs(fitted.mean - truth) <= 2 * fitted.std) > 0.9


def test_an_exact_mde_keeps_a_slope_near_one():
    truth, mde = _scene()
    sp = g.sample_uniform(mde * 1.3, n=80, rng=3)
    post = g.complete(mde, sp)
    assert abs(post.mde_slope - 1.0) < 0.05
    np.testing.assert_allclose(post.mean, 1.3 * mde, rtol=0.03)


def test_slope_is_kept_by_save_and_load(tmp_path):
    truth, mde = _scene()
    post = g.complete(mde, g.sample_uniform(truth, n=60, rng=4))
    post.save(tmp_path / "p.npz")
    back = g.DepthPosterior.load(tmp_path / "p.npz")
    assert back.mde_slope == pytest.approx(post.mde_slope) and post.mde_slope != 1.0


def test_sparse_without_points_and_outliers():
    truth, mde = _scene()
    empty = SparseDepth(np.zeros(0), np.zeros(0), np.zeros(0), mde.shape)
    with pytest.warns(g.PosteriorWarning):
        post = g.complete(mde, empty)
    assert post.mde_slope == 1.0


def test_an_mde_the_points_contradict_warns(recwarn):
    """Disparity passed as depth: the points run against the MDE's ordering, the slope goes negative and says so."""
    truth, _ = _scene()
    disparity = 1.0 / truth
    with pytest.warns(g.PosteriorWarning, match=r"frame 7: the points follow the MDE's depth differences only weakly"):
        post = g.complete(disparity, g.sample_uniform(truth, n=80, rng=5), frame="7")
    assert post.mde_slope < 0.2
    assert np.sqrt(np.mean((post.mean - truth) ** 2)) < 0.5 * np.sqrt(
        np.mean((disparity * np.median(truth / disparity) - truth) ** 2)
    )


class TestCholeskySolve:
    """`gpdepth3d.gp.slope._cholesky_solve`: scipy's cho_factor / cho_solve, bit for bit, with a jitter when needed."""

    def test_equals_cho_factor_and_cho_solve(self):
        from scipy.linalg import cho_factor, cho_solve

        from gpdepth3d.gp.slope import _cholesky_solve

        rng = np.random.default_rng(0)
        X = rng.standard_normal((40, 50))
        K, rhs = X @ X.T, rng.standard_normal((40, 3))
        diag = rng.uniform(0.5, 2.0, 40)
        ref = cho_solve(cho_factor(K + np.diag(diag), lower=True, check_finite=False), rhs, check_finite=False)
        work = np.empty((40, 40), order="F")
        for _ in range(2):  # the buffer reused: K is left as it was
            np.testing.assert_array_equal(_cholesky_solve(K, diag, rhs, work), ref)
        np.testing.assert_array_equal(K, X @ X.T)

    def test_a_singular_matrix_gets_the_jitter_and_a_negative_one_is_refused(self):
        from scipy.linalg import cho_factor, cho_solve

        from gpdepth3d.gp.slope import _cholesky_solve

        rng = np.random.default_rng(1)
        X = rng.standard_normal((30, 5))
        S, rhs = X @ X.T, rng.standard_normal((30, 2))  # rank 5
        jittered = S + np.eye(30) * 1e-10 * np.trace(S) / 30
        ref = cho_solve(cho_factor(jittered, lower=True, check_finite=False), rhs, check_finite=False)
        np.testing.assert_array_equal(_cholesky_solve(S, np.zeros(30), rhs, np.empty((30, 30), order="F")), ref)
        with pytest.raises(np.linalg.LinAlgError):
            _cholesky_solve(-np.eye(4), np.zeros(4), np.ones(4), np.empty((4, 4), order="F"))
