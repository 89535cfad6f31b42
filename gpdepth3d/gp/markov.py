"""State-space (Markov) form of the one-dimensional Matern correlation.

A Matern process with nu = p + 1/2 is the first component of a p+1 dimensional linear SDE
dx = F x dt + L dW (Hartikainen & Sarkka, "Kalman filtering and smoothing solutions to temporal
Gaussian process regression models", MLSP 2010). Sampled at sorted coordinates x_0 < ... < x_{n-1}
the states form a Gauss-Markov chain,

    x_0 ~ N(0, P_inf),   x_{i+1} = A_i x_i + q_i,   A_i = expm(F d_i),   q_i ~ N(0, P_inf - A_i P_inf A_i^T),

so the joint precision of all states is block tridiagonal with d x d blocks (d = p + 1).
The states are f and its derivatives in units of 1 / lam = l / sqrt(2 nu) (x_k = f^(k) / lam^k),
whose covariance is O(1) at any length scale, and the process noise of a step is integrated by
quadrature for short steps (P_inf - A P_inf A^T cancels catastrophically there): both keep the
chains accurate at long length scales, where the raw form loses digits (tests/gp/test_fast.py). For
nu = 0.5 (d = 1) this is the Ornstein-Uhlenbeck precision with rho_i = exp(-d_i / l). The
separable 2-D field then has the Kronecker precision Qv (x) Qu over (row state, column state)
pairs, which is what `gpdepth3d.gp.fast` factorises.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidInputError
from .kernels import state_dim as state_dim
from .kernels import unit_sde as _unit_sde


# Gauss-Legendre rule of the process-noise integral (integrand: exponentials times polynomials of
# degree <= 2 (d - 1) on [0, h < 2]: 24 nodes integrate it to rounding).
_GAUSS = np.polynomial.legendre.leggauss(24)
# Steps (in units of 1 / lam) from which P - A P A^T loses less than ~2 digits to cancellation.
_SUBTRACT_FROM = 2.0


def _expm_unit(d: int, s: float) -> np.ndarray:
    """expm(F s) (d, d) for the lam = 1 feedback matrix: F + I is nilpotent ((s + 1)^d is its
    characteristic polynomial), so expm(F s) = e^-s sum_{k < d} ((F + I) s)^k / k! exactly."""
    N = _unit_sde(d)[0] + np.eye(d)
    out = np.eye(d)
    term = np.eye(d)
    for k in range(1, d):
        term = term @ N * (s / k)
        out = out + term
    return np.exp(-s) * out


@lru_cache(maxsize=256)
def _step(d: int, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition A = expm(F h) and process noise Q(h) = int_0^h e^{Fs} G e^{F^T s} ds (lam = 1).

    Q is computed by quadrature for short steps: the textbook P - A P A^T cancels catastrophically
    there (at h = 0.001, d = 3 it keeps no correct digit; Q's smallest entries are O(h^(2d - 1))).
    """
    F, P, G = _unit_sde(d)
    A = _expm_unit(d, h)
    if h >= _SUBTRACT_FROM:
        Q = P - A @ P @ A.T
    else:
        x, wq = _GAUSS
        Q = np.zeros((d, d))
        for s, wk in zip(0.5 * h * (x + 1.0), wq):
            E = _expm_unit(d, s)
            Q += wk * (E @ G @ E.T)
        Q *= 0.5 * h
    Q = 0.5 * (Q + Q.T)
    A.setflags(write=False)
    Q.setflags(write=False)
    return A, Q


def _lam(nu: float, lengthscale: float) -> float:
    return float(np.sqrt(2.0 * nu) / lengthscale)


def _sde(nu: float, lengthscale: float) -> tuple[np.ndarray, np.ndarray]:
    """Feedback matrix F (d, d) and stationary covariance P_inf (d, d) of the scaled states.

    The states are f and its derivatives scaled to unit time 1 / lam = l / sqrt(2 nu):
    x_k = f^(k) / lam^k. Their stationary covariance is O(1) whatever the length scale (the raw
    derivatives' variances are O(lam^(2k)): at l = 100 px and nu = 2.5 they span 7 orders and
    make the chain precision too ill-conditioned for float64).
    """
    F, P, _ = _unit_sde(state_dim(nu))
    return F * _lam(nu, lengthscale), P


def transition(nu: float, lengthscale: float, delta: float) -> np.ndarray:
    """State transition A = expm(F delta) (d, d) of the scaled states over a step delta >= 0."""
    return _step(state_dim(nu), _lam(float(nu), float(lengthscale)) * float(delta))[0].copy()


def process_noise(nu: float, lengthscale: float, delta: float) -> np.ndarray:
    """Covariance (d, d) of x(t + delta) given x(t) (scaled states), accurate for small steps."""
    return _step(state_dim(nu), _lam(float(nu), float(lengthscale)) * float(delta))[1].copy()


def stationary_cov(nu: float, lengthscale: float) -> np.ndarray:
    """Stationary covariance P_inf (d, d) of the scaled states (first state: unit variance)."""
    return _unit_sde(state_dim(nu))[1].copy()


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
    d = state_dim(nu)
    lam = _lam(float(nu), float(lengthscale))
    P = _unit_sde(d)[1]
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
            A, Qn = _step(d, lam * key)
            Qi = np.linalg.inv(Qn)
            Qi = 0.5 * (Qi + Qi.T)
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


@lru_cache(maxsize=128)
def chain_conditioning(n: int, nu: float, lengthscale: float) -> tuple[float, float]:
    """Norms (||Q||_inf, ||C||_inf) of the chain precision Q and state covariance C on 0..n-1.

    Their product bounds the condition number of the 1-D chain precision; for the separable 2-D
    field the products of the two axes bound that of the prior precision Qv (x) Qu, which is what
    limits the accuracy of a factorisation in float64 (it grows like (l / pixel)^(2 nu + 1) per axis).
    ||C||_inf is the largest row sum of |C| over lags up to n - 1 from the middle row (|C(k)| =
    |A^k P|, summed until the terms fall below 1e-17 of the total).

    Args:
        n: Number of grid coordinates (unit spacing), >= 1.
        nu: Matern smoothness.
        lengthscale: Length scale in pixels.
    """
    if int(n) < 1:
        raise InvalidInputError("n", "an integer >= 1", n)
    n = int(n)
    d = state_dim(nu)
    Q, _ = chain_precision(np.arange(min(n, 64), dtype=np.float64), nu, lengthscale)  # rows repeat beyond
    q_norm = float(abs(Q).sum(axis=1).max())
    P = _unit_sde(d)[1]
    A = _step(d, _lam(float(nu), float(lengthscale)))[0]
    total = np.abs(P).sum(axis=1)
    M = P.copy()
    for k in range(1, n):
        M = A @ M
        term = np.abs(M).sum(axis=1) * (2.0 if k < n // 2 else 1.0)
        total = total + term
        if term.max() < 1e-17 * total.max():
            break
    return q_norm, float(total.max())


def _cross_cov(nu: float, lengthscale: float, t: float, s: float) -> np.ndarray:
    """Cov(x(t), x(s)) (d, d) of the unit-variance stationary SDE states."""
    P = stationary_cov(nu, lengthscale)
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
