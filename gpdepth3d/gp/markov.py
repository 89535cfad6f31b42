"""State-space (Markov) form of the one-dimensional Matern correlation.

A Matern process with nu = p + 1/2 is the first component of a p+1 dimensional linear SDE
dx = F x dt + L dW (Hartikainen & Sarkka, "Kalman filtering and smoothing solutions to temporal
Gaussian process regression models", MLSP 2010). Sampled at sorted coordinates x_0 < ... < x_{n-1}
the states form a Gauss-Markov chain,

    x_0 ~ N(0, P_inf),   x_{i+1} = A_i x_i + q_i,   A_i = expm(F d_i),   q_i ~ N(0, P_inf - A_i P_inf A_i^T),

so the joint precision of all states is block tridiagonal with d x d blocks (d = p + 1). For
nu = 0.5 (d = 1) this is the Ornstein-Uhlenbeck precision with rho_i = exp(-d_i / l). The
separable 2-D field then has the Kronecker precision Qv (x) Qu over (row state, column state)
pairs, which is what `gpdepth3d.gp.fast` factorises.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.linalg
import scipy.special
import scipy.sparse as sp

from ..errors import InvalidInputError


def state_dim(nu: float) -> int:
    """Number of states per coordinate of the Matern-nu SDE (nu = 0.5, 1.5, 2.5 -> 1, 2, 3)."""
    if nu not in (0.5, 1.5, 2.5):
        raise InvalidInputError("nu", "0.5, 1.5 or 2.5", nu)
    return int(nu + 0.5)


@lru_cache(maxsize=32)
def _sde(nu: float, lengthscale: float) -> tuple[np.ndarray, np.ndarray]:
    """Feedback matrix F (d, d) and stationary covariance P_inf (d, d), unit variance."""
    d = state_dim(nu)
    lam = np.sqrt(2.0 * nu) / lengthscale
    coeffs = [scipy.special.comb(d, k) * lam ** (d - k) for k in range(d)]  # (s + lam)^d, low order first
    F = np.zeros((d, d))
    F[np.arange(d - 1), np.arange(1, d)] = 1.0
    F[d - 1, :] = -np.asarray(coeffs)
    Lq = np.zeros((d, d))
    Lq[d - 1, d - 1] = 1.0
    P = scipy.linalg.solve_continuous_lyapunov(F, -Lq)
    P = 0.5 * (P + P.T) / P[0, 0]
    return F, P


def transition(nu: float, lengthscale: float, delta: float) -> np.ndarray:
    """State transition A = expm(F delta) (d, d) over a coordinate step delta >= 0."""
    F, _ = _sde(float(nu), float(lengthscale))
    if F.shape == (1, 1):
        return np.array([[np.exp(F[0, 0] * delta)]])
    return scipy.linalg.expm(F * delta)


def stationary_cov(nu: float, lengthscale: float) -> np.ndarray:
    """Stationary state covariance P_inf (d, d) of the unit-variance Matern SDE."""
    return _sde(float(nu), float(lengthscale))[1].copy()


def chain_precision(coords: np.ndarray, nu: float, lengthscale: float) -> tuple[sp.csr_matrix, float]:
    """Joint precision of the SDE states at sorted distinct coordinates.

    Args:
        coords: (n,) strictly increasing coordinates (pixels).
        nu: Matern smoothness.
        lengthscale: Length scale in the units of ``coords``.

    Returns:
        The (n d, n d) block-tridiagonal precision (state index i * d + k) of unit-variance
        states, and its log-determinant.
    """
    x = np.asarray(coords, dtype=np.float64)
    if x.ndim != 1 or x.size == 0 or np.any(np.diff(x) <= 0):
        raise InvalidInputError("coords", "a non-empty strictly increasing 1-D array", x)
    F, P = _sde(float(nu), float(lengthscale))
    d = F.shape[0]
    n = x.shape[0]
    J = np.zeros((n, d, d))
    off = np.zeros((max(n - 1, 0), d, d))  # block (i + 1, i)
    Pinv = np.linalg.inv(P)
    J[0] += Pinv
    logdet_cov = np.linalg.slogdet(P)[1]
    deltas = np.diff(x)
    cache: dict[float, tuple[np.ndarray, np.ndarray, float]] = {}
    for i, dlt in enumerate(deltas):
        key = float(dlt)
        if key not in cache:
            A = transition(nu, lengthscale, key)
            Qn = P - A @ P @ A.T
            Qi = np.linalg.inv(0.5 * (Qn + Qn.T))
            cache[key] = (A, Qi, np.linalg.slogdet(Qn)[1])
        A, Qi, ld = cache[key]
        J[i] += A.T @ Qi @ A
        J[i + 1] += Qi
        off[i] = -Qi @ A
        logdet_cov += ld
    rows, cols, vals = [], [], []
    ii, kk, ll = np.meshgrid(np.arange(n), np.arange(d), np.arange(d), indexing="ij")
    rows.append((ii * d + kk).ravel())
    cols.append((ii * d + ll).ravel())
    vals.append(J.ravel())
    if n > 1:
        ii, kk, ll = np.meshgrid(np.arange(n - 1), np.arange(d), np.arange(d), indexing="ij")
        r, c = ((ii + 1) * d + kk).ravel(), (ii * d + ll).ravel()
        rows += [r, c]
        cols += [c, r]
        vals += [off.ravel(), off.ravel()]
    Q = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * d, n * d))
    return Q, -float(logdet_cov)


def _cross_cov(nu: float, lengthscale: float, t: float, s: float) -> np.ndarray:
    """Cov(x(t), x(s)) (d, d) of the unit-variance stationary SDE states."""
    F, P = _sde(float(nu), float(lengthscale))
    if t >= s:
        return transition(nu, lengthscale, t - s) @ P
    return P @ transition(nu, lengthscale, s - t).T


def readout_weights(
    coords: np.ndarray, targets: np.ndarray, nu: float, lengthscale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kriging weights of the field value at each target on the states of its grid neighbours.

    By the Markov property, E[f(t) | all states on the grid] depends only on the states at the
    nearest grid coordinate on each side of t (one side outside the grid, one node when t is a
    grid coordinate).

    Args:
        coords: (n,) strictly increasing grid coordinates, n >= 2.
        targets: (m,) target coordinates (anywhere).
        nu: Matern smoothness.
        lengthscale: Length scale.

    Returns:
        first: (m,) index of the left node of the two-node block [first, first + 1] used.
        weights: (m, 2, d) weights on the states of nodes first and first + 1.
        resid: (m,) conditional variance 1 - Var(E[f(t) | states]) of the unit-variance field.
    """
    x = np.asarray(coords, dtype=np.float64)
    t = np.asarray(targets, dtype=np.float64)
    n = x.shape[0]
    d = state_dim(nu)
    if n < 2:
        raise InvalidInputError("coords", "at least 2 grid coordinates", n)
    first = np.clip(np.searchsorted(x, t, side="right") - 1, 0, n - 2)
    weights = np.zeros((t.shape[0], 2, d))
    resid = np.zeros(t.shape[0])
    P = stationary_cov(nu, lengthscale)
    cache: dict[tuple, tuple[np.ndarray, float]] = {}
    for j, tj in enumerate(t):
        i = int(first[j])
        a, b = x[i], x[i + 1]
        if tj == a or tj == b:
            weights[j, 0 if tj == a else 1, 0] = 1.0
            continue
        if tj < a:
            key, nodes = ("left", a - tj), [0]
        elif tj > b:
            key, nodes = ("right", tj - b), [1]
        else:
            key, nodes = ("mid", tj - a, b - tj), [0, 1]
        if key not in cache:
            pos = [a, b]
            sel = [pos[k] for k in nodes]
            S = np.block([[_cross_cov(nu, lengthscale, p, q) for q in sel] for p in sel])
            c = np.concatenate([_cross_cov(nu, lengthscale, tj, p)[0] for p in sel])
            w = np.linalg.solve(S, c)
            cache[key] = (w, max(P[0, 0] - float(c @ w), 0.0))
        w, r = cache[key]
        for k, node in enumerate(nodes):
            weights[j, node] = w[k * d : (k + 1) * d]
        resid[j] = r
    return first, weights, resid
