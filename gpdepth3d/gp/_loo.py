"""Compiled leave-one-out kriging: the numeric kernels of `gpdepth3d.gp.points.loo_zscores`.

Neighbours (`grid_neighbours`): the k nearest usable points of each target in L1 pixel distance,
ties at equal distance broken by the position on the ring of that radius, scanned from a
starting pixel that a hash of the target fixes: the neighbourhood of a point is a function of the
point set alone, whichever search finds it, does not depend on the points' order and favours no
direction. The search reads a bucket image of the points (a cell per pixel), in parallel over
targets: near points walk the rings pixel by pixel, sparse ones gather the rows of a diamond and
sort it by that order (O(rows and points within the k-th neighbour's distance) per target),
against a k-d tree's O(log N) queries with large constants.

For every target point i with neighbours N (found by the caller), the simple-kriging weights
w = (K_NN + diag(tau^2 + noise_N))^-1 k_Ni of the separable Matern kernel, the prediction
w . r_N and the predictive variance s^2 + tau^2 + noise_i - w . k_Ni, in one compiled loop over
the targets (a k x k Cholesky each, in parallel over targets) instead of NumPy's batched LU over
an (N, k, k) stack and its (N, k, k) correlation tables. For nu = 0.5 and integer pixel
coordinates (points on the GP grid) the correlations are products of two tabulated exponentials.
The same loop gives the share of the predictive variance that a part of the noise makes (the points'
stated sigmas, `gpdepth3d.gp.local_calibration`): (stated_i + sum_j w_j^2 stated_j) / variance.
"""

from __future__ import annotations

import math
import threading
import time
from typing import NamedTuple

import numba as nb
import numpy as np

from ._cholesky import cholesky_in_place
from .kernels import Kernel, unit_separable_correlation

_FLAGS = dict(nogil=True, cache=True)


@nb.njit(**_FLAGS)
def _corr(dr: float, dc: float, inv_l: float, code: int, er, ec) -> float:
    """Separable Matern correlation M(|dr| / l) M(|dc| / l); tables er / ec (exponential kernel, integer offsets) when given."""
    if er.size:
        return er[int(abs(dr))] * ec[int(abs(dc))]
    return unit_separable_correlation(abs(dr) * inv_l, abs(dc) * inv_l, code)


#: Targets per parallel chunk; fewer targets than this run on the calling thread (waking the
#: worker threads costs more than the work, and much more on a busy machine).
CHUNK = 512


#: Targets computed side by side (SIMD lanes) by `_loo_lanes`.
LANES = 8


@nb.njit(**_FLAGS)
def _loo_range(lo, hi, z, share, rows, cols, r, noise, stated, targets, nn, s2, tau2, inv_l, code, er, ec):
    """z[q] for the targets lo <= q < hi (see `loo_predict`)."""
    k = nn.shape[1]
    if er.size:
        _loo_lanes(lo, hi, z, share, rows, cols, r, noise, stated, targets, nn, s2, tau2, er, ec)
        return
    A = np.empty((k, k))
    y = np.empty(k)
    kx = np.empty(k)
    ij = np.empty((2, k), dtype=np.int64)
    for q in range(lo, hi):
        _loo_one(q, rows, cols, r, noise, stated, targets, nn, s2, tau2, inv_l, code, er, ec, A, y, kx, ij, z, share)


@nb.njit(**_FLAGS)
def _loo_lanes(lo, hi, z, share, rows, cols, r, noise, stated, targets, nn, s2, tau2, er, ec):
    """`_loo_one` with tabulated correlations for LANES targets at a time, each lane the same arithmetic.

    The lanes are the innermost (contiguous) axis of every work array, so the Cholesky
    factorisation and the solves vectorise across targets. A lane whose matrix is not
    numerically positive definite gets NaN (the caller solves it by least squares).
    """
    k = nn.shape[1]
    W = LANES
    A = np.empty((k, k, W))
    y = np.empty((k, W))
    kx = np.empty((k, W))
    acc = np.empty(W)
    ok = np.empty(W, dtype=np.bool_)
    ir = np.empty((k, W), dtype=np.int64)
    ic = np.empty((k, W), dtype=np.int64)
    ri = np.empty(W, dtype=np.int64)
    ci = np.empty(W, dtype=np.int64)
    for q0 in range(lo, hi, W):
        n = min(W, hi - q0)
        for l in range(W):  # lanes past the end repeat the last target (results dropped)
            q = q0 + min(l, n - 1)
            i = targets[q]
            ri[l], ci[l] = int(rows[i]), int(cols[i])
            for a in range(k):
                ir[a, l] = int(rows[nn[q, a]])
                ic[a, l] = int(cols[nn[q, a]])
        for a in range(k):  # the lanes innermost here too: each entry's W values written side by side
            for l in range(W):
                y[a, l] = s2 * (er[abs(ri[l] - ir[a, l])] * ec[abs(ci[l] - ic[a, l])])
                kx[a, l] = y[a, l]
                A[a, a, l] = s2 + tau2 + noise[nn[q0 + min(l, n - 1), a]]
            for b in range(a):
                for l in range(W):
                    A[a, b, l] = s2 * (er[abs(ir[a, l] - ir[b, l])] * ec[abs(ic[a, l] - ic[b, l])])
        ok[:] = True
        for j in range(k):  # Cholesky A = L L^T in the lower triangle, column j from its diagonal down
            for a in range(j, k):
                for l in range(W):
                    acc[l] = A[a, j, l]
                for m in range(j):
                    for l in range(W):
                        acc[l] -= A[a, m, l] * A[j, m, l]
                if a == j:
                    for l in range(W):
                        if not acc[l] > 0.0:
                            ok[l] = False
                            acc[l] = 1.0  # keeps the lane finite; its result is dropped
                        A[j, j, l] = math.sqrt(acc[l])
                else:
                    for l in range(W):
                        A[a, j, l] = acc[l] / A[j, j, l]
        for a in range(k):  # y = L^-1 kx
            for l in range(W):
                acc[l] = y[a, l]
            for m in range(a):
                for l in range(W):
                    acc[l] -= A[a, m, l] * y[m, l]
            for l in range(W):
                y[a, l] = acc[l] / A[a, a, l]
        for a in range(k - 1, -1, -1):  # w = L^-T y
            for l in range(W):
                acc[l] = y[a, l]
            for m in range(a + 1, k):
                for l in range(W):
                    acc[l] -= A[m, a, l] * y[m, l]
            for l in range(W):
                y[a, l] = acc[l] / A[a, a, l]
        for l in range(n):
            q = q0 + l
            i = targets[q]
            pred = 0.0
            quad = 0.0
            spread = stated[i]
            for a in range(k):
                pred += y[a, l] * r[nn[q, a]]
                quad += y[a, l] * kx[a, l]
                spread += y[a, l] * y[a, l] * stated[nn[q, a]]
            var = max(s2 + tau2 + noise[i] - quad, 1e-30)
            z[q] = (r[i] - pred) / math.sqrt(var) if ok[l] else np.nan
            share[q] = min(spread / var, 1.0) if ok[l] else np.nan


@nb.njit(parallel=True, **_FLAGS)
def _loo_parallel(z, share, rows, cols, r, noise, stated, targets, nn, s2, tau2, inv_l, code, er, ec):
    t = nn.shape[0]
    for c0 in nb.prange((t + CHUNK - 1) // CHUNK):
        _loo_range(
            c0 * CHUNK,
            min(t, (c0 + 1) * CHUNK),
            z,
            share,
            rows,
            cols,
            r,
            noise,
            stated,
            targets,
            nn,
            s2,
            tau2,
            inv_l,
            code,
            er,
            ec,
        )


@nb.njit(**_FLAGS)
def _loo_one(q, rows, cols, r, noise, stated, targets, nn, s2, tau2, inv_l, code, er, ec, A, y, kx, ij, z, share):
    """z[q] of target q (see `loo_predict`), in the work arrays A (k, k), y (k,), kx (k,), ij (2, k) int."""
    k = nn.shape[1]
    i = targets[q]
    if er.size:  # tabulated correlations: the neighbours' integer offsets gathered once
        ri, ci = int(rows[i]), int(cols[i])
        for a in range(k):
            ij[0, a] = int(rows[nn[q, a]])
            ij[1, a] = int(cols[nn[q, a]])
        for a in range(k):
            y[a] = s2 * (er[abs(ri - ij[0, a])] * ec[abs(ci - ij[1, a])])
            for b in range(a):
                A[a, b] = s2 * (er[abs(ij[0, a] - ij[0, b])] * ec[abs(ij[1, a] - ij[1, b])])
            A[a, a] = s2 + tau2 + noise[nn[q, a]]
            kx[a] = y[a]
    else:
        for a in range(k):
            ja = nn[q, a]
            y[a] = s2 * _corr(rows[i] - rows[ja], cols[i] - cols[ja], inv_l, code, er, ec)
            for b in range(a):
                jb = nn[q, b]
                A[a, b] = s2 * _corr(rows[ja] - rows[jb], cols[ja] - cols[jb], inv_l, code, er, ec)
            A[a, a] = s2 + tau2 + noise[ja]
            kx[a] = y[a]
    if not cholesky_in_place(A, k):  # A = L L^T in the lower triangle
        z[q] = np.nan  # the caller solves this one by least squares
        share[q] = np.nan
        return
    for a in range(k):  # y = L^-1 kx
        acc = y[a]
        for m in range(a):
            acc -= A[a, m] * y[m]
        y[a] = acc / A[a, a]
    for a in range(k - 1, -1, -1):  # w = L^-T y
        acc = y[a]
        for m in range(a + 1, k):
            acc -= A[m, a] * y[m]
        y[a] = acc / A[a, a]
    pred = 0.0
    quad = 0.0
    spread = stated[i]
    for a in range(k):
        pred += y[a] * r[nn[q, a]]
        quad += y[a] * kx[a]
        spread += y[a] * y[a] * stated[nn[q, a]]
    var = max(s2 + tau2 + noise[i] - quad, 1e-30)
    z[q] = (r[i] - pred) / math.sqrt(var)
    share[q] = min(spread / var, 1.0)


@nb.njit(**_FLAGS)
def _ring_start(key, d):
    """Where target (hash ``key``) starts the ring of radius d >= 1: a position 0 .. 4d - 1, from 32
    pseudo-random bits of the target and d scaled by multiplication (no division)."""
    h = ((key >> 16) + d * 2654435769) & 0xFFFFFFFF
    return (h * (4 * d)) >> 32


#: The previous target's k-th distance up to which `_ring_range` walks the rings pixel by pixel (`_walk`); beyond it,
#: fewer points per pixel, it gathers a diamond row by row (`_diamond`). Both give the same neighbours.
WALK_RADIUS = 4


@nb.njit(**_FLAGS)
def _ring_range(lo, hi, r, c, width, start, members, column, usable, key, targets, k, nn, dist):
    """nn[q] / dist[q] for lo <= q < hi: the k nearest members of each target, in the order of rings of equal L1
    distance.

    ``r``, ``c``: integer cell coordinates of every point; the image has (start.size - 1) / width
    rows; the members of cell x are members[start[x]:start[x + 1]] in index order (``column``: their
    columns); only the members that are ``usable`` count (so an image of more points serves any
    subset). The ring of radius d >= 1 is the cycle of its 4d pixels clockwise from the top
    (`ring_offset`: four diagonal sides of d pixels); each target reads it from its own starting
    position (`_ring_start`, a hash of the target's pixel and d), a pixel's members by index: that
    is the tie order, with no preferred direction over the targets. Other points on the target's
    own pixel (distance 0) come first, by index. With fewer than k members (other than the target)
    the rest of the row is -1. Where the previous target's k-th distance is small, the rings are
    walked pixel by pixel (`_walk`), else a diamond is gathered row by row and sorted (`_diamond`).
    """
    height = (start.size - 1) // width
    cap = members.size
    cand = np.empty(cap, dtype=np.int64)
    cdr = np.empty(cap, dtype=np.int64)
    cdc = np.empty(cap, dtype=np.int64)
    order = np.empty(cap, dtype=np.int64)
    hist = np.zeros(height + width + 1, dtype=np.int64)
    s0 = np.empty(height + width + 1, dtype=np.int64)
    guess = np.int64(1)  # int64, not the literal 1: _diamond is compiled for one signature, not two
    for q in range(lo, hi):
        if guess <= WALK_RADIUS:
            far = _walk(q, r, c, width, height, start, members, usable, key, targets, k, nn, dist)
        else:
            far = _diamond(q, guess, r, c, width, height, start, members, column, usable, key, targets, k, nn, dist,
                           cand, cdr, cdc, order, hist, s0)  # fmt: skip
        if far >= 0:
            guess = far


@nb.njit(**_FLAGS)
def _walk(q, r, c, width, height, start, members, usable, key, targets, k, nn, dist):
    """`_ring_range` for target q, walking the rings pixel by pixel; its k-th distance (-1 with fewer than k)."""
    i = targets[q]
    ri, ci = r[i], c[i]
    count = 0
    x = ri * width + ci
    for a in range(start[x], start[x + 1]):  # d = 0: other points on the target's pixel
        p = members[a]
        if p != i and usable[p] and count < k:
            nn[q, count] = p
            dist[q, count] = 0
            count += 1
    dmax = max(ri, height - 1 - ri) + max(ci, width - 1 - ci)
    last = members.size - 1
    d = np.int64(1)  # int64, not the literal 1: one compiled signature of _ring_start and _side_offset
    while count < k and d <= dmax:
        s0 = _ring_start(key[i], d)
        side = (s0 >= d) + (s0 >= 2 * d) + (s0 >= 3 * d)  # s0 // d without an integer division (s0 < 4d)
        t = s0 - side * d
        dr, dc = _side_offset(d, side, t)
        rr, cc = ri + dr, ci + dc
        for _ in range(4 * d):
            if rr >= 0 and rr < height and cc >= 0 and cc < width:
                x = rr * width + cc
                a0, a1 = start[x], start[x + 1]
                if a1 - a0 <= 1 and last >= 0:  # no member or one: written, then counted if real and usable
                    p = members[min(a0, last)]  # (no branch on the pixel's occupancy, which is as good as random)
                    nn[q, count] = p
                    dist[q, count] = d
                    count += int(a1 > a0) & int(usable[p])
                else:
                    for a in range(a0, a1):
                        if count < k and usable[members[a]]:
                            nn[q, count] = members[a]
                            dist[q, count] = d
                            count += 1
                if count == k:
                    break
            t += 1
            if t == d:  # the next side starts at a corner
                t = np.int64(0)  # (int64, not the literal 0: one compiled signature of _side_offset)
                side = (side + 1) & 3
                dr, dc = _side_offset(d, side, t)
                rr, cc = ri + dr, ci + dc
            else:  # along the side: sides 0 .. 3 step (+1, +1), (+1, -1), (-1, -1), (-1, +1)
                rr += 1 if side < 2 else -1
                cc += 1 if side == 0 or side == 3 else -1
        d += 1
    for a in range(count, k):
        nn[q, a] = -1
        dist[q, a] = -1
    return int(dist[q, k - 1])


@nb.njit(**_FLAGS)
def _diamond(q, guess, r, c, width, height, start, members, column, usable, key, targets, k, nn, dist, cand, cdr, cdc,
             order, hist, s0):  # fmt: skip
    """`_ring_range` for target q: the members of a diamond (L1 ball) around it gathered row by row, widened from the radius ``guess`` until it holds k of them, those up to the k-th distance sorted by (distance,
    ring position from the start); its k-th distance (-1 with fewer than k). Work arrays: ``cand`` .. ``order``
    (members.size), ``hist``, ``s0`` (height + width + 1)."""
    i = targets[q]
    ri, ci = r[i], c[i]
    dmax = max(ri, height - 1 - ri) + max(ci, width - 1 - ci)
    radius = min(max(guess, 1), dmax)
    while True:  # the members within L1 ``radius`` other than i, row by row (a row's cells: one run of members)
        m = 0
        for rr in range(max(0, ri - radius), min(height - 1, ri + radius) + 1):
            rem = radius - abs(rr - ri)
            x = rr * width
            for a in range(start[x + max(0, ci - rem)], start[x + min(width - 1, ci + rem) + 1]):
                p = members[a]
                if p != i and usable[p]:
                    cand[m] = p
                    cdr[m] = rr - ri
                    cdc[m] = column[a] - ci
                    m += 1
        if m >= k or radius >= dmax:
            break
        radius = min(radius + 1 + radius // 4, dmax)
    for a in range(radius + 1):
        hist[a] = 0
    for a in range(m):
        hist[abs(cdr[a]) + abs(cdc[a])] += 1
    far, below = radius, 0  # the k-th distance (the radius when fewer than k)
    for d in range(radius + 1):
        below += hist[d]
        if below >= k:
            far = d
            break
    s0[0] = 0
    for d in range(1, far + 1):
        s0[d] = _ring_start(key[i], d)
    n = 0
    for a in range(m):  # the candidates up to the k-th distance, keyed by (distance, ring position), without branches
        dr, dc = cdr[a], cdc[a]
        d = abs(dr) + abs(dc)
        rel = _ring_position(dr, dc, d) - s0[min(d, far)]  # from the target's start (0 at d = 0)
        rel += 4 * d * int(rel < 0)
        order[n] = (d * (4 * far + 4) + rel) * m + n  # n: a pixel's members in index order (the keys distinct)
        cand[n] = cand[a]
        cdr[n] = d
        n += int(d <= far)  # (written, then kept if within the k-th distance)
    for a in range(min(n, k), k):
        nn[q, a] = -1
        dist[q, a] = -1
    for a in range(n):  # each candidate's rank among the (distinct) keys, by comparisons without branches
        o = order[a]
        rank = 0
        for b in range(n):
            rank += int(order[b] < o)
        if rank < k:
            nn[q, rank] = cand[a]
            dist[q, rank] = cdr[a]
    return far if m >= k else -1


@nb.njit(**_FLAGS)
def _ring_position(dr, dc, d):
    """The position on the ring of radius d (the inverse of `ring_offset`) of the offset (dr, dc), d = |dr| + |dc|;
    0 at d = 0. Arithmetic on the four sides' indicators, not branches: the sides of a target's candidates come
    in no order a branch predictor could learn."""
    top = int(dr < 0) & int(dc >= 0)
    right = int(dr >= 0) & int(dc > 0)
    bottom = int(dr > 0) & int(dc <= 0)
    left = int(dr <= 0) & int(dc < 0)
    return top * dc + right * (d + dr) + bottom * (2 * d - dc) + left * (3 * d - dr)


@nb.njit(**_FLAGS)
def ring_offset(d, pos):
    """(row, column) offset of position ``pos`` (0 .. 4d - 1) on the ring of L1 radius d >= 1, clockwise from the top."""
    side = pos // d
    return _side_offset(d, side, pos - side * d)


@nb.njit(**_FLAGS)
def _side_offset(d, side, t):
    """`ring_offset` of the position t (0 .. d - 1) along side ``side`` (0 .. 3) of the ring of radius d (the walk
    steps along the sides: an integer division per pixel would cost more than reading it)."""
    if side == 0:
        return -d + t, t
    if side == 1:
        return t, d - t
    if side == 2:
        return d - t, -t
    return -t, -d + t


@nb.njit(parallel=True, **_FLAGS)
def _ring_parallel(r, c, width, start, members, column, usable, key, targets, k, nn, dist):
    t = targets.size
    for c0 in nb.prange((t + CHUNK - 1) // CHUNK):
        _ring_range(
            c0 * CHUNK, min(t, (c0 + 1) * CHUNK), r, c, width, start, members, column, usable, key, targets, k, nn, dist
        )


@nb.njit(**_FLAGS)
def _ring_claim(claimed, backward, r, c, width, start, members, column, usable, key, targets, k, nn, dist):
    """`_ring_range` over the chunks of CHUNK targets (``claimed``: one flag per chunk) from the first, or with
    ``backward`` from the last, claiming each, until a chunk that the other caller has claimed: two callers, one
    from each end, share the targets without a lock. A chunk that both claim at once is computed twice, to the
    same values (each of its rows ends with its final values written), which costs time, not correctness."""
    chunks = claimed.size
    for a in range(chunks):
        x = chunks - 1 - a if backward else a
        if claimed[x]:
            return
        claimed[x] = True
        _ring_range(
            x * CHUNK, min(targets.size, (x + 1) * CHUNK), r, c, width, start, members, column, usable, key, targets,
            k, nn, dist,
        )  # fmt: skip


#: Most times `SharedSearch` yields the interpreter lock for its thread to start its search: the caller then runs
#: Python code, which would otherwise keep the thread waiting for the lock for the interpreter's switch interval
#: (a thread that no core runs soon is not waited for: the caller then finds the chunks unclaimed and computes them).
HANDOFFS = 50


class SharedSearch:
    """`grid_neighbours` of every point among all of them (the outlier screen's first round), started on a second
    thread that works through the targets from the first while the caller does other work (the frame's slope fit):
    `result` then computes the rest from the last target down and waits for the thread. The neighbours are those of
    `grid_neighbours`, whichever thread finds them (a function of the pixels alone)."""

    def __init__(self, image: NeighbourImage, k: int):
        n = image.r.size
        self.image, self.k = image, int(k)
        self.nn = np.empty((n, self.k), dtype=np.int64)
        self.dist = np.empty((n, self.k))
        self._claimed = np.zeros((n + CHUNK - 1) // CHUNK, dtype=np.bool_)
        r, c, width, start, members, column, key = image
        usable = np.ones(n, dtype=np.bool_)
        self._args = (r, c, width, start, members, column, usable, key, np.arange(n), self.k, self.nn, self.dist)
        self._thread = threading.Thread(target=_ring_claim, args=(self._claimed, False, *self._args), daemon=True)
        self._thread.start()
        for _ in range(HANDOFFS):  # until the thread's compiled search runs (it has claimed its first chunk)
            if self._claimed.any() or not self._thread.is_alive():
                break
            time.sleep(0)  # lets the thread take the interpreter lock, which it needs until its compiled search starts

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """(nn (N, k) int64, dist (N, k) float64) as `grid_neighbours` gives them for all points, all usable."""
        _ring_claim(self._claimed, True, *self._args)
        self._thread.join()
        return self.nn, self.dist


def pixel_hash(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N,) non-negative int64: a fixed pseudo-random hash (splitmix64) of each point's pixel."""
    r = np.asarray(np.rint(rows), dtype=np.int64).astype(np.uint64)
    c = np.asarray(np.rint(cols), dtype=np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        z = (r << np.uint64(32)) ^ (c & np.uint64(0xFFFFFFFF))
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(1)).astype(np.int64)


class NeighbourImage(NamedTuple):
    """The bucket image of a point set that `grid_neighbours` searches (one cell per pixel of the box around the
    points); built once (`neighbour_image`), it serves searches among any subset of its points.

    Attributes:
        r, c: (N,) int64 cell of every point (its pixel less the points' smallest row and column).
        width: Cells per image row.
        start: (cells + 1,) int64: the members of cell x are members[start[x]:start[x + 1]].
        members: The points in the image, by cell, then by index.
        column: (members.size,) the members' cell columns.
        key: (N,) `pixel_hash` of every point (the tie rule's starting positions).
    """

    r: np.ndarray
    c: np.ndarray
    width: int
    start: np.ndarray
    members: np.ndarray
    column: np.ndarray
    key: np.ndarray


def image_spans(image: NeighbourImage) -> tuple[int, int]:
    """The row and column ranges (max - min, pixels) of the points of ``image`` (its cells' box)."""
    return (image.start.size - 1) // image.width - 1, image.width - 1


def neighbour_image(rows: np.ndarray, cols: np.ndarray, pool: np.ndarray | None = None) -> NeighbourImage:
    """The `NeighbourImage` of the points ``pool`` (indices; default all) among (N,) integer-valued ``rows``,
    ``cols`` (any origin)."""
    key = pixel_hash(rows, cols)
    r = np.asarray(rows, dtype=np.float64).astype(np.int64)
    c = np.asarray(cols, dtype=np.float64).astype(np.int64)
    r -= r.min()
    c -= c.min()
    height, width = int(r.max()) + 1, int(c.max()) + 1
    cell = r * width + c if pool is None else r[pool] * width + c[pool]
    order = np.argsort(cell, kind="stable")
    members = order if pool is None else pool[order]  # by cell, then by index
    return NeighbourImage(r, c, width, _cell_starts(cell[order], height * width), members, c[members], key)


@nb.njit(**_FLAGS)
def _cell_starts(cells, size):
    """(size + 1,) int64: entry x is the number of ``cells`` (sorted cell numbers 0 .. size - 1) below x, in one
    pass over the image (a count per cell and its running sum would write it three times)."""
    start = np.empty(size + 1, dtype=np.int64)
    x = 0
    for a in range(cells.size):
        while x <= cells[a]:
            start[x] = a
            x += 1
    while x <= size:
        start[x] = cells.size
        x += 1
    return start


def grid_neighbours(
    rows: np.ndarray,
    cols: np.ndarray,
    usable: np.ndarray,
    targets: np.ndarray,
    k: int,
    image: NeighbourImage | None = None,
):
    """The k nearest usable points of each target in L1 distance, ties broken by the ring order.

    Points at equal distance d >= 1 from a target come in the order of their pixel on the ring
    of radius d, clockwise from a starting pixel that a hash of the target's pixel and d fixes
    (`ring_offset`, `_ring_start`); other points on the target's own pixel (distance 0) by index.
    The rule is a function of the pixels alone: a point's neighbourhood does not depend on the
    search that finds it or on the order of the points, and over the targets no direction is
    preferred (a fixed rule such as "upper rows first" tilts every neighbourhood of scan-line
    data the same way).

    Args:
        rows, cols: (N,) integer-valued pixel coordinates of all points (any origin).
        usable: (N,) bool, the points that may be neighbours.
        targets: (T,) indices of the points whose neighbours to find (a target is never its own
            neighbour; another point on the same pixel is one, at distance 0).
        k: Neighbours per target, at least 1 and at most the usable points other than any target.
        image: The points' `NeighbourImage` (holding at least the usable ones), for searches
            repeated on the same points with other usable sets; None: one of the usable points is built.

    Returns:
        (nn (T, k) int64, dist (T, k) float64): each row's neighbours in that order, and their
        L1 distances.
    """
    usable = np.ascontiguousarray(usable, dtype=np.bool_)
    if image is None:
        image = neighbour_image(rows, cols, np.flatnonzero(usable))
    r, c, width, start, members, column, key = image
    targets = np.ascontiguousarray(targets, dtype=np.int64)
    nn = np.empty((targets.size, k), dtype=np.int64)
    dist = np.empty((targets.size, k))  # whole numbers, written as float64 by the search
    args = (r, c, width, start, members, column, usable, key, targets, int(k), nn, dist)
    if targets.size <= CHUNK:
        _ring_range(0, targets.size, *args)
    else:
        _ring_parallel(*args)
    return nn, dist


def loo_predict(
    rows: np.ndarray,
    cols: np.ndarray,
    r: np.ndarray,
    noise: np.ndarray,
    targets: np.ndarray,
    nn: np.ndarray,
    *,
    outputscale: float,
    nugget: float,
    lengthscale: float,
    nu: float,
    stated: np.ndarray | None = None,
    spans: tuple[int, int] | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Leave-one-out z-scores of the targets given their neighbours (see the module docstring).

    Args:
        rows, cols: (N,) pixel coordinates of all points.
        r: (N,) residuals with the constant removed.
        noise: (N,) measurement variances.
        targets: (T,) indices of the points to score.
        nn: (T, k) indices of each target's neighbours (never the target itself).
        outputscale, nugget, lengthscale, nu: The kernel (s, tau, l in pixels, Matern nu).
        stated: (N,) a part of ``noise`` (each entry between 0 and the point's noise): with it, also
            return each target's share of it.
        spans: The points lie on integer pixels with these row and column ranges (max - min; `image_spans` of their
            image), which the caller knows; None: checked here.

    Returns:
        (T,) z = (r_i - w . r_N) / sqrt(max(var, 1e-30)); NaN where the neighbourhood's matrix is
        not numerically positive definite. With ``stated``, also the (T,) share of the predictive
        variance that this part of the noise makes, (stated_i + sum_j w_j^2 stated_j) / var in
        [0, 1] (NaN with z): E[z^2] is at least this whatever the field, if the noises are
        independent.
    """
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    cols = np.ascontiguousarray(cols, dtype=np.float64)
    none = np.zeros(0)
    er = ec = none
    kernel = Kernel(nu, float(lengthscale), float(outputscale))
    if (
        spans is None
        and kernel.exponential
        and rows.size
        and np.all(rows == np.rint(rows))
        and np.all(cols == np.rint(cols))
    ):
        spans = (float(np.ptp(rows)), float(np.ptp(cols)))
    if kernel.exponential and spans is not None:
        span_r, span_c = spans
        if span_r + span_c <= 1e6:  # tables e^{-d / l} over every offset that occurs
            er = kernel.lag_correlation(int(span_r) + 1)
            ec = kernel.lag_correlation(int(span_c) + 1)
    noise = np.ascontiguousarray(noise, dtype=np.float64)
    part = noise if stated is None else np.ascontiguousarray(stated, dtype=np.float64)
    args = (
        rows,
        cols,
        np.ascontiguousarray(r, dtype=np.float64),
        noise,
        part,
        np.ascontiguousarray(targets, dtype=np.int64),
        np.ascontiguousarray(nn, dtype=np.int64),
        float(outputscale) ** 2,
        float(nugget) ** 2,
        1.0 / float(lengthscale),
        kernel.code,
        er,
        ec,
    )
    z, share = np.empty(nn.shape[0]), np.empty(nn.shape[0])
    if nn.shape[0] <= CHUNK:
        _loo_range(0, nn.shape[0], z, share, *args)
    else:
        _loo_parallel(z, share, *args)
    return z if stated is None else (z, share)
