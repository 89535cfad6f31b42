"""Tests of the running sigma calibration of the Mapper's own points (`gpdepth3d.mapping.point_calibration`)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.point_calibration import SigmaCalibration, paired_z_scores
from gpdepth3d.measurements import SparseDepth

SHAPE = (100, 100)


def _grid(depth: np.ndarray, sigma: float, offset: float = 0.0) -> SparseDepth:
    """One point in the middle of every 10-pixel cell (offset moves it inside the cell)."""
    v, u = np.mgrid[5:100:10, 5:100:10].reshape(2, -1) + offset
    return SparseDepth.from_arrays(u.astype(float), v.astype(float), depth, SHAPE, np.full(u.size, sigma))


def test_z_scores_pair_the_most_certain_point_of_each_shared_cell():
    truth = np.full(100, 2.0)
    own = _grid(truth + 0.03, 0.03)
    other = _grid(truth - 0.01, 0.04, offset=2.0)
    z = paired_z_scores(own, other, 10.0)
    assert z.size == 100 and np.allclose(z, 0.04 / 0.05)
    # a second, less certain point in a cell does not count twice
    both = SparseDepth.from_arrays(
        np.r_[other.u, 5.5], np.r_[other.v, 5.5], np.r_[other.depth, 9.0], SHAPE, np.r_[other.sigma, 1.0]
    )
    assert np.allclose(paired_z_scores(own, both, 10.0), z)
    # cells held by one side only give nothing
    assert paired_z_scores(own.subset(np.arange(10)), other.subset(np.arange(10, 20)), 10.0).size == 0
    assert paired_z_scores(SparseDepth.empty(SHAPE), other, 10.0).size == 0
    with pytest.raises(InvalidInputError, match="cell"):
        paired_z_scores(own, other, 0.0)


def test_factor_is_the_robust_spread_of_the_z_scores_at_least_one():
    rng = np.random.default_rng(5)
    cal = SigmaCalibration(frames=3, min_pairs=30)
    cal.add(rng.normal(0, 0.7, 20))
    assert cal.factor == 1.0  # too few yet
    for _ in range(3):
        cal.add(rng.normal(0, 0.7, 200))
    assert cal.factor == 1.0  # honest (or pessimistic) sigmas are kept
    for _ in range(3):  # the older frames are forgotten
        cal.add(rng.normal(0, 2.5, 200))
    assert cal.factor == pytest.approx(2.5, rel=0.1)
    cal.add(np.array([np.nan, np.inf]))
    assert np.isfinite(cal.factor)
    with pytest.raises(InvalidInputError, match="frames"):
        SigmaCalibration(0)


def test_poses_worse_than_the_prior_widen_the_sigma_by_what_the_points_show():
    """Two frames' points of one wall, each off by its pose error: the factor is that error over the sigma."""
    rng = np.random.default_rng(9)
    cal = SigmaCalibration(frames=10)
    for _ in range(10):
        own = _grid(2.0 * (1 + rng.normal(0, 0.06)) + rng.normal(0, 0.01, 100), 0.02)
        other = _grid(2.0 * (1 + rng.normal(0, 0.06)) + rng.normal(0, 0.01, 100), 0.02, offset=1.0)
        cal.add(paired_z_scores(own, other, 10.0))
    # the frames differ by 2 m x 6 % x sqrt(2) ~ 0.17 m against a combined sigma of 0.028 m
    assert 3.0 < cal.factor < 9.0
