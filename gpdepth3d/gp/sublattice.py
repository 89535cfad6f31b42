"""The field's detail below a coarse lattice, kriged locally from the points' residuals.

When the log-residual GP (`gpdepth3d.completion.complete`) runs on every k-th pixel (a lattice of
stride k), its posterior is the exact read-out of the lattice nodes: between the nodes it only knows
the field's conditional prior, and a point inside a cell enters at its node with that variance
added to its noise. What the lattice misses is the sub-lattice residual

    e(x) = g(x) - E[g(x) | g at the nodes],

which for the separable exponential kernel (nu = 0.5, k(x, x') = s^2 rho_r rho_c) has the prior
covariance, per axis with E_a the 1-D residual covariance given that axis' nodes (an
Ornstein-Uhlenbeck bridge: zero unless both coordinates lie between the same two nodes),

    C_e(x, x') = s^2 (rho_r E_c + rho_c E_r - E_r E_c)

(from rho_r rho_c minus the product of the explained parts rho_a - E_a). This module adds the
kriging of e at each output pixel from the points in a window of GP-grid pixels around its lattice
cell (the cell and `window_reach` pixels on each side; one factorisation per cell), given their
residuals against the lattice posterior, r_i = y_i - E_L[g(x_i)], with their own noise (the two-step "full-scale approximation": a lattice for the long range, a
tapered local process for the rest; Sang & Huang 2012):

    E[g(x)] += w' r,   Var[g(x)] -= w' c,   w = (C_e[pts, pts] + N)^-1 c,   c = C_e[pts, x].

The window is the taper (C_e's correlation along a row or column of cells beyond it is dropped). Its cost
grows with its points (n^3 per cell) and the output pixels per cell, so `gpdepth3d.completion` krigs at the
GP grid's own pixels and resizes the result to a finer output. The effect on accuracy and time is measured
(see docs/results.md).

Coordinates are GP-grid pixels (pixel centres at integers), the lattice nodes at k j + (k - 1) / 2.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

from ..errors import InvalidInputError, ShapeError, describe
from ._cholesky import cholesky_in_place
from .kernels import smoothness_code, unit_correlation
from .model import LatticeConfig


def window_reach(stride: int) -> int:
    """Pixels of the GP grid around a lattice cell of stride k whose points krige its detail (the taper): k // 2 + 1.

    A 6 x 6-pixel window for stride 2 and 10 x 10 for stride 4 (their effect: see docs/results.md).
    """
    return int(stride) // 2 + 1


_EXPONENTIAL = smoothness_code(0.5)  # the bridge below is the exponential kernel's Markov conditioning


@njit(cache=True, nogil=True)
def _rho(r):  # pragma: no cover - compiled
    """The exponential kernel's correlation at the scaled distance r = |d| / l (`gpdepth3d.gp.kernels`)."""
    return unit_correlation(r, _EXPONENTIAL)


@njit(cache=True, nogil=True)
def _bridge(x, y, k, n_nodes, inv_l):  # pragma: no cover - compiled
    """1-D residual covariance E(x, y) of the unit exponential field given nodes k j + (k - 1) / 2, j < n_nodes."""
    off = 0.5 * (k - 1)
    jx = min(max(math.floor((x - off) / k), -1), n_nodes - 1)
    jy = min(max(math.floor((y - off) / k), -1), n_nodes - 1)
    rho = _rho(abs(x - y) * inv_l)
    if jx != jy:
        return 0.0
    if jx < 0 or jx == n_nodes - 1:  # outside the first or last node: one node conditions
        a = off if jx < 0 else off + k * (n_nodes - 1)
        return rho - _rho(abs(x - a) * inv_l) * _rho(abs(y - a) * inv_l)
    a = off + k * jx
    b = a + k
    rab = _rho(k * inv_l)
    rax, rbx = _rho(abs(x - a) * inv_l), _rho(abs(x - b) * inv_l)
    ray, rby = _rho(abs(y - a) * inv_l), _rho(abs(y - b) * inv_l)
    explained = (rax * ray + rbx * rby - rab * (rax * rby + rbx * ray)) / (1.0 - rab * rab)
    return rho - explained


@njit(cache=True, nogil=True)
def _tables(targets, centres, k, n_nodes, inv_l, reach):  # pragma: no cover - compiled
    """(E, rho) of each target against the integer coordinates centre + d, d in [-reach, reach]."""
    m = targets.shape[0]
    E = np.empty((m, 2 * reach + 1))
    R = np.empty((m, 2 * reach + 1))
    for i in range(m):
        for d in range(-reach, reach + 1):
            y = float(centres[i] + d)
            E[i, d + reach] = _bridge(targets[i], y, k, n_nodes, inv_l)
            R[i, d + reach] = _rho(abs(targets[i] - y) * inv_l)
    return E, R


@njit(cache=True, nogil=True, parallel=True)
def _krige(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, index, pt_r,
           pt_c, resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """`_krige_row` for the rows of cells ``cell_rows``, in parallel."""
    for ii in prange(cell_rows.shape[0]):  # rows of cells in parallel, each with its own buffers
        _krige_row(cell_rows[ii], row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, index,
                   pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred)


@njit(cache=True, nogil=True)
def _krige_serial(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, index,
                  pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """`_krige` on the calling thread (few points: waking the worker threads costs more than their work)."""
    for ii in range(cell_rows.shape[0]):
        _krige_row(cell_rows[ii], row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, index,
                   pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred)


#: Fewer points than this are kriged on the calling thread (`_krige_serial`).
SERIAL_POINTS = 1024


@njit(cache=True, nogil=True)
def _krige_row(ci, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, index, pt_r, pt_c,
               resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """The cells of row ci: per cell one factorisation of its window's points (at most max_points), then every
    output pixel in it (four at a time from `BY_FOUR` points on, `_pixels_by_four`)."""
    h, w = index.shape
    m = resid.shape[1]
    side = k + 2 * reach
    size = side * side
    span = Rr_p.shape[0] // 2
    if row_start[ci] < row_start[ci + 1]:
        ids = np.empty(size, np.int64)
        dist = np.empty(size, np.int64)
        count = np.empty(4 * side + 2, np.int64)
        picked = np.empty(size, np.int64)
        A = np.empty((size, size))
        y = np.empty((size, m))
        c = np.empty(size)
        dinv = np.empty(size)
        V = np.empty((size, 4))
        for cj in range(col_start.shape[0] - 1):
            if col_start[cj] == col_start[cj + 1]:
                continue
            n = 0
            for rr in range(max(k * ci - reach, 0), min(k * ci + k + reach, h)):
                for cc_ in range(max(k * cj - reach, 0), min(k * cj + k + reach, w)):
                    p = index[rr, cc_]
                    if p >= 0:
                        ids[n] = p
                        n += 1
            if n == 0:
                continue
            if n > max_points:  # the max_points nearest the cell's centre (L1; ties: the earlier in the window)
                _nearest(ids, n, max_points, 2 * k * ci + k - 1, 2 * k * cj + k - 1, pt_r, pt_c, dist, count, picked)
                n = max_points
            for a in range(n):
                pa = ids[a]
                for b in range(a + 1):
                    pb = ids[b]
                    du = pt_r[pb] - pt_r[pa] + span
                    dv = pt_c[pb] - pt_c[pa] + span
                    er, rr_ = Er_p[pt_r[pa], du], Rr_p[du]
                    ec, rc = Ec_p[pt_c[pa], dv], Rc_p[dv]
                    A[a, b] = s2 * (rr_ * ec + rc * er - er * ec)
                A[a, a] += noise[pa]
            if not cholesky_in_place(A, n):  # numerically singular: leave this cell uncorrected
                continue
            for a in range(n):
                dinv[a] = 1.0 / A[a, a]
            for a in range(n):  # y = L^-1 r, three right-hand sides at a time (independent sums in flight)
                q = 0
                while q + 2 < m:
                    s, s_1, s_2 = resid[ids[a], q], resid[ids[a], q + 1], resid[ids[a], q + 2]
                    for t in range(a):
                        x = A[a, t]
                        s -= x * y[t, q]
                        s_1 -= x * y[t, q + 1]
                        s_2 -= x * y[t, q + 2]
                    y[a, q], y[a, q + 1], y[a, q + 2] = s * dinv[a], s_1 * dinv[a], s_2 * dinv[a]
                    q += 3
                for q in range(q, m):
                    s = resid[ids[a], q]
                    for t in range(a):
                        s -= A[a, t] * y[t, q]
                    y[a, q] = s * dinv[a]
            if n >= BY_FOUR:
                _pixels_by_four(ids, n, A, dinv, y, row_start[ci], row_start[ci + 1], col_start[cj], col_start[cj + 1],
                                cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pt_r, pt_c, s2, span, V, corr, vred)
                continue
            for i in range(row_start[ci], row_start[ci + 1]):
                for j in range(col_start[cj], col_start[cj + 1]):
                    red = 0.0
                    for a in range(n):  # v = L^-1 c, c = C_e(points, x)
                        pa = ids[a]
                        dr = pt_r[pa] - cr[i] + span
                        dc = pt_c[pa] - cc[j] + span
                        er, rr_ = Er_o[i, dr], Rr_o[i, dr]
                        ec, rc = Ec_o[j, dc], Rc_o[j, dc]
                        s = s2 * (rr_ * ec + rc * er - er * ec)
                        for t in range(a):
                            s -= A[a, t] * c[t]
                        c[a] = s * dinv[a]
                        red += c[a] * c[a]
                    vred[i, j] = red
                    for q in range(m):
                        s = 0.0
                        for a in range(n):
                            s += c[a] * y[a, q]
                        corr[q, i, j] = s


#: Window points from which `_krige_row` computes a cell's output pixels four at a time (`_pixels_by_four`); below,
#: the call costs more than it saves. The results are the same.
BY_FOUR = 8


@njit(cache=True, nogil=True)
def _nearest(ids, n, keep, centre_r2, centre_c2, pt_r, pt_c, dist, count, picked):  # pragma: no cover - compiled
    """ids[:keep]: the ``keep`` of the points ids[:n] nearest the cell's centre (twice its coordinates: centre_r2,
    centre_c2; L1; ties: the earlier in ids), by a counting sort (twice an L1 distance in the window < count.size - 1)."""
    count[:] = 0
    for a in range(n):
        dist[a] = abs(2 * pt_r[ids[a]] - centre_r2) + abs(2 * pt_c[ids[a]] - centre_c2)
        count[dist[a] + 1] += 1
    for d in range(1, count.size):
        count[d] += count[d - 1]
    for a in range(n):
        picked[count[dist[a]]] = ids[a]
        count[dist[a]] += 1
    for a in range(keep):
        ids[a] = picked[a]


@njit(cache=True, nogil=True)
def _pixels_by_four(ids, n, A, dinv, y, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pt_r, pt_c, s2, span, V, corr,
                    vred):  # pragma: no cover - compiled
    """The output pixels i0 <= i < i1, j0 <= j < j1 of one cell from its window's points ids[:n] (L in A's lower
    triangle, 1 / diag(L) in ``dinv``, y = L^-1 r): v = L^-1 c, vred = v . v and corr = v . y, four pixels at a
    time: four independent sums in flight, each pixel's arithmetic in the order of `_krige_row`'s one pixel.
    V: (n, 4) work array (a pixel past the last repeats it; its results are dropped)."""
    m = y.shape[1]
    nj = j1 - j0
    npix = (i1 - i0) * nj
    for p0 in range(0, npix, 4):
        i_0, j_0 = i0 + p0 // nj, j0 + p0 % nj
        i_1, j_1 = i0 + min(p0 + 1, npix - 1) // nj, j0 + min(p0 + 1, npix - 1) % nj
        i_2, j_2 = i0 + min(p0 + 2, npix - 1) // nj, j0 + min(p0 + 2, npix - 1) % nj
        i_3, j_3 = i0 + min(p0 + 3, npix - 1) // nj, j0 + min(p0 + 3, npix - 1) % nj
        r0 = r1 = r2 = r3 = 0.0
        for a in range(n):
            pa = ids[a]
            # c = C_e(points, x) as `_krige_row` computes it, for each of the four pixels
            dr, dc = pt_r[pa] - cr[i_0] + span, pt_c[pa] - cc[j_0] + span
            er, rr_, ec, rc = Er_o[i_0, dr], Rr_o[i_0, dr], Ec_o[j_0, dc], Rc_o[j_0, dc]
            u0 = s2 * (rr_ * ec + rc * er - er * ec)
            dr, dc = pt_r[pa] - cr[i_1] + span, pt_c[pa] - cc[j_1] + span
            er, rr_, ec, rc = Er_o[i_1, dr], Rr_o[i_1, dr], Ec_o[j_1, dc], Rc_o[j_1, dc]
            u1 = s2 * (rr_ * ec + rc * er - er * ec)
            dr, dc = pt_r[pa] - cr[i_2] + span, pt_c[pa] - cc[j_2] + span
            er, rr_, ec, rc = Er_o[i_2, dr], Rr_o[i_2, dr], Ec_o[j_2, dc], Rc_o[j_2, dc]
            u2 = s2 * (rr_ * ec + rc * er - er * ec)
            dr, dc = pt_r[pa] - cr[i_3] + span, pt_c[pa] - cc[j_3] + span
            er, rr_, ec, rc = Er_o[i_3, dr], Rr_o[i_3, dr], Ec_o[j_3, dc], Rc_o[j_3, dc]
            u3 = s2 * (rr_ * ec + rc * er - er * ec)
            for t in range(a):  # v = L^-1 c
                x = A[a, t]
                u0 -= x * V[t, 0]
                u1 -= x * V[t, 1]
                u2 -= x * V[t, 2]
                u3 -= x * V[t, 3]
            d = dinv[a]
            V[a, 0], V[a, 1], V[a, 2], V[a, 3] = u0 * d, u1 * d, u2 * d, u3 * d
            r0 += V[a, 0] * V[a, 0]
            r1 += V[a, 1] * V[a, 1]
            r2 += V[a, 2] * V[a, 2]
            r3 += V[a, 3] * V[a, 3]
        for lane, red in enumerate((r0, r1, r2, r3)):
            if p0 + lane < npix:
                i, j = i0 + (p0 + lane) // nj, j0 + (p0 + lane) % nj
                vred[i, j] = red
                for q in range(m):
                    s = 0.0
                    for a in range(n):
                        s += V[a, lane] * y[a, q]
                    corr[q, i, j] = s


def sublattice_kriging(
    out_rows: np.ndarray,
    out_cols: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    residuals: np.ndarray,
    noise: np.ndarray,
    shape: tuple[int, int],
    *,
    stride: int,
    lengthscale: float,
    outputscale: float,
    max_window_points: int = LatticeConfig.max_window_points,
) -> tuple[np.ndarray, np.ndarray]:
    """The sub-lattice kriging of residuals at an output tensor grid (see the module docstring).

    Args:
        out_rows, out_cols: (Ho,), (Wo,) output coordinates in GP-grid pixels.
        rows, cols: (n,) integer GP-grid pixels of the points, at most one point per pixel.
        residuals: (n,) or (n, m) residuals of the points against the lattice posterior (one
            column per right-hand side; all share the kriging weights).
        noise: (n,) the points' noise variances (>= 0; a cell whose window's system is singular, e.g. a
            noise-free point on a lattice node, is left uncorrected).
        shape: (h, w) of the GP grid.
        stride: The lattice's stride k >= 2 (nodes at k j + (k - 1) / 2).
        lengthscale: Length scale of the exponential kernel, GP-grid pixels.
        outputscale: Its standard deviation s.
        max_window_points: Most points of one cell's window (the nearest to its centre); it bounds the
            cost of coarse lattices (stride k: (k + 2 window_reach(k))^2 pixels per window).

    Returns:
        corrections (m, Ho, Wo) (``(Ho, Wo)`` for 1-D ``residuals``) to add to the posterior
        mean(s), and the variance reduction (Ho, Wo) to subtract from the posterior variance.

    Raises:
        InvalidInputError: a stride below 2, non-positive scales, negative noise, two points on one pixel.
        ShapeError: arrays of mismatched lengths, or points outside the grid.
    """
    h, w = (int(x) for x in shape)
    k = int(stride)
    if k < 2:
        raise InvalidInputError("stride", "an integer >= 2", describe(stride))
    if not (lengthscale > 0 and outputscale > 0):
        raise InvalidInputError("lengthscale, outputscale", "positive scales", f"{lengthscale!r}, {outputscale!r}")
    rows = np.asarray(rows, dtype=np.int64)
    cols = np.asarray(cols, dtype=np.int64)
    res = np.asarray(residuals, dtype=np.float64)
    one = res.ndim == 1
    res = np.ascontiguousarray(res[:, None] if one else res)
    noise = np.ascontiguousarray(noise, dtype=np.float64)
    n = rows.shape[0]
    if cols.shape != (n,) or res.shape[0] != n or noise.shape != (n,):
        raise ShapeError("rows, cols, residuals, noise", f"{n} points each", f"{cols.shape}, {res.shape}, {noise.shape}")
    if n and (rows.min() < 0 or rows.max() >= h or cols.min() < 0 or cols.max() >= w):
        raise ShapeError("rows, cols", f"pixels of the {h} x {w} grid", "points outside it")
    if n and not np.all(np.isfinite(noise) & (noise >= 0)):
        raise InvalidInputError("noise", "finite variances >= 0", "negative or non-finite values")
    index = np.full((h, w), -1, dtype=np.int64)
    index[rows, cols] = np.arange(n)
    if np.count_nonzero(index >= 0) != n:
        raise InvalidInputError("rows, cols", "at most one point per pixel", "two points on one pixel")
    out_rows = np.asarray(out_rows, dtype=np.float64)
    out_cols = np.asarray(out_cols, dtype=np.float64)
    reach = window_reach(k)
    inv_l = 1.0 / float(lengthscale)
    hl, wl = -(-h // k), -(-w // k)
    cr = np.clip(np.rint(out_rows), 0, h - 1).astype(np.int64)
    cc = np.clip(np.rint(out_cols), 0, w - 1).astype(np.int64)
    if np.any(np.diff(cr) < 0) or np.any(np.diff(cc) < 0):
        raise InvalidInputError("out_rows, out_cols", "increasing coordinates", "unsorted ones")
    # output pixels per lattice cell (rows, columns): the cell of the GP pixel each is nearest to
    row_start = np.searchsorted(cr // k, np.arange(hl + 1)).astype(np.int64)
    col_start = np.searchsorted(cc // k, np.arange(wl + 1)).astype(np.int64)
    span = k + 2 * reach  # farthest offset between a window's pixel and a pixel of its cell, or two of its pixels
    Er_o, Rr_o = _tables(out_rows, cr, k, hl, inv_l, span)
    Ec_o, Rc_o = _tables(out_cols, cc, k, wl, inv_l, span)
    Er_p, Rr_p = _tables(np.arange(h, dtype=np.float64), np.arange(h), k, hl, inv_l, span)
    Ec_p, Rc_p = _tables(np.arange(w, dtype=np.float64), np.arange(w), k, wl, inv_l, span)
    corr = np.zeros((res.shape[1], out_rows.size, out_cols.size))
    vred = np.zeros((out_rows.size, out_cols.size))
    if n:
        # prange hands each thread one contiguous share of the rows of cells; the points often fill only part of
        # the image (the LiDAR its lower two thirds), so each share takes every t-th row, not one block of rows
        threads = get_num_threads() if n >= SERIAL_POINTS else 1
        cell_rows = np.concatenate([np.arange(t, hl, threads) for t in range(threads)]).astype(np.int64)
        kernel = _krige if threads > 1 else _krige_serial
        kernel(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p[0], Ec_p, Rc_p[0], index,
               rows, cols, res, noise, float(outputscale) ** 2, k, reach, int(max_window_points), corr, vred)
    return (corr[0] if one else corr), vred
