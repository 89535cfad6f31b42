"""The Matérn kernel object (`gpdepth3d.gp.kernels`): its correlation, state-space form and precision stencil agree."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.kernels import (
    SMOOTHNESS,
    Kernel,
    MaternKernel,
    check_nu,
    is_exponential,
    matern_1d,
    separable_correlation,
    smoothness_code,
    state_dim,
    unit_correlation,
    unit_separable_correlation,
    unit_sde,
)
from gpdepth3d.gp.markov import chain_precision

REFERENCE = {  # the docstring's formulas, written out independently
    0.5: lambda r: np.exp(-r),
    1.5: lambda r: (1 + math.sqrt(3) * r) * np.exp(-math.sqrt(3) * r),
    2.5: lambda r: (1 + math.sqrt(5) * r + 5 * r**2 / 3) * np.exp(-math.sqrt(5) * r),
}


@pytest.mark.parametrize("nu", SMOOTHNESS)
class TestMaternKernel:
    def test_correlation_is_the_documented_formula(self, nu):
        k = MaternKernel(nu, 3.0, 2.0)
        d = np.linspace(-20, 20, 81)
        np.testing.assert_allclose(k.correlation(d), REFERENCE[nu](np.abs(d) / 3.0), rtol=1e-14, atol=1e-300)
        np.testing.assert_array_equal(k.correlation(d), matern_1d(d, nu, 3.0))
        assert k.correlation(np.zeros(1))[0] == 1.0

    def test_compiled_formulas_match_numpy(self, nu):
        code = smoothness_code(nu)
        r = np.linspace(0, 7, 50)
        compiled = np.array([unit_correlation(x, code) for x in r])
        np.testing.assert_allclose(compiled, REFERENCE[nu](r), rtol=1e-14)
        pairs = np.array([unit_separable_correlation(a, b, code) for a, b in zip(r, r[::-1])])
        np.testing.assert_allclose(pairs, REFERENCE[nu](r) * REFERENCE[nu](r[::-1]), rtol=1e-13)

    def test_matrix_is_the_separable_product(self, nu):
        rng = np.random.default_rng(0)
        ra, ca, rb, cb = (rng.uniform(0, 30, 7) for _ in range(4))
        k = Kernel(nu, 4.0, 0.5)
        want = 0.25 * REFERENCE[nu](np.abs(ra[:, None] - rb) / 4) * REFERENCE[nu](np.abs(ca[:, None] - cb) / 4)
        np.testing.assert_allclose(k.matrix(ra, ca, rb, cb), want, rtol=1e-13)
        dr, dc = ra[:, None] - rb, ca[:, None] - cb
        np.testing.assert_allclose(k.separable_correlation(dr, dc), want / 0.25, rtol=1e-13)
        np.testing.assert_allclose(separable_correlation(dr, dc, 4.0, nu), want / 0.25, rtol=1e-13)

    def test_lag_table(self, nu):
        k = MaternKernel(nu, 2.5, 1.0)
        np.testing.assert_allclose(k.lag_correlation(9), REFERENCE[nu](np.arange(9) / 2.5), rtol=1e-14)

    def test_state_space_reproduces_the_correlation(self, nu):
        """The first state's covariance e^{F d} P_inf [0, 0] is M_nu(d / l) (the SDE's defining property)."""
        k = MaternKernel(nu, 5.0, 1.0)
        F, P = k.state_space()
        assert F.shape == P.shape == (k.state_dim, k.state_dim) and P[0, 0] == pytest.approx(1.0)
        for d in (0.0, 0.7, 3.0, 11.0):
            assert (scipy.linalg.expm(F * d) @ P)[0, 0] == pytest.approx(REFERENCE[nu](d / 5.0), rel=1e-9, abs=1e-14)

    def test_precision_stencil_inverts_the_covariance(self, nu):
        """The chain precision (block tridiagonal, d x d blocks) of the states inverts their covariance."""
        k = MaternKernel(nu, 3.0, 1.0)
        x = np.arange(12, dtype=np.float64)
        Q, _ = chain_precision(x, nu, 3.0)
        Q = Q.toarray()
        d = k.state_dim
        assert Q.shape == (12 * d, 12 * d) and k.stencil_block == d * d
        band = np.abs(np.subtract.outer(np.arange(12 * d) // d, np.arange(12 * d) // d))
        assert np.all(Q[band > 1] == 0)  # neighbours only: the 1-D stencil
        cov = np.linalg.inv(Q)[::d, ::d]  # first states
        np.testing.assert_allclose(cov, REFERENCE[nu](np.abs(np.subtract.outer(x, x)) / 3.0), rtol=1e-8, atol=1e-12)

    def test_capabilities(self, nu):
        k = MaternKernel(nu, 1.0, 1.0)
        assert k.state_dim == state_dim(nu) == int(nu + 0.5)
        assert k.exponential == is_exponential(nu) == (nu == 0.5)
        assert k.code == SMOOTHNESS.index(nu)
        assert unit_sde(k.state_dim)[0].shape == (k.state_dim, k.state_dim)


@pytest.mark.parametrize("bad", [1.0, 3.5, True, "0.5", None])
def test_other_smoothnesses_are_refused(bad):
    with pytest.raises(InvalidInputError, match="nu: expected 0.5, 1.5 or 2.5"):
        check_nu(bad)
    with pytest.raises(InvalidInputError, match="nu"):
        MaternKernel(bad, 1.0, 1.0)
    with pytest.raises(InvalidInputError, match="nu"):
        matern_1d(np.zeros(2), bad, 1.0)
