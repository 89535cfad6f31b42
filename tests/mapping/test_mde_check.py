"""Tests of the held-out test of a frame's refinement against its rescaled MDE (`gpdepth3d.mapping.mde_check`)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.mde_check import (
    HELD_OUT_COARSENING,
    HeldOutCheck,
    held_out_check,
    held_out_shape,
    mde_fallback,
    rescaled_mde,
    sample_at,
    split_held_out,
)
from gpdepth3d.measurements import SparseDepth

SHAPE = (60, 80)  # the points' image; the MDE is at half its size
RNG = np.random.default_rng(3)


def _points(depth_of, n: int = 200) -> SparseDepth:
    u, v = RNG.uniform(0, SHAPE[1] - 1, n), RNG.uniform(0, SHAPE[0] - 1, n)
    return SparseDepth.from_arrays(u, v, depth_of(u, v), SHAPE, np.full(n, 0.02))


def _ramp(u, v):
    return 1.0 + 0.02 * u


def test_split_is_seeded_disjoint_and_of_the_share():
    kept, held = split_held_out(100, 0.2, seed=7)
    assert held.size == 20 and kept.size == 80
    assert np.array_equal(np.sort(np.r_[kept, held]), np.arange(100))
    again = split_held_out(100, 0.2, seed=7)
    assert np.array_equal(held, again[1])
    assert not np.array_equal(held, split_held_out(100, 0.2, seed=8)[1])
    with pytest.raises(InvalidInputError, match="fraction"):
        split_held_out(10, 1.0, seed=0)


def test_sample_at_rescales_the_points_to_the_image():
    image = np.arange(30 * 40, dtype=float).reshape(30, 40)
    sp = SparseDepth.from_arrays(np.array([0.0, 79.0, 10.0]), np.array([0.0, 59.0, 20.0]), np.ones(3), SHAPE)
    assert np.array_equal(sample_at(image, sp), [image[0, 0], image[29, 39], image[10, 5]])


def test_rescaled_mde_is_the_median_ratio_and_the_spread_after_it():
    mde = np.full((30, 40), 2.0)
    sp = _points(lambda u, v: np.full(u.shape, 3.0) * np.exp(RNG.normal(0, 0.1, u.shape)))
    scale, sigma = rescaled_mde(mde, sp)
    assert scale == pytest.approx(1.5, rel=0.03)
    assert sigma == pytest.approx(0.1, rel=0.2)
    assert np.isnan(rescaled_mde(np.zeros((30, 40)), sp)[1])


def _mde_ramp():
    v, u = np.mgrid[0:30, 0:40] * 2.0
    return 0.5 * _ramp(u, v)  # right in shape, half the scale


def test_a_gp_that_follows_the_points_is_kept():
    sp = _points(_ramp)
    v, u = np.mgrid[0:30, 0:40] * 2.0
    check = held_out_check(
        lambda kept: _ramp(u, v) * 1.001, np.sqrt(_mde_ramp()), sp, fraction=0.2, min_held_out=10, seed=0
    )
    assert check.held_out == 40 and check.gp_better
    assert check.gp_error < check.mde_error


def test_a_gp_worse_than_the_rescaled_mde_falls_back_to_it_with_its_variance():
    sp = _points(_ramp)
    mde = _mde_ramp()
    calls = []

    def misled(kept):  # a GP pulled 30 % off by wrong points
        calls.append(len(kept))
        return 2.0 * mde * 1.3

    check = held_out_check(misled, mde, sp, fraction=0.2, min_held_out=10, seed=1)
    assert calls == [160] and not check.gp_better
    assert check.mde_scale == pytest.approx(2.0, rel=0.03) and check.mde_sigma < 0.03
    depth, variance = mde_fallback(mde, check)
    assert np.allclose(depth, check.mde_scale * mde) and np.all(variance >= 0)
    assert "worse than the MDE" in check.describe(5) and "frame 5" in check.describe(5)


def test_too_few_points_are_not_tested():
    sp = _points(_ramp, n=20)
    check = held_out_check(
        lambda kept: pytest.fail("no GP without a test"), _mde_ramp(), sp, fraction=0.2, min_held_out=10, seed=0
    )
    assert check.held_out == 0 and check.gp_better and np.isnan(check.gp_error)


def test_fallback_variance_is_relative_to_the_depth():
    check = HeldOutCheck(20, 0.2, 0.1, 1.5, 0.1)
    depth, variance = mde_fallback(np.array([[2.0, 0.0]]), check)
    assert np.allclose(depth, [[3.0, 0.0]]) and np.allclose(variance, [[0.09, 0.0]])


def test_held_out_shape_divides_each_side_rounding_up():
    assert held_out_shape((240, 320), 2) == (120, 160)
    assert held_out_shape((240, 320)) == held_out_shape((240, 320), HELD_OUT_COARSENING)
    assert HELD_OUT_COARSENING > 1  # the check's GP skips the full-size output
    assert held_out_shape((213, 320), 4) == (54, 80)
    assert held_out_shape((3, 5), 8) == (1, 1)
    assert held_out_shape((30, 40), 1) == (30, 40)
    for bad in (0, 1.5):
        with pytest.raises(InvalidInputError, match="coarsening"):
            held_out_shape((30, 40), bad)


def _gp_at_held_out_shape(mde, corrupt=None):
    """The default model's GP on the kept points, at the held-out check's coarse output (as the Mapper runs it)."""
    import warnings

    from gpdepth3d.completion.complete import DepthCompleter
    from gpdepth3d.mapping.map_scale import fused_depth

    completer = DepthCompleter()

    def refine(kept):
        if corrupt is not None:
            kept = SparseDepth.from_arrays(kept.u, kept.v, corrupt(kept.depth), kept.image_size, kept.sigma)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = fused_depth(completer.complete(mde, kept, output_shape=held_out_shape(mde.shape)))
        assert out.shape == held_out_shape(mde.shape)
        return out

    return refine


def _bump(u, v):  # a ramp with a bump the MDE below does not have
    return _ramp(u, v) * (1.0 + 0.4 * np.exp(-((u - 40.0) ** 2 + (v - 30.0) ** 2) / 300.0))


def test_the_coarse_gp_that_corrects_the_mde_is_kept():
    # points on a surface with a bump, an MDE without it: the GP from the kept points predicts the
    # held-out ones (read off its coarse output) better than the MDE rescaled by one median
    sp = _points(_bump, n=400)
    check = held_out_check(_gp_at_held_out_shape(_mde_ramp()), _mde_ramp(), sp, fraction=0.2, min_held_out=10, seed=2)
    assert check.held_out == 80 and check.gp_better
    assert check.gp_error < 0.5 * check.mde_error


def test_the_coarse_gp_misled_by_its_points_falls_back():
    # an MDE of the right shape, and kept points scattered far beyond the sigma they state (a wrong pose, a
    # moving surface): the GP follows them and predicts the held-out points worse than the rescaled MDE
    sp = _points(_ramp, n=400)
    rng = np.random.default_rng(5)
    scatter = _gp_at_held_out_shape(_mde_ramp(), corrupt=lambda d: d * np.exp(rng.normal(0.0, 0.4, d.shape)))
    check = held_out_check(scatter, _mde_ramp(), sp, fraction=0.2, min_held_out=10, seed=2)
    assert check.held_out == 80 and not check.gp_better
