"""Tests of gpdepth3d.mde.align: robust scale / scale+shift fits of MDE depth to measurements."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.mde.align import AlignmentResult, align_depth, align_to_sparse

RNG = np.random.default_rng(0)
X = RNG.uniform(1.0, 20.0, size=200)


class TestAlignmentResult:
    def test_apply_depth(self):
        fit = AlignmentResult(2.0, -1.0, 5)
        out = fit.apply(np.array([[1.0, 0.0], [3.0, 0.25]]))
        np.testing.assert_allclose(out, [[1.0, 0.0], [5.0, 1e-6]])  # 0 stays 0; <= 0 clamped to 1e-6

    def test_apply_inverse(self):
        fit = AlignmentResult(2.0, 0.1, 5, "inverse")
        out = fit.apply(np.array([4.0, 0.0, 10.0]))
        np.testing.assert_allclose(out, [1.0 / (2.0 / 4.0 + 0.1), 0.0, 1.0 / 0.3])


class TestAlignDepth:
    def test_scale_exact(self):
        fit = align_depth(X, 1.3 * X, "scale")
        assert fit.scale == pytest.approx(1.3, rel=1e-9) and fit.shift == 0.0 and fit.n_used == X.size

    def test_scale_shift_exact(self):
        fit = align_depth(X, 0.8 * X + 0.5, "scale_shift")
        assert fit.scale == pytest.approx(0.8, rel=1e-6) and fit.shift == pytest.approx(0.5, abs=1e-6)
        np.testing.assert_allclose(fit.apply(X), 0.8 * X + 0.5, rtol=1e-6)

    @pytest.mark.parametrize("mode", ["scale", "scale_shift"])
    def test_robust_to_outliers(self, mode):
        y = 1.2 * X * (1 + 0.01 * RNG.normal(size=X.size))
        bad = RNG.random(X.size) < 0.2
        y[bad] *= RNG.uniform(0.2, 3.0, size=bad.sum())
        fit = align_depth(X, y, mode)
        assert fit.scale == pytest.approx(1.2, rel=0.02)
        assert abs(fit.shift) < 0.2
        # A plain least-squares fit is dragged by the outliers much more.
        ls = np.sum(X * y) / np.sum(X * X)
        assert abs(ls - 1.2) > 3 * abs(fit.scale - 1.2)

    def test_inverse_space(self):
        y = 1.0 / (2.0 / X + 0.1)
        fit = align_depth(X, y, "scale_shift", space="inverse")
        assert fit.space == "inverse"
        assert fit.scale == pytest.approx(2.0, rel=1e-6) and fit.shift == pytest.approx(0.1, abs=1e-6)
        np.testing.assert_allclose(fit.apply(X), y, rtol=1e-6)

    def test_identity_cases(self):
        for fit in (
            align_depth(X, 2 * X, "none"),
            align_depth(np.array([]), np.array([]), "scale"),
            align_depth(X[:2], 2 * X[:2], "scale_shift"),  # fewer than 3 points
            align_depth(np.array([np.nan, 0.0, -1.0]), np.array([1.0, 1.0, 1.0]), "scale"),
        ):
            assert (fit.scale, fit.shift, fit.n_used) == (1.0, 0.0, 0)

    def test_invalid_pairs_ignored(self):
        x = np.concatenate([X, [np.nan, 0.0, 5.0, 5.0]])
        y = np.concatenate([1.5 * X, [3.0, 3.0, np.inf, -2.0]])
        fit = align_depth(x, y, "scale")
        assert fit.n_used == X.size and fit.scale == pytest.approx(1.5)

    def test_errors(self):
        with pytest.raises(InvalidInputError):
            align_depth(X, X[:-1])
        with pytest.raises(InvalidInputError):
            align_depth(X, X, "affine")  # type: ignore[arg-type]
        with pytest.raises(InvalidInputError):
            align_depth(X, X, space="log")  # type: ignore[arg-type]


class TestAlignToSparse:
    def test_scale_from_higher_resolution_points(self):
        depth = RNG.uniform(1.0, 5.0, size=(12, 16))
        depth[0, 0] = 0.0
        # Measurements at twice the resolution, all 1.4 x the MDE of the pixel they fall into.
        rows, cols = np.mgrid[1:12:3, 2:16:3]
        u, v = cols.ravel() * 2.0 + 0.5, rows.ravel() * 2.0 + 0.5
        sparse = SparseDepth(u, v, 1.4 * depth[rows.ravel(), cols.ravel()], (24, 32))
        aligned, fit = align_to_sparse(depth, sparse)
        assert fit.scale == pytest.approx(1.4) and fit.n_used == rows.size
        np.testing.assert_allclose(aligned[depth > 0], 1.4 * depth[depth > 0])
        assert aligned[0, 0] == 0.0

    def test_no_points_identity(self):
        depth = np.full((4, 4), 2.0)
        aligned, fit = align_to_sparse(depth, SparseDepth.empty((4, 4)))
        assert fit.scale == 1.0 and np.array_equal(aligned, depth)

    def test_synthetic_mde_scale_error_is_found(self, street_frame):
        f = street_frame
        _, fit = align_to_sparse(f.mde, f.lidar)
        # The simulated MDE is 1.15 x too far on average (times a smooth error field).
        assert 1 / fit.scale == pytest.approx(1.15, rel=0.1)

    def test_errors(self):
        with pytest.raises(ShapeError):
            align_to_sparse(np.ones((2, 2, 1)), SparseDepth.empty((2, 2)))
        with pytest.raises(InvalidInputError):
            align_to_sparse(np.ones((2, 2)), np.ones((2, 2)))  # type: ignore[arg-type]
