"""The shared frame pieces of the experiments: MDE on the GP grid, the metric row."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.pipelines.frames import holdout_lidar, mde_to_grid
from gpdepth3d.pipelines.scoring import CALIBRATION_NAMES, metric_row
from gpdepth3d.metrics import METRIC_NAMES, calibration_metrics, depth_metrics


class TestMdeToGrid:
    def test_block_means_of_whole_blocks(self):
        rng = np.random.default_rng(0)
        full = rng.uniform(1, 10, (10, 14))  # 3 x 4 whole 3x3 blocks; row 9 and columns 12-13 dropped
        grid = mde_to_grid(full, 3)
        expected = full[:9, :12].reshape(3, 3, 4, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(grid, expected, rtol=1e-6)  # OpenCV sums area weights in float32

    def test_factor_one_is_a_copy(self):
        full = np.ones((4, 5), np.float32)
        grid = mde_to_grid(full, 1)
        assert grid.dtype == np.float64 and grid.shape == (4, 5)
        grid[0, 0] = 7
        assert full[0, 0] == 1

    def test_grid_matches_the_lidar_grid(self):
        lidar = np.zeros((20, 31))
        lidar[::2, ::3] = 5.0
        assert mde_to_grid(np.ones((20, 31)), 3).shape == holdout_lidar(lidar, factor=3).gt_grid.shape

    def test_errors(self):
        with pytest.raises(InvalidInputError, match="factor"):
            mde_to_grid(np.ones((6, 6)), 0)
        with pytest.raises(InvalidInputError, match="factor"):
            mde_to_grid(np.ones((6, 6)), 1.5)
        with pytest.raises(ShapeError, match="mde_depth"):
            mde_to_grid(np.ones((2, 6)), 3)
        with pytest.raises(ShapeError, match="mde_depth"):
            mde_to_grid(np.ones((6, 6, 3)), 3)


class TestMetricRow:
    def setup_method(self):
        rng = np.random.default_rng(1)
        self.gt = rng.uniform(1, 5, (8, 9))
        self.gt[0] = 0.0
        self.mean = self.gt + rng.normal(0, 0.1, self.gt.shape)
        self.var = np.full(self.gt.shape, 0.01)

    def test_values_and_order(self):
        row = metric_row(self.mean, self.var, self.gt)
        assert list(row) == list(METRIC_NAMES) + list(CALIBRATION_NAMES)
        d, c = depth_metrics(self.mean, self.gt), calibration_metrics(self.mean, self.var, self.gt)
        assert all(row[k] == d[k] for k in METRIC_NAMES) and all(row[k] == c[k] for k in CALIBRATION_NAMES)

    def test_no_or_bad_variance_gives_nan_calibration(self):
        for var in (None, np.where(self.gt > 2, self.var, np.nan)):
            row = metric_row(self.mean, var, self.gt)
            assert all(math.isnan(row[k]) for k in CALIBRATION_NAMES) and np.isfinite(row["rmse"])

    def test_key_selection(self):
        row = metric_row(self.mean, self.var, self.gt, depth_keys=("rmse", "n"), calibration_keys=("nll",))
        assert list(row) == ["rmse", "n", "nll"] and row["n"] == 8 * 9 - 9
        with pytest.raises(InvalidInputError, match="depth_keys"):
            metric_row(self.mean, self.var, self.gt, depth_keys=("rsme",))
        with pytest.raises(InvalidInputError, match="calibration_keys"):
            metric_row(self.mean, self.var, self.gt, calibration_keys=("coverage",))
