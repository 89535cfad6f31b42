"""Tests of gpdepth3d.metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpdepth3d.errors import EmptyInputError, ShapeError
from gpdepth3d.metrics import METRIC_NAMES, SPARSIFICATION_FRACTIONS, calibration_metrics, depth_metrics, sparsification

PRED = np.array([[1.0, 2.0], [4.0, 9.0]])
GT = np.array([[1.0, 1.0], [5.0, 0.0]])  # the last pixel has no ground truth


class TestDepthMetrics:
    def test_hand_computed(self):
        m = depth_metrics(PRED, GT)
        # errors 0, +1, -1 m; inverse errors 0, -0.5, +0.05 1/m; ratios 1, 2, 1.25
        assert set(METRIC_NAMES) <= set(m) and m["n"] == 3
        assert m["rmse"] == pytest.approx(math.sqrt(2 / 3) * 1000)
        assert m["mae"] == pytest.approx(2 / 3 * 1000)
        assert m["irmse"] == pytest.approx(math.sqrt((0.25 + 0.0025) / 3) * 1000)
        assert m["imae"] == pytest.approx(0.55 / 3 * 1000)
        assert m["rel"] == pytest.approx(1.2 / 3)
        assert m["delta1"] == pytest.approx(1 / 3)  # 1.25 is not < 1.25
        assert m["delta2"] == pytest.approx(2 / 3)
        assert m["delta3"] == pytest.approx(2 / 3)

    def test_perfect_prediction(self):
        m = depth_metrics(GT, GT)
        assert m["rmse"] == m["mae"] == m["irmse"] == m["imae"] == m["rel"] == 0.0
        assert m["delta1"] == 1.0

    def test_invalid_gt_ignored_nan_and_inf(self):
        gt = np.array([1.0, np.nan, np.inf, -2.0, 0.0, 2.0])
        pred = np.array([2.0, 5.0, 5.0, 5.0, 5.0, 2.0])
        m = depth_metrics(pred, gt)
        assert m["n"] == 2 and m["mae"] == pytest.approx(500.0)

    def test_mask(self):
        m = depth_metrics(PRED, GT, mask=np.array([[False, True], [True, True]]))
        assert m["n"] == 2 and m["mae"] == pytest.approx(1000.0)

    def test_bad_predictions_are_penalised(self):
        pred = np.array([np.nan, -1.0, 0.0])
        gt = np.array([1.0, 1.0, 1.0])
        m = depth_metrics(pred, gt, min_depth=0.01)
        assert m["n"] == 3 and m["mae"] == pytest.approx(990.0)
        assert m["delta3"] == 0.0

    def test_errors(self):
        with pytest.raises(ShapeError):
            depth_metrics(np.ones((2, 3)), np.ones((3, 2)))
        with pytest.raises(ShapeError):
            depth_metrics(np.ones((2, 2)), np.ones((2, 2)), mask=np.ones((2, 3), bool))
        with pytest.raises(EmptyInputError):
            depth_metrics(np.ones((2, 2)), np.zeros((2, 2)))
        with pytest.raises(EmptyInputError):
            depth_metrics(PRED, GT, mask=np.zeros((2, 2), bool))

    def test_synthetic_mde_numbers(self, street_frame):
        f = street_frame
        m = depth_metrics(f.mde, f.depth_gt)
        valid = f.depth_gt > 0
        assert m["n"] == valid.sum()
        assert m["rmse"] == pytest.approx(np.sqrt(np.mean((f.mde - f.depth_gt)[valid] ** 2)) * 1000)


class TestCalibrationMetrics:
    def test_hand_computed(self):
        mean = np.array([1.0, 2.0, 7.0])
        var = np.array([1.0, 4.0, np.nan])  # NaN at a pixel without ground truth is fine
        gt = np.array([2.0, 2.0, 0.0])
        m = calibration_metrics(mean, var, gt)
        nll = ((0.5 * math.log(2 * math.pi) + 0.5) + 0.5 * math.log(8 * math.pi)) / 2
        assert m["nll"] == pytest.approx(nll)
        assert m["coverage_1sigma"] == 1.0 and m["coverage_2sigma"] == 1.0
        assert m["z_rms"] == pytest.approx(math.sqrt(0.5))
        assert m["coverage_3sigma"] == 1.0 and m["median_abs_z"] == pytest.approx(0.5)
        assert m["n"] == 2

    def test_calibrated_gaussian(self):
        rng = np.random.default_rng(0)
        std = rng.uniform(0.1, 1.0, size=200_000)
        gt = 10.0 + rng.normal(size=std.size) * std
        m = calibration_metrics(np.full(std.size, 10.0), std**2, gt)
        assert m["coverage_1sigma"] == pytest.approx(0.6827, abs=0.005)
        assert m["coverage_2sigma"] == pytest.approx(0.9545, abs=0.003)
        assert m["z_rms"] == pytest.approx(1.0, abs=0.01)
        assert m["coverage_3sigma"] == pytest.approx(0.9973, abs=0.001)
        assert m["median_abs_z"] == pytest.approx(0.6745, abs=0.01)
        # the std ranks the errors only in expectation: some sparsification error, less than with a constant std
        flat = calibration_metrics(np.full(std.size, 10.0), np.full(std.size, 0.3), gt)
        assert 0 < m["ause"] < flat["ause"]
        # Overconfident variances give a worse NLL and lower coverage.
        over = calibration_metrics(np.full(std.size, 10.0), (std / 3) ** 2, gt)
        assert over["nll"] > m["nll"] and over["coverage_1sigma"] < 0.4

    def test_heavy_tails_show_in_the_shape_not_at_2_sigma(self):
        """Most errors far below the std and a few far above: +-2 sigma looks calibrated, the median |z| does not."""
        gt = np.full(1000, 10.0)
        err = np.where(np.arange(1000) < 950, 0.01, 4.0)  # 95 % small, 5 % gross
        m = calibration_metrics(gt + err, np.ones(1000), gt)
        assert m["coverage_2sigma"] == pytest.approx(0.95) and m["coverage_3sigma"] == pytest.approx(0.95)
        assert m["median_abs_z"] == pytest.approx(0.01)

    def test_sparsification_by_hand(self):
        err = np.array([1.0, 2.0, 3.0, 4.0])
        full = math.sqrt(30 / 4)
        by_std, oracle = sparsification(err, np.array([4.0, 3.0, 2.0, 1.0]))  # the std ranks them backwards
        f = SPARSIFICATION_FRACTIONS
        one = (f >= 0.25) & (f < 0.5)  # one pixel removed
        np.testing.assert_allclose(by_std[one], math.sqrt(29 / 3) / full)  # the smallest error went
        np.testing.assert_allclose(oracle[one], math.sqrt(14 / 3) / full)  # the largest
        assert by_std[0] == oracle[0] == 1.0
        np.testing.assert_allclose(by_std[f >= 0.75], 4 / full)
        np.testing.assert_allclose(oracle[f >= 0.75], 1 / full)
        # a std proportional to the error ranks them perfectly: no sparsification error
        same, oracle2 = sparsification(err, 0.5 * err)
        np.testing.assert_allclose(same, oracle2)
        gt = np.full(4, 5.0)
        assert calibration_metrics(gt + err, (0.5 * err) ** 2, gt)["ause"] == pytest.approx(0.0, abs=1e-12)
        assert calibration_metrics(gt + err, np.array([4.0, 3.0, 2.0, 1.0]) ** 2, gt)["ause"] > 0.3
        with pytest.raises(ShapeError):
            sparsification(np.ones(3), np.ones(2))
        with pytest.raises(ShapeError):
            sparsification(np.ones(0), np.ones(0))
        np.testing.assert_array_equal(sparsification(np.zeros(3), np.ones(3))[0], 1.0)  # no error at all

    def test_errors(self):
        with pytest.raises(ShapeError):
            calibration_metrics(np.ones(3), np.ones(2), np.ones(3))
        with pytest.raises(ShapeError):
            calibration_metrics(np.ones(3), np.array([1.0, np.nan, 1.0]), np.ones(3))
        with pytest.raises(EmptyInputError):
            calibration_metrics(np.ones(3), np.ones(3), np.zeros(3))
