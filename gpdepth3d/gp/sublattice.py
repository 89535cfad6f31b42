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
from numba import get_num_threads, njit, prange, uint64

from ..errors import InvalidInputError, ShapeError, describe
from ._cholesky import cholesky_dots_in_place
from .compile_wait import ready as compiled_ahead
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
def _tables(targets, centres, k, n_nodes, inv_l, reach):  # pragma: no cover - compiled
    """(E, rho) of each target x against the integer coordinates y = centre + d, d in [-reach, reach]: rho the unit
    exponential correlation, E(x, y) the 1-D residual covariance given nodes k j + (k - 1) / 2, j < n_nodes (an
    Ornstein-Uhlenbeck bridge: zero unless x and y lie between the same two nodes, or beyond the same end node).
    The target's own correlations with its nodes are computed once per target."""
    m = targets.shape[0]
    E = np.empty((m, 2 * reach + 1))
    R = np.empty((m, 2 * reach + 1))
    off = 0.5 * (k - 1)
    rab = _rho(k * inv_l)
    for i in range(m):
        x = targets[i]
        jx = min(max(math.floor((x - off) / k), -1), n_nodes - 1)
        edge = jx < 0 or jx == n_nodes - 1  # outside the first or last node: one node conditions
        a = (off if jx < 0 else off + k * (n_nodes - 1)) if edge else off + k * jx
        b = a + k
        rax, rbx = _rho(abs(x - a) * inv_l), _rho(abs(x - b) * inv_l)
        for d in range(-reach, reach + 1):
            y = float(centres[i] + d)
            rho = _rho(abs(x - y) * inv_l)
            R[i, d + reach] = rho
            jy = min(max(math.floor((y - off) / k), -1), n_nodes - 1)
            if jx != jy:
                E[i, d + reach] = 0.0
            elif edge:
                E[i, d + reach] = rho - rax * _rho(abs(y - a) * inv_l)
            else:
                ray, rby = _rho(abs(y - a) * inv_l), _rho(abs(y - b) * inv_l)
                explained = (rax * ray + rbx * rby - rab * (rax * rby + rbx * ray)) / (1.0 - rab * rab)
                E[i, d + reach] = rho - explained
    return E, R


@njit(cache=True, nogil=True, parallel=True)
def _krige(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, row_ptr, by_row,
           pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """`_krige_row` for the rows of cells ``cell_rows``, in parallel."""
    for ii in prange(cell_rows.shape[0]):  # rows of cells in parallel, each with its own buffers
        _krige_row(cell_rows[ii], row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p,
                   row_ptr, by_row, pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred)


@njit(cache=True, nogil=True)
def _krige_serial(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, row_ptr,
                  by_row, pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """`_krige` on the calling thread (few points: waking the worker threads costs more than their work)."""
    for ii in range(cell_rows.shape[0]):
        _krige_row(cell_rows[ii], row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p,
                   row_ptr, by_row, pt_r, pt_c, resid, noise, s2, k, reach, max_points, corr, vred)


#: Fewer points than this are kriged on the calling thread (`_krige_serial`).
SERIAL_POINTS = 1024


@njit(cache=True, nogil=True)
def _krige_row(ci, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p, Ec_p, Rc_p, row_ptr, by_row, pt_r,
               pt_c, resid, noise, s2, k, reach, max_points, corr, vred):  # pragma: no cover - compiled
    """The cells of row ci: per cell one factorisation of its window's points (at most max_points, `_window`;
    `cholesky_dots_in_place`, vectorised dot products, so equal to the plain loop's factor to rounding only), then
    every output pixel in it (`_cell_pixels`; one at a time below `BY_LANES` points, `_cell_pixels_few`, written
    out for at most four, `_cell_pixels_four`)."""
    h = row_ptr.shape[0] - 1
    m = resid.shape[1]
    side = k + 2 * reach
    size = side * side
    span = Rr_p.shape[0] // 2
    if row_start[ci] == row_start[ci + 1]:
        return
    r0, r1 = max(k * ci - reach, 0), min(k * ci + k + reach, h)
    cursor = row_ptr[r0:r1].copy()  # per window row: its first point at or right of the window (`_window`)
    ids = np.empty(size, np.int64)
    pr = np.empty(size, np.int64)
    pc = np.empty(size, np.int64)
    dist = np.empty(size, np.int64)
    count = np.empty(4 * side + 2, np.int64)
    picked = np.empty(size, np.int64)
    A = np.empty((size, size))
    dinv = np.empty(size)
    widest = 0  # most output columns of a cell
    for cj in range(col_start.shape[0] - 1):
        widest = max(widest, col_start[cj + 1] - col_start[cj])
    V = np.empty((size, _lanes((row_start[ci + 1] - row_start[ci]) * widest + m)))
    acc = np.empty(max(V.shape[1], size))
    F = np.empty((2, widest))
    for cj in range(col_start.shape[0] - 1):
        if col_start[cj] == col_start[cj + 1]:
            continue
        n = _window(r0, k * cj - reach, k * cj + k + reach, row_ptr, by_row, pt_c, cursor, ids)
        if n == 0:
            continue
        if n > max_points:  # the max_points nearest the cell's centre (L1; ties: the earlier in the window)
            _nearest(ids, n, max_points, 2 * k * ci + k - 1, 2 * k * cj + k - 1, pt_r, pt_c, dist, count, picked)
            n = max_points
        for a in range(n):
            pa = uint64(ids[a])
            pr[a], pc[a] = pt_r[pa], pt_c[pa]
        _window_covariance(n, pr, pc, ids, noise, Er_p, Rr_p, Ec_p, Rc_p, s2, span, A)
        if not cholesky_dots_in_place(A, n):  # numerically singular: leave this cell uncorrected
            continue
        for a in range(n):
            dinv[a] = 1.0 / A[a, a]
        i0, i1, j0, j1 = row_start[ci], row_start[ci + 1], col_start[cj], col_start[cj + 1]
        if n >= BY_LANES:
            _cell_pixels(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span, V,
                         acc, F, corr, vred)
        elif n <= 4:
            _cell_pixels_four(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span,
                              V, corr, vred)
        else:
            _cell_pixels_few(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span,
                             V, acc, corr, vred)


#: Window points from which `_krige_row` computes a cell's output pixels side by side (`_cell_pixels`); below,
#: one at a time (`_cell_pixels_few`). The results are the same.
BY_LANES = 8


@njit(cache=True, nogil=True)
def _window(r0, c0, c1, row_ptr, by_row, pt_c, cursor, ids):  # pragma: no cover - compiled
    """The points of the window's rows r0 + u (u < cursor.size), columns c0 <= c < c1, into ids, row by row and
    left to right (the order of a scan of the window's pixels); their number.

    by_row: the point ids ordered by row, then column; row_ptr: each row's first position in it. cursor[u]: a
    position in row r0 + u at or left of its first point in the window, moved forwards (the windows of a row
    of cells are visited left to right, so each row's points are passed over once).
    """
    n = 0
    for u in range(cursor.shape[0]):
        q, end = cursor[u], row_ptr[r0 + u + 1]
        while q < end and pt_c[uint64(by_row[uint64(q)])] < c0:  # unsigned: see `_window_covariance`
            q += 1
        cursor[u] = q
        while q < end and pt_c[uint64(by_row[uint64(q)])] < c1:
            ids[n] = by_row[uint64(q)]
            n += 1
            q += 1
    return n


@njit(cache=True, nogil=True)
def _window_covariance(n, pr, pc, ids, noise, Er_p, Rr_p, Ec_p, Rc_p, s2, span, A):  # pragma: no cover - compiled
    """A[:n, :n]'s lower triangle: C_e between the window's points (rows pr, columns pc) plus their noise.

    The tables' offsets are >= 0 by construction; as unsigned integers they index without numba's check for
    negative indices (which the loop pays for at every entry otherwise)."""
    for a in range(n):
        Era, Eca, Aa = Er_p[pr[a]], Ec_p[pc[a]], A[a]
        off_r, off_c = span - pr[a], span - pc[a]
        for b in range(a + 1):
            du = uint64(pr[b] + off_r)
            dv = uint64(pc[b] + off_c)
            er, rr_ = Era[du], Rr_p[du]
            ec, rc = Eca[dv], Rc_p[dv]
            Aa[b] = s2 * (rr_ * ec + rc * er - er * ec)
        A[a, a] += noise[ids[a]]


@njit(cache=True, nogil=True, inline="always")
def _residual_solve(ids, n, A, dinv, resid, y):  # pragma: no cover - compiled
    """y = L^-1 r for the window's points ``ids[:n]`` (L in A's lower triangle, 1 / diag(L) in ``dinv``): each
    point's residual right-hand sides, one at a time (inlined into the per-pixel paths of few points)."""
    for a in range(n):
        pa = uint64(ids[a])
        for q in range(resid.shape[1]):
            s = resid[pa, q]
            for t in range(a):
                s -= A[a, t] * y[t, q]
            y[a, q] = s * dinv[a]


@njit(cache=True, nogil=True)
def _cell_pixels_few(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span, y, c,
                     corr, vred):  # pragma: no cover - compiled
    """`_cell_pixels` one output pixel at a time (few points: the lanes would cost more than they save); y, c:
    work arrays of at least (n, m) and n."""
    m = resid.shape[1]
    _residual_solve(ids, n, A, dinv, resid, y)
    for i_ in range(i0, i1):
        i = uint64(i_)  # indices >= 0 as unsigned integers: no check for negative ones (`_window_covariance`)
        for j_ in range(j0, j1):
            j = uint64(j_)
            red = 0.0
            for a in range(n):  # v = L^-1 c, c = C_e(points, x)
                dr = uint64(pr[a] + span - cr[i])
                dc = uint64(pc[a] + span - cc[j])
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


@njit(cache=True, nogil=True, inline="always")
def _cell_pixels_four(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span, y,
                      corr, vred):  # pragma: no cover - compiled
    """`_cell_pixels_few` for n <= 4 points written out for four (at a few points the loops' overhead is most of the
    work); inlined into `_krige_row`, as a call would pass every array's fields and count its references.

    The missing points are padded with copies of the first whose rows of L and 1 / L[a, a] are zero (A and dinv hold
    at least four rows): they add exact zeros, so the sums are those of `_cell_pixels_few`. No branches but the
    loops (they keep numba from pruning the arrays' reference counting). y: a work array of at least (4, m).
    """
    m = resid.shape[1]
    _residual_solve(ids, n, A, dinv, resid, y)
    for a in range(n, 4):  # the padding
        pr[a], pc[a], dinv[a] = pr[0], pc[0], 0.0
        for t in range(a):
            A[a, t] = 0.0
        for q in range(m):
            y[a, q] = 0.0
    d0, d1, d2, d3 = dinv[0], dinv[1], dinv[2], dinv[3]
    l10, l20, l21, l30, l31, l32 = A[1, 0], A[2, 0], A[2, 1], A[3, 0], A[3, 1], A[3, 2]
    for i_ in range(i0, i1):
        i = uint64(i_)  # indices >= 0 as unsigned integers: no check for negative ones (`_window_covariance`)
        o = span - cr[i]
        u0, u1, u2, u3 = uint64(pr[0] + o), uint64(pr[1] + o), uint64(pr[2] + o), uint64(pr[3] + o)
        er0, rr0, er1, rr1 = Er_o[i, u0], Rr_o[i, u0], Er_o[i, u1], Rr_o[i, u1]
        er2, rr2, er3, rr3 = Er_o[i, u2], Rr_o[i, u2], Er_o[i, u3], Rr_o[i, u3]
        for j_ in range(j0, j1):
            j = uint64(j_)
            o = span - cc[j]
            w0, w1, w2, w3 = uint64(pc[0] + o), uint64(pc[1] + o), uint64(pc[2] + o), uint64(pc[3] + o)
            ec, rc = Ec_o[j, w0], Rc_o[j, w0]
            v0 = s2 * (rr0 * ec + rc * er0 - er0 * ec) * d0
            ec, rc = Ec_o[j, w1], Rc_o[j, w1]
            v1 = (s2 * (rr1 * ec + rc * er1 - er1 * ec) - l10 * v0) * d1
            ec, rc = Ec_o[j, w2], Rc_o[j, w2]
            v2 = (s2 * (rr2 * ec + rc * er2 - er2 * ec) - l20 * v0 - l21 * v1) * d2
            ec, rc = Ec_o[j, w3], Rc_o[j, w3]
            v3 = (s2 * (rr3 * ec + rc * er3 - er3 * ec) - l30 * v0 - l31 * v1 - l32 * v2) * d3
            vred[i, j] = v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3
            for q in range(m):
                corr[q, i, j] = v0 * y[0, q] + v1 * y[1, q] + v2 * y[2, q] + v3 * y[3, q]


@njit(cache=True, nogil=True)
def _nearest(ids, n, keep, centre_r2, centre_c2, pt_r, pt_c, dist, count, picked):  # pragma: no cover - compiled
    """ids[:keep]: the ``keep`` of the points ids[:n] nearest the cell's centre (twice its coordinates: centre_r2,
    centre_c2; L1; ties: the earlier in ids), by a counting sort (twice an L1 distance in the window < count.size - 1)."""
    count[:] = 0
    for a in range(n):
        pa = uint64(ids[a])  # unsigned: see `_window_covariance`
        dist[a] = abs(2 * pt_r[pa] - centre_r2) + abs(2 * pt_c[pa] - centre_c2)
        count[dist[a] + 1] += 1
    for d in range(1, count.size):
        count[d] += count[d - 1]
    for a in range(n):
        picked[count[dist[a]]] = ids[a]
        count[dist[a]] += 1
    for a in range(keep):
        ids[a] = picked[a]


@njit(cache=True, nogil=True)
def _scatter(values, i0, i1, j0, j1, out):  # pragma: no cover - compiled
    """out[i0:i1, j0:j1] = values, row by row."""
    nj = j1 - j0
    for i in range(i1 - i0):
        row = out[uint64(i0 + i)]
        for j in range(nj):
            row[uint64(j0 + j)] = values[i * nj + j]


@njit(cache=True, nogil=True)
def _lanes(count):  # pragma: no cover - compiled
    """``count`` rounded up to a multiple of four: the columns of `_cell_pixels`' work array."""
    return (count + 3) // 4 * 4


@njit(cache=True, nogil=True)
def _cell_pixels(ids, n, A, dinv, resid, i0, i1, j0, j1, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, pr, pc, s2, span, V, acc, F,
                 corr, vred):  # pragma: no cover - compiled
    """The output pixels i0 <= i < i1, j0 <= j < j1 of one cell from its window's points ids[:n] (L in A's lower
    triangle, 1 / diag(L) in ``dinv``): v = L^-1 c and y = L^-1 r in one forward solve, its right-hand sides side by
    side in V's columns (the pixels' c, then the residuals r, then zeros to a multiple of four), so that its inner
    loops run along contiguous rows; then vred = v . v and corr = v . y. Each sum in the order of a one-column solve.
    """
    m = resid.shape[1]
    nj = j1 - j0
    npix = (i1 - i0) * nj
    lanes = _lanes(npix + m)
    ec, rc = F[0], F[1]
    for a in range(n):  # the right-hand sides: c = C_e(points, x) per pixel, the residuals, zeros
        pa = uint64(ids[a])  # indices >= 0 as unsigned integers: no check for negative ones (`_window_covariance`)
        for j in range(nj):
            jj = uint64(j0 + j)
            dc = uint64(pc[a] + span - cc[jj])
            ec[j], rc[j] = Ec_o[jj, dc], Rc_o[jj, dc]
        va = V[a]
        for i in range(i1 - i0):
            ii = uint64(i0 + i)
            dr = uint64(pr[a] + span - cr[ii])
            er, rr_ = Er_o[ii, dr], Rr_o[ii, dr]
            vi = va[i * nj:]
            for j in range(nj):
                vi[j] = s2 * (rr_ * ec[j] + rc[j] * er - er * ec[j])
        for q in range(m):
            V[a, npix + q] = resid[pa, q]
        for p in range(npix + m, lanes):
            V[a, p] = 0.0
    for a in range(n):  # V[a] = (V[a] - sum_t L[a, t] V[t]) / L[a, a], by ascending t
        for p in range(lanes):
            acc[p] = V[a, p]
        for t in range(a):
            x = A[a, t]
            for p in range(lanes):
                acc[p] -= x * V[t, p]
        d = dinv[a]
        for p in range(lanes):
            V[a, p] = acc[p] * d
    for p in range(npix):  # vred (the pixels' columns only)
        acc[p] = 0.0
    for a in range(n):
        for p in range(npix):
            acc[p] += V[a, p] * V[a, p]
    _scatter(acc, i0, i1, j0, j1, vred)
    for q in range(m):  # corr = v . y
        for p in range(npix):
            acc[p] = 0.0
        for a in range(n):
            yq = V[a, npix + q]
            for p in range(npix):
                acc[p] += V[a, p] * yq
        _scatter(acc, i0, i1, j0, j1, corr[q])


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
    flat = rows * w + cols
    by_row = np.argsort(flat, kind="stable")  # the points by row, then column (fast when they come so)
    flat = flat[by_row]
    if n > 1 and np.any(flat[1:] == flat[:-1]):
        raise InvalidInputError("rows, cols", "at most one point per pixel", "two points on one pixel")
    row_ptr = np.searchsorted(rows[by_row], np.arange(h + 1)).astype(np.int64)
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
    threads = get_num_threads() if n >= SERIAL_POINTS else 1
    compiled_ahead("detail" if threads > 1 else "detail_serial")  # a cold cache: from the second process
    Er_p, Rr_p = _tables(np.arange(h, dtype=np.float64), np.arange(h), k, hl, inv_l, span)
    Ec_p, Rc_p = _tables(np.arange(w, dtype=np.float64), np.arange(w), k, wl, inv_l, span)
    # at the grid's own pixels (how `gpdepth3d.completion` krigs) the output's tables are the points' tables
    same_rows = np.array_equal(out_rows, np.arange(h))
    same_cols = np.array_equal(out_cols, np.arange(w))
    Er_o, Rr_o = (Er_p, Rr_p) if same_rows else _tables(out_rows, cr, k, hl, inv_l, span)
    Ec_o, Rc_o = (Ec_p, Rc_p) if same_cols else _tables(out_cols, cc, k, wl, inv_l, span)
    corr = np.zeros((res.shape[1], out_rows.size, out_cols.size))
    vred = np.zeros((out_rows.size, out_cols.size))
    if n:
        # prange hands each thread one contiguous share of the rows of cells; the points often fill only part of
        # the image (the LiDAR its lower two thirds), so each share takes every t-th row, not one block of rows
        cell_rows = np.concatenate([np.arange(t, hl, threads) for t in range(threads)]).astype(np.int64)
        kernel = _krige if threads > 1 else _krige_serial
        kernel(cell_rows, row_start, col_start, cr, cc, Er_o, Rr_o, Ec_o, Rc_o, Er_p, Rr_p[0], Ec_p, Rc_p[0], row_ptr,
               by_row.astype(np.int64), rows, cols, res, noise, float(outputscale) ** 2, k, reach, int(max_window_points),
               corr, vred)
    return (corr[0] if one else corr), vred
