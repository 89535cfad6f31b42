r"""The prior kernel: the separable Matérn family, its correlation, state-space form and precision stencil.

Every smoothness-dependent formula of the package lives here; engines and stages ask the kernel object
(`MaternKernel.state_dim`, `MaternKernel.exponential`, `MaternKernel.code` for compiled code) instead of
branching on ``nu``. A new smoothness is one entry of `SMOOTHNESS` with its formula in `_unit_matern`
and `matern_1d`; a route that relies on a property of the kernel states it as a capability flag
(`gpdepth3d.gp.routes`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numba as nb
import numpy as np
import scipy.linalg
import scipy.special

from ..errors import InvalidInputError

SMOOTHNESS: tuple[float, ...] = (0.5, 1.5, 2.5)
"""The Matérn smoothnesses nu the package computes (half-integers: each has a finite state-space form)."""


def check_nu(nu) -> float:
    """``nu`` as a float when it is one of `SMOOTHNESS`, else `InvalidInputError` naming ``nu``."""
    real = not isinstance(nu, (bool, np.bool_)) and isinstance(nu, (int, float, np.integer, np.floating))
    if not real or nu not in SMOOTHNESS:
        expected = ", ".join(f"{v:g}" for v in SMOOTHNESS[:-1]) + f" or {SMOOTHNESS[-1]:g}"
        raise InvalidInputError("nu", expected, f"{type(nu).__name__} {nu!r}")
    return float(nu)


def smoothness_code(nu: float) -> int:
    """The index of ``nu`` in `SMOOTHNESS`: the number compiled (numba) code receives for the kernel."""
    return SMOOTHNESS.index(check_nu(nu))


def state_dim(nu: float) -> int:
    """Number of states per coordinate of the Matérn-nu SDE, nu + 1/2 (0.5, 1.5, 2.5 -> 1, 2, 3)."""
    return int(check_nu(nu) + 0.5)


def is_exponential(nu: float) -> bool:
    """True for nu = 1/2: the exponential kernel, a first-order Markov chain along each axis."""
    return smoothness_code(nu) == 0


def matern_1d(distance: np.ndarray, nu: float, lengthscale: float) -> np.ndarray:
    """One-dimensional Matérn correlation M_nu(|d| / l) (1 at d = 0); see `MaternKernel` for M_nu."""
    r = np.abs(np.asarray(distance, dtype=np.float64)) / lengthscale
    code = smoothness_code(nu)
    if code == 0:
        return np.exp(-r)
    if code == 1:
        a = np.sqrt(3.0) * r
        return (1.0 + a) * np.exp(-a)
    a = np.sqrt(5.0) * r
    return (1.0 + a + a * a / 3.0) * np.exp(-a)


def separable_correlation(dr: np.ndarray, dc: np.ndarray, lengthscale: float, nu: float) -> np.ndarray:
    """Separable Matérn correlation M_nu(|dr| / l) M_nu(|dc| / l) of row and column offsets (any matching shapes)."""
    if is_exponential(nu):  # the separable exponential is one exponential of the L1 distance
        return np.exp(-(np.abs(dr) + np.abs(dc)) / lengthscale)
    return matern_1d(dr, nu, lengthscale) * matern_1d(dc, nu, lengthscale)


@nb.njit(cache=True, nogil=True)
def unit_correlation(r: float, code: int) -> float:  # pragma: no cover - compiled
    """M_nu(r) of one scaled distance r = |d| / l >= 0 for the smoothness ``code`` (`smoothness_code`)."""
    if code == 0:
        return math.exp(-r)
    if code == 1:
        a = math.sqrt(3.0) * r
        return (1.0 + a) * math.exp(-a)
    a = math.sqrt(5.0) * r
    return (1.0 + a + a * a / 3.0) * math.exp(-a)


@nb.njit(cache=True, nogil=True)
def unit_separable_correlation(a: float, b: float, code: int) -> float:  # pragma: no cover - compiled
    """M_nu(a) M_nu(b) of two scaled distances a, b >= 0 for the smoothness ``code`` (one exponential)."""
    if code == 0:
        return math.exp(-(a + b))
    if code == 1:
        a, b = math.sqrt(3.0) * a, math.sqrt(3.0) * b
        return (1.0 + a) * (1.0 + b) * math.exp(-(a + b))
    a, b = math.sqrt(5.0) * a, math.sqrt(5.0) * b
    return (1.0 + a + a * a / 3.0) * (1.0 + b + b * b / 3.0) * math.exp(-(a + b))


@lru_cache(maxsize=8)
def unit_sde(d: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """State-space form of the Matérn field with nu = d - 1/2 and lam = sqrt(2 nu) / l = 1.

    The SDE dx = F x dt + L dW has the characteristic polynomial (s + 1)^d (Hartikainen & Särkkä,
    MLSP 2010), so F is the companion matrix of its binomial coefficients.

    Returns:
        Feedback F (d, d), stationary covariance P (d, d) and noise covariance G (d, d), scaled to a
        unit variance of the first state.
    """
    coeffs = [scipy.special.comb(d, k) for k in range(d)]  # (s + 1)^d, low order first
    F = np.zeros((d, d))
    F[np.arange(d - 1), np.arange(1, d)] = 1.0
    F[d - 1, :] = -np.asarray(coeffs)
    Lq = np.zeros((d, d))
    Lq[d - 1, d - 1] = 1.0
    P = scipy.linalg.solve_continuous_lyapunov(F, -Lq)
    c = P[0, 0]
    return F, 0.5 * (P + P.T) / c, Lq / c


@dataclass(frozen=True)
class MaternKernel:
    r"""Separable Matérn kernel on pixel coordinates, in physical units (metres, pixels).

    .. math::

        k((u, v), (u', v')) = s^2 \, M_\nu(|u - u'| / l) \, M_\nu(|v - v'| / l),

        M_{1/2}(r) = e^{-r}, \quad
        M_{3/2}(r) = (1 + \sqrt{3} r) e^{-\sqrt{3} r}, \quad
        M_{5/2}(r) = (1 + \sqrt{5} r + 5 r^2 / 3) e^{-\sqrt{5} r}.

    Its three faces, used by different engines:

    * correlation: `correlation`, `separable_correlation`, `matrix` (the dense and kriging engines);
    * state space: M_nu is the first state of a linear SDE with d = nu + 1/2 states (`state_dim`,
      `state_space`), so samples along an axis form a Gauss-Markov chain (`gpdepth3d.gp.markov`);
    * precision stencil: each axis has a block-tridiagonal chain precision of d x d blocks, so the
      separable field's precision Qv (x) Qu is a 9-point stencil of `stencil_block` = d^2 entries per
      pixel pair (`gpdepth3d.gp.grid_prior`). For nu = 1/2 (`exponential`) the blocks are scalars and
      the 2-D correlation is one exponential of the L1 distance: the Woodbury, Neumann and sub-lattice
      routes need this.

    Attributes:
        nu: Smoothness, one of `SMOOTHNESS`.
        lengthscale: l, pixels of the GP grid.
        outputscale: s, the prior standard deviation (metres, or the units of the field).
    """

    nu: float
    lengthscale: float
    outputscale: float

    def __post_init__(self) -> None:
        check_nu(self.nu)

    @property
    def code(self) -> int:
        """The smoothness as the int compiled code receives (`smoothness_code`)."""
        return smoothness_code(self.nu)

    @property
    def state_dim(self) -> int:
        """States per coordinate of the state-space form, d = nu + 1/2."""
        return state_dim(self.nu)

    @property
    def stencil_block(self) -> int:
        """Entries of one pixel pair's block of the precision stencil, d^2."""
        return self.state_dim**2

    @property
    def exponential(self) -> bool:
        """Capability: nu = 1/2, a first-order Markov chain per axis (scalar precision stencil)."""
        return is_exponential(self.nu)

    def correlation(self, distance: np.ndarray) -> np.ndarray:
        """1-D correlation M_nu(|d| / l) of offsets ``distance`` (pixels, any shape)."""
        return matern_1d(distance, self.nu, self.lengthscale)

    def lag_correlation(self, n: int) -> np.ndarray:
        """(n,) correlations M_nu(k / l) at the integer lags k = 0 .. n - 1 (a table for grid offsets)."""
        if self.exponential:
            return np.exp(-(1.0 / float(self.lengthscale)) * np.arange(n))
        return self.correlation(np.arange(n, dtype=np.float64))

    def separable_correlation(self, dr: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """Correlation M_nu(|dr| / l) M_nu(|dc| / l) of row and column offsets (matching shapes)."""
        return separable_correlation(dr, dc, self.lengthscale, self.nu)

    def state_space(self) -> tuple[np.ndarray, np.ndarray]:
        """Feedback F (d, d) and stationary covariance P_inf (d, d) of the states x_k = f^(k) / lam^k.

        lam = sqrt(2 nu) / l; scaling the derivatives to unit time keeps P_inf O(1) at any length scale.
        """
        F, P, _ = unit_sde(self.state_dim)
        return F * (math.sqrt(2.0 * self.nu) / self.lengthscale), P.copy()

    def factor(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """1-D correlation matrix between coordinate vectors a (n,) and b (m,)."""
        return matern_1d(np.subtract.outer(np.asarray(a, float), np.asarray(b, float)), self.nu, self.lengthscale)

    def matrix(self, rows_a, cols_a, rows_b, cols_b) -> np.ndarray:
        """Dense kernel matrix (n, m) between point sets given by their (row, col) coordinates."""
        if self.exponential:  # exp(-|du| / l) exp(-|dv| / l) as one exponential
            du = np.abs(np.subtract.outer(np.asarray(rows_a, float), np.asarray(rows_b, float)))
            du += np.abs(np.subtract.outer(np.asarray(cols_a, float), np.asarray(cols_b, float)))
            du *= -1.0 / self.lengthscale  # in place: the (n, m) temporaries are the cost at a few hundred points
            np.exp(du, out=du)
            du *= self.outputscale**2
            return du
        return self.outputscale**2 * self.factor(rows_a, rows_b) * self.factor(cols_a, cols_b)


Kernel = MaternKernel
"""The name the engines and `GridProblem` use for the prior kernel."""
