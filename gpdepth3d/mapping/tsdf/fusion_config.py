"""Options of the TSDF fusion (`FusionConfig`): voxel grid, depth range, per-pixel weighting and truncation.

Truncation from the variance (``truncation_sigma`` k > 0): a pixel's truncation is
``tau = clip(k * sigma, truncation, truncation_max)``, sigma its depth standard deviation, and every
signed distance is divided by ``tau_max = truncation_max`` (`FusionConfig.pixel_truncation`,
`FusionConfig.tsdf_scale`). A fixed truncation far below the depth error clips an uncertain frame's
signed distance to +-1 within a few centimetres of its surface: where frames disagree by more than
the truncation the volume does not average them but keeps several thin surfaces and carves between
them. With the truncation growing with sigma the signed distances of uncertain frames stay linear
over their error band, so the zero crossing is their weighted mean (the least-squares surface of
Curless and Levoy, https://graphics.stanford.edu/papers/volrange/), while certain pixels keep the
sharp band. The grid itself is Open3D's
https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ...checks import Bool, Choice, Int, Real, check_fields, non_negative, positive
from ...errors import InvalidInputError, ShapeError, describe

Weighting = Literal["uniform", "variance"]


@dataclass(frozen=True)
class FusionConfig:
    """Options of the TSDF fusion.

    Attributes:
        voxel_size: Voxel edge length, metres.
        truncation: Truncation distance of the signed distance, metres (>= voxel_size).
        depth_min: Depth readings at or below this are ignored, metres.
        depth_max: Depth readings at or above this are ignored, metres.
        weight_cap: Largest accumulated weight of a voxel (later frames keep a share of
            ``w / (cap + w)``; makes the map adapt).
        weighting: "uniform" (every pixel weight 1) or "variance" (from the posterior variance,
            `gpdepth3d.mapping.tsdf.fusion_weights`).
        sigma_ref: Variance weighting without ``relative_sigma_ref``: depth standard deviation
            (metres) at which a pixel counts as half an observation.
        relative_sigma_ref: Variance weighting: sigma / depth at which a pixel counts as half an
            observation (None: ``sigma_ref`` in metres). Relative, so that a room at 1 m and a hall at
            5 m meet the same ``weight_threshold``.
        max_relative_sigma: Variance weighting: pixels with sigma / depth above this count as
            uninformed (no point near them: the MDE's shape alone, with the GP prior's sigma) and get
            the fallback weight instead (None: none does).
        fallback_weight: Weight in [0, 1] of the uninformed pixels of a frame without points: such
            a frame falls back to its MDE depth, down-weighted. A frame with points gives them
            ``fallback_weight * exp(-points / fallback_points)`` (`fallback_for`): what its points
            do not inform, the frames whose points do inform it fill in.
        fallback_points: Points at which a frame's fallback weight has fallen by 1/e.
        weight_threshold: Extraction keeps voxels with accumulated weight > this.
        truncation_sigma: k of the truncation from the variance (see the module docstring): a
            pixel's truncation is ``clip(k * sigma, truncation, truncation_max)`` when a variance
            is given to `TSDFFusion.integrate`; 0 keeps the fixed ``truncation``.
        truncation_max: Largest truncation with ``truncation_sigma`` > 0, metres (then >=
            truncation); the signed distances are then stored divided by it.
        block_resolution: Voxels per block edge of the VoxelBlockGrid.
        block_count: Initial number of blocks of the hash map (it grows when needed).
        integrate_color: Fuse colours as well.
        integrate_variance: Keep a per-voxel depth variance (m^2; `gpdepth3d.mapping.tsdf.fusion`);
            `TSDFFusion.integrate` then needs a ``variance`` for every frame.
        device: Open3D device string, "CPU:0" or "CUDA:0".
        cpu_threads: torch threads of the voxel update on the CPU while it runs (0 = leave
            torch's setting alone). The update is memory-bound: on a busy
            machine torch's default (one thread per core) makes the threads wait on each other.
    """

    voxel_size: float = 0.02
    truncation: float = 0.08
    depth_min: float = 0.1
    depth_max: float = 5.0
    weight_cap: float = 100.0
    weighting: Weighting = "variance"
    sigma_ref: float = 0.1
    relative_sigma_ref: float | None = None
    max_relative_sigma: float | None = 0.2
    fallback_weight: float = 0.5
    fallback_points: float = 10.0
    weight_threshold: float = 0.5
    truncation_sigma: float = 0.0
    truncation_max: float = 0.4
    block_resolution: int = 8
    block_count: int = 20000
    integrate_color: bool = True
    integrate_variance: bool = False
    device: str = "CPU:0"
    cpu_threads: int = 1

    def __post_init__(self) -> None:
        rules = {name: positive() for name in ("voxel_size", "depth_max", "weight_cap", "sigma_ref", "fallback_points")}
        rules.update(truncation=Real(self.voxel_size, unit="metres, >= voxel_size"), depth_min=non_negative("m"))
        rules.update(relative_sigma_ref=positive(optional=True), max_relative_sigma=positive(optional=True))
        rules.update(weighting=Choice(("uniform", "variance")), fallback_weight=Real(0.0, 1.0, unit="a weight"))
        rules.update(weight_threshold=non_negative(), truncation_sigma=non_negative(), truncation_max=Real())
        rules.update(block_resolution=Int(2), block_count=Int(1), cpu_threads=Int(0))
        rules.update(integrate_color=Bool(), integrate_variance=Bool())
        check_fields(self, rules)
        if not self.depth_min < self.depth_max:
            raise InvalidInputError(
                "depth_min, depth_max", "0 <= depth_min < depth_max", (self.depth_min, self.depth_max)
            )
        if self.truncation_sigma > 0 and self.truncation_max < self.truncation:
            raise InvalidInputError("truncation_max", f">= truncation ({self.truncation} m)", self.truncation_max)

    def fallback_for(self, points: int) -> float:
        """Weight of the uninformed pixels of a frame with ``points`` measurements: ``fallback_weight *
        exp(-points / fallback_points)``, 0 once that factor is below 1e-3 (a frame without points falls
        back to its MDE; one with points leaves what they do not inform to the frames whose points do)."""
        if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 0:
            raise InvalidInputError("points", "a count >= 0", points)
        share = np.exp(-int(points) / self.fallback_points)
        return float(self.fallback_weight * share) if share > 1e-3 else 0.0  # below 1e-3: not worth a voxel update

    @property
    def tsdf_scale(self) -> float:
        """The distance (metres) the stored signed distances are divided by: ``truncation_max``
        with a truncation from the variance (``truncation_sigma`` > 0), else ``truncation``."""
        return float(self.truncation_max if self.truncation_sigma > 0 else self.truncation)

    def pixel_truncation(self, variance: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) float32 truncation of each pixel, metres: ``clip(truncation_sigma * sigma,
        truncation, truncation_max)`` from a variance (m^2; non-finite or negative entries get
        ``truncation``), or ``truncation`` everywhere without one or with ``truncation_sigma`` 0."""
        if self.truncation_sigma == 0 or variance is None:
            return np.full(shape, self.truncation, np.float32)
        var = np.asarray(variance, dtype=np.float64)
        if var.shape != tuple(shape):
            raise ShapeError("variance", f"the shape of depth {tuple(shape)}", describe(var))
        with np.errstate(invalid="ignore"):
            sigma = np.sqrt(np.where(np.isfinite(var) & (var >= 0), var, 0.0))
        return np.clip(self.truncation_sigma * sigma, self.truncation, self.truncation_max).astype(np.float32)
