"""Exact posterior over few observed pixels (Woodbury) for the separable exponential kernel (nu = 0.5).

The ``fast`` engine's route for sparse points: O(m^3) for the m points' factor, O(m^2) splats and
O(Ho Wo) recursive filtering instead of O(Ho Wo m^2). Derivation: docs/engines.md#the-woodbury-route-in-detail.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import scipy.linalg

from .cost_model import woodbury_seconds as woodbury_seconds  # the cost model of this route
from .model import GridProblem
from .multifrontal import numeric_section, inverse_from_cholesky

_LOG_2PI = float(np.log(2 * np.pi))


# Layout of the impulse images: buf (Ho + 1, Wo + 1, 9), slot 3 X + Y for row operator X and
# column operator Y (0 = C interval, 1 = F after, 2 = B before). Per axis, C and F impulses are
# stored at their output index i (index n = trash), B impulses at i + 1 (index 0 = trash), so the
# C start and the B impulse of a point share a cell, as do the C end and the F impulse: a pair
# writes 16 values into 4 cells. Only the rows that hold an impulse (at most two per point row)
# are stored: buf (nq, Wo + 1, 9) with qmap (Ho + 1,) the stored row of each row index (-1 =
# none), so the column pass costs nq Wo, not Ho Wo. The mean has F and B only: its buffer
# (nq, k, Wo + 1, 4) holds slot 2 X + Y (0 = F, 1 = B) of each of its k right-hand sides.


@nb.njit(cache=True, nogil=True)
def _splat_pairs(M, K, cc, ri, rv, ci, cv, buf):
    """Adds the impulses of every pair (k, j), k <= j, of points sorted by row into buf (see the layout above).

    M: A^-1 in column-major order (lower triangle read); K: the point correlations (read above
    the diagonal). ri / ci (2, m): per point, the storage index of its "start" cell (first
    x >= p: C start, B) and of its "end" cell (first x > p: C end, F) along rows / columns;
    rv / cv (2, m): its B and F values. A pair adds w = M_jk K_jk (twice off the diagonal) times
    the outer product of its row and column impulses: C +1 at the start of the lower point and -1
    at the end of the higher one, F at the end of the higher point, B at the start of the lower
    one. Rows are sorted, so point k is the lower one along rows.
    """
    m = M.shape[0]
    for k in range(m):
        sa, rb0 = ri[0, k], rv[0, k]
        for j in range(k, m):
            w = M[j, k] * (2.0 * K[k, j] if k != j else 1.0)
            sf = ri[1, j]
            wb, wf = w * rb0, w * rv[1, j]
            if cc[k] <= cc[j]:
                ta, tf, cb, cf = ci[0, k], ci[1, j], cv[0, k], cv[1, j]
            else:
                ta, tf, cb, cf = ci[0, j], ci[1, k], cv[0, j], cv[1, k]
            buf[sa, ta, 0] += w
            buf[sa, ta, 2] += w * cb
            buf[sa, ta, 6] += wb
            buf[sa, ta, 8] += wb * cb
            buf[sa, tf, 0] -= w
            buf[sa, tf, 1] += w * cf
            buf[sa, tf, 6] -= wb
            buf[sa, tf, 7] += wb * cf
            buf[sf, ta, 0] -= w
            buf[sf, ta, 2] -= w * cb
            buf[sf, ta, 3] += wf
            buf[sf, ta, 5] += wf * cb
            buf[sf, tf, 0] += w
            buf[sf, tf, 1] -= w * cf
            buf[sf, tf, 3] -= wf
            buf[sf, tf, 4] += wf * cf


@nb.njit(cache=True, nogil=True)
def _splat_points(alphas, ri, rv, ci, cv, buf):
    """Adds every point's F / B impulses for each right-hand side into buf (nq, k, Wo + 1, 4) (see `_filter_means`).

    alphas (k, m): the weights (A^-1 r) of the k right-hand sides. The mean's F impulse starts at
    the first x >= p, so a point writes one cell per right-hand side.
    """
    for h in range(alphas.shape[0]):
        for j in range(alphas.shape[1]):
            s, t = ri[0, j], ci[0, j]
            a = alphas[h, j]
            buf[s, h, t, 0] += a * rv[1, j] * cv[1, j]
            buf[s, h, t, 1] += a * rv[1, j] * cv[0, j]
            buf[s, h, t, 2] += a * rv[0, j] * cv[1, j]
            buf[s, h, t, 3] += a * rv[0, j] * cv[0, j]


@nb.njit(cache=True, nogil=True)
def _filter_means(buf, lam_r, lam_c, g, qmap, prior, out):
    """out[h] (Ho, Wo) = prior + sum_X rowop_X(sum_Y colop_Y(buf[h] slot 2 X + Y)) for each right-hand side h.

    The mean's operators are F and B only (X, Y: 0 = F, 1 = B; the recursions of `_filter`).
    buf (nq, k, Wo + 1, 4): the stored rows' impulses (qmap as in `_filter`), left all zero;
    g (nq, 4, Wo) is scratch: the column pass per row operator, its F and B parts apart (slots
    X and 2 + X: the two recursions run in one loop, their chains overlapping in the pipeline).
    """
    hs, w = buf.shape[0], buf.shape[2] - 1
    h = out.shape[1]
    rowf = np.empty(w)
    for k in range(buf.shape[1]):
        for s in range(hs):  # columns: F forward, B backward (B input stored at i + 1)
            f1 = f2 = b1 = b2 = 0.0
            for i in range(w):
                li = lam_c[i]
                f1 = li * f1 + buf[s, k, i, 0]
                f2 = li * f2 + buf[s, k, i, 2]
                g[s, 0, i] = f1
                g[s, 1, i] = f2
                e = w - 1 - i
                le = lam_c[e + 1]
                b1 = le * b1 + buf[s, k, e + 1, 1]
                b2 = le * b2 + buf[s, k, e + 1, 3]
                g[s, 2, e] = b1
                g[s, 3, e] = b2
            buf[s, k, :, :] = 0.0
        o = out[k]
        rowf[:] = 0.0
        for i in range(h):  # rows: F forward
            li = lam_r[i]
            q = qmap[i]
            if q >= 0:
                for c in range(w):
                    rowf[c] = li * rowf[c] + (g[q, 0, c] + g[q, 2, c])
                    o[i, c] = rowf[c]
            else:
                for c in range(w):
                    rowf[c] = li * rowf[c]
                    o[i, c] = rowf[c]
        rowf[:] = 0.0
        for i in range(h - 1, -1, -1):  # rows: B backward, then the prior mean
            li = lam_r[i + 1]
            q = qmap[i + 1]
            if q >= 0:
                for c in range(w):
                    rowf[c] = li * rowf[c] + (g[q, 1, c] + g[q, 3, c])
                    o[i, c] = prior[i, c] + (o[i, c] + rowf[c])
            else:
                for c in range(w):
                    rowf[c] = li * rowf[c]
                    o[i, c] = prior[i, c] + (o[i, c] + rowf[c])


@nb.njit(cache=True, nogil=True)
def _filter(buf, lam_r, lam_c, g, out, qmap, s2):
    """out (Ho, Wo) = max(s2 (1 - corr), 0), corr = sum_X rowop_X(sum_Y colop_Y(slot 3 X + Y of buf)) (layout above).

    C: cumulative sum; F: y_i = lam[i] y_{i-1} + u_i; B: y_i = lam[i + 1] y_{i+1} + u_{i+1 stored}.
    lam (n + 1,): lam[i] = e^{-rate (x_i - x_{i-1})}, lam[0] and lam[n] unused / 0. buf (nq, Wo + 1,
    9): the stored rows (qmap (Ho + 1,): row index -> stored row or -1); g (nq, 3, Wo) is scratch:
    the column pass per row operator. corr is the posterior correlation's reduction (the variance
    over s2's complement); the clamp keeps the variance >= 0 under rounding. buf is left all zero.
    """
    hs, ws, _ = buf.shape
    h, w = out.shape[0], ws - 1
    for s in range(hs):  # columns: C and F forward, B backward (B input stored at i + 1)
        c0 = c1 = c2 = f0 = f1 = f2 = 0.0
        for i in range(w):
            li = lam_c[i]
            c0 += buf[s, i, 0]
            c1 += buf[s, i, 3]
            c2 += buf[s, i, 6]
            f0 = li * f0 + buf[s, i, 1]
            f1 = li * f1 + buf[s, i, 4]
            f2 = li * f2 + buf[s, i, 7]
            g[s, 0, i] = c0 + f0
            g[s, 1, i] = c1 + f1
            g[s, 2, i] = c2 + f2
        b0 = b1 = b2 = 0.0
        for i in range(w - 1, -1, -1):
            li = lam_c[i + 1]
            b0 = li * b0 + buf[s, i + 1, 2]
            b1 = li * b1 + buf[s, i + 1, 5]
            b2 = li * b2 + buf[s, i + 1, 8]
            g[s, 0, i] += b0
            g[s, 1, i] += b1
            g[s, 2, i] += b2
        buf[s, :, :] = 0.0
    rowc = np.zeros(w)
    rowf = np.zeros(w)
    for i in range(h):  # rows: C and F forward
        li = lam_r[i]
        q = qmap[i]
        if q >= 0:
            for c in range(w):
                rowc[c] += g[q, 0, c]
                rowf[c] = li * rowf[c] + g[q, 1, c]
                out[i, c] = rowc[c] + rowf[c]
        else:
            for c in range(w):
                rowf[c] = li * rowf[c]
                out[i, c] = rowc[c] + rowf[c]
    rowf[:] = 0.0
    for i in range(h - 1, -1, -1):  # rows: B backward, then the variance
        li = lam_r[i + 1]
        q = qmap[i + 1]
        if q >= 0:
            for c in range(w):
                rowf[c] = li * rowf[c] + g[q, 2, c]
                v = s2 * (1.0 - (out[i, c] + rowf[c]))
                out[i, c] = 0.0 if v < 0.0 else v
        else:
            for c in range(w):
                rowf[c] = li * rowf[c]
                v = s2 * (1.0 - (out[i, c] + rowf[c]))
                out[i, c] = 0.0 if v < 0.0 else v


@nb.njit(cache=True, nogil=True)
def _correlations(rr, cc, er, ec, diag):
    """(m, m) matrix er[|r_j - r_k|] ec[|c_j - c_k|] (integer pixel coordinates) plus ``diag`` on its diagonal."""
    m = rr.shape[0]
    A = np.empty((m, m))
    for j in range(m):
        for k in range(j):
            v = er[abs(rr[j] - rr[k])] * ec[abs(cc[j] - cc[k])]
            A[j, k] = v
            A[k, j] = v
        A[j, j] = 1.0 + diag[j]
    return A


class _Axis:
    """One output axis: its coordinates in sorted order and the impulse tables of points on it."""

    def __init__(self, coords: np.ndarray):
        coords = np.asarray(coords, dtype=np.float64)
        self.sorted = bool(np.all(np.diff(coords) >= 0))
        self.order = np.arange(coords.size) if self.sorted else np.argsort(coords, kind="stable")
        self.x = coords[self.order]
        self.n = self.x.size

    def decay(self, rate: float) -> np.ndarray:
        """(n + 1,) decays e^{-rate (x_i - x_{i-1})} of the recursions (entries 0 and n: 0)."""
        lam = np.zeros(self.n + 1)
        lam[1 : self.n] = np.exp(-rate * np.diff(self.x))
        return lam

    def impulses(self, p: np.ndarray, rate: float, *, interval: bool):
        """Storage indices (2, m) and values (2, m) of the points p along this axis (see the layout).

        Indices: the start cell (first x >= p) and the end cell (first x > p for the variance's
        interval, the start cell again for the mean). Values: B, e^{-rate (p - x)} at the last
        x < p (0 if none), and F, e^{-rate (x - p)} at the first x > p (variance) or x >= p (mean).
        """
        x = self.x
        ge = np.searchsorted(x, p, side="left")
        end = np.searchsorted(x, p, side="right") if interval else ge
        x_pad = np.concatenate([[-np.inf], x, [np.inf]])  # x_pad[i + 1] = x[i]
        vb = np.exp(-rate * (p - x_pad[ge]))  # x[ge - 1]; 0 when ge = 0
        vf = np.exp(-rate * (x_pad[end + 1] - p))  # 0 when end = n
        return np.stack([ge, end]).astype(np.int64), np.stack([vb, vf])


def _workspace(store: dict | None, key: str, buf_shape: tuple, scratch_shape: tuple):
    """All-zero impulse buffer of ``buf_shape`` and scratch of ``scratch_shape`` (the filters use their first rows).

    Taken from ``store[key]`` when it has these shapes (``dict.pop``: one taker at a time), else
    new. The filters clear the buffer as they read it, and `WoodburyPosterior` puts the pair back
    only then, so a buffer in the store is always zero.
    """
    free = store.pop(key, None) if store is not None else None
    if free is not None and free[0].shape == buf_shape and free[1].shape == scratch_shape:
        return free
    return np.zeros(buf_shape), np.zeros(scratch_shape)


def _stored_rows(ri: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(qmap (n + 1,): the stored row of each row storage index or -1, ri mapped to stored rows) (see the layout)."""
    used = np.unique(ri)
    qmap = np.full(n + 1, -1, dtype=np.int64)
    qmap[used] = np.arange(used.size)
    return qmap, qmap[ri]


class WoodburyPosterior:
    """Exact posterior of a `GridProblem` with few observed pixels and nu = 0.5 (docs/engines.md#the-woodbury-route-in-detail).

    Args:
        problem: The grid problem; its kernel must have nu = 0.5.
        workspace: A dict in which the image buffers are kept for the next call of the same
            output shape (the engine keeps one).
    """

    def __init__(self, problem: GridProblem, workspace: dict | None = None):
        k = problem.kernel
        if not k.exponential:
            raise ValueError("internal error: the Woodbury route needs the exponential kernel (nu = 0.5)")
        self.problem = problem
        self._store = workspace
        prec = np.asarray(problem.precision, dtype=np.float64)
        rows, cols = np.divmod(np.flatnonzero(prec.ravel() > 0), prec.shape[1])
        self.rr, self.cc = rows.astype(np.float64), cols.astype(np.float64)
        self.s2 = float(k.outputscale) ** 2
        self.inv_l = 1.0 / float(k.lengthscale)
        self.resid = (
            np.asarray(problem.obs, np.float64)[rows, cols] - np.asarray(problem.prior_mean, np.float64)[rows, cols]
        )
        self._rows_axis = _Axis(problem.out_rows)
        self._cols_axis = _Axis(problem.out_cols)
        self.m = int(rows.size)
        if not self.m:
            return
        h, w = problem.shape
        er = k.lag_correlation(h)
        ec = k.lag_correlation(w)
        with numeric_section():
            self.A = _correlations(rows, cols, er, ec, 1.0 / (prec[rows, cols] * self.s2))
            self.L, info = scipy.linalg.lapack.dpotrf(self.A, lower=1, clean=0)
            if info != 0:
                raise np.linalg.LinAlgError(
                    f"the observed-pixel covariance is not positive definite (dpotrf info={info})"
                )
            self.alpha, _ = scipy.linalg.lapack.dpotrs(self.L, self.resid, lower=1)

    def _unsort(self, img: np.ndarray) -> np.ndarray:
        ra, ca = self._rows_axis, self._cols_axis
        if ra.sorted and ca.sorted:
            return img
        out = np.empty_like(img)
        out[np.ix_(ra.order, ca.order)] = img
        return out

    def _release(self, key: str, buf: np.ndarray, g: np.ndarray) -> None:
        if self._store is not None:
            self._store[key] = (buf, g)  # all zero again

    def _sorted_prior(self, prior: np.ndarray) -> np.ndarray:
        ra, ca = self._rows_axis, self._cols_axis
        return prior if ra.sorted and ca.sorted else prior[np.ix_(ra.order, ca.order)]

    def mean(self, obs: np.ndarray | None = None) -> np.ndarray:
        """Posterior mean (Ho, Wo), metres.

        Args:
            obs: Another (H, W) observation array to use instead of the problem's (the same
                precision, prior mean and kernel: the factorisation is shared).
        """
        if obs is None:
            return self.means()[0]
        return self._means([self._alpha(obs)])[0]

    def means(self, extra_obs=()) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """The posterior mean (Ho, Wo), metres, and that of each of ``extra_obs`` in one pass.

        Args:
            extra_obs: Further (H, W) observation arrays (the same precision, prior mean and
                kernel); each mean equals ``mean(obs)``, read out together with the problem's.
        """
        out = self._means([self.alpha if self.m else None] + [self._alpha(e) for e in extra_obs])
        return out[0], tuple(out[1:])

    def _alpha(self, obs: np.ndarray) -> np.ndarray | None:
        """Weights A^-1 r of the residuals of ``obs`` at the observed pixels (None without points)."""
        if not self.m:
            return None
        p = self.problem
        rows, cols = self.rr.astype(np.int64), self.cc.astype(np.int64)
        resid = np.asarray(obs, np.float64)[rows, cols] - np.asarray(p.prior_mean, np.float64)[rows, cols]
        alpha, _ = scipy.linalg.lapack.dpotrs(self.L, resid, lower=1)
        return alpha

    def _means(self, alphas: list) -> list[np.ndarray]:
        """prior + the read-out of each weight vector of ``alphas`` (the recursive filters, one pass per vector)."""
        ra, ca = self._rows_axis, self._cols_axis
        prior = np.asarray(self.problem.out_prior_mean, np.float64)
        if not self.m:
            return [prior.copy() for _ in alphas]
        ri, rv = ra.impulses(self.rr, self.inv_l, interval=False)
        ci, cv = ca.impulses(self.cc, self.inv_l, interval=False)
        qmap, ri = _stored_rows(ri, ra.n)
        k = len(alphas)
        buf, g = _workspace(self._store, f"means{k}", (ra.n + 1, k, ca.n + 1, 4), (ra.n + 1, 4, ca.n))
        nq = int(qmap.max()) + 1
        out = np.empty((k, ra.n, ca.n))
        with numeric_section():
            _splat_points(np.stack(alphas), ri, rv, ci, cv, buf)
            lam_r, lam_c = ra.decay(self.inv_l), ca.decay(self.inv_l)
            _filter_means(buf[:nq], lam_r, lam_c, g[:nq], qmap, np.ascontiguousarray(self._sorted_prior(prior)), out)
        self._release(f"means{k}", buf, g)
        return [self._unsort(o) for o in out]

    def variance(self) -> np.ndarray:
        """Posterior marginal variance (Ho, Wo), m^2."""
        ra, ca = self._rows_axis, self._cols_axis
        if not self.m:
            return np.full((ra.n, ca.n), self.s2)
        rate = 2.0 * self.inv_l
        ri, rv = ra.impulses(self.rr, rate, interval=True)
        ci, cv = ca.impulses(self.cc, rate, interval=True)
        qmap, ri = _stored_rows(ri, ra.n)
        buf, g = _workspace(self._store, "variance", (ra.n + 1, ca.n + 1, 9), (ra.n + 1, 3, ca.n))
        nq = int(qmap.max()) + 1
        out = np.empty((ra.n, ca.n))
        with numeric_section():
            Minv = inverse_from_cholesky(np.array(self.L, order="F"))
            _splat_pairs(Minv, self.A, self.cc, ri, rv, ci, cv, buf)  # rr is sorted (row-major order)
            _filter(buf[:nq], ra.decay(rate), ca.decay(rate), g[:nq], out, qmap, self.s2)
        self._release("variance", buf, g)
        return self._unsort(out)

    def log_marginal_likelihood(self) -> float:
        """log p(y) of the observed pixels (nats)."""
        if not self.m:
            return 0.0
        logdet = 2.0 * float(np.sum(np.log(np.diag(self.L)))) + self.m * np.log(self.s2)
        quad = float(self.resid @ self.alpha) / self.s2
        return -0.5 * (quad + logdet + self.m * _LOG_2PI)
