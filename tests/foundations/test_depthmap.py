"""The shared map helpers: nearest-valid fill and resize (gpdepth3d.depthmap)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.depthmap import INTERPOLATIONS, fill_nearest, resize_map
from gpdepth3d.errors import EmptyInputError, InvalidInputError, ShapeError


class TestFillNearest:
    def test_fills_from_the_nearest_valid_pixel(self):
        values = np.array([[1.0, 0.0, 0.0, 0.0, 5.0]])
        valid = values > 0
        out = fill_nearest(values, valid)
        # columns 1 and 3 are nearest to 1.0 and 5.0; column 2 is equidistant (either is right)
        assert out[0, 0] == 1.0 and out[0, 1] == 1.0 and out[0, 3] == 5.0 and out[0, 4] == 5.0
        assert out[0, 2] in (1.0, 5.0)

    def test_matches_brute_force_nearest(self):
        rng = np.random.default_rng(0)
        values = rng.uniform(1, 9, (17, 23))
        valid = rng.random((17, 23)) < 0.1
        out = fill_nearest(values, valid)
        vr, vc = np.nonzero(valid)
        for r in range(17):
            for c in range(23):
                d2 = (vr - r) ** 2 + (vc - c) ** 2
                nearest = values[vr[d2 == d2.min()], vc[d2 == d2.min()]]
                assert out[r, c] in nearest
        np.testing.assert_array_equal(out[valid], values[valid])

    def test_all_valid_returns_the_input(self):
        values = np.ones((3, 4))
        assert fill_nearest(values, np.ones((3, 4), bool)) is values

    def test_errors(self):
        with pytest.raises(EmptyInputError, match="valid"):
            fill_nearest(np.zeros((3, 3)), np.zeros((3, 3), bool))
        with pytest.raises(ShapeError, match="valid"):
            fill_nearest(np.zeros((3, 3)), np.ones((3, 4), bool))
        with pytest.raises(ShapeError, match="values"):
            fill_nearest(np.zeros(3), np.ones(3, bool))


class TestResizeMap:
    def test_same_shape_is_returned_as_is(self):
        a = np.arange(12.0).reshape(3, 4)
        assert resize_map(a, (3, 4)) is a

    def test_area_shrink_is_the_block_mean(self):
        a = np.arange(36.0).reshape(6, 6)
        out = resize_map(a, (2, 2), shrink="area")
        np.testing.assert_allclose(out, a.reshape(2, 3, 2, 3).mean(axis=(1, 3)), rtol=1e-6)

    def test_nearest_keeps_values_and_linear_interpolates(self):
        a = np.array([[1.0, 3.0], [5.0, 7.0]])
        near = resize_map(a, (4, 4), grow="nearest")
        assert set(np.unique(near)) == {1.0, 3.0, 5.0, 7.0}
        lin = resize_map(a, (4, 4))
        assert 1.0 <= lin.min() and lin.max() <= 7.0 and len(np.unique(lin)) > 4
        # shrinking with nearest never mixes depths (no value that was not there)
        b = np.kron(np.array([[1.0, 9.0], [9.0, 1.0]]), np.ones((3, 3)))
        assert set(np.unique(resize_map(b, (2, 2), shrink="nearest"))) <= {1.0, 9.0}

    def test_shrink_and_grow_choose_by_rows(self):
        a = np.kron(np.array([[1.0, 9.0]]), np.ones((4, 4)))
        shrunk = resize_map(a, (2, 4), shrink="nearest", grow="linear")
        assert set(np.unique(shrunk)) <= {1.0, 9.0}
        grown = resize_map(a, (8, 16), shrink="nearest", grow="linear")
        assert len(np.unique(grown)) > 2

    def test_colour_image_and_dtype(self):
        rgb = np.zeros((4, 6, 3), np.uint8)
        out = resize_map(rgb, (2, 3), shrink="area")
        assert out.shape == (2, 3, 3) and out.dtype == np.uint8

    def test_errors(self):
        with pytest.raises(ShapeError, match="shape"):
            resize_map(np.ones((3, 3)), (0, 3))
        with pytest.raises(ShapeError, match="shape"):
            resize_map(np.ones((3, 3)), (2.5, 3))
        with pytest.raises(ShapeError, match="image"):
            resize_map(np.ones(3), (2, 2))
        with pytest.raises(InvalidInputError, match="shrink"):
            resize_map(np.ones((3, 3)), (2, 2), shrink="bicubic")
        assert "area" in INTERPOLATIONS
