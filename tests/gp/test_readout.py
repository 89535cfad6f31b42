"""Tests of gpdepth3d.gp.readout.read_mean: the compiled read-out of state means equals the sparse products."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from gpdepth3d.gp.readout import Readout, read_mean


@pytest.mark.parametrize("d", [1, 2])
def test_read_mean_equals_the_sparse_products(d):
    rng = np.random.default_rng(d)
    h, w, ho, wo = 5, 7, 9, 11
    nvar = h * w * d * d + 13
    x = rng.standard_normal(nvar)
    real_vars = (rng.permutation(h * w) * d * d).reshape(h, w)  # state (k, l) of a pixel at + k d + l
    wv = sp.random(ho, h * d, density=0.4, format="csr", random_state=rng)
    wu = sp.random(wo, w * d, density=0.4, format="csr", random_state=rng)
    prior = rng.standard_normal((ho, wo))
    states = x[real_vars[..., None] + np.arange(d * d)].reshape(h, w, d, d)
    M = states.transpose(0, 2, 1, 3).reshape(h * d, w * d)
    expected = prior + wv @ (wu @ M.T).T
    got = read_mean(Readout(wv, wu, None, None, None, None, None), x, real_vars, d, prior)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)
    assert got.shape == (ho, wo)
