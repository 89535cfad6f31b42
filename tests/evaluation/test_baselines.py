"""Tests of the IP-Basic baseline."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.evaluation.baselines import ip_basic
from gpdepth3d.errors import InvalidDepthError, InvalidInputError, ShapeError
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.sampling import sample_uniform


def _scene():
    """A 60x80 scene: a near box (2 m) in front of a far wall (6 m)."""
    d = np.full((60, 80), 6.0)
    d[20:45, 25:55] = 2.0
    return d


class TestIpBasic:
    def test_fills_and_keeps_measurements(self):
        gt = _scene()
        sparse = sample_uniform(gt, n=600, rng=0)
        out = ip_basic(sparse)
        assert out.shape == gt.shape and np.all(out > 0) and np.all(np.isfinite(out))
        np.testing.assert_array_equal(out[sparse.v.astype(int), sparse.u.astype(int)], sparse.depth)
        err = np.abs(out - gt)
        assert np.median(err) < 0.05  # piecewise-constant scene is recovered nearly everywhere
        assert np.mean(err) < 0.5

    def test_near_wins_over_far(self):
        # two points in one 5x5 neighbourhood: dilation of the inverted depth keeps the near one
        d = np.zeros((20, 20))
        d[10, 10], d[10, 12] = 2.0, 8.0
        out = ip_basic(d, keep_measurements=False, blur=False)
        assert out[10, 11] == pytest.approx(2.0)

    def test_very_sparse_is_dense(self):
        d = np.zeros((100, 100))
        d[5, 5] = 3.0
        out = ip_basic(d)
        assert np.allclose(out, 3.0)

    def test_better_than_constant_on_real_frame(self, seven_scenes_frame):
        gt = seven_scenes_frame.depth[::4, ::4]
        sparse = sample_uniform(gt, n=300, rng=0)
        out = ip_basic(sparse)
        valid = gt > 0
        rmse = np.sqrt(np.mean((out - gt)[valid] ** 2))
        const = np.sqrt(np.mean((np.median(sparse.depth) - gt[valid]) ** 2))
        assert rmse < 0.7 * const

    def test_options_and_errors(self):
        assert np.all(ip_basic(np.zeros((5, 5))) == 0)
        sparse = SparseDepth.from_arrays([2.0], [3.0], [4.0], (10, 10))
        assert ip_basic(sparse, (20, 20)).shape == (20, 20)
        with pytest.raises(ShapeError):
            ip_basic(np.zeros(5))
        with pytest.raises(ShapeError):
            ip_basic(np.zeros((5, 5)), (6, 6))
        with pytest.raises(InvalidDepthError):
            ip_basic(-np.ones((5, 5)))
        with pytest.raises(InvalidInputError):
            ip_basic(np.ones((5, 5)), max_depth=0)
