"""Posterior of a diagonally dominant precision (nu = 0.5) by a Neumann series with a certified bound.

The ``fast`` engine's route when every pixel is observed strongly (the paper's balanced set-up):
the omitted terms are bounded by `NEUMANN_MEAN_TOL` / `NEUMANN_VAR_TOL`. Derivation:
docs/engines.md#the-neumann-route-in-detail.
"""

from __future__ import annotations

from functools import lru_cache

import numba as nb
import numpy as np

from .compile_wait import ready as compiled_ahead
from .markov import chain_precision
from .model import GridProblem
from .multifrontal import numeric_section

# Tolerances of the series (bounds on the omitted terms): relative to max |M^-1/2 b| for the mean
# (the error of a pixel's mean is at most sqrt(max M / M_i) times that, times the largest
# residual), relative to each variance.
# The variance's 2e-9 keeps standard deviations within 1e-9 of the exact ones.
NEUMANN_MEAN_TOL = 1e-13
NEUMANN_VAR_TOL = 2e-9
_PAD = 8  # zero border of the coefficient images: windows of up to 2 * _PAD - 1 pixels need no bounds checks
MAX_VARIANCE_TERMS = 2 * _PAD - 2


@lru_cache(maxsize=64)
def _tridiagonal(n: int, lengthscale: float) -> tuple[np.ndarray, np.ndarray]:
    """(diagonal (n,), super-diagonal (n - 1,)) of the unit-variance OU chain precision on 0..n-1."""
    Q, _ = chain_precision(np.arange(n, dtype=np.float64), 0.5, lengthscale)
    Q = Q.tocsr()
    return Q.diagonal().copy(), Q.diagonal(1).copy()


@nb.njit(cache=True, nogil=True, parallel=True)
def _coefficients(dv, ov, du, ou, prec, inv_s2, coef):
    """diag(P) (H, W), M^-1/2, E's 8 neighbour coefficients and rho.

    coef (H + 2 _PAD, W + 2 _PAD, 8) must be zero on entry or hold an earlier call's values for
    the same shape: entries without a neighbour in the grid are never written, so they stay zero.

    Neighbour k = 0..7 is the offset (dr, dc) in (-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1),
    (1, -1), (1, 0), (1, 1); E[(r, c), (r + dr, c + dc)] = -Qv[r, r + dr] Qu[c, c + dc] / s^2 /
    sqrt(M_i M_j).
    """
    h, w = prec.shape
    M = np.empty((h, w))
    isq = np.zeros((h + 2, w + 2))
    rowmax = np.zeros(h)
    for r in nb.prange(h):
        for c in range(w):
            M[r, c] = dv[r] * du[c] * inv_s2 + prec[r, c]
            isq[r + 1, c + 1] = 1.0 / np.sqrt(M[r, c])
    for r in nb.prange(h):
        for c in range(w):
            total = 0.0
            k = 0
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= h:
                    qv = 0.0
                else:
                    qv = dv[r] if dr == 0 else (ov[r] if dr == 1 else ov[r - 1])
                for dc in range(-1, 2):
                    if dr == 0 and dc == 0:
                        continue
                    cc = c + dc
                    if cc < 0 or cc >= w:
                        qu = 0.0
                    else:
                        qu = du[c] if dc == 0 else (ou[c] if dc == 1 else ou[c - 1])
                    # isq is zero outside the grid, so a missing neighbour gives 0
                    e = -qv * qu * inv_s2 * isq[r + 1, c + 1] * isq[rr + 1, cc + 1]
                    coef[r + _PAD, c + _PAD, k] = e
                    total += abs(e)
                    k += 1
            rowmax[r] = max(rowmax[r], total)
    return M, isq[1:-1, 1:-1].copy(), coef, rowmax.max()


@nb.njit(cache=True, nogil=True, inline="always")
def _apply_at(coef, r, c, x, a, b):
    """(E x)_(r, c) for a window x whose cell (a, b) is pixel (r, c) (coef indices unpadded + _PAD)."""
    e = coef[r + _PAD, c + _PAD]
    return (
        e[0] * x[a - 1, b - 1]
        + e[1] * x[a - 1, b]
        + e[2] * x[a - 1, b + 1]
        + e[3] * x[a, b - 1]
        + e[4] * x[a, b + 1]
        + e[5] * x[a + 1, b - 1]
        + e[6] * x[a + 1, b]
        + e[7] * x[a + 1, b + 1]
    )


@nb.njit(cache=True, nogil=True)
def _neumann_mean(coef, cvec, terms):
    """z = sum_{k <= terms} E^k c (Horner form z <- c + E z); c, z (H, W)."""
    h, w = cvec.shape
    z = np.zeros((h + 2, w + 2))
    z[1:-1, 1:-1] = cvec
    nxt = z.copy()
    for _ in range(terms):
        _horner_step(coef, cvec, z, nxt)
        z, nxt = nxt, z
    return z[1:-1, 1:-1].copy()


@nb.njit(cache=True, nogil=True, parallel=True)
def _horner_step(coef, cvec, z, nxt):
    """nxt = c + E z over the interior of the one-pixel-padded images z, nxt."""
    h, w = cvec.shape
    for r in nb.prange(h):
        for c in range(w):
            nxt[r + 1, c + 1] = cvec[r, c] + _apply_at(coef, r, c, z, r + 1, c + 1)


@nb.njit(cache=True, nogil=True, parallel=True)
def _diag_series(coef, h, w, terms):
    """(H, W) image of sum_{k <= terms} (E^k)_ii by local walks (docs/engines.md#the-neumann-route-in-detail).

    Per pixel i, v_j = E^j e_i lives on a flat window of side S around i (cell a * S + b is pixel
    (r + a - C, c + b - C), C the centre). v_(j+1) = E v_j is scattered from the support of v_j:
    cell q adds v_j[q] times its own 8 coefficients (E symmetric: E[q + d, q] = E[q, q + d]).
    """
    J = (terms + 1) // 2
    S = 2 * J + 3  # v_j has radius <= J; one zero border
    C = J + 1
    ws = w + 2 * _PAD
    flat = coef.reshape(-1)
    out = np.empty((h, w))
    for r in nb.prange(h):
        va = np.zeros(S * S)
        vb = np.zeros(S * S)
        for c in range(w):
            total = 1.0
            va[:] = 0.0
            va[C * S + C] = 1.0  # v_0 = e_i
            for j in range(1, J + 1):
                for a in range(C - j, C + j + 1):  # v_j's support, cleared
                    for b in range(C - j, C + j + 1):
                        vb[a * S + b] = 0.0
                for a in range(C - j + 1, C + j):  # scatter from v_(j-1)'s support
                    for b in range(C - j + 1, C + j):
                        x = va[a * S + b]
                        if x == 0.0:
                            continue
                        q = a * S + b
                        f = ((r + a - C + _PAD) * ws + c + b - C + _PAD) * 8
                        vb[q - S - 1] += flat[f] * x
                        vb[q - S] += flat[f + 1] * x
                        vb[q - S + 1] += flat[f + 2] * x
                        vb[q - 1] += flat[f + 3] * x
                        vb[q + 1] += flat[f + 4] * x
                        vb[q + S - 1] += flat[f + 5] * x
                        vb[q + S] += flat[f + 6] * x
                        vb[q + S + 1] += flat[f + 7] * x
                dot_prev = 0.0
                for a in range(C - j + 1, C + j):
                    for b in range(C - j + 1, C + j):
                        dot_prev += va[a * S + b] * vb[a * S + b]
                total += dot_prev  # (E^(2j-1))_ii = v_(j-1) . v_j
                if 2 * j <= terms:
                    norm2 = 0.0
                    for a in range(C - j, C + j + 1):
                        for b in range(C - j, C + j + 1):
                            v = vb[a * S + b]
                            norm2 += v * v
                            va[a * S + b] = v
                    total += norm2  # (E^(2j))_ii = |v_j|^2
            out[r, c] = total
    return out


class NeumannPosterior:
    """Posterior of a nu = 0.5 `GridProblem` on its own grid by the Neumann series of the scaled precision.

    Args:
        problem: The grid problem (nu = 0.5).
        workspace: A dict that keeps a free coefficient buffer for the next problem of the same
            shape (the engine keeps one); this object takes it and `release` hands it back.

    Attributes:
        rho: The bound max_i sum_j |E_ij| on ||E|| (the series converges when < 1).
    """

    def __init__(self, problem: GridProblem, workspace: dict | None = None):
        k = problem.kernel
        if not k.exponential:
            raise ValueError("internal error: the Neumann route needs the exponential kernel (nu = 0.5)")
        compiled_ahead("neumann")  # a cold cache: the route's kernels come from the second process
        self.problem = problem
        h, w = problem.shape
        dv, ov = _tridiagonal(h, float(k.lengthscale))
        du, ou = _tridiagonal(w, float(k.lengthscale))
        prec = np.ascontiguousarray(problem.precision, dtype=np.float64)
        shape = (h + 2 * _PAD, w + 2 * _PAD, 8)
        coef = workspace.pop("free", None) if workspace is not None else None  # dict.pop: one taker
        if coef is None or coef.shape != shape:
            coef = np.zeros(shape)
        self._workspace = workspace
        with numeric_section():  # numba parallel regions: one at a time per process
            self.M, self.isq, self.coef, rho = _coefficients(
                dv, ov, du, ou, prec, 1.0 / float(k.outputscale) ** 2, coef
            )
        self.rho = float(rho)

    def release(self) -> None:
        """Hands the coefficient buffer back to the workspace it came from (no use of this object after)."""
        if self._workspace is not None:
            self._workspace["free"] = self.coef
        self._workspace = None

    def terms(self, tol: float) -> int | None:
        """Smallest K with rho^(K+1) / (1 - rho) <= tol (None if the series does not converge)."""
        if not self.rho < 1.0:
            return None
        if self.rho == 0.0:
            return 0
        return max(0, int(np.ceil(np.log(tol * (1.0 - self.rho)) / np.log(self.rho))) - 1)

    def seconds(self, variance: bool) -> float | None:
        """Seconds of this route at the default tolerances, None when too slow to take.

        Per pixel and term for the mean, per multiply-add (8 per window cell) for the variance's
        local walks; rates fitted as `gpdepth3d.gp.cost_model`'s.
        """
        n = self.M.size
        km, kv = self.terms(NEUMANN_MEAN_TOL), self.terms(NEUMANN_VAR_TOL)
        if km is None or km > 200 or (variance and kv > MAX_VARIANCE_TERMS):
            return None
        t = n * (50e-9 + 8e-9 * km)
        if variance:
            cells = sum((2 * j + 1) ** 2 if 2 * j <= kv else (2 * j - 1) ** 2 for j in range(1, (kv + 1) // 2 + 1))
            t += n * cells * 8 * 0.7e-9
        return t

    def mean(self, terms: int, obs: np.ndarray | None = None) -> np.ndarray:
        """Posterior mean (H, W) in metres with ``terms`` terms of the series.

        Args:
            terms: Terms of the series (`terms`).
            obs: Another (H, W) observation array to use instead of the problem's (same precision).
        """
        p = self.problem
        prec = np.asarray(p.precision, np.float64)
        y = np.asarray(p.obs if obs is None else obs, np.float64)
        b = np.where(prec > 0, prec * (y - np.asarray(p.prior_mean, np.float64)), 0.0)
        with numeric_section():
            z = _neumann_mean(self.coef, b * self.isq, int(terms))
        return np.asarray(p.out_prior_mean, np.float64) + z * self.isq

    def variance(self, terms: int) -> np.ndarray:
        """Posterior marginal variance (H, W) in m^2 with ``terms`` (<= MAX_VARIANCE_TERMS) terms of the series."""
        if not 0 <= terms <= MAX_VARIANCE_TERMS:
            raise ValueError(f"internal error: terms must be in [0, {MAX_VARIANCE_TERMS}], got {terms}")
        h, w = self.M.shape
        with numeric_section():
            return _diag_series(self.coef, h, w, int(terms)) / self.M
