"""The log-residual posterior's per-pixel read-out as one compiled pass (see `gpdepth3d.gp.model`).

From the engine's stationary posterior of g (mean, variance) and the kriging weights of the extra
right-hand sides (sum w1 = k(x)' (K + N)^-1 1, log-MDE-weighted wx = k(x)' (K + N)^-1 (x - c)),
each output pixel gets

    rho = exp(-a |x - c - wx / w1| / l_z)          (depth-aware; 1 where |w1| < floor or off)
    mu  = log MDE'(x) + b + rho E0[g]
    v   = s^2 - rho^2 (s^2 - Var0[g]) + tau^2 + Var[b] (1 - rho w1)^2 + Var[a] (x - c - rho wx)^2
    mean = exp(mu + v / 2),  variance = (e^v - 1) mean^2

without the dozens of full-image temporaries the same formula costs in NumPy (at KITTI's full
resolution ~0.5 M pixels each).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _assemble(log_out, g_mean, g_var, w1, wx, x_out, b, s2, tau2, var_b, var_a, a, inv_lz, floor,
              depth_aware, scale_term, slope_term, want_var, mean, var):  # pragma: no cover - compiled
    n = log_out.size
    for i in range(n):
        rho = 1.0
        if depth_aware and abs(w1[i]) >= floor:
            rho = math.exp(-a * abs(x_out[i] - wx[i] / w1[i]) * inv_lz)
        mu = log_out[i] + b + rho * g_mean[i]
        v = 0.0
        if want_var:
            gv = g_var[i]
            if depth_aware:
                gv = s2 - rho * rho * (s2 - gv)
            if scale_term:
                t = 1.0 - rho * w1[i]
                bt = var_b * t * t
            else:
                bt = var_b
            v = gv + tau2 + bt
            if slope_term:
                t = x_out[i] - rho * wx[i]
                v += var_a * t * t
        m = math.exp(mu + 0.5 * v)
        mean[i] = m
        if want_var:
            var[i] = math.expm1(v) * m * m


def assemble(log_out, g_mean, g_var, w1, wx, x_out, *, b, s2, tau2, var_b, var_a, a, lz, floor,
             scale_term, slope_term, variance):
    """Posterior mean and variance (depth, m and m^2) of every output pixel; see the module docstring.

    ``w1``, ``wx``, ``x_out`` may be None when neither the depth-aware correlation (``lz`` None),
    the scale term nor the slope term needs them; ``g_var`` may be None without ``variance``.
    Returns (mean, variance) with the shape of ``log_out`` (variance NaN without ``variance``).
    """
    shape = log_out.shape
    flat = lambda x: np.ascontiguousarray(x, dtype=np.float64).ravel()  # noqa: E731
    zeros = np.zeros(1)
    depth_aware = lz is not None
    mean = np.empty(log_out.size)
    var = np.empty(log_out.size) if variance else zeros
    _assemble(
        flat(log_out), flat(g_mean), flat(g_var) if variance else zeros,
        flat(w1) if w1 is not None else zeros, flat(wx) if wx is not None else zeros,
        flat(x_out) if x_out is not None else zeros,
        float(b), float(s2), float(tau2), float(var_b), float(var_a), float(a),
        1.0 / float(lz) if depth_aware else 0.0, float(floor),
        bool(depth_aware), bool(scale_term and variance), bool(slope_term and variance), bool(variance), mean, var,
    )
    return mean.reshape(shape), (var.reshape(shape) if variance else np.full(shape, np.nan))
