"""The small in-place Cholesky factorisations of the local kriging kernels (gpdepth3d.gp._cholesky)."""

import numpy as np
import pytest

from gpdepth3d.gp._cholesky import cholesky_dots_in_place, cholesky_in_place

FACTORS = (cholesky_in_place, cholesky_dots_in_place)


def _spd(n, rng, size=40):
    """An (size, size) array whose leading n x n block is SPD and the rest is marked (to see it left alone)."""
    X = rng.standard_normal((n, n + 3))
    A = np.full((size, size), 7.0)
    A[:n, :n] = X @ X.T / n + 0.05 * np.eye(n)
    return A


@pytest.mark.parametrize("factor", FACTORS)
@pytest.mark.parametrize("n", [1, 3, 4, 7, 20, 36])
def test_the_factor_is_numpys_and_only_the_lower_triangle_of_the_block_changes(factor, n):
    A = _spd(n, np.random.default_rng(n))
    W = A.copy()
    assert factor(W, n)
    np.testing.assert_allclose(np.tril(W[:n, :n]), np.linalg.cholesky(A[:n, :n]), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.triu(W[:n, :n], 1), np.triu(A[:n, :n], 1))
    np.testing.assert_array_equal(W[n:], A[n:])
    np.testing.assert_array_equal(W[:, n:], A[:, n:])


@pytest.mark.parametrize("n", [5, 13, 36])
def test_the_dot_product_factor_agrees_with_the_plain_one_to_rounding(n):
    A = _spd(n, np.random.default_rng(100 + n))
    L1, L2 = A.copy(), A.copy()
    assert cholesky_in_place(L1, n) and cholesky_dots_in_place(L2, n)
    scale = np.abs(np.tril(L1[:n, :n])).max()
    assert np.abs(np.tril(L1[:n, :n]) - np.tril(L2[:n, :n])).max() <= 1e-13 * scale


@pytest.mark.parametrize("factor", FACTORS)
def test_not_positive_definite_or_nan_is_refused(factor):
    A = _spd(6, np.random.default_rng(1))
    A[4, 4] = -1.0
    assert not factor(A.copy(), 6)
    B = _spd(6, np.random.default_rng(2))
    B[3, 1] = B[1, 3] = np.nan
    assert not factor(B.copy(), 6)
