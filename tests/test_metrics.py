"""Tests of gpdepth3d.metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpdepth3d.errors import EmptyInputError, ShapeError
from gpdepth3d.metrics import METRIC_NAMES, calibration_metrics, depth_metrics

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
        assert m["n"] == 2

    def test_calibrated_gaussian(self):
        rng = np.random.default_rng(0)
        std = rng.uniform(0.1, 1.0, size=200_000)
        gt = 10.0 + rng.normal(size=std.size) * std
        m = calibration_metrics(np.full(std.size, 10.0), std**2, gt)
        assert m["coverage_1sigma"] == pytest.approx(0.6827, abs=0.005)
        assert m["coverage_2sigma"] == pytest.approx(0.9545, abs=0.003)
        assert m["z_rms"] == pytest.approx(1.0, abs=0.01)
        # Overconfident variances give a worse NLL and lower coverage.
        over = calibration_metrics(np.full(std.size, 10.0), (std / 3) ** 2, gt)
        assert over["nll"] > m["nll"] and over["coverage_1sigma"] < 0.4

    def test_errors(self):
        with pytest.raises(ShapeError):
            calibration_metrics(np.ones(3), np.ones(2), np.ones(3))
        with pytest.raises(ShapeError):
            calibration_metrics(np.ones(3), np.array([1.0, np.nan, 1.0]), np.ones(3))
        with pytest.raises(EmptyInputError):
            calibration_metrics(np.ones(3), np.ones(3), np.zeros(3))
