"""The sub-lattice kriging (gpdepth3d.gp.sublattice) against dense linear algebra."""

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, ShapeError
from gpdepth3d.gp.model import LatticeConfig
from gpdepth3d.gp.sublattice import sublattice_kriging, window_reach

MAX_WINDOW_POINTS = LatticeConfig().max_window_points


def _kernel(a_r, a_c, b_r, b_c, l, s):
    return s**2 * np.exp(-(np.abs(a_r[:, None] - b_r[None]) + np.abs(a_c[:, None] - b_c[None])) / l)


def _dense(out_rows, out_cols, rows, cols, resid, noise, shape, k, l, s):
    """The same kriging with C_e from the dense conditional covariance given every lattice node."""
    h, w = shape
    nr = k * np.arange(-(-h // k)) + (k - 1) / 2
    nc = k * np.arange(-(-w // k)) + (k - 1) / 2
    NR, NC = (x.ravel() for x in np.meshgrid(nr, nc, indexing="ij"))
    Knn = _kernel(NR, NC, NR, NC, l, s)

    def ce(ar, ac, br, bc):
        return _kernel(ar, ac, br, bc, l, s) - _kernel(ar, ac, NR, NC, l, s) @ np.linalg.solve(
            Knn, _kernel(NR, NC, br, bc, l, s)
        )

    corr = np.zeros((out_rows.size, out_cols.size))
    vred = np.zeros_like(corr)
    rows_f, cols_f = rows.astype(float), cols.astype(float)
    for i, y in enumerate(out_rows):
        for j, x in enumerate(out_cols):
            cy, cx = np.clip(np.rint(y), 0, h - 1), np.clip(np.rint(x), 0, w - 1)
            reach = k // 2 + 1  # window_reach(k), written out: the reference must not follow a change of it
            r0, c0 = k * (cy // k) - reach, k * (cx // k) - reach  # the window of the pixel's cell
            side = k + 2 * reach
            near = (rows_f >= r0) & (rows_f < r0 + side) & (cols_f >= c0) & (cols_f < c0 + side)
            if near.sum() > MAX_WINDOW_POINTS:  # the nearest to the cell's centre, ties by window (row-major) order
                idx = np.flatnonzero(near)
                centre_r, centre_c = r0 + reach + (k - 1) / 2, c0 + reach + (k - 1) / 2
                dist = np.abs(rows_f[idx] - centre_r) + np.abs(cols_f[idx] - centre_c)
                window_order = (rows_f[idx] - r0) * side + (cols_f[idx] - c0)
                near = np.zeros_like(near)
                near[idx[np.lexsort((window_order, dist))[:MAX_WINDOW_POINTS]]] = True
            if not near.any():
                continue
            A = ce(rows_f[near], cols_f[near], rows_f[near], cols_f[near]) + np.diag(noise[near])
            c = ce(rows_f[near], cols_f[near], np.array([y]), np.array([x]))[:, 0]
            wv = np.linalg.solve(A, c)
            corr[i, j] = wv @ resid[near]
            vred[i, j] = wv @ c
    return corr, vred


@pytest.mark.parametrize(
    "k, shape, share",
    [(2, (9, 11), 3), (2, (10, 12), 3), (3, (10, 13), 3), (4, (13, 17), 3), (4, (13, 17), 1), (2, (14, 18), 12)],
)
def test_matches_the_dense_conditional_covariance(k, shape, share):
    """share 1: a point on every pixel, so stride 4's 10 x 10 windows keep only their MAX_WINDOW_POINTS nearest;
    share 12: one to four points in most windows (the written-out path)."""
    rng = np.random.default_rng(k + shape[0])
    h, w = shape
    flat = rng.choice(h * w, size=h * w // share, replace=False)
    rows, cols = flat // w, flat % w
    resid = rng.normal(0, 0.1, rows.size)
    noise = rng.uniform(1e-4, 4e-3, rows.size)
    out_rows = np.array([0.0, 1.0, 2.5, 4.0, (h - 1) / 2 + 0.3, h - 1.0])
    out_cols = np.array([0.0, 0.7, 3.0, 5.5, w - 1.0])
    corr, vred = sublattice_kriging(
        out_rows, out_cols, rows, cols, resid, noise, shape, stride=k, lengthscale=4.0, outputscale=0.3
    )
    c_ref, v_ref = _dense(out_rows, out_cols, rows, cols, resid, noise, shape, k, 4.0, 0.3)
    np.testing.assert_allclose(corr, c_ref, atol=1e-10)
    np.testing.assert_allclose(vred, v_ref, atol=1e-12)
    assert np.all(vred >= 0) and np.any(vred > 0)


def test_several_right_hand_sides_share_the_weights():
    rows, cols = np.array([1, 2, 4]), np.array([3, 2, 5])
    r = np.array([[0.1, 1.0], [-0.2, 2.0], [0.05, 0.0]])
    noise = np.full(3, 1e-3)
    args = (np.arange(6.0), np.arange(8.0), rows, cols)
    both, vred = sublattice_kriging(*args, r, noise, (6, 8), stride=2, lengthscale=5.0, outputscale=0.2)
    for q in range(2):
        one, v1 = sublattice_kriging(*args, r[:, q], noise, (6, 8), stride=2, lengthscale=5.0, outputscale=0.2)
        np.testing.assert_array_equal(both[q], one)
        np.testing.assert_array_equal(vred, v1)


@pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
def test_every_row_of_cells_is_done_whatever_the_thread_count():
    """The rows of cells are dealt to the threads round-robin; 1, 2 or 3 threads give the same answer."""
    numba = pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    shape = (23, 17)
    flat = rng.choice(shape[0] * shape[1], 60, replace=False)
    flat = flat[flat // shape[1] > 9]  # points in the lower rows only, as with a LiDAR
    rows, cols = flat // shape[1], flat % shape[1]
    resid, noise = rng.normal(0, 0.1, rows.size), np.full(rows.size, 1e-3)
    args = (np.arange(23.0), np.arange(17.0), rows, cols, resid, noise, shape)
    before = numba.get_num_threads()
    try:
        outs = []
        for t in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS), min(3, numba.config.NUMBA_NUM_THREADS)}):
            numba.set_num_threads(t)
            outs.append(sublattice_kriging(*args, stride=2, lengthscale=6.0, outputscale=0.3))
    finally:
        numba.set_num_threads(before)
    c_ref, v_ref = _dense(*args, 2, 6.0, 0.3)
    for corr, vred in outs:
        np.testing.assert_allclose(corr, c_ref, atol=1e-10)
        np.testing.assert_allclose(vred, v_ref, atol=1e-12)


def test_a_point_corrects_its_own_pixel_and_nothing_far_away():
    corr, vred = sublattice_kriging(
        np.arange(20.0),
        np.arange(20.0),
        np.array([9]),
        np.array([9]),
        np.array([0.3]),
        np.array([1e-6]),
        (20, 20),
        stride=2,
        lengthscale=8.0,
        outputscale=0.3,
    )
    # one point: w = c / (c + n) with c its residual's prior variance, vred = w c
    c = vred[9, 9] / 2 + np.sqrt(vred[9, 9] ** 2 / 4 + vred[9, 9] * 1e-6)
    assert corr[9, 9] == pytest.approx(0.3 * c / (c + 1e-6), rel=1e-9)
    assert corr[9, 9] == pytest.approx(0.3, rel=1e-3)
    assert 0 < corr[8, 10] < corr[9, 9]
    assert np.all(corr[:5] == 0) and np.all(corr[:, 14:] == 0)


def test_bad_input_is_refused_by_name():
    args = (np.arange(4.0), np.arange(4.0))
    with pytest.raises(InvalidInputError, match="stride"):
        sublattice_kriging(*args, [1], [1], [0.1], [1e-3], (4, 4), stride=1, lengthscale=2.0, outputscale=0.1)
    with pytest.raises(InvalidInputError, match="one point per pixel"):
        sublattice_kriging(
            *args, [1, 1], [1, 1], [0.1, 0.2], [1e-3, 1e-3], (4, 4), stride=2, lengthscale=2.0, outputscale=0.1
        )
    with pytest.raises(ShapeError, match="outside"):
        sublattice_kriging(*args, [4], [1], [0.1], [1e-3], (4, 4), stride=2, lengthscale=2.0, outputscale=0.1)
    with pytest.raises(InvalidInputError, match="noise"):
        sublattice_kriging(*args, [1], [1], [0.1], [-1e-3], (4, 4), stride=2, lengthscale=2.0, outputscale=0.1)


def test_a_noise_free_point_on_a_node_leaves_its_cell_uncorrected():
    """Stride 3: pixel 1 is a node, where the residual's prior variance is 0 (a singular system without noise)."""
    corr, vred = sublattice_kriging(
        np.arange(9.0), np.arange(9.0), [1], [1], [0.2], [0.0], (9, 9), stride=3, lengthscale=4.0, outputscale=0.3
    )
    assert np.all(np.isfinite(corr)) and np.all(np.isfinite(vred))
    assert np.all(corr[:3, :3] == 0) and np.all(vred[:3, :3] == 0)


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
def test_separable_correlation_is_the_product_of_the_axes(nu):
    from gpdepth3d.gp.model import Kernel, matern_1d, separable_correlation

    dr, dc = np.array([0.0, 1.0, -2.5, 7.0]), np.array([0.0, -3.0, 0.5, 2.0])
    got = separable_correlation(dr, dc, 4.0, nu)
    np.testing.assert_allclose(got, matern_1d(dr, nu, 4.0) * matern_1d(dc, nu, 4.0), rtol=1e-14)
    assert got[0] == 1.0 and np.all((got[1:] > 0) & (got[1:] < 1))
    if nu == 0.5:  # one exponential of the L1 distance
        np.testing.assert_allclose(got, np.exp(-(np.abs(dr) + np.abs(dc)) / 4.0), rtol=1e-14)
    assert Kernel(nu, 4.0, 1.0).nu == nu


def test_the_window_grows_with_the_stride():
    """6 x 6 pixels for stride 2, 10 x 10 for stride 4 (the taper scales with the cells it covers)."""
    assert [k + 2 * window_reach(k) for k in (2, 3, 4, 8)] == [6, 7, 10, 18]


def test_an_output_finer_than_the_grid_matches_the_dense_conditional_covariance():
    """Three output pixels per grid pixel and axis: a cell holds more output pixels than k x k."""
    rng = np.random.default_rng(11)
    shape, k = (10, 13), 2
    flat = rng.choice(shape[0] * shape[1], size=60, replace=False)
    rows, cols = flat // shape[1], flat % shape[1]
    resid, noise = rng.normal(0, 0.1, rows.size), rng.uniform(1e-4, 4e-3, rows.size)
    out_rows = (np.arange(3 * shape[0]) + 0.5) / 3 - 0.5
    out_cols = (np.arange(3 * shape[1]) + 0.5) / 3 - 0.5
    corr, vred = sublattice_kriging(
        out_rows, out_cols, rows, cols, resid, noise, shape, stride=k, lengthscale=4.0, outputscale=0.3
    )
    c_ref, v_ref = _dense(out_rows, out_cols, rows, cols, resid, noise, shape, k, 4.0, 0.3)
    np.testing.assert_allclose(corr, c_ref, atol=1e-10)
    np.testing.assert_allclose(vred, v_ref, atol=1e-12)


def test_calls_on_other_grids_in_between_change_nothing():
    """A call keeps no state: a call on another grid or stride between two equal calls leaves the second equal to
    the first."""

    def call(shape, k):
        rng = np.random.default_rng(shape[0] + k)
        h, w = shape
        flat = rng.choice(h * w, size=40, replace=False)
        rows, cols = flat // w, flat % w
        resid, noise = rng.normal(0, 0.1, 40), np.full(40, 1e-3)
        grid = (np.arange(float(h)), np.arange(float(w)))
        return sublattice_kriging(*grid, rows, cols, resid, noise, shape, stride=k, lengthscale=5.0, outputscale=0.2)

    first = call((12, 15), 2)
    call((14, 11), 2)
    call((12, 15), 4)
    again = call((12, 15), 2)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    assert np.any(first[0] != 0)
