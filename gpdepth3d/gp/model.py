"""The GP depth model: its configuration, the kernel and the grid problem every engine solves.

Three formulations share the separable Matern kernel k(x, x') = s^2 M_nu(|du| / l) M_nu(|dv| / l) on
pixel coordinates (the kernel KISS-GP computes on a Kronecker grid, Yoon & Kim, IROS 2020,
arXiv:2008.05158): ``balanced`` (the paper: MDE pixels and points are both observations of depth),
``residual`` (the MDE is the prior mean, the points the observations) and ``log_residual`` (the default:
a GP on log(depth / MDE)). The default model's generative story, its stages and their approximations
are written down in docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from functools import cache
from typing import Literal

import numpy as np

from ..checks import Bool, Choice, Int, Real, Reals, check_fields
from ..errors import InvalidInputError, describe
from .kernels import Kernel, check_nu
from .kernels import matern_1d as matern_1d
from .kernels import separable_correlation as separable_correlation

Formulation = Literal["log_residual", "balanced", "residual"]


@dataclass(frozen=True)
class ScreenConfig:
    """How the default model fits its scales to a frame's points and screens them for outliers (docs/model.md).

    Attributes:
        neighbours: Points each leave-one-out z-score is predicted from (their kriging carries almost
            all of the weight under the exponential kernel's screening effect).
        iterations: Most fit / reject rounds.
        max_points: Points of the dense marginal-likelihood fit (an evenly strided or paired subset above).
        fit_lengthscales: Length scales (GP-grid pixels) searched when ``DepthGPConfig.fit`` is True.
        fit_nuggets: Nugget shares (tau / s)^2 searched when ``DepthGPConfig.fit`` is True.
        outlier_threshold: Points whose leave-one-out z-score (given their neighbours) exceeds this are
            rejected (a z-score); None keeps every point.
        raise_outputscale: Without ``DepthGPConfig.fit``: ``outputscale`` is a floor the points may raise
            (an MDE out of its range gets a wider prior, not a confident wrong mean).
    """

    neighbours: int = 12
    iterations: int = 3
    max_points: int = 150
    fit_lengthscales: tuple[float, ...] = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)
    fit_nuggets: tuple[float, ...] = (0.01, 0.03, 0.1, 0.3, 1.0)
    outlier_threshold: float | None = 3.5
    raise_outputscale: bool = True

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "neighbours": Int(1),
                "iterations": Int(1),
                "max_points": Int(3),
                "fit_lengthscales": Reals(Real(1e-6, 1e6, unit="GP-grid pixels")),
                "fit_nuggets": Reals(Real(1e-6, 1e6, unit="shares (tau / s)^2")),
                "outlier_threshold": _ranged("outlier_threshold", optional=True),
                "raise_outputscale": Bool(),
            },
        )


@dataclass(frozen=True)
class SlopeConfig:
    """How the MDE's log-depth slope a is fitted per frame (`gpdepth3d.gp.slope`; docs/model.md, "fit slope").

    Attributes:
        prior_sigma: Prior standard deviation of the slope around 1 (a monocular network's depth is right
            up to scale, its log-depth slope near 1); None fixes a = 1.
        max_points: Points of the dense robust fit (an evenly strided subset above).
        huber: Huber threshold on the standardised residuals.
        iterations: Huber re-weighting rounds.
        min_points: Fewer points than this keep a = 1.
    """

    prior_sigma: float | None = 0.5
    max_points: int = 150
    huber: float = 2.0
    iterations: int = 3
    min_points: int = 3

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "prior_sigma": _ranged("prior_sigma", optional=True),
                "max_points": Int(2),
                "huber": Real(0.1, 100.0, unit="standard deviations"),
                "iterations": Int(1),
                "min_points": Int(3),
            },
        )


@dataclass(frozen=True)
class LatticeConfig:
    """The automatic lattice of the default model's field (``EngineConfig.lattice_stride`` None; docs/model.md).

    A stride-k lattice holds the field on every k-th pixel per side; the field's detail below it is kriged
    back from the points (`gpdepth3d.gp.sublattice`) where nu = 0.5 and the output is at least as fine as
    the grid.

    Attributes:
        sparse_share: Without the detail: points on at most this share of the pixels take stride 2, else 1.
        detail_share: With the detail: points on at most this share take stride 2, else ``dense_stride``.
        dense_stride: The stride of dense points with the detail.
        min_lengthscale: A stride k needs a length scale of at least k / 2 times this (pixels).
        min_side: Grids with a side below this keep every pixel.
        max_window_points: Most points of one cell's detail kriging (the nearest to its centre).
    """

    sparse_share: float = 1 / 32
    detail_share: float = 1 / 10
    dense_stride: int = 4
    min_lengthscale: float = 8.0
    min_side: int = 16
    max_window_points: int = 36

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "sparse_share": Real(0.0, 1.0, unit="a share of the pixels"),
                "detail_share": Real(0.0, 1.0, unit="a share of the pixels"),
                "dense_stride": Int(1, 16),
                "min_lengthscale": Real(0.0, 1e6, unit="pixels"),
                "min_side": Int(2),
                "max_window_points": Int(1, 400),
            },
        )


@dataclass(frozen=True)
class AssemblyConfig:
    """The default model's per-pixel read-out: depth awareness, edge variance and two numerical choices
    (docs/model.md, "assemble").

    Attributes:
        depth_lengthscale: Length scale l_z of the depth-aware correlation, log depth (corrections fade
            across depths the points do not share); None: off.
        edge_sigma: Extra standard deviation at MDE depth edges, a share of the MDE's depth range over a
            3-pixel window (colour and range are never perfectly registered); it also enters the points'
            noise in the slope fit and the screen; 0: off.
        weight_floor: Pixels whose kriging weights sum below this keep the depth-aware factor rho = 1 (their
            field is at its prior there whatever rho is, and the weighted mean depth is undefined).
        scale_var_share: The global scale's variance term is bounded by Var[b] instead of solved for when
            Var[b] is below this share of the nugget variance (thousands of points: high by at most this share).
    """

    depth_lengthscale: float | None = 0.7
    edge_sigma: float = 1.0
    weight_floor: float = 1e-3
    scale_var_share: float = 0.05

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "depth_lengthscale": _ranged("depth_lengthscale", optional=True),
                "edge_sigma": _ranged("edge_sigma"),
                "weight_floor": Real(1e-12, 1.0, unit="a weight sum"),
                "scale_var_share": Real(0.0, 1.0, unit="a share of tau^2"),
            },
        )


@dataclass(frozen=True)
class CalibrationConfig:
    """The local calibration of the variance from the points' z-scores (`gpdepth3d.gp.local_calibration`).

    Attributes:
        reach: Reach of the calibration, mean point spacings (how far one point's z-score scales the
            variance around it); None: off.
        prior_points: Pseudo-points at a factor of 1 (the weight of the model's own variance).
        zscore_cap: Squared z-scores enter capped at this (one point must not set a region's variance alone).
        min_points: Frames with fewer kept points keep the model's variance (and warn).
    """

    reach: float | None = 1.5
    prior_points: float = 2.0
    zscore_cap: float = 16.0
    min_points: int = 10

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "reach": _ranged("reach", optional=True),
                "prior_points": Real(1e-3, 1e3, unit="points"),
                "zscore_cap": Real(1.0, 1e4, unit="a squared z-score"),
                "min_points": Int(1),
            },
        )


_NESTED = {
    "screen": ScreenConfig,
    "slope": SlopeConfig,
    "lattice": LatticeConfig,
    "assembly": AssemblyConfig,
    "calibration": CalibrationConfig,
}


@dataclass(frozen=True)
class DepthGPConfig:
    """The GP depth model: formulation, kernel, noise and the default model's stages (docs/model.md).

    Scales: with ``units="relative"`` ``outputscale``, ``sigma_dl`` and ``sigma_meas`` are fractions of the
    frame's median MDE depth (the paper's values then act alike on KITTI and indoors), with "metres" metres;
    in ``log_residual`` ``outputscale`` and ``nugget`` are log-depth standard deviations. ``lengthscale`` is
    in pixels of the GP grid (the MDE's). Per-point sigmas of a `SparseDepth` are metres. Each number must lie
    in its interval of `RANGES`.

    Attributes:
        formulation: "log_residual" (the default: a GP on log(depth / MDE), robust to bad points),
            "balanced" (the paper: MDE pixels and points are both observations) or "residual" (the MDE
            is the prior mean, the points the observations).
        nu: Matern smoothness, one of 0.5, 1.5, 2.5.
        lengthscale: Matern length scale, pixels of the GP grid.
        outputscale: Prior standard deviation s of the field (log_residual: of the log ratio).
        sigma_dl: Noise of an MDE pixel (balanced).
        sigma_meas: Noise of a point that carries no sigma of its own.
        units: "relative" (fractions of the median MDE depth) or "metres".
        align: residual: fit the MDE to the points before it is the prior mean: "none", "scale" (robust
            median ratio) or "scale_shift" (robust affine).
        fit: Fit the scales to each frame: balanced / residual by the exact marginal likelihood
            (`gpdepth3d.completion.marginal_fit`), log_residual l, s and tau on the frame's points (`gpdepth3d.gp.fit`).
        nugget: log_residual: standard deviation tau of the white part of the MDE's log error.
        screen: log_residual: the fit and outlier screen (`ScreenConfig`).
        slope: log_residual: the slope fit (`SlopeConfig`).
        lattice: log_residual: the automatic lattice (`LatticeConfig`).
        assembly: log_residual: depth awareness, edge variance and the per-pixel read-out (`AssemblyConfig`).
        calibration: log_residual: the local calibration (`CalibrationConfig`).

    Compute options (engine, its limits, the lattice stride) are `gpdepth3d.gp.EngineConfig`'s; a config
    stored as a dict (a posterior file, a saved map) reads back with `from_dict`.
    """

    formulation: Formulation = "log_residual"
    nu: float = 0.5
    lengthscale: float = 32.0
    outputscale: float = 0.2
    sigma_dl: float = 0.05
    sigma_meas: float = 0.01
    units: Literal["relative", "metres"] = "relative"
    align: Literal["none", "scale", "scale_shift"] = "scale"
    fit: bool = False
    nugget: float = 0.02
    screen: ScreenConfig = field(default_factory=ScreenConfig)
    slope: SlopeConfig = field(default_factory=SlopeConfig)
    lattice: LatticeConfig = field(default_factory=LatticeConfig)
    assembly: AssemblyConfig = field(default_factory=AssemblyConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def __post_init__(self) -> None:
        nested, rules, log_outputscale = _config_rules()
        check_fields(self, nested)
        check_fields(self, rules)
        if self.formulation == "log_residual":  # log-depth scales: exp() of their squares must stay finite
            log_outputscale("outputscale", self.outputscale)

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
            screen=ScreenConfig(outlier_threshold=None),
            slope=SlopeConfig(prior_sigma=None),
            assembly=AssemblyConfig(depth_lengthscale=None, edge_sigma=0.0),
            calibration=CalibrationConfig(reach=None),
        )
        return base.replace(**overrides)

    @classmethod
    def residual(cls, **overrides) -> "DepthGPConfig":
        """The residual formulation set for sparse points (hundreds): l = 30 px, s = 0.2 x the median depth."""
        base = cls(
            formulation="residual",
            lengthscale=30.0,
            outputscale=0.2,
            sigma_meas=0.01,
            fit=False,
            screen=ScreenConfig(outlier_threshold=None),
            slope=SlopeConfig(prior_sigma=None),
            assembly=AssemblyConfig(depth_lengthscale=None, edge_sigma=0.0),
            calibration=CalibrationConfig(reach=None),
        )
        return base.replace(**overrides)

    def replace(self, **changes) -> "DepthGPConfig":
        """A copy with some fields changed; a dict for a nested config changes only its keys there
        (``config.replace(calibration={"reach": None})``)."""
        for name, kind in _NESTED.items():
            if isinstance(changes.get(name), dict):
                unknown = sorted(set(changes[name]) - {f.name for f in fields(kind)})
                if unknown:
                    raise InvalidInputError(name, f"fields of {kind.__name__}", f"unknown keys {unknown}")
                changes[name] = replace(getattr(self, name), **changes[name])
        return replace(self, **changes)

    @classmethod
    def from_dict(cls, data: dict) -> "DepthGPConfig":
        """The config a dict holds (``dataclasses.asdict`` of one, e.g. a posterior file's ``config_json``).

        Raises:
            InvalidInputError: ``data`` not a dict, or a key that is no field (argument ``config``).
        """
        if not isinstance(data, dict):
            raise InvalidInputError("config", "a dict of DepthGPConfig fields", type(data).__name__)
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise InvalidInputError("config", "DepthGPConfig fields", f"unknown keys {unknown}")
        return cls(**data)


RANGES: dict[str, tuple[float, float, str]] = {
    "lengthscale": (1e-3, 1e5, "GP-grid pixels"),
    "outputscale": (1e-9, 1e6, "relative or metres"),
    "log_outputscale": (1e-9, 3.0, "log depth, formulation log_residual"),
    "sigma_dl": (1e-9, 1e6, "relative or metres"),
    "sigma_meas": (1e-9, 1e6, "relative or metres"),
    "nugget": (0.0, 3.0, "log depth"),
    "edge_sigma": (0.0, 10.0, "shares of the local MDE depth range"),
    "outlier_threshold": (1e-3, 1e6, "a z-score"),
    "depth_lengthscale": (1e-3, 1e3, "log depth"),
    "prior_sigma": (1e-3, 3.0, "standard deviations of the MDE's log-depth slope"),
    "reach": (0.1, 100.0, "mean point spacings"),
}
"""Accepted interval (inclusive) of each numeric hyperparameter, with its unit. Each bound keeps the
posterior finite in float64: a log-depth scale above 3 (a factor of 20 at one sigma) puts exp(v / 2)
of the log-normal mean beyond any depth, a reach or slope sigma of 1e-300 divides by zero."""


def _ranged(name: str, *, optional: bool = False) -> Real:
    """The rule of the hyperparameter ``name``: a number in its `RANGES` interval (``optional``: or None)."""
    low, high, unit = RANGES[name]
    return Real(low, high, unit=unit, optional=optional)


@cache
def _config_rules() -> tuple[dict, dict, Real]:
    """`DepthGPConfig`'s field rules: (nested configs, the other fields, the log-depth bound of ``outputscale``);
    built once, as every config (each frame's fitted one too) is checked by them."""
    nested = {name: _nested(kind) for name, kind in _NESTED.items()}
    rules = {name: _ranged(name) for name in ("lengthscale", "outputscale", "sigma_dl", "sigma_meas", "nugget")}
    rules.update(formulation=Choice(("log_residual", "balanced", "residual")), nu=lambda _, v: check_nu(v))
    rules.update(units=Choice(("relative", "metres")), align=Choice(("none", "scale", "scale_shift")), fit=Bool())
    return nested, rules, _ranged("log_outputscale")


def _nested(kind: type):
    """The rule of a nested stage config: an instance of ``kind``, or the dict of one read back from JSON."""

    def rule(name: str, value):
        if isinstance(value, dict):
            known = {f.name for f in fields(kind)}
            value = kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items() if k in known})
        if not isinstance(value, kind):
            raise InvalidInputError(name, f"a {kind.__name__}", describe(value))
        return value

    return rule


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
