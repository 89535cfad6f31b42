"""The leave-one-out screening's parts: neighbour search (tie order), compiled kriging, incremental rounds.

References are brute force: every other usable point sorted by (L1 distance, position on that ring
from the target's start, index), NumPy's dense solves per neighbourhood, and a screening loop that
recomputes every point each round.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from gpdepth3d.gp import _loo, points
from gpdepth3d.gp._loo import grid_neighbours, loo_predict
from gpdepth3d.gp.model import separable_correlation
from gpdepth3d.gp.fit import PointFit
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.model import ScreenConfig
from gpdepth3d.gp.points import _distance_to, loo_zscores, neighbours_of, screen_points, start_screen_search


def _ring_position(dr, dc, d):
    """Position of offset (dr, dc) on the ring of L1 radius d, clockwise from the top (`_loo.ring_offset`)."""
    side = np.select([(dr < 0) & (dc >= 0), (dr >= 0) & (dc > 0), (dr > 0) & (dc <= 0)], [0, 1, 2], 3)
    return side * d + np.choose(side, [dc, dr, -dc, -dr])


def _brute_neighbours(rows, cols, usable, targets, k):
    """Every other usable point by (L1 distance, position on that ring from the target's start, index)."""
    key = _loo.pixel_hash(rows, cols)
    nn = np.empty((len(targets), k), dtype=np.int64)
    dist = np.empty((len(targets), k))
    pool = np.flatnonzero(usable)
    for q, i in enumerate(targets):
        c = pool[pool != i]
        dr = (rows[c] - rows[i]).astype(np.int64)
        dc = (cols[c] - cols[i]).astype(np.int64)
        d = np.abs(dr) + np.abs(dc)
        ring = np.maximum(d, 1)
        start = ((((key[i] >> 16) + ring * 2654435769) & 0xFFFFFFFF) * (4 * ring)) >> 32
        order = np.where(d == 0, 0, (_ring_position(dr, dc, ring) - start) % (4 * ring))
        pick = np.lexsort((c, order, d))[:k]
        nn[q], dist[q] = c[pick], d[pick]
    return nn, dist


def _brute_by_index(rows, cols, usable, targets, k):
    """Every other usable point by (L1 distance, index): the k-d tree path's rule off the pixel grid."""
    nn = np.empty((len(targets), k), dtype=np.int64)
    dist = np.empty((len(targets), k))
    pool = np.flatnonzero(usable)
    for q, i in enumerate(targets):
        c = pool[pool != i]
        d = np.abs(rows[c] - rows[i]) + np.abs(cols[c] - cols[i])
        pick = np.lexsort((c, d))[:k]
        nn[q], dist[q] = c[pick], d[pick]
    return nn, dist


def _points(rng, n, h, w, dup=False):
    rows = rng.integers(0, h, n).astype(np.float64) + 7.0
    cols = rng.integers(0, w, n).astype(np.float64) - 3.0
    if not dup:  # one point per pixel, as on the GP grid
        _, first = np.unique(rows * 10_000 + cols, return_index=True)
        rows, cols = rows[np.sort(first)], cols[np.sort(first)]
    return rows, cols


class TestNeighbours:
    @pytest.mark.parametrize("seed", range(6))
    def test_ring_search_is_brute_force_with_the_tie_order(self, seed):
        """Random point sets (with and without several points on a pixel), exclusions and target subsets."""
        rng = np.random.default_rng(seed)
        rows, cols = _points(
            rng, int(rng.integers(20, 600)), int(rng.integers(2, 90)), int(rng.integers(2, 120)), dup=seed % 2 == 1
        )
        n = rows.size
        usable = rng.random(n) > 0.2
        usable[:2] = True
        k = int(min(12, usable.sum() - 1))
        targets = rng.choice(n, min(n, 700), replace=False)  # more than one parallel chunk when n is large
        got = grid_neighbours(rows, cols, usable, targets, k)
        ref = _brute_neighbours(rows, cols, usable, targets, k)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])

    @pytest.mark.parametrize("seed", range(4))
    def test_one_image_serves_every_usable_set(self, seed):
        """An image of all the points (`neighbour_image`) searched with a subset usable, in both searches (dense and
        sparse points, several on a pixel), gives the brute-force neighbours of that subset."""
        rng = np.random.default_rng(40 + seed)
        rows, cols = _points(rng, 500, *((30, 160) if seed < 2 else (12, 30)), dup=True)  # sparse, dense
        n = rows.size
        image = _loo.neighbour_image(rows, cols)
        for drop in (0.0, 0.05, 0.6):
            usable = rng.random(n) >= drop
            usable[:2] = True
            targets = rng.choice(n, 300, replace=False)
            got = grid_neighbours(rows, cols, usable, targets, 12, image)
            ref = _brute_neighbours(rows, cols, usable, targets, 12)
            np.testing.assert_array_equal(got[0], ref[0])
            np.testing.assert_array_equal(got[1], ref[1])

    def test_far_neighbours(self):
        """Few points far apart: rings of radius up to the image's extent."""
        rows = np.array([0.0, 0.0, 50.0, 90.0, 10.0, 80.0])
        cols = np.array([0.0, 70.0, 3.0, 90.0, 200.0, 150.0])
        usable = np.ones(6, dtype=bool)
        got = grid_neighbours(rows, cols, usable, np.arange(6), 5)
        ref = _brute_neighbours(rows, cols, usable, np.arange(6), 5)
        np.testing.assert_array_equal(got[0], ref[0])
        assert ref[1].max() > 100

    def test_off_pixel_points_use_a_tree_with_ties_by_index(self):
        rng = np.random.default_rng(7)
        rows, cols = _points(rng, 300, 40, 60, dup=True)
        rows = rows + 0.5  # half pixels: ties stay exact in binary floating point
        usable = rng.random(rows.size) > 0.1
        usable[:2] = True
        targets = np.arange(rows.size)
        got = neighbours_of(rows, cols, usable, targets, 12)
        ref = _brute_by_index(rows, cols, usable, targets, 12)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_allclose(got[1], ref[1])

    def test_order_of_the_points_does_not_matter(self):
        """Ties go by pixel positions, so permuting the points permutes the answer and nothing else."""
        rng = np.random.default_rng(3)
        rows, cols = _points(rng, 400, 30, 50)
        n = rows.size
        perm = rng.permutation(n)
        a, _ = neighbours_of(rows, cols, np.ones(n, bool), np.arange(n), 12)
        b, _ = neighbours_of(rows[perm], cols[perm], np.ones(n, bool), np.arange(n), 12)
        np.testing.assert_array_equal(perm[b], a[perm])

    def test_ties_favour_no_direction(self):
        """On a full grid every ring is tied: the last neighbours taken (from the ring that does not fit)
        point in every direction about equally often over the targets."""
        rr, cc = np.meshgrid(np.arange(60.0), np.arange(80.0), indexing="ij")
        rows, cols = rr.ravel(), cc.ravel()
        n = rows.size
        inner = np.flatnonzero((rows >= 5) & (rows < 55) & (cols >= 5) & (cols < 75))
        nn, dist = neighbours_of(rows, cols, np.ones(n, bool), inner, 7)  # rings of 4 and 8: the second splits
        last = nn[:, 4:]
        dr, dc = rows[last] - rows[inner][:, None], cols[last] - cols[inner][:, None]
        assert np.all(dist[:, :4] == 1) and np.all(dist[:, 4:] == 2)
        assert abs(np.mean(dr < 0) - np.mean(dr > 0)) < 0.03 and abs(np.mean(dc < 0) - np.mean(dc > 0)) < 0.03

    def test_dense_and_sparse_parts_both_searches(self):
        """A dense block (rings walked pixel by pixel) beside sparse points (diamonds gathered by rows and sorted),
        with targets alternating between them so that each search starts from the other's distance."""
        rng = np.random.default_rng(11)
        dense = np.unique(rng.integers(0, 12, (300, 2)), axis=0).astype(np.float64)
        sparse = np.unique(rng.integers(0, 200, (60, 2)) + [20, 0], axis=0).astype(np.float64)
        pts = np.concatenate([dense, sparse])
        order = np.argsort(np.arange(len(pts)) % 7, kind="stable")  # dense and sparse points interleaved
        rows, cols = pts[order, 0], pts[order, 1]
        usable = rng.random(rows.size) > 0.1
        targets = np.arange(rows.size)
        got = grid_neighbours(rows, cols, usable, targets, 12)
        ref = _brute_neighbours(rows, cols, usable, targets, 12)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        assert ref[1][:, -1].max() > 2 * _loo.WALK_RADIUS and ref[1][:, -1].min() <= _loo.WALK_RADIUS

    def test_two_callers_share_the_targets_from_both_ends(self):
        """`_loo._ring_claim` from the first chunk and from the last, each alone or after the other has claimed some
        chunks, and `_loo.SharedSearch` (a second thread and the caller), give `grid_neighbours` of every point."""
        rng = np.random.default_rng(21)
        rows, cols = _points(rng, 2600, 60, 90, dup=True)
        n, k = rows.size, 12
        image = _loo.neighbour_image(rows, cols)
        ref_nn, ref_dist = grid_neighbours(rows, cols, np.ones(n, dtype=bool), np.arange(n), k, image)
        r, c, width, start, members, column, key = image
        chunks = (n + _loo.CHUNK - 1) // _loo.CHUNK
        assert chunks >= 4
        for backward in (False, True):
            for taken in (0, 2):  # chunks the other caller holds at the far end
                nn, dist = np.full((n, k), -7), np.full((n, k), -7.0)
                claimed = np.zeros(chunks, dtype=bool)
                far = slice(chunks - taken, chunks) if not backward else slice(0, taken)
                claimed[far] = True
                args = (r, c, width, start, members, column, np.ones(n, dtype=bool), key, np.arange(n), k, nn, dist)
                _loo._ring_claim(claimed, backward, *args)
                held = np.zeros(n, dtype=bool)
                held[far.start * _loo.CHUNK : far.stop * _loo.CHUNK] = True
                done = ~held
                assert claimed.all()
                np.testing.assert_array_equal(nn[done], ref_nn[done])
                np.testing.assert_array_equal(dist[done], ref_dist[done])
                assert np.all(nn[held] == -7)  # the other caller's chunks are left to it
        for _ in range(3):
            got_nn, got_dist = _loo.SharedSearch(image, k).result()
            np.testing.assert_array_equal(got_nn, ref_nn)
            np.testing.assert_array_equal(got_dist, ref_dist)

    def test_ring_offsets_cover_each_ring_once(self):
        for d in (1, 2, 5, 40):
            offs = np.array([_loo.ring_offset(d, p) for p in range(4 * d)])
            assert np.all(np.abs(offs).sum(1) == d) and len({tuple(o) for o in offs}) == 4 * d
            np.testing.assert_array_equal(_ring_position(offs[:, 0], offs[:, 1], d), np.arange(4 * d))


def _kriging_reference(rows, cols, r, noise, fit, targets, nn, nu, share=False):
    """z-scores (and noise shares: the variance of the noise terms of r_i - w . r_N over its predictive variance)."""
    s2, tau2 = fit.outputscale**2, fit.nugget**2
    out, shares = np.empty(len(targets)), np.empty(len(targets))
    for q, i in enumerate(targets):
        N = nn[q]
        K = s2 * separable_correlation(
            rows[N][:, None] - rows[N][None], cols[N][:, None] - cols[N][None], fit.lengthscale, nu
        )
        K[np.diag_indices(len(N))] += tau2 + noise[N]
        kx = s2 * separable_correlation(rows[i] - rows[N], cols[i] - cols[N], fit.lengthscale, nu)
        w = np.linalg.solve(K, kx)
        var = s2 + tau2 + noise[i] - w @ kx
        out[q] = (r[i] - w @ r[N]) / np.sqrt(var)
        shares[q] = (noise[i] + np.sum(w**2 * noise[N])) / var
    return (out, shares) if share else out


class TestKriging:
    @pytest.mark.parametrize("n_targets", [1, 13, 700])  # a partial lane group; more than one parallel chunk
    @pytest.mark.parametrize("nu", [0.5, 1.5])  # tabulated SIMD lanes; the generic loop
    def test_equals_dense_solves(self, n_targets, nu):
        rng = np.random.default_rng(n_targets)
        rows, cols = _points(rng, 900, 40, 60)
        n = rows.size
        r = rng.normal(0.0, 0.1, n)
        noise = rng.uniform(1e-5, 1e-3, n)
        fit = PointFit(9.0, 0.2, 0.02, 0.0, 1e-4, n)
        targets = rng.choice(n, n_targets, replace=False)
        nn, _ = neighbours_of(rows, cols, np.ones(n, bool), targets, 12)
        z, share = loo_predict(
            rows, cols, r, noise, targets, nn, outputscale=0.2, nugget=0.02, lengthscale=9.0, nu=nu, stated=noise
        )
        z_ref, share_ref = _kriging_reference(rows, cols, r, noise, fit, targets, nn, nu, share=True)
        np.testing.assert_allclose(z, z_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(share, share_ref, rtol=1e-9, atol=1e-12)
        assert np.all((share > 0) & (share < 1))
        _, half = loo_predict(
            rows, cols, r, noise, targets, nn, outputscale=0.2, nugget=0.02, lengthscale=9.0, nu=nu, stated=noise / 2
        )
        np.testing.assert_allclose(half, share / 2, rtol=1e-12)  # the share of the stated part only
        np.testing.assert_array_equal(
            loo_predict(rows, cols, r, noise, targets, nn, outputscale=0.2, nugget=0.02, lengthscale=9.0, nu=nu), z
        )  # z alone without `stated`

    def test_spans_of_the_image_give_the_same_tables(self):
        """`loo_predict` with the points' spans from their image (`_loo.image_spans`) equals it checking them."""
        rng = np.random.default_rng(12)
        rows, cols = _points(rng, 400, 30, 50)
        image = _loo.neighbour_image(rows, cols)
        assert _loo.image_spans(image) == (np.ptp(rows), np.ptp(cols))
        n = rows.size
        nn, _ = grid_neighbours(rows, cols, np.ones(n, dtype=bool), np.arange(n), 12, image)
        r, noise = rng.standard_normal(n), np.full(n, 1e-3)
        kw = dict(outputscale=0.3, nugget=0.03, lengthscale=7.0, nu=0.5, stated=noise)
        ref = loo_predict(rows, cols, r, noise, np.arange(n), nn, **kw)
        got = loo_predict(rows, cols, r, noise, np.arange(n), nn, spans=_loo.image_spans(image), **kw)
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)

    def test_noise_share_is_a_floor_of_the_mean_squared_zscore(self):
        """With independent noises as stated, E[z^2] = share + (1 - share) x (field calibration): a field drawn
        from the model gives mean z^2 ~ 1; a field with no variation (all residuals from the noise) gives mean
        z^2 ~ the mean share, never less. This is what `local_variance_factor` floors z^2 at."""
        rng = np.random.default_rng(5)
        h, w = 30, 30
        rows, cols = (a.ravel().astype(np.float64) for a in np.mgrid[0:h, 0:w])
        n = rows.size
        noise = np.full(n, 0.01**2)
        fit = PointFit(6.0, 0.05, 0.0, 0.0, 1e-4, n)
        C = 0.05**2 * separable_correlation(rows[:, None] - rows[None], cols[:, None] - cols[None], 6.0, 0.5)
        L = np.linalg.cholesky(C + 1e-12 * np.eye(n))
        field_z2, flat_z2, shares = [], [], []
        for _ in range(20):
            eps = rng.normal(0.0, 0.01, n)
            z, share = loo_zscores(rows, cols, L @ rng.standard_normal(n) + eps, noise, fit, stated=noise)
            flat, _ = loo_zscores(rows, cols, eps, noise, fit, stated=noise)
            field_z2.append(np.mean(z**2))
            flat_z2.append(np.mean(flat**2))
            shares.append(np.mean(share))
        assert 0.85 < np.mean(field_z2) < 1.15
        assert 0.1 < np.mean(shares) < 0.9
        assert abs(np.mean(flat_z2) - np.mean(shares)) < 0.1 * np.mean(shares)

    def test_singular_neighbourhood_is_flagged_in_its_lane_only(self):
        """Two noiseless points on one pixel with no nugget: that neighbourhood's matrix is singular (NaN, solved
        by least squares in `loo_zscores`); the other targets of its lane group are unaffected."""
        rng = np.random.default_rng(11)
        rows, cols = _points(rng, 60, 12, 12)
        rows = np.concatenate([rows, rows[:1]])
        cols = np.concatenate([cols, cols[:1]])  # point n - 1 duplicates point 0
        n = rows.size
        r = rng.normal(0.0, 0.1, n)
        noise = np.zeros(n)
        targets = np.arange(8)
        nn, _ = neighbours_of(rows, cols, np.ones(n, bool), targets, 12)
        z = loo_predict(rows, cols, r, noise, targets, nn, outputscale=0.2, nugget=0.0, lengthscale=9.0, nu=0.5)
        singular = np.array([np.isin(0, nn[q]) and np.isin(n - 1, nn[q]) for q in range(8)])
        assert singular.any() and not singular.all()
        assert np.all(np.isnan(z[singular])) and np.all(np.isfinite(z[~singular]))
        fit = PointFit(9.0, 0.2, 0.0, 0.0, 1e-4, n)
        full = loo_zscores(rows, cols, r, noise, fit)
        assert np.all(np.isfinite(full))
        # noisy points around the noiseless duplicate pair: the least-squares lanes' z and noise share
        noise = rng.uniform(1e-4, 1e-3, n)
        noise[[0, n - 1]] = 0.0
        z, share = loo_zscores(rows, cols, r, noise, fit, only=targets, stated=noise)
        for q in np.flatnonzero(singular):
            N = nn[q]
            K = 0.04 * separable_correlation(
                rows[N][:, None] - rows[N][None], cols[N][:, None] - cols[N][None], 9.0, 0.5
            )
            K[np.diag_indices(len(N))] += noise[N]
            kx = 0.04 * separable_correlation(rows[q] - rows[N], cols[q] - cols[N], 9.0, 0.5)
            wq = np.linalg.lstsq(K, kx, rcond=None)[0]
            var = 0.04 + noise[q] - wq @ kx
            assert z[q] == pytest.approx((r[q] - wq @ r[N]) / np.sqrt(var), rel=1e-6)
            assert share[q] == pytest.approx((noise[q] + np.sum(wq**2 * noise[N])) / var, rel=1e-6)


def _screen_reference(rows, cols, resid, noise, fit, threshold, iterations=3):
    """Screening that recomputes every point's z-score in every round."""
    rejected = np.zeros(resid.size, dtype=bool)
    z = None
    for _ in range(iterations):
        z = loo_zscores(rows, cols, resid, noise, fit, exclude=rejected)
        new = np.abs(z) > threshold
        if np.array_equal(new, rejected):
            break
        rejected = new
    return rejected, z


class TestScreening:
    @pytest.mark.parametrize("seed", range(3))
    def test_rounds_recomputing_only_the_points_near_a_change_equal_full_rounds(self, seed):
        rng = np.random.default_rng(seed)
        rows, cols = _points(rng, 1500, 50, 80)
        n = rows.size
        resid = 0.1 * np.sin(rows / 9.0) * np.cos(cols / 13.0) + rng.normal(0.0, 0.02, n)
        bad = rng.choice(n, n // 20, replace=False)
        resid[bad] += rng.choice([-1.0, 0.7, 1.5], bad.size)
        noise = np.full(n, 1e-4)
        fit = PointFit(16.0, 0.2, 0.02, 0.0, 1e-4, n)
        _, rejected, z, _ = screen_points(rows, cols, resid, noise, threshold=3.5, start=fit)
        ref_rejected, ref_z = _screen_reference(rows, cols, resid, noise, fit, 3.5)
        np.testing.assert_array_equal(rejected, ref_rejected)
        np.testing.assert_allclose(z, ref_z, rtol=1e-12, atol=1e-12)
        assert rejected[bad].mean() > 0.8

    def test_a_search_started_before_gives_the_same_screen(self):
        """`start_screen_search` (the first round's search on a second thread) changes nothing in `screen_points`;
        it is None where the screen would not search (no threshold, few points, off the pixel grid), and a search
        of other points is refused."""
        rng = np.random.default_rng(3)
        rows, cols = _points(rng, 1500, 50, 80)
        n = rows.size
        resid = 0.1 * np.sin(rows / 9.0) + rng.normal(0.0, 0.02, n)
        resid[rng.choice(n, 40, replace=False)] += 1.0
        noise = np.full(n, 1e-4)
        fit = PointFit(16.0, 0.2, 0.02, 0.0, 1e-4, n)
        ref = screen_points(rows, cols, resid, noise, threshold=3.5, start=fit, raise_outputscale=True)
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            assert start_screen_search(rows, cols) is None  # one thread: nothing to share the search with
        finally:
            numba.set_num_threads(threads)
        if threads < 2:
            pytest.skip("numba has one thread: no search is started")
        search = start_screen_search(rows, cols, ScreenConfig(outlier_threshold=3.5))
        assert search is not None
        got = screen_points(rows, cols, resid, noise, threshold=3.5, start=fit, raise_outputscale=True, search=search)
        assert got.fit == ref.fit and got.rejected.any()
        for name in ("rejected", "zscores", "noise_share"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
        assert start_screen_search(rows, cols, ScreenConfig(outlier_threshold=None)) is None
        assert start_screen_search(rows[:400], cols[:400]) is None  # one chunk: not split
        assert start_screen_search(rows + 0.5, cols) is None
        other = start_screen_search(rows[:-1], cols[:-1])
        with pytest.raises(InvalidInputError, match="search"):
            screen_points(rows, cols, resid, noise, threshold=3.5, start=fit, search=other)
        other.result()

    @pytest.mark.parametrize("pairs", [0, 1 << 30])  # a k-d tree off the grid; every pair
    def test_distance_to_sources_grid_and_tree_agree(self, pairs, monkeypatch):
        monkeypatch.setattr(points, "DISTANCE_PAIRS", pairs)
        rng = np.random.default_rng(5)
        rows, cols = _points(rng, 500, 40, 70)
        sources = rng.choice(rows.size, 9, replace=False)
        d = _distance_to(rows, cols, sources, np.full(rows.size, np.inf))
        ref = np.min(np.abs(rows[:, None] - rows[sources]) + np.abs(cols[:, None] - cols[sources]), axis=1)
        np.testing.assert_array_equal(d, ref)
        image = _loo.neighbour_image(rows, cols)  # the transform on the image's cells
        np.testing.assert_array_equal(_distance_to(rows, cols, sources, np.full(rows.size, np.inf), image), ref)
        reach = np.full(rows.size, 6.0)
        d_off = _distance_to(rows + 0.5, cols, sources, reach)  # off the pixel grid: inf beyond 6 from the tree
        np.testing.assert_array_equal(d_off[ref <= 6], ref[ref <= 6])
        assert np.all(np.isinf(d_off[ref > 6]) if pairs == 0 else d_off == ref)
