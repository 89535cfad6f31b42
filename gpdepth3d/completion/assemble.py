"""Stage 6 of the default model: the depth's posterior mean and variance at every output pixel (docs/model.md).

From the field's stationary posterior (E0[g], Var0[g]) and the extra read-outs (w1 = k(x)' (K + N)^-1 1,
wx = k(x)' (K + N)^-1 (x - c)), each output pixel gets, in one compiled pass::

    rho  = exp(-|a| |x - c - wx / w1| / l_z)           in (0, 1]; 1 where |w1| < floor or l_z is off
    mu   = log MDE'(x) + b + rho E0[g]
    v    = (1 - rho^2) s^2 + rho^2 Var0[g] + tau^2 + Var[b] (1 - rho w1)^2 + Var[a] (x - c - rho wx)^2
    mean = exp(mu + v / 2),   variance = (e^v - 1) mean^2

Every term of v is >= 0, so the variance is >= 0 by construction: with rho in (0, 1] the field's part is
the marginal posterior of g(x) = rho g0(x) + sqrt(1 - rho^2) h(x), h independent with the prior variance s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange, uint64

from ..errors import InvalidInputError
from ..gp.model import DepthGPConfig
from .lattice import Lattice
from .log_frame import LogFrame
from .screen import Screened
from .mde_slope import Sloped
from .solve import FieldPosterior


@dataclass(frozen=True)
class DepthMoments:
    """The log-normal depth posterior on the output grid.

    Attributes:
        mean: (Ho, Wo) posterior mean depth, metres (> 0).
        variance: (Ho, Wo) its variance, m^2 (>= 0), before the calibration stage.
        mde: (Ho, Wo) the re-sloped MDE depth on the output grid, metres.
    """

    mean: np.ndarray
    variance: np.ndarray
    mde: np.ndarray


def assemble_depth(
    frame: LogFrame, sloped: Sloped, screened: Screened, lattice: Lattice, field: FieldPosterior, config: DepthGPConfig
) -> DepthMoments:
    """The depth's moments from the field, the global scale b and the slope a (see the module docstring).

    Raises:
        InvalidInputError: an MDE and points whose posterior overflows float64 (log depths far apart
            and a loosely fitted slope).
    """
    fit = screened.fit
    mde = np.exp(sloped.log_mde) if sloped.fit is not None else frame.base
    mde_out = frame.to_output(mde)
    log_out = sloped.log_mde if frame.same_grid else np.log(mde_out)
    x_out = None
    if lattice.depth_aware or lattice.slope_term:  # the raw log MDE (centred on lattice.centre in the pass)
        x_out = frame.log_mde if frame.same_grid else np.log(frame.to_output(frame.base))
    w1 = field.extra[0] if field.extra else None
    wx = field.extra[1] if len(field.extra) > 1 else None
    mean, var, bad = _read_out(
        log_out,
        field.mean,
        field.variance,
        w1,
        wx,
        x_out,
        b=fit.log_scale,
        s2=fit.outputscale**2,
        tau2=fit.nugget**2,
        var_b=fit.log_scale_var,
        var_a=sloped.fit.slope_var if lattice.slope_term else 0.0,
        a=sloped.a,
        lz=config.assembly.depth_lengthscale if lattice.depth_aware else None,
        floor=config.assembly.weight_floor,
        scale_term=lattice.scale_term,
        slope_term=lattice.slope_term,
        variance=True,
        centre=lattice.centre,
    )
    if bad:
        raise InvalidInputError(
            "mde_depth, sparse",
            "an MDE and points whose log-normal posterior is finite in float64",
            f"{bad} pixels overflow (MDE depths {float(frame.base.min()):g}-"
            f"{float(frame.base.max()):g} m, fitted slope {sloped.a:.3g})",
        )
    return DepthMoments(mean, var, mde_out)


#: The phases of `_assemble`; numpy's vectorised exponentials run between them (`_read_out`).
_RHO_EXPONENT, _LOG_MOMENTS, _MOMENTS = 0, 1, 2


@njit(cache=True, nogil=True)
def _assemble(
    log_out,
    g_mean,
    g_var,
    w1,
    wx,
    x_out,
    b,
    s2,
    tau2,
    var_b,
    var_a,
    a,
    inv_lz,
    floor,
    depth_aware,
    scale_term,
    slope_term,
    want_var,
    mean,
    var,
    centre,
    phase,
    lo,
    hi,
):  # pragma: no cover - compiled
    """One phase of the read-out of pixels lo..hi-1 (``x_out`` centred on ``centre`` here), each pixel's operations
    those of the formula in its order; the exponentials are numpy's, over the whole arrays, between the phases.

    `_RHO_EXPONENT`: ``mean`` = the exponent of rho. `_LOG_MOMENTS`: from rho (``mean`` exponentiated, read
    only where the depth-aware rho applies), ``mean`` = the log mean and ``var`` = v. `_MOMENTS`: from ``mean``
    exponentiated and ``var`` = expm1(v), ``var`` = the variance; returns 1 when one of the pixels may have a mean
    that is not finite and > 0 or a variance that is not finite (the running sum of means and variances is not
    finite, or their minimum mean not > 0), else 0. The arithmetic's loops vectorise."""
    if phase == _RHO_EXPONENT:
        for i_ in range(lo, hi):
            i = uint64(i_)  # unsigned: no check for negative indices, so the loop vectorises
            w = w1[i] if abs(w1[i]) >= floor else 1.0  # rho = 1 there: the quotient is not used
            mean[i] = -abs(a) * abs((x_out[i] - centre) - wx[i] / w) * inv_lz
        return 0
    if phase == _LOG_MOMENTS:
        for i_ in range(lo, hi):
            i = uint64(i_)  # unsigned: no check for negative indices, so the loop vectorises
            rho = mean[i] if depth_aware and abs(w1[i]) >= floor else 1.0
            mu = log_out[i] + b + rho * g_mean[i]
            v = 0.0
            if want_var:
                gv = max(g_var[i], 0.0)  # an engine's rounding below 0
                if depth_aware:
                    gv = (1.0 - rho * rho) * s2 + rho * rho * gv
                if scale_term:
                    t = 1.0 - rho * w1[i]
                    bt = var_b * t * t
                else:
                    bt = var_b
                v = gv + tau2 + bt
                if slope_term:
                    t = (x_out[i] - centre) - rho * wx[i]
                    v += var_a * t * t
                var[i] = v
            mean[i] = mu + 0.5 * v
        return 0
    total, low = 0.0, math.inf
    for i_ in range(lo, hi):
        i = uint64(i_)
        m = mean[i]
        low = min(low, m)
        total += m
        if want_var:
            vv = var[i] * m * m
            var[i] = vv
            total += vv
    return 0 if math.isfinite(total) and low > 0.0 else 1


#: Output pixels per parallel chunk of `_assemble_parallel`; smaller outputs run on the calling thread.
CHUNK = 65536


@njit(cache=True, nogil=True, parallel=True)
def _assemble_parallel(*args):  # pragma: no cover - compiled
    """`_assemble` over chunks of `CHUNK` pixels in parallel (each pixel's arithmetic is the serial one)."""
    n = args[0].size
    suspect = 0
    for c in prange((n + CHUNK - 1) // CHUNK):
        suspect += _assemble(*args, c * CHUNK, min(n, (c + 1) * CHUNK))
    return suspect


def assemble(
    log_out, g_mean, g_var, w1, wx, x_out, *, b, s2, tau2, var_b, var_a, a, lz, floor, scale_term, slope_term, variance
):
    """Posterior mean and variance (depth, m and m^2) of every output pixel, as arrays (the compiled pass).

    ``w1``, ``wx``, ``x_out`` may be None when neither the depth-aware correlation (``lz`` None),
    the scale term nor the slope term needs them (``x_out`` centred); ``g_var`` may be None without ``variance``.
    Returns (mean, variance) with the shape of ``log_out`` (variance NaN without ``variance``).
    """
    terms = dict(b=b, s2=s2, tau2=tau2, var_b=var_b, var_a=var_a, a=a, lz=lz, floor=floor, scale_term=scale_term)
    mean, var, _ = _read_out(log_out, g_mean, g_var, w1, wx, x_out, **terms, slope_term=slope_term, variance=variance)
    return mean, var


def _read_out(
    log_out,
    g_mean,
    g_var,
    w1,
    wx,
    x_out,
    *,
    b,
    s2,
    tau2,
    var_b,
    var_a,
    a,
    lz,
    floor,
    scale_term,
    slope_term,
    variance,
    centre=0.0,
):
    """`assemble` with ``x_out`` centred on ``centre`` in the pass; also returns how many pixels have a mean that is
    not finite and > 0 or (with ``variance``) a variance that is not finite (counted only when the pass saw one)."""
    shape = log_out.shape
    flat = lambda x: np.ascontiguousarray(x, dtype=np.float64).ravel()  # noqa: E731
    zeros = np.zeros(1)
    depth_aware = lz is not None
    mean = np.empty(log_out.size)
    var = np.empty(log_out.size) if variance else zeros
    kernel = _assemble_parallel if log_out.size > CHUNK else _assemble
    args = (
        flat(log_out),
        flat(g_mean),
        flat(g_var) if variance else zeros,
        flat(w1) if w1 is not None else zeros,
        flat(wx) if wx is not None else zeros,
        flat(x_out) if x_out is not None else zeros,
        float(b),
        float(s2),
        float(tau2),
        float(var_b),
        float(var_a),
        float(a),
        1.0 / float(lz) if depth_aware else 0.0,
        float(floor),
        bool(depth_aware),
        bool(scale_term and variance),
        bool(slope_term and variance),
        bool(variance),
        mean,
        var,
        float(centre),
    )
    span = (0, log_out.size) if kernel is _assemble else ()
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is counted below
        if depth_aware:
            kernel(*args, _RHO_EXPONENT, *span)
            np.exp(mean, out=mean)
        kernel(*args, _LOG_MOMENTS, *span)
        np.exp(mean, out=mean)
        if variance:
            np.expm1(var, out=var)
        suspect = kernel(*args, _MOMENTS, *span)
    mean, var = mean.reshape(shape), (var.reshape(shape) if variance else np.full(shape, np.nan))
    bad = 0
    if suspect:  # NaN fails every comparison
        bad = int(np.count_nonzero(~((mean > 0) & np.isfinite(mean) & (np.isfinite(var) if variance else True))))
    return mean, var, bad
