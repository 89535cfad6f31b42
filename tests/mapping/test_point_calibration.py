"""Tests of the running sigma calibration of the Mapper's own points (`gpdepth3d.mapping.point_calibration`)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.point_calibration import SigmaCalibration, misplacement_sigma, paired_z_scores
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


def _edge_scene(h: int = 120, w: int = 160) -> np.ndarray:
    """A depth map: a slanted floor (2-4 m) with a box (1.5 m) in front of it."""
    v, u = np.mgrid[0:h, 0:w]
    depth = 2.0 + 2.0 * (h - v) / h + 0.003 * u
    depth[30:80, 50:110] = 1.5
    return depth


def test_misplacement_sigma_is_the_depth_range_around_each_point():
    depth = _edge_scene()
    # the points' image is twice the map's resolution
    pts = SparseDepth.from_arrays(
        np.array([20.0, 160.0, 98.0, 108.0]), np.array([200.0, 100.0, 60.0, 68.0]), np.full(4, 2.0), (240, 320)
    )
    sigma = misplacement_sigma(pts, depth, radius=4.0)  # 2 map pixels
    # a flat patch (the box's inside) gives 0; the slanted floor a little; a point near the box's edge much
    assert sigma[1] == 0.0
    floor = depth[98:103, 8:13]
    assert sigma[0] == pytest.approx(2.0 * (floor.max() - floor.min()) / (4 * depth[100, 10]))
    corner = depth[28:33, 47:52]  # map pixel (49, 30): on the floor, beside the box's corner
    assert sigma[2] == pytest.approx(2.0 * (corner.max() - corner.min()) / (4 * depth[30, 49]))
    assert sigma[2] > 10 * sigma[0]
    assert sigma[3] == 0.0  # 4 map pixels inside the box
    assert np.all(misplacement_sigma(pts, depth, radius=0.9) == 0.0)  # under half a map pixel
    assert misplacement_sigma(pts, np.zeros((120, 160)), radius=4.0).tolist() == [0.0] * 4  # no depth there
    with pytest.raises(InvalidInputError, match="radius"):
        misplacement_sigma(pts, depth, radius=-1.0)
    with pytest.raises(InvalidInputError, match="depth_map"):
        misplacement_sigma(pts, depth[0], radius=1.0)


def test_misplaced_points_are_covered_by_their_misplacement_sigma():
    """Points drawn where a pose error moved them (Rayleigh, median D pixels) with the depth of where they came from:
    +-2 sigma with ``radius = 2 D`` covers about 95 % of them against the depth at the pixel drawn; without it, not."""
    rng = np.random.default_rng(8)
    depth = _edge_scene(240, 320)
    n, d_median = 4000, 6.0
    u, v = rng.uniform(20, 300, n), rng.uniform(20, 220, n)
    step = rng.normal(0, d_median / np.sqrt(2 * np.log(2)), (n, 2))
    true_depth = depth[np.rint(v + step[:, 1]).astype(int), np.rint(u + step[:, 0]).astype(int)]
    pts = SparseDepth.from_arrays(u, v, true_depth, (240, 320), np.full(n, 0.001))
    at_pixel = depth[np.rint(v).astype(int), np.rint(u).astype(int)]
    sigma = np.hypot(pts.sigma, misplacement_sigma(pts, depth, radius=2.0 * d_median))
    covered = np.mean(np.abs(pts.depth - at_pixel) <= 2 * sigma)
    assert 0.93 <= covered <= 1.0
    assert np.mean(np.abs(pts.depth - at_pixel) <= 2 * pts.sigma) < 0.8
