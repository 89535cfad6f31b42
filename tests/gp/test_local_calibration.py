"""Local calibration of the variance (`gpdepth3d.gp.local_calibration`): the factor against a direct
evaluation of its formula, its limits, its errors, and what it does inside `complete()`."""

from __future__ import annotations

import math

import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.local_calibration import local_variance_factor
from gpdepth3d.gp.model import CalibrationConfig, ScreenConfig

ZSCORE_CAP = CalibrationConfig().zscore_cap


def _direct(shape, rows, cols, z, reach, prior_points):
    """f(x) evaluated pixel by pixel: Gaussian weights of radius reach x sqrt(A / N) (A: the points' bounding
    box), cut at ceil(3 radius) per axis."""
    h, w = shape
    radius = reach * math.sqrt((np.ptp(rows) + 1) * (np.ptp(cols) + 1) / len(z))
    cut = math.ceil(3 * radius)
    rr, cc = np.mgrid[0:h, 0:w]
    dr = rr.ravel()[:, None] - rows[None]
    dc = cc.ravel()[:, None] - cols[None]
    wgt = np.exp(-(dr**2 + dc**2) / (2 * radius**2)) * ((np.abs(dr) <= cut) & (np.abs(dc) <= cut))
    q = np.minimum(z**2, ZSCORE_CAP)
    return ((wgt @ q + prior_points) / (wgt.sum(1) + prior_points)).reshape(h, w)


def _points(shape, n, seed):
    rng = np.random.default_rng(seed)
    flat = rng.choice(shape[0] * shape[1], size=n, replace=False)
    return flat // shape[1], flat % shape[1], rng.standard_normal(n) * rng.uniform(0.2, 2.5, n)


class TestFactor:
    def test_equals_its_formula_pixel_by_pixel(self):
        """Radius below 3 px: no binning, the blur is the Gaussian sum itself."""
        shape = (30, 40)
        rows, cols, z = _points(shape, 300, 0)
        for reach, prior in ((1.0, 1.0), (0.6, 3.0)):
            got = local_variance_factor(shape, rows, cols, z, reach=reach, prior_points=prior)
            np.testing.assert_allclose(got, _direct(shape, rows, cols, z, reach, prior), rtol=2e-3)
        # points in the left third only: the spacing is theirs (bounding box 30 x 13), not the grid's
        left = cols < 13
        got = local_variance_factor(shape, rows[left], cols[left], z[left])
        np.testing.assert_allclose(got, _direct(shape, rows[left], cols[left], z[left], 1.5, 2.0), rtol=2e-3)
        assert np.all(np.abs(got[:, 22:] - 1.0) < 1e-6)  # beyond the blur (3 radii of 2.8 px) from the band: f = 1

    def test_binned_blur_follows_the_formula_at_wide_radii(self):
        """Few points, radius 17-40 px: bins of 5-13 px (points splatted bilinearly, the factor resized back);
        within ~1 % of the direct sum in the median, 15 % at worst."""
        for shape, n, seed in (((60, 80), 16, 1), ((120, 400), 30, 3)):
            rows, cols, z = _points(shape, n, seed)
            got = local_variance_factor(shape, rows, cols, z, reach=1.0, prior_points=1.0)
            ref = _direct(shape, rows, cols, z, 1.0, 1.0)
            err = np.abs(got - ref) / ref
            assert np.median(err) < 0.015 and np.max(err) < 0.16
            assert np.corrcoef(got.ravel(), ref.ravel())[0, 1] > 0.995

    def test_limits(self):
        shape = (50, 60)
        rr, cc = np.mgrid[0:50:2, 0:30:2]  # points in the left half only, every 2nd pixel
        rows, cols = rr.ravel(), cc.ravel()
        radius = math.sqrt(49 * 29 / rows.size)  # spacing over the points' bounding box, 49 x 29 pixels
        inside = 2 * math.pi * radius**2 / 4  # points under the Gaussian inside them: one per 4 pixels
        for q in (0.25, 4.0):
            f = local_variance_factor(shape, rows, cols, np.full(rows.size, math.sqrt(q)), reach=1.0, prior_points=1.0)
            # inside the points: their mean z^2 against one pseudo-point at 1
            assert f[10:40, 5:25] == pytest.approx((inside * q + 1) / (inside + 1), rel=0.01)
            assert f[:, 55:] == pytest.approx(1.0, abs=1e-6)  # far from them: the model's own variance
            assert np.all((f >= min(q, 1.0) - 1e-12) & (f <= max(q, 1.0) + 1e-12))
        assert np.all(local_variance_factor(shape, np.zeros(0), np.zeros(0), np.zeros(0)) == 1.0)
        # one huge z-score counts as |z| = 4 at most
        f = local_variance_factor(shape, np.array([25]), np.array([30]), np.array([1e6]))
        assert 1.0 < f.max() <= ZSCORE_CAP

    def test_noise_share_floors_each_squared_zscore(self):
        """A point's z^2 enters as max(z^2, q): points that agree better than their own noise allows (errors
        shared with their neighbours) cannot argue the variance below that noise; z^2 above q is unchanged."""
        shape = (30, 40)
        rows, cols, z = _points(shape, 300, 4)
        share = np.random.default_rng(4).uniform(0.0, 1.0, z.size)
        got = local_variance_factor(shape, rows, cols, z, reach=1.0, prior_points=1.0, noise_share=share)
        floored = np.sqrt(np.maximum(z**2, share))
        np.testing.assert_allclose(got, _direct(shape, rows, cols, floored, 1.0, 1.0), rtol=2e-3)
        same = local_variance_factor(shape, rows, cols, z, reach=1.0, prior_points=1.0, noise_share=np.zeros(z.size))
        np.testing.assert_array_equal(same, local_variance_factor(shape, rows, cols, z, reach=1.0, prior_points=1.0))
        agree = local_variance_factor(shape, rows, cols, np.zeros(z.size), noise_share=np.full(z.size, 0.5))
        assert np.all((agree >= 0.5 - 1e-9) & (agree <= 1.0 + 1e-9))  # z = 0 everywhere: no lower than the share

    @pytest.mark.parametrize(
        "args, kwargs, name",
        [
            (((10, 10), [1], [1], [0.5]), {"noise_share": [1.5]}, "noise_share"),
            (((10, 10), [1, 2], [1, 2], [0.5, 0.5]), {"noise_share": [0.5]}, "noise_share"),
            (((10, 10), [1, 2], [1], [0.5, 0.5]), {}, "rows, cols, zscores"),
            (((10, 10), [1], [10], [0.5]), {}, "rows, cols"),
            (((10, 10), [-1], [1], [0.5]), {}, "rows, cols"),
            (((10, 10), [1], [1], [np.nan]), {}, "zscores"),
            (((10, 10), [1], [1], [0.5]), {"reach": 0.0}, "reach"),
            (((10, 10), [1], [1], [0.5]), {"prior_points": -1.0}, "prior_points"),
        ],
    )
    def test_bad_input_is_refused_by_name(self, args, kwargs, name):
        with pytest.raises(InvalidInputError, match=name):
            local_variance_factor(*(np.asarray(a) if isinstance(a, list) else a for a in args), **kwargs)


def _halves(seed=0):
    """A smooth MDE off by a smooth scale; the truth is as smooth on the left and rough at the pixel scale on
    the right (10 % log noise), which the MDE does not show (so its edge term cannot see it either)."""
    rng = np.random.default_rng(seed)
    h, w = 48, 64
    rr, cc = np.mgrid[0:h, 0:w]
    smooth = 3.0 + 0.3 * np.sin(rr / 9.0)
    truth = smooth * np.exp(np.where(cc >= w // 2, 0.1 * rng.standard_normal((h, w)), 0.0))
    mde = smooth * np.exp(-0.2 + 0.05 * np.sin(cc / 11.0))
    return truth, mde


class TestInsideComplete:
    def test_variance_moves_to_where_the_points_disagree(self):
        truth, mde = _halves()
        sp = g.sample_uniform(truth, n=400, rng=1)
        post = g.complete(mde, sp)
        off = g.complete(mde, sp, config=g.DepthGPConfig(calibration=CalibrationConfig(reach=None)))
        np.testing.assert_array_equal(post.mean, off.mean)  # the mean is untouched
        rel, rel_off = post.std / post.mean, off.std / off.mean
        left, right = np.s_[8:40, 4:26], np.s_[8:40, 38:60]
        # without it the two halves get about the same sigma; with it the rough half gets far more,
        # and its errors are covered far better (measured, seeds 0-2: 69-70 % -> 83-85 %) while the
        # smooth half, now with a smaller sigma, stays covered
        assert np.median(rel_off[right]) / np.median(rel_off[left]) < 1.2
        assert np.median(rel[right]) / np.median(rel[left]) > 3.0
        err = np.abs(post.mean - truth)
        cover = lambda p, part: np.mean(err[part] <= 2 * p.std[part])  # noqa: E731
        assert cover(post, right) > cover(off, right) + 0.1
        assert cover(post, left) > 0.95 and np.median(rel[left]) < np.median(rel_off[left])

    def test_without_the_screen_the_zscores_are_computed(self):
        truth, mde = _halves(1)
        sp = g.sample_uniform(truth, n=300, rng=2)
        base = g.DepthGPConfig(screen=ScreenConfig(outlier_threshold=None))
        post = g.complete(mde, sp, config=base)
        off = g.complete(mde, sp, config=base.replace(calibration={"reach": None}))
        assert np.all(np.isfinite(post.variance)) and np.all(post.variance > 0)
        ratio = post.variance / off.variance
        assert np.median(ratio[:, 38:]) > 2 * np.median(ratio[:, :26])

    def test_few_points_keep_the_model_variance(self):
        truth, mde = _halves(2)
        sp = g.sample_uniform(truth, n=8, rng=3)
        with pytest.warns(g.PosteriorWarning, match="usable points"):
            post = g.complete(mde, sp)
        with pytest.warns(g.PosteriorWarning, match="usable points"):
            off = g.complete(mde, sp, config=g.DepthGPConfig(calibration=CalibrationConfig(reach=None)))
        np.testing.assert_array_equal(post.variance, off.variance)

    def test_upsampled_output_gets_the_resized_factor(self):
        truth, mde = _halves(3)
        sp = g.sample_uniform(truth, n=300, rng=4)
        post = g.complete(mde, sp, output_shape=(96, 128))
        small = g.complete(mde, sp)
        assert post.variance.shape == (96, 128) and np.all(post.variance > 0)
        # the same sigma map, twice the size
        big = np.median(post.std[:, 76:] / post.mean[:, 76:]) / np.median(post.std[:, :52] / post.mean[:, :52])
        ref = np.median(small.std[:, 38:] / small.mean[:, 38:]) / np.median(small.std[:, :26] / small.mean[:, :26])
        assert big == pytest.approx(ref, rel=0.15)

    @pytest.mark.parametrize("value", [0.0, -1.0, float("inf"), "1"])
    def test_config_refuses_a_bad_reach(self, value):
        with pytest.raises(InvalidInputError, match="reach"):
            g.DepthGPConfig(calibration=CalibrationConfig(reach=value))

    def test_presets_of_the_paper_and_the_residual_model_leave_it_off(self):
        assert g.DepthGPConfig.paper().calibration.reach is None
        assert g.DepthGPConfig.residual().calibration.reach is None
        assert g.DepthGPConfig().calibration.reach == 1.5


@pytest.mark.parametrize("c", [2, 3, 5])
def test_the_splat_equals_one_bincount_per_corner_added_in_turn(c):
    """`_splat` (the compiled bilinear splat onto bins of c pixels) gives the sums of the plain NumPy form to the bit:
    per corner one np.bincount of the points' shares, the corners added in turn; points on the borders clipped."""
    from gpdepth3d.gp.local_calibration import _splat

    rng = np.random.default_rng(c)
    h, w = 23, 31
    flat = rng.choice(h * w, 150, replace=False)
    rows, cols = np.concatenate([flat // w, [0, h - 1]]), np.concatenate([flat % w, [0, w - 1]])
    q = rng.uniform(0, 4, rows.size)
    hb, wb = -(-h // c), -(-w // c)
    sums, weights = np.zeros(hb * wb), np.zeros(hb * wb)
    _splat(rows, cols, q, c, hb, wb, sums, weights, np.zeros(hb * wb), np.zeros(hb * wb))
    ref_s, ref_w = np.zeros(hb * wb), np.zeros(hb * wb)
    y, x = (rows - (c - 1) / 2) / c, (cols - (c - 1) / 2) / c
    i0, j0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    fy, fx = y - i0, x - j0
    for di, wy in ((0, 1 - fy), (1, fy)):
        for dj, wx in ((0, 1 - fx), (1, fx)):
            cell = np.clip(i0 + di, 0, hb - 1) * wb + np.clip(j0 + dj, 0, wb - 1)
            share = wy * wx
            ref_s += np.bincount(cell, share * q, hb * wb)
            ref_w += np.bincount(cell, share, hb * wb)
    np.testing.assert_array_equal(sums, ref_s)
    np.testing.assert_array_equal(weights, ref_w)
    np.testing.assert_allclose(weights.sum(), rows.size)
