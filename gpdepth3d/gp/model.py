"""The GP depth model: configuration, kernel and the grid problem every engine solves.

Model (Yoon & Kim, "Balanced Depth Completion between Dense Depth Inference and Sparse Range
Measurements via KISS-GP", IROS 2020, arXiv:2008.05158)::

    f ~ GP(m(x), k(x, x')),    x = (u, v) pixel coordinates of the GP grid
    k(x, x') = s^2 * M_nu(|u - u'| / l) * M_nu(|v - v'| / l)
    MDE pixel i:          y_i = f(x_i) + e_i,  e_i ~ N(0, sigma_DL^2)   (balanced only)
    range measurement j:  z_j = f(x_j) + e_j,  e_j ~ N(0, sigma_meas^2)

``M_nu`` is the one-dimensional Matern correlation. The kernel is the *separable* (product)
Matern: this is exactly the kernel KISS-GP computes on a Kronecker grid (GPyTorch's
``GridKernel`` evaluates the base kernel per dimension and takes the Kronecker product), so it
is the kernel the paper's method used, and every engine here (``exact``, ``kissgp``, ``fast``)
computes the posterior of this one model.

Formulations:

* ``balanced`` (the paper): constant prior mean m = mean of the valid MDE depths; every valid
  MDE pixel is an observation with sigma_DL, every measurement one with sigma_meas.
* ``residual`` (beyond the paper): the prior mean is the MDE (optionally scale-aligned to the
  measurements); only measurements are observations, so the GP models the spatially correlated
  error of the MDE and keeps MDE detail where no measurement speaks.
* ``log_residual`` (the default, beyond the paper): the GP models the MDE's error as a log
  ratio, which is what a monocular network gets wrong (scale, locally and globally)::

      log d(x) = log MDE(x) + b + g(x) + w(x),   g ~ GP(0, s^2 M(du/l) M(dv/l)),  w ~ N(0, tau^2)
      measurement j:  log z_j = log d(x_j) + e_j,  e_j ~ N(0, (sigma_j / z_j)^2)

  b is a global log scale with a flat prior (generalised least squares), w the white part of the
  MDE error (the nugget). b is estimated on each frame's points (their median log ratio; with
  ``fit=True`` l, s, tau and b are fitted by marginal likelihood, `gpdepth3d.gp.points`; without,
  s is a floor that the points may raise, ``raise_outputscale``), points
  whose leave-one-out z-score given their neighbours exceeds ``outlier_threshold`` are rejected
  (judged with the edge term below added to their noise), and the engines solve for g with the
  points as observations of noise tau^2 + (sigma_j / z_j)^2. The depth posterior is log-normal: mean
  exp(mu + v/2) and variance (exp(v) - 1) exp(2 mu + v), with v = Var[g] + tau^2 + Var[b]
  (1 - k(x)' (K + N)^-1 1)^2; an edge term (``edge_sigma`` x the local MDE depth range) is
  added to the variance.

  Depth-aware correlation (``depth_lengthscale`` l_z, log-depth units): a correction learned on
  points at one depth should not carry to pixels at a very different depth (the road at 10 m
  says little about a building at 30 m right above it; a table's points little about the wall
  behind it). The cross-covariance of a pixel with the points is multiplied by
  rho(x) = exp(-|log MDE(x) - zbar(x)| / l_z), where zbar(x) is the kriging-weighted mean log
  MDE depth of the points that inform x (two further right-hand sides of the one solve: the
  weights applied to log MDE and to ones). Then E[g(x)] = rho(x) E_0[g(x)], Var[g(x)] = s^2 - rho(x)^2 (s^2 - Var_0[g(x)])
  and the scale term's weights become rho(x) k(x)' (K + N)^-1 1, with E_0, Var_0 the
  stationary posterior: exactly the posterior of the product kernel
  s^2 M(du/l) M(dv/l) exp(-|dz|/l_z) when the informing points share one MDE depth. A pixel at
  a depth no point speaks for returns to the prior (the scaled MDE, the prior variance) instead
  of inheriting a correction.

  MDE slope (``mde_slope_sigma``): the MDE's log depth enters with a coefficient a fitted per
  frame (`gpdepth3d.gp.slope`: generalised least squares on the points, prior N(1,
  mde_slope_sigma^2), Huber-robust, refitted without the rejected points), i.e. the MDE is
  re-sloped about the points' median log depth c to c + a (log MDE - c) before the model above
  sees it; the variance gains Var[a] (log MDE(x) - c - k(x)' (K + N)^-1 (log MDE - c))^2 and the
  depth-aware gap is measured on the re-sloped MDE. A network that over-states the depth
  differences of a scene (FastDepth on 7-Scenes: a = 0.4-0.7) is then trusted for its shape as
  far as the points confirm it; a = 1 is the plain model (KITTI with a KITTI-trained network).

  Means are positive by construction; errors that scale with depth
  (outdoors: a few cm at 5 m, metres at 60 m) get variances that scale with depth, and the
  fitted length scale follows the point density (short with full LiDAR, long with 50 points).

Units: with ``units="relative"`` (the default) ``outputscale``, ``sigma_dl`` and ``sigma_meas``
are fractions of the frame's depth scale (the median valid MDE depth), which makes the paper's
values (sigma_DL = 0.05, sigma_meas = 0.001: 5 % and 0.1 % of the typical depth; at KITTI's
~15 m median that is 0.75 m and 1.5 cm) behave the same on KITTI and indoors. With
``units="metres"`` they are metres. ``lengthscale`` is in pixels of the GP grid (the MDE's
resolution; the paper used l = 1.5 at 1/3 KITTI resolution). Per-point sigmas given in a
`SparseDepth` are always metres. Output: posterior mean (metres) and marginal variance (m^2)
of the latent depth f at every output pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from ..errors import InvalidInputError

Formulation = Literal["log_residual", "balanced", "residual"]
EngineName = Literal["exact", "kissgp", "fast"]


@dataclass(frozen=True)
class DepthGPConfig:
    """Hyperparameters and options of the GP depth model (see the module docstring for the maths).

    Attributes:
        formulation: "log_residual" (the default: a GP on log(depth / MDE), robust to bad
            points; see the module docstring), "balanced" (the paper: MDE pixels
            and measurements are both observations) or "residual" (MDE is the prior mean,
            measurements the only observations).
        nu: Matern smoothness, one of 0.5, 1.5, 2.5.
        lengthscale: Matern length scale, pixels of the GP grid.
        outputscale: Prior standard deviation s of the field (relative or metres, see units;
            log_residual: of the log ratio, dimensionless).
        sigma_dl: Noise of an MDE pixel (balanced formulation).
        sigma_meas: Noise of a range measurement (used where a point carries no sigma).
        units: "relative" (scales are fractions of the median MDE depth) or "metres".
        align: Residual formulation: fit the MDE to the measurements before using it as the
            prior mean: "none", "scale" (robust median ratio) or "scale_shift" (robust affine).
        engine: Which engine computes the posterior: "exact" (dense Cholesky, the reference),
            "kissgp" (GPyTorch KISS-GP, as the paper), "fast" (grid-structured, the default).
        max_exact_points: The exact engine refuses problems with more observed pixels.
        fit: Fit the hyperparameters to each frame before computing its posterior, by maximising
            the exact marginal likelihood (`gpdepth3d.completion.fit.fit_hyperparameters`: lengthscale,
            outputscale and, balanced, sigma_dl). A `DepthCompleter` warm-starts each frame's fit
            from the previous frame's values. Costs ~10-60 factorisations per frame.
            log_residual: lengthscale, outputscale and nugget are fitted on the frame's points
            (`gpdepth3d.gp.points.fit_log_residual`, a few ms).
        nugget: log_residual: standard deviation of the white (pixel-level) part of the MDE's log
            error, dimensionless (used as given when ``fit`` is False).
        outlier_threshold: log_residual: a point whose leave-one-out z-score given its
            neighbours exceeds this is rejected (reported on the posterior); None keeps all.
        edge_sigma: log_residual: extra standard deviation at MDE depth edges, as a share of
            the MDE's depth range over a 3-pixel window (colour and range sensors are never
            perfectly registered, and MDE edges are blurred); 0 turns it off.
        depth_lengthscale: log_residual: length scale of the depth-aware correlation in log-depth
            units (0.7: corrections fade to 1/e across a factor of 2 in MDE depth); None turns it
            off (the stationary pixel kernel alone). Costs two further right-hand sides of the solve.
        mde_slope_sigma: log_residual: prior standard deviation of the MDE's log-depth coefficient
            around 1, fitted per frame on the points (`gpdepth3d.gp.slope`); None fixes it at 1
            (the MDE's depth ordering taken as exact).
        raise_outputscale: log_residual with ``fit`` False: ``outputscale`` is a floor, raised per
            frame to the marginal-likelihood s of the points the screen keeps when that is larger
            (l, nugget and b as configured; `gpdepth3d.gp.points.raised_outputscale`). False keeps
            s fixed. Measured: 7-Scenes, KITTI (all protocols and densities) and vio_sparse
            unchanged (s stays 0.2 in all but 3 of ~150 frames and cells, <= 0.23); the iBims hall
            (3-20 m, FastDepth 2.5x too near) +-2 sigma 83-84 -> 88-91 %, RMSE 3.39 / 2.33 / 2.24 ->
            2.88 / 2.20 / 2.21 m at 50 / 200 / 500 points (bench/default_model.py, 3 seeds; s raised
            to 0.23-0.37; a `PosteriorWarning` above 1.25x the configured s).
        lattice_stride: log_residual: pixels of the GP grid per lattice node of the field, per
            side; None (automatic, `gpdepth3d.completion.complete.lattice_stride`): with nu = 0.5
            and an output at least as fine as the grid, where the field's detail below the lattice
            is kriged back from the points (`gpdepth3d.gp.sublattice`), 2 where the points are on at
            most 1 in 10 pixels and 4 above; otherwise 2 up to 1 in 32 and 1 above. 1 is the exact
            model on every pixel; on KITTI at 1/3 (bench/results/lattice.json) stride 2 has
            0.97-1.00x every pixel's RMSE up to 1/4 of the LiDAR in about half the time, stride 4
            0.99-1.01x from 1/2 of it on in 0.57-0.78x. The output is at any resolution either way.
        local_calibration: log_residual: the posterior variance is multiplied per pixel by the
            local mean squared leave-one-out z-score of the points, Gaussian-weighted with a radius of
            this many mean point spacings, two pseudo-points at 1 (`gpdepth3d.gp.local_calibration`):
            the variance shrinks where the points agree with their neighbours and grows where they
            do not, its level set by the data (a point with a sigma of its own enters with z^2 at
            least its noise share: errors shared between triangulated points must not shrink sigma
            between them). The z-scores are the screen's (with
            ``outlier_threshold`` None they are computed for this); frames with fewer than 10 kept
            points keep the model's variance. None turns it off. Measured (bench/calibration.py):
            AUSE 7-Scenes 0.58-0.66 -> 0.32-0.43, KITTI 0.26-0.40 -> 0.14-0.22, +-2 sigma kept in 94-97 %.
    """

    formulation: Formulation = "log_residual"
    nu: float = 0.5
    lengthscale: float = 32.0
    outputscale: float = 0.2
    sigma_dl: float = 0.05
    sigma_meas: float = 0.01
    units: Literal["relative", "metres"] = "relative"
    align: Literal["none", "scale", "scale_shift"] = "scale"
    engine: EngineName = "fast"
    max_exact_points: int = 6000
    fit: bool = False
    nugget: float = 0.02
    outlier_threshold: float | None = 3.5
    edge_sigma: float = 1.0
    depth_lengthscale: float | None = 0.7
    mde_slope_sigma: float | None = 0.5
    raise_outputscale: bool = True
    lattice_stride: int | None = None
    local_calibration: float | None = 1.5

    def __post_init__(self) -> None:
        if not isinstance(self.formulation, str) or self.formulation not in ("log_residual", "balanced", "residual"):
            raise InvalidInputError("formulation", "'log_residual', 'balanced' or 'residual'", self.formulation)
        if not _is_real(self.nu) or self.nu not in (0.5, 1.5, 2.5):
            raise InvalidInputError("nu", "0.5, 1.5 or 2.5", f"{type(self.nu).__name__} {self.nu!r}")
        object.__setattr__(self, "nu", float(self.nu))
        for name in ("lengthscale", "outputscale", "sigma_dl", "sigma_meas"):
            value = getattr(self, name)
            if not _is_real(value) or not np.isfinite(value) or not 1e-100 <= value <= 1e100:
                raise InvalidInputError(
                    name, "a finite number in [1e-100, 1e100] (> 0)", f"{type(value).__name__} {value!r}"
                )
            object.__setattr__(self, name, float(value))
        m = self.max_exact_points
        if isinstance(m, (bool, np.bool_)) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InvalidInputError("max_exact_points", "an integer >= 1", f"{type(m).__name__} {m!r}")
        object.__setattr__(self, "max_exact_points", int(m))
        if not isinstance(self.units, str) or self.units not in ("relative", "metres"):
            raise InvalidInputError("units", "'relative' or 'metres'", self.units)
        if not isinstance(self.align, str) or self.align not in ("none", "scale", "scale_shift"):
            raise InvalidInputError("align", "'none', 'scale' or 'scale_shift'", self.align)
        if not isinstance(self.engine, str) or self.engine not in ("exact", "kissgp", "fast"):
            raise InvalidInputError("engine", "'exact', 'kissgp' or 'fast'", self.engine)
        for name in ("fit", "raise_outputscale"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InvalidInputError(name, "True or False", getattr(self, name))
        for name in ("nugget", "edge_sigma"):
            value = getattr(self, name)
            if not _is_real(value) or not np.isfinite(value) or not 0 <= value <= 1e100:
                raise InvalidInputError(name, "a finite number >= 0", f"{type(value).__name__} {value!r}")
            object.__setattr__(self, name, float(value))
        k = self.lattice_stride
        if k is not None:
            if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or not 1 <= k <= 16:
                raise InvalidInputError("lattice_stride", "an integer 1-16, or None (automatic)", f"{type(k).__name__} {k!r}")
            object.__setattr__(self, "lattice_stride", int(k))
        t = self.outlier_threshold
        if t is not None and (not _is_real(t) or not np.isfinite(t) or t <= 0):
            raise InvalidInputError("outlier_threshold", "a z-score > 0, or None", f"{type(t).__name__} {t!r}")
        for name, what in (
            ("depth_lengthscale", "a log-depth length scale > 0, or None"),
            ("mde_slope_sigma", "a standard deviation > 0, or None"),
            ("local_calibration", "a reach in point spacings > 0, or None"),
        ):
            value = getattr(self, name)
            if value is not None:
                if not _is_real(value) or not np.isfinite(value) or value <= 0:
                    raise InvalidInputError(name, what, f"{type(value).__name__} {value!r}")
                object.__setattr__(self, name, float(value))

    @classmethod
    def paper(cls, **overrides) -> "DepthGPConfig":
        """The paper's balanced set-up exactly as it states it (KITTI, 1/3 resolution).

        nu = 0.5, l = 1.5 px, s = 1, sigma_DL = 0.05, sigma_meas = 0.001 (relative units), fixed
        hyperparameters, every point kept.
        """
        base = cls(
            formulation="balanced",
            lengthscale=1.5,
            outputscale=1.0,
            sigma_dl=0.05,
            sigma_meas=0.001,
            fit=False,
            outlier_threshold=None,
            edge_sigma=0.0,
            depth_lengthscale=None,
            mde_slope_sigma=None,
            local_calibration=None,
        )
        return replace(base, **overrides)

    @classmethod
    def residual(cls, **overrides) -> "DepthGPConfig":
        """Residual formulation with defaults for sparse measurements (hundreds of points).

        Defaults tuned on 7-Scenes with FastDepth at 320x240 (50-500 points; see README):
        l = 30 px and s = 0.2 x median depth give +-2 sigma coverage ~95 %.
        """
        base = cls(
            formulation="residual",
            lengthscale=30.0,
            outputscale=0.2,
            sigma_meas=0.01,
            fit=False,
            outlier_threshold=None,
            edge_sigma=0.0,
            depth_lengthscale=None,
            mde_slope_sigma=None,
            local_calibration=None,
        )
        return replace(base, **overrides)

    def replace(self, **changes) -> "DepthGPConfig":
        """A copy with some fields changed."""
        return replace(self, **changes)


def _is_real(value) -> bool:
    """True for a real number (int or float, numpy scalars included), False for bool, str, None."""
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, float, np.integer, np.floating))


def matern_1d(distance: np.ndarray, nu: float, lengthscale: float) -> np.ndarray:
    """One-dimensional Matern correlation M_nu(|d| / l) (1 at d = 0)."""
    r = np.abs(np.asarray(distance, dtype=np.float64)) / lengthscale
    if nu == 0.5:
        return np.exp(-r)
    if nu == 1.5:
        a = np.sqrt(3.0) * r
        return (1.0 + a) * np.exp(-a)
    if nu == 2.5:
        a = np.sqrt(5.0) * r
        return (1.0 + a + a * a / 3.0) * np.exp(-a)
    raise InvalidInputError("nu", "0.5, 1.5 or 2.5", nu)


def separable_correlation(dr: np.ndarray, dc: np.ndarray, lengthscale: float, nu: float) -> np.ndarray:
    """Separable Matern correlation M_nu(|dr| / l) M_nu(|dc| / l) of row and column offsets (any matching shapes)."""
    if nu == 0.5:  # the separable exponential is one exponential of the L1 distance
        return np.exp(-(np.abs(dr) + np.abs(dc)) / lengthscale)
    return matern_1d(dr, nu, lengthscale) * matern_1d(dc, nu, lengthscale)


@dataclass(frozen=True)
class Kernel:
    """Separable Matern kernel s^2 * M(du / l) * M(dv / l) in physical units (metres, pixels)."""

    nu: float
    lengthscale: float
    outputscale: float  # s, metres

    def factor(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """1-D correlation matrix between coordinate vectors a (n,) and b (m,)."""
        return matern_1d(np.subtract.outer(np.asarray(a, float), np.asarray(b, float)), self.nu, self.lengthscale)

    def matrix(self, rows_a, cols_a, rows_b, cols_b) -> np.ndarray:
        """Dense kernel matrix between point sets given by their (row, col) coordinates."""
        if self.nu == 0.5:  # exp(-|du| / l) exp(-|dv| / l) as one exponential
            du = np.abs(np.subtract.outer(np.asarray(rows_a, float), np.asarray(rows_b, float)))
            du += np.abs(np.subtract.outer(np.asarray(cols_a, float), np.asarray(cols_b, float)))
            return self.outputscale**2 * np.exp(du * (-1.0 / self.lengthscale))
        return self.outputscale**2 * self.factor(rows_a, rows_b) * self.factor(cols_a, cols_b)


@dataclass(frozen=True)
class GridProblem:
    """A GP depth field on a regular pixel grid: what every engine solves.

    The GP grid has the input resolution (height, width) with pixel centres at integer
    coordinates. Observations are combined per pixel (precision-weighted), so each pixel holds
    at most one observation. The output grid is a tensor grid given by its row and column
    coordinates expressed in GP-grid pixel units (finer output = more, closer coordinates).

    Attributes:
        prior_mean: (H, W) prior mean at the GP grid pixels, metres.
        obs: (H, W) observed depth per pixel, metres (ignored where precision == 0).
        precision: (H, W) observation precision 1/sigma^2 per pixel, 1/m^2; 0 = unobserved.
        out_rows: (Ho,) row coordinates of the output pixels in GP-grid units.
        out_cols: (Wo,) column coordinates of the output pixels in GP-grid units.
        out_prior_mean: (Ho, Wo) prior mean at the output pixels, metres.
        kernel: The covariance, in metres.
    """

    prior_mean: np.ndarray
    obs: np.ndarray
    precision: np.ndarray
    out_rows: np.ndarray
    out_cols: np.ndarray
    out_prior_mean: np.ndarray
    kernel: Kernel

    @property
    def shape(self) -> tuple[int, int]:
        return self.prior_mean.shape  # type: ignore[return-value]

    @property
    def out_shape(self) -> tuple[int, int]:
        return (self.out_rows.shape[0], self.out_cols.shape[0])

    @property
    def output_is_input(self) -> bool:
        """True when the output grid is the GP grid itself."""
        h, w = self.shape
        return (
            self.out_shape == (h, w)
            and np.array_equal(self.out_rows, np.arange(h))
            and np.array_equal(self.out_cols, np.arange(w))
        )


def output_coordinates(n_in: int, n_out: int) -> np.ndarray:
    """Centres of n_out output pixels in units of n_in input pixels (pixel-centre convention)."""
    return (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
