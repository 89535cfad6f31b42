"""The city-block distance transform against brute force, and its argument checks."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.gp.distance import taxicab_transform


@pytest.mark.parametrize("seed", range(4))
def test_is_brute_force(seed):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
    n = int(rng.integers(1, 12))
    r, c = rng.integers(0, h, n), rng.integers(0, w, n)
    got = taxicab_transform((h, w), r, c)
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    ref = np.min(np.abs(ii[..., None] - r) + np.abs(jj[..., None] - c), axis=-1)
    np.testing.assert_array_equal(got, ref)
    assert got.dtype == np.int64 and got.shape == (h, w)


def test_no_source_and_bad_arguments():
    np.testing.assert_array_equal(taxicab_transform((3, 4), [], []), np.full((3, 4), 7))
    with pytest.raises(InvalidInputError):
        taxicab_transform((0, 4), [], [])
    with pytest.raises(ShapeError):
        taxicab_transform((3, 4), [1, 2], [1])
    with pytest.raises(ShapeError):
        taxicab_transform((3, 4), [3], [0])
