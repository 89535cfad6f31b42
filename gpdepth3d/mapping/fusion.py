"""TSDF fusion of posed depth frames with per-pixel weights (Open3D tensor `VoxelBlockGrid`).

Open3D's stock ``VoxelBlockGrid.integrate`` gives every pixel the weight 1. Here the voxel
update is written out with Open3D core tensor operations (after Open3D's
``examples/python/t_reconstruction_system/integrate_custom.py``), so each pixel carries its own
weight ``w_p``. For every voxel centre ``x`` (world frame) in the truncation band of frame t::

    (u, v), z = project(T_camera_world @ x)            nearest pixel, z-depth of the voxel
    d   = depth[v, u],  w = w_p[v, u]                   observed depth and its weight
    sdf = min(d - z, tau) / tau_max                     kept when d - z >= -tau
    tsdf  <- (W * tsdf + w * sdf) / (W + w)
    color <- (W * color + w * rgb[v, u]) / (W + w)
    W     <- min(W + w, weight_cap)

with ``tau = tau_max = truncation`` (the usual TSDF), or, with ``truncation_sigma = k > 0`` and
a variance given, a truncation per pixel that follows its depth uncertainty (below).

Implementation: the blocks to allocate are found by sampling every valid pixel's ray through
the truncation band (Open3D's ``compute_unique_block_coordinates`` samples the band too
sparsely for truncations of several blocks and would leave band voxels un-updated); the voxel
update runs in torch on zero-copy DLPack views of the grid's buffers, the same code on CPU and
CUDA (``FusionConfig.device``).

Weightings (`FusionConfig.weighting`):

* ``"uniform"``: ``w = 1`` for every valid pixel (what the stock integration does).
* ``"variance"``: ``w = 1 / (1 + variance / sigma_ref^2)`` in (0, 1] from the posterior depth
  variance (m^2). A pixel known to ``sigma << sigma_ref`` counts as one full observation, one
  with ``sigma = sigma_ref`` as half, and one with ``sigma >> sigma_ref`` as
  ``(sigma_ref / sigma)^2``: inverse-variance weighting (the optimal weights for averaging
  independent Gaussian readings of the signed distance) saturated at one observation, so that
  ``weight_cap`` and ``weight_threshold`` keep their usual meaning ("number of observations").
  With ``relative_sigma_ref`` (the `Mapper`'s default) the reference is that fraction of the pixel's depth.
  Pixels whose sigma exceeds ``max_relative_sigma`` (default 0.2) times their depth, the pixels no
  point informs, get the frame's fallback weight (`FusionConfig.fallback_for`: a frame without
  points falls back to its MDE depth, one with many leaves them out); `TSDFFusion.weights_for`
  then needs the depth map.

Truncation from the variance (``FusionConfig.truncation_sigma`` k > 0): a pixel's truncation is
``tau = clip(k * sigma, truncation, truncation_max)``, sigma its depth standard deviation, and every
signed distance is divided by ``tau_max = truncation_max``. A fixed truncation far below the
depth error clips an uncertain frame's signed distance to +-1 within a few centimetres of its
surface: where frames disagree by more than the truncation (the refined depth of 7-Scenes is
typically 10-30 cm off, the truncation 8 cm) the volume does not average them but keeps
several thin surfaces and carves between them. With the truncation growing with sigma the
signed distances of uncertain frames stay linear over their error band, so the zero crossing is
their weighted mean (the least-squares surface of Curless and Levoy), while certain pixels keep
the sharp band. The band of blocks each pixel reaches grows accordingly (`_band_keys`).

Bad depth readings never stop a sequence: negative and non-finite depths (a GP posterior
mean can dip below zero next to an outlier measurement) are masked like "no depth" and
counted on the returned `IntegrationStats`.

Per-voxel variance (``FusionConfig.integrate_variance``): the volume then also carries the
per-pixel depth variance of the frames, averaged with the same weights as the TSDF. It is
deliberately *not* the variance of an inverse-variance-weighted mean of independent readings
(``1 / sum(1 / var_i)``): the depth errors of consecutive frames (the same MDE mistakes, the same
sparse points) are strongly correlated, so averaging the variances is the honest summary.

Re-integration (`TSDFFusion.reset_blocks` and the ``blocks`` argument of `TSDFFusion.integrate`):
every voxel's value depends only on the frames whose truncation band reached its block, in the
order they came. Zeroing a set of blocks and integrating the frames again restricted to those
blocks therefore reproduces, voxel for voxel (bit for bit on one device), the volume that
integrating the same frames from scratch gives; `gpdepth3d.mapping.Mapper.update_poses` uses
this after a loop closure.

Extraction (`TSDFFusion.extract_mesh`, `TSDFFusion.extract_point_cloud`) keeps voxels whose
accumulated weight exceeds ``weight_threshold`` (Open3D's test is strict). Meshes are `trimesh.Trimesh` with vertex
colours; `save_mesh` writes PLY, GLB or OBJ atomically.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Literal

import numba as nb
import numpy as np

from ..camera import PinholeCamera, check_pose
from .cloud import ColoredCloud
from ..errors import DataFormatError, EmptyInputError, InvalidInputError, ProblemTooLargeError, ShapeError, describe
from ..extras import require
from ..io import atomic_path, write_json

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

    from ..completion.complete import DepthPosterior

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
            see the module docstring).
        sigma_ref: Variance weighting without ``relative_sigma_ref``: depth standard deviation
            (metres) at which a pixel counts as half an observation.
        relative_sigma_ref: Variance weighting: sigma / depth at which a pixel counts as half an
            observation (None, default: ``sigma_ref`` in metres; the `Mapper`'s default fusion,
            ``MAPPER_FUSION``, uses 0.05). Relative, so that a room at 1 m and a hall at 5 m meet the
            same ``weight_threshold``.
        max_relative_sigma: Variance weighting: pixels with sigma / depth above this count as
            uninformed (no point near them: the MDE's shape alone, with the GP prior's sigma,
            0.20-0.22 for the default model) and get the fallback weight instead (None: none does).
        fallback_weight: Weight in [0, 1] of the uninformed pixels of a frame without points: such
            a frame falls back to its MDE depth, down-weighted. A frame with points gives them
            ``fallback_weight * exp(-points / fallback_points)`` (`fallback_for`): what its points
            do not inform, the frames whose points do inform it fill in.
        fallback_points: Points at which a frame's fallback weight has fallen by 1/e.
        weight_threshold: Extraction keeps voxels with accumulated weight > this.
        truncation_sigma: k of the truncation from the variance (see the module docstring): a
            pixel's truncation is ``clip(k * sigma, truncation, truncation_max)`` when a variance
            is given to `TSDFFusion.integrate`; 0 (default) keeps the fixed ``truncation`` (the
            variance-dependent one did not gain on every split of the shared 7-Scenes frames).
        truncation_max: Largest truncation with ``truncation_sigma`` > 0, metres (then >=
            truncation); the signed distances are then stored divided by it.
        block_resolution: Voxels per block edge of the VoxelBlockGrid.
        block_count: Initial number of blocks of the hash map (it grows when needed).
        integrate_color: Fuse colours as well.
        integrate_variance: Keep a per-voxel depth variance (m^2; see the module docstring);
            `TSDFFusion.integrate` then needs a ``variance`` for every frame.
        device: Open3D device string, "CPU:0" or "CUDA:0".
        cpu_threads: torch threads of the voxel update on the CPU while it runs (0 = leave
            torch's setting alone). 1 by default: the update is memory-bound, and on a busy
            machine torch's default (one thread per core) made it 5-20x slower (measured on the
            shared 2-core development machine: 1-9 s instead of 0.3-0.4 s a 320x240 frame).
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
        for name in ("voxel_size", "truncation", "depth_max", "weight_cap", "sigma_ref", "fallback_points"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise InvalidInputError(name, "a finite value > 0", value)
        if self.truncation < self.voxel_size:
            raise InvalidInputError("truncation", f">= voxel_size ({self.voxel_size} m)", self.truncation)
        if not (0 <= self.depth_min < self.depth_max):
            raise InvalidInputError(
                "depth_min, depth_max", "0 <= depth_min < depth_max", (self.depth_min, self.depth_max)
            )
        if self.weighting not in ("uniform", "variance"):
            raise InvalidInputError("weighting", "'uniform' or 'variance'", self.weighting)
        if not (np.isfinite(self.fallback_weight) and 0 <= self.fallback_weight <= 1):
            raise InvalidInputError("fallback_weight", "a weight in [0, 1]", self.fallback_weight)
        if self.relative_sigma_ref is not None and (
            isinstance(self.relative_sigma_ref, bool)
            or not np.isfinite(self.relative_sigma_ref)
            or self.relative_sigma_ref <= 0
        ):
            raise InvalidInputError("relative_sigma_ref", "a finite value > 0 (or None)", self.relative_sigma_ref)
        if self.max_relative_sigma is not None and (
            isinstance(self.max_relative_sigma, bool)
            or not np.isfinite(self.max_relative_sigma)
            or self.max_relative_sigma <= 0
        ):
            raise InvalidInputError("max_relative_sigma", "a finite value > 0 (or None)", self.max_relative_sigma)
        if not np.isfinite(self.weight_threshold) or self.weight_threshold < 0:
            raise InvalidInputError("weight_threshold", "a finite value >= 0", self.weight_threshold)
        if not np.isfinite(self.truncation_sigma) or self.truncation_sigma < 0:
            raise InvalidInputError("truncation_sigma", "a finite value >= 0", self.truncation_sigma)
        if not np.isfinite(self.truncation_max) or (
            self.truncation_sigma > 0 and self.truncation_max < self.truncation
        ):
            raise InvalidInputError(
                "truncation_max", f"a finite value >= truncation ({self.truncation} m)", self.truncation_max
            )
        if int(self.block_resolution) != self.block_resolution or self.block_resolution < 2:
            raise InvalidInputError("block_resolution", "an integer >= 2", self.block_resolution)
        if int(self.block_count) != self.block_count or self.block_count < 1:
            raise InvalidInputError("block_count", "an integer >= 1", self.block_count)
        if isinstance(self.cpu_threads, bool) or int(self.cpu_threads) != self.cpu_threads or self.cpu_threads < 0:
            raise InvalidInputError("cpu_threads", "an integer >= 0", self.cpu_threads)

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


def memory_limit() -> int:
    """Bytes a TSDF volume may plan to use: half the machine's physical memory (8 GiB when unknown)."""
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 2
    except (AttributeError, ValueError, OSError):
        return 8 * 2**30


def weights_from_variance(
    variance: np.ndarray,
    *,
    sigma_ref: float,
    depth: np.ndarray | None = None,
    max_relative_sigma: float | None = None,
    relative_sigma_ref: float | None = None,
    fallback_weight: float = 0.0,
) -> np.ndarray:
    """Per-pixel fusion weights in [0, 1]: ``1 / (1 + variance / s^2)``, s = sigma_ref or relative_sigma_ref * depth.

    Pixels less certain than ``max_relative_sigma`` x depth (no point informs them: the MDE alone)
    get ``fallback_weight`` instead (`FusionConfig.max_relative_sigma`, `FusionConfig.fallback_weight`).

    Args:
        variance: (H, W) depth variance, m^2. Non-finite or negative entries get weight 0.
        sigma_ref: Standard deviation (metres) at which the weight is 0.5 (without ``relative_sigma_ref``).
        depth: (H, W) depth, metres; needed with ``max_relative_sigma`` or ``relative_sigma_ref``.
        max_relative_sigma: sigma / depth above which a pixel counts as uninformed (None: none does).
        relative_sigma_ref: sigma / depth at which the weight is 0.5 (None: ``sigma_ref`` in metres).
        fallback_weight: Weight of the uninformed pixels, in [0, 1].

    Returns:
        (H, W) float64 weights.
    """
    var = np.asarray(variance, dtype=np.float64)
    if not np.isfinite(sigma_ref) or sigma_ref <= 0:
        raise InvalidInputError("sigma_ref", "a finite value > 0 (metres)", sigma_ref)
    for name, value in (("max_relative_sigma", max_relative_sigma), ("relative_sigma_ref", relative_sigma_ref)):
        if value is not None and (not np.isfinite(value) or value <= 0):
            raise InvalidInputError(name, "a finite value > 0 (or None)", value)
    if not (np.isfinite(fallback_weight) and 0 <= fallback_weight <= 1):
        raise InvalidInputError("fallback_weight", "a weight in [0, 1]", fallback_weight)
    ok = np.isfinite(var) & (var >= 0)
    var = np.where(ok, var, 0.0)
    if max_relative_sigma is None and relative_sigma_ref is None:
        return np.where(ok, 1.0 / (1.0 + var / sigma_ref**2), 0.0)
    if depth is None:
        raise InvalidInputError("depth", "the (H, W) depth map the variance belongs to (relative sigmas are set)", None)
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != var.shape:
        raise ShapeError("depth", f"the shape of variance {var.shape}", describe(d))
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = np.where(np.isfinite(d) & (d > 0), d * d, np.inf)
        scale2 = sigma_ref**2 if relative_sigma_ref is None else relative_sigma_ref**2 * d2
        w = 1.0 / (1.0 + var / scale2)
        if max_relative_sigma is not None:
            w = np.where(var <= max_relative_sigma**2 * d2, w, fallback_weight)
    return np.where(ok & np.isfinite(w), w, 0.0)


@dataclass(frozen=True)
class IntegrationStats:
    """What `TSDFFusion.integrate` did with one frame.

    Attributes:
        voxels: Number of voxel updates.
        pixels: Pixels that were fused (valid depth in range, weight > 0).
        invalid_pixels: Pixels masked because their depth was negative or non-finite (NaN/inf);
            0 = "no depth" is not counted.
        block_keys: (M,) int64 keys of the blocks the frame's truncation band touched (see
            `TSDFFusion.block_keys`); with ``blocks=`` given, only those among them.
    """

    voxels: int
    pixels: int
    invalid_pixels: int
    block_keys: np.ndarray


_KEY_BIAS, _KEY_SPAN = 1 << 20, 1 << 21


def _blocks_to_keys(blocks: np.ndarray) -> np.ndarray:
    """(M, 3) integer block coordinates to (M,) int64 keys (one number per block)."""
    b = np.asarray(blocks, dtype=np.int64) + _KEY_BIAS
    return (b[:, 0] * _KEY_SPAN + b[:, 1]) * _KEY_SPAN + b[:, 2]


def _keys_to_blocks(keys: np.ndarray) -> np.ndarray:
    """(M,) int64 keys to (M, 3) int32 block coordinates."""
    k = np.asarray(keys, dtype=np.int64)
    b = np.stack([k // (_KEY_SPAN * _KEY_SPAN), (k // _KEY_SPAN) % _KEY_SPAN, k % _KEY_SPAN], axis=1) - _KEY_BIAS
    return b.astype(np.int32)


class TSDFFusion:
    """A TSDF volume that integrates posed depth frames with per-pixel weights.

    Example:
        >>> fusion = TSDFFusion(camera, FusionConfig(voxel_size=0.02))  # doctest: +SKIP
        >>> fusion.integrate(depth, T_world_camera, rgb=rgb, weights=w)  # doctest: +SKIP
        >>> fusion.save_mesh("room.glb")  # doctest: +SKIP
    """

    def __init__(self, camera: PinholeCamera, config: FusionConfig | None = None, *, _vbg: Any = None):
        o3d = require("open3d")
        o3c = require("open3d.core")

        if not isinstance(camera, PinholeCamera):
            raise InvalidInputError("camera", "a PinholeCamera", type(camera).__name__)
        self.camera = camera
        self.config = config or FusionConfig()
        self._o3d, self._o3c = o3d, o3c
        try:
            self._device = o3c.Device(self.config.device)
            o3c.Tensor([0.0], device=self._device)
        except Exception as exc:  # noqa: BLE001 - Open3D raises RuntimeError for unavailable devices
            raise InvalidInputError("device", "an Open3D device this build supports", f"{self.config.device}: {exc}")
        if _vbg is None and self.config.block_count * self.block_bytes > memory_limit():
            raise ProblemTooLargeError(
                f"block_count: expected initial blocks that fit in {memory_limit() / 2**30:.1f} GiB, got "
                f"{self.config.block_count} blocks of {self.block_bytes} bytes"
            )
        if _vbg is not None:
            self.vbg = _vbg
        else:
            names, dtypes, channels = ["tsdf", "weight"], [o3c.float32, o3c.float32], [1, 1]
            if self.config.integrate_color:
                names.append("color")
                dtypes.append(o3c.float32)
                channels.append(3)
            if self.config.integrate_variance:
                names.append("variance")
                dtypes.append(o3c.float32)
                channels.append(1)
            self.vbg = o3d.t.geometry.VoxelBlockGrid(
                tuple(names),
                tuple(dtypes),
                tuple(channels),
                float(self.config.voxel_size),
                int(self.config.block_resolution),
                int(self.config.block_count),
                self._device,
            )
        dev_type = "cuda" if self._device.get_type() == o3c.Device.DeviceType.CUDA else "cpu"
        self._torch_device = f"{dev_type}:{self._device.get_id()}" if dev_type == "cuda" else "cpu"
        self.frames_integrated = 0
        self._dirty: list[np.ndarray] = []  # block keys changed since the last incremental extraction
        self._chunks: dict[int, tuple[np.ndarray, np.ndarray]] | None = None  # chunk key -> (triangles, colours)

    @property
    def _attributes(self) -> tuple[str, ...]:
        names = ["tsdf", "weight"]
        if self.config.integrate_color:
            names.append("color")
        if self.config.integrate_variance:
            names.append("variance")
        return tuple(names)

    # ------------------------------------------------------------------ integration
    def integrate(
        self,
        depth: np.ndarray,
        T_world_camera: np.ndarray,
        *,
        rgb: np.ndarray | None = None,
        weights: np.ndarray | None = None,
        variance: np.ndarray | None = None,
        blocks: np.ndarray | None = None,
    ) -> IntegrationStats:
        """Fuses one posed depth frame.

        Args:
            depth: (H, W) z-depth in metres of the camera's image (0 = none). Negative and
                non-finite values are masked like 0 and counted (``invalid_pixels``).
            T_world_camera: 4x4 rigid pose of the camera.
            rgb: Optional (H, W, 3) uint8 RGB image (needed for coloured meshes).
            weights: Optional (H, W) per-pixel weights >= 0 (default 1 for every pixel).
            variance: (H, W) depth variance, m^2; needed with ``config.integrate_variance``
                (pixels with a non-finite or negative variance are then not fused); sets each
                pixel's truncation with ``config.truncation_sigma`` > 0 (without it: the fixed
                truncation).
            blocks: Optional (M,) int64 block keys (`block_keys`): update only voxels of these
                blocks (re-integration after `reset_blocks`).

        Returns:
            `IntegrationStats` (voxel updates, pixels fused and masked, blocks touched).

        Raises:
            ShapeError: if depth, rgb, weights or variance do not have the camera's size.
            CalibrationError: if the pose is not a rigid transform.
            InvalidInputError: for negative or non-finite weights, or a missing variance with
                ``config.integrate_variance``.
            EmptyInputError: if the frame has no depth inside [depth_min, depth_max] with weight > 0.
        """
        cfg = self.config
        T = check_pose(T_world_camera)
        d = np.asarray(depth)
        if d.ndim != 2:
            raise ShapeError("depth", "a 2-D (H, W) depth map", describe(d))
        self.camera.check_image(d, "depth")
        if weights is None:
            w = np.ones(d.shape)
        else:
            w = np.ascontiguousarray(weights, dtype=np.float64)
            if w.shape != d.shape:
                raise ShapeError("weights", f"the shape of depth {d.shape}", describe(w))
        var = np.zeros((0, 0))
        if cfg.integrate_variance:
            if variance is None:
                raise InvalidInputError("variance", "an (H, W) variance map (config.integrate_variance is on)", None)
            var = np.ascontiguousarray(variance, dtype=np.float64)
            if var.shape != d.shape:
                raise ShapeError("variance", f"the shape of depth {d.shape}", describe(var))
        trunc = cfg.pixel_truncation(variance, d.shape)
        self._check_band_memory(d, trunc)
        d, w, var32, n_bad, pixels, bad_weights = _masked_frame(
            np.ascontiguousarray(d, dtype=np.float64), w, var, float(cfg.depth_min), float(cfg.depth_max)
        )
        if bad_weights:
            raise InvalidInputError("weights", "finite weights >= 0", "negative or non-finite weights")
        if pixels == 0:
            raise EmptyInputError(
                "depth", f"at least one pixel with depth in ({cfg.depth_min}, {cfg.depth_max}) m and weight > 0", "none"
            )
        color = None
        if cfg.integrate_color:
            if rgb is None:
                color = np.full(d.shape + (3,), 128.0, np.float32)
            else:
                rgb = np.asarray(rgb)
                if rgb.ndim != 3 or rgb.shape[2] < 3:
                    raise ShapeError("rgb", "an (H, W, 3) RGB image", describe(rgb))
                self.camera.check_image(rgb, "rgb")
                # Open3D's extraction divides the stored colour by 255.
                color = rgb[..., :3].astype(np.float32)
                if not np.issubdtype(rgb.dtype, np.integer):
                    color = color * 255.0

        with self._threads():
            keys = self._band_keys(d, T, trunc)
            if blocks is not None:
                keys = np.intersect1d(keys, np.asarray(blocks, dtype=np.int64), assume_unique=False)
            n = 0
            if keys.size:
                n = self._update(keys, d, w, color, var32 if cfg.integrate_variance else None, T, trunc)
        self._dirty.append(keys)
        self.frames_integrated += 1
        return IntegrationStats(voxels=n, pixels=pixels, invalid_pixels=n_bad, block_keys=keys)

    @property
    def block_bytes(self) -> int:
        """Bytes one voxel block holds (float32 channels of ``block_resolution``^3 voxels)."""
        channels = 2 + 3 * bool(self.config.integrate_color) + bool(self.config.integrate_variance)
        return int(self.config.block_resolution) ** 3 * 4 * channels

    def _check_band_memory(self, depth: np.ndarray, trunc: np.ndarray) -> None:
        """Refuses a frame whose truncation band would need more than `memory_limit` (blocks and search grid).

        Estimate: the frame's surface area (each pixel's footprint ``d^2 / (fx fy)``) in blocks,
        times the blocks the band spans along a ray, plus the dense grid `_band_blocks` marks them in.
        """
        cam, b = self.camera, float(self.config.voxel_size * self.config.block_resolution)
        with np.errstate(invalid="ignore"):
            dv = np.asarray(depth, dtype=np.float64)
            dv = dv[np.isfinite(dv) & (dv > self.config.depth_min) & (dv < self.config.depth_max)]
        if not dv.size:
            return
        tau = float(np.max(trunc))
        area = float(np.sum(dv * dv)) / (cam.fx * cam.fy)
        blocks = area / b**2 * (2.0 * tau / b + 1.0)
        reach = (float(dv.max()) + tau) * float(np.hypot(np.hypot(cam.width / cam.fx, cam.height / cam.fy), 1.0))
        grid = (reach / b + 2.0) ** 3  # one byte a cell
        need = blocks * self.block_bytes + grid
        limit = memory_limit()
        if need > limit:
            raise ProblemTooLargeError(
                f"voxel_size: expected a voxel whose blocks for one {cam.width}x{cam.height} frame fit in "
                f"{limit / 2**30:.1f} GiB (half the machine's memory), got {self.config.voxel_size} m: about "
                f"{need / 2**30:.3g} GiB; use a larger voxel_size (or a smaller truncation / depth_max)"
            )

    @contextlib.contextmanager
    def _threads(self) -> Iterator[None]:
        """Runs the block with ``config.cpu_threads`` torch threads (on the CPU), then restores them."""
        import torch

        n = int(self.config.cpu_threads)
        if n == 0 or self._torch_device != "cpu" or torch.get_num_threads() == n:
            yield
            return
        before = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    def _activate(self, keys: np.ndarray) -> Any:
        """Buffer indices of the blocks ``keys``, allocating (zeroed) the missing ones."""
        o3c = self._o3c
        blocks = o3c.Tensor(_keys_to_blocks(keys), device=self._device)
        hashmap = self.vbg.hashmap()
        buf, fresh = hashmap.activate(blocks)
        fresh_np = fresh.cpu().numpy().astype(bool).reshape(-1)
        if fresh_np.any():
            # New blocks start at zero (a buffer slot may hold old values).
            import torch

            idx = buf.cpu().numpy().astype(np.int64).reshape(-1)[fresh_np]
            self._zero(torch.as_tensor(idx, device=self._torch_device))
        buf_indices, _ = hashmap.find(blocks)
        return buf_indices

    def _zero(self, buf_idx: Any) -> None:
        """Sets every attribute of the blocks at torch buffer indices ``buf_idx`` to zero."""
        if buf_idx.numel() == 0:
            return
        for name in self._attributes:
            _to_torch(self.vbg.attribute(name))[buf_idx] = 0.0

    def _update(
        self,
        keys: np.ndarray,
        d: np.ndarray,
        w: np.ndarray,
        color: np.ndarray | None,
        var: np.ndarray | None,
        T: np.ndarray,
        trunc: np.ndarray | None = None,
    ) -> int:
        """The voxel update of one frame over the blocks ``keys`` (see the module docstring).

        On the CPU a compiled loop (`_update_voxels`, numba) visits every voxel of the blocks
        once; on CUDA the same update runs as torch tensor operations (`_update_torch`).
        """
        if trunc is None:
            trunc = np.full(d.shape, self.config.truncation, np.float32)
        if self._torch_device != "cpu":
            return self._update_torch(keys, d, w, color, var, T, trunc)
        buf = self._activate(keys).cpu().numpy().astype(np.int64).reshape(-1)
        blocks = _keys_to_blocks(keys).astype(np.int64)
        T_cw = np.linalg.inv(T)
        cfg = self.config
        tsdf = _to_torch(self.vbg.attribute("tsdf")).view(-1).numpy()
        weight = _to_torch(self.vbg.attribute("weight")).view(-1).numpy()
        col = (
            _to_torch(self.vbg.attribute("color")).view(-1).numpy() if cfg.integrate_color else np.zeros(0, np.float32)
        )
        vvox = (
            _to_torch(self.vbg.attribute("variance")).view(-1).numpy()
            if cfg.integrate_variance
            else np.zeros(0, np.float32)
        )
        cam = self.camera
        return int(
            _update_voxels(
                blocks,
                buf,
                int(cfg.block_resolution),
                float(cfg.voxel_size),
                T_cw[:3, :3].copy(),
                T_cw[:3, 3].copy(),
                float(cam.fx),
                float(cam.fy),
                float(cam.cx),
                float(cam.cy),
                np.ascontiguousarray(d, np.float32),
                np.ascontiguousarray(w, np.float32),
                np.zeros((0, 0, 3), np.float32) if color is None else np.ascontiguousarray(color, np.float32),
                np.zeros((0, 0), np.float32) if var is None else np.ascontiguousarray(var, np.float32),
                np.ascontiguousarray(trunc, np.float32),
                float(cfg.tsdf_scale),
                float(cfg.weight_cap),
                tsdf,
                weight,
                col,
                vvox,
            )
        )

    def _update_torch(
        self,
        keys: np.ndarray,
        d: np.ndarray,
        w: np.ndarray,
        color: np.ndarray | None,
        var: np.ndarray | None,
        T: np.ndarray,
        trunc: np.ndarray | None = None,
    ) -> int:
        """`_update` as torch tensor operations (CUDA, and the CPU reference in the tests)."""
        # The voxel update runs in torch on zero-copy (DLPack) views of the grid's buffers.
        import torch

        cfg, tdev = self.config, self._torch_device
        buf_indices = self._activate(keys)
        voxel_coords, voxel_indices = self.vbg.voxel_coordinates_and_flattened_indices(buf_indices)
        coords = _to_torch(voxel_coords)
        flat = _to_torch(voxel_indices)
        Tcw = torch.as_tensor(np.linalg.inv(T), dtype=torch.float32, device=tdev)
        K = torch.as_tensor(self.camera.K, dtype=torch.float32, device=tdev)
        xyz = coords @ Tcw[:3, :3].T + Tcw[:3, 3]
        z = xyz[:, 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        u = torch.round(K[0, 0] * xyz[:, 0] / zs + K[0, 2]).to(torch.int64)
        v = torch.round(K[1, 1] * xyz[:, 1] / zs + K[1, 2]).to(torch.int64)
        in_view = front & (u >= 0) & (v >= 0) & (u < self.camera.width) & (v < self.camera.height)
        sel = torch.nonzero(in_view).squeeze(1)
        u, v, z = u[sel], v[sel], z[sel]
        depth_pix = torch.as_tensor(d, device=tdev)
        w_pix = torch.as_tensor(w, device=tdev)
        reading = depth_pix[v, u]
        wnew = w_pix[v, u]
        if trunc is None:
            trunc = np.full(d.shape, cfg.truncation, np.float32)
        tau = torch.as_tensor(np.asarray(trunc, np.float32), device=tdev)[v, u]
        sdf = reading - z
        inlier = (reading > 0) & (wnew > 0) & (sdf >= -tau)
        keep = torch.nonzero(inlier).squeeze(1)
        n = int(keep.shape[0])
        if n == 0:
            return 0
        idx = flat[sel[keep]]
        sdf = torch.minimum(sdf[keep], tau[keep]) / float(cfg.tsdf_scale)
        wnew = wnew[keep]
        tsdf = _to_torch(self.vbg.attribute("tsdf")).view(-1)
        weight = _to_torch(self.vbg.attribute("weight")).view(-1)
        wold = weight[idx]
        wsum = wold + wnew
        tsdf[idx] = (tsdf[idx] * wold + sdf * wnew) / wsum
        if color is not None:
            col_pix = torch.as_tensor(color, device=tdev)[v[keep], u[keep]]
            col = _to_torch(self.vbg.attribute("color")).view(-1, 3)
            col[idx] = (col[idx] * wold[:, None] + col_pix * wnew[:, None]) / wsum[:, None]
        if var is not None:
            var_pix = torch.as_tensor(var, device=tdev)[v[keep], u[keep]]
            vvox = _to_torch(self.vbg.attribute("variance")).view(-1)
            vvox[idx] = (vvox[idx] * wold + var_pix * wnew) / wsum
        weight[idx] = torch.clamp(wsum, max=float(cfg.weight_cap))
        return n

    def block_keys(
        self, depth: np.ndarray, T_world_camera: np.ndarray, variance: np.ndarray | None = None
    ) -> np.ndarray:
        """(M,) sorted int64 keys of the blocks a depth frame's truncation band touches.

        The depth is filtered as `integrate` filters it (range and validity, not weights); the
        variance sets the truncation as in `integrate` (``config.truncation_sigma``).
        """
        T = check_pose(T_world_camera)
        d = np.asarray(depth, dtype=np.float64)
        self.camera.check_image(d, "depth")
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(d) & (d > self.config.depth_min) & (d < self.config.depth_max)
        return self._band_keys(
            np.where(ok, d, 0.0).astype(np.float32), T, self.config.pixel_truncation(variance, d.shape)
        )

    def reset_blocks(self, keys: np.ndarray) -> int:
        """Zeroes TSDF, weight, colour and variance of the given blocks; returns how many existed.

        Args:
            keys: (M,) int64 block keys (`block_keys`, `IntegrationStats.block_keys`).
        """
        import torch

        keys = np.unique(np.asarray(keys, dtype=np.int64))
        if keys.size == 0:
            return 0
        blocks = self._o3c.Tensor(_keys_to_blocks(keys), device=self._device)
        buf, found = self.vbg.hashmap().find(blocks)
        found_np = found.cpu().numpy().astype(bool).reshape(-1)
        idx = torch.as_tensor(buf.cpu().numpy().astype(np.int64).reshape(-1)[found_np], device=self._torch_device)
        self._zero(idx)
        self._dirty.append(keys)
        return int(idx.numel())

    BAND_TILE = 3
    """Pixels per side of the tiles whose centre rays sample the truncation band (`_band_keys`)."""

    BAND_CONSERVATIVE = False
    """`_band_keys`: also take every block the tile's other pixel rays may reach (see there)."""

    def _band_keys(self, depth: np.ndarray, T: np.ndarray, trunc: np.ndarray | None = None) -> np.ndarray:
        """(M,) sorted int64 keys of the blocks the truncation band of a depth frame touches.

        Open3D's ``compute_unique_block_coordinates`` samples the band too sparsely (with a
        truncation of several blocks it skips blocks in the middle of the band, so some voxels
        in the band would never be updated). Here the image is cut into `BAND_TILE` x
        `BAND_TILE` pixel tiles and the ray through each tile's centre is sampled from the
        tile's smallest valid depth minus its truncation to its largest plus its truncation
        (``trunc``: (H, W) per pixel, metres; default ``config.truncation``),
        at steps of at most two voxels; `BAND_CONSERVATIVE` also marks every block the tile's
        other rays may reach. On the CPU a compiled loop marks the blocks in a dense grid over
        the frame's bounding box (`_band_blocks`, no sort); on CUDA torch computes the same
        samples and keeps the unique keys.
        """
        cfg, cam = self.config, self.camera
        step = 2.0 * cfg.voxel_size
        if trunc is None:
            trunc = np.full(np.shape(depth), cfg.truncation, np.float32)
        if self._torch_device == "cpu":
            blocks = _band_blocks(
                np.ascontiguousarray(depth, np.float32),
                float(cam.fx),
                float(cam.fy),
                float(cam.cx),
                float(cam.cy),
                np.ascontiguousarray(T[:3, :3], np.float64),
                np.ascontiguousarray(T[:3, 3], np.float64),
                np.ascontiguousarray(trunc, np.float32),
                step,
                float(cfg.voxel_size * cfg.block_resolution),
                int(self.BAND_TILE),
                bool(self.BAND_CONSERVATIVE),
            )
            return _blocks_to_keys(blocks)  # the grid is walked in key order: sorted, unique
        return self._band_keys_torch(depth, T, trunc)

    def _band_keys_torch(self, depth: np.ndarray, T: np.ndarray, trunc: np.ndarray | None = None) -> np.ndarray:
        """`_band_keys` with torch (CUDA, and the CPU reference in the tests): the same samples."""
        import torch

        cfg, cam, tdev = self.config, self.camera, self._torch_device
        tile = int(self.BAND_TILE)
        d = torch.as_tensor(np.asarray(depth, np.float32), device=tdev)
        h, w = d.shape
        if trunc is None:
            trunc = np.full(np.shape(depth), cfg.truncation, np.float32)
        tau = torch.as_tensor(np.asarray(trunc, np.float32), device=tdev)
        valid = d > 0
        # per tile: the nearest (depth - truncation) and the farthest (depth + truncation)
        big = torch.where(valid, d - tau, torch.full_like(d, float("inf")))[None, None]
        dmin = -torch.nn.functional.max_pool2d(-big, tile, ceil_mode=True)[0, 0]
        dmax = torch.nn.functional.max_pool2d(
            torch.where(valid, d + tau, torch.full_like(d, -1.0))[None, None], tile, ceil_mode=True
        )[0, 0]
        ty, tx = torch.nonzero(dmax > 0, as_tuple=True)
        if ty.numel() == 0:
            return np.zeros(0, np.int64)
        dmin, dmax = dmin[ty, tx].double(), dmax[ty, tx].double()
        u0, v0 = tx * tile, ty * tile
        u1, v1 = torch.clamp(u0 + tile, max=w), torch.clamp(v0 + tile, max=h)
        rx = (0.5 * (u0 + u1 - 1).double() - cam.cx) / cam.fx
        ry = (0.5 * (v0 + v1 - 1).double() - cam.cy) / cam.fy
        Tw = torch.as_tensor(T, dtype=torch.float64, device=tdev)
        block_size = float(cfg.voxel_size * cfg.block_resolution)
        rays = torch.stack([rx, ry, torch.ones_like(rx)], dim=1) @ Tw[:3, :3].T / block_size  # blocks per metre
        origin = Tw[:3, 3] / block_size
        a0 = torch.clamp(dmin, min=1e-3)
        a1 = dmax
        step = 2.0 * cfg.voxel_size
        n = torch.ceil((a1 - a0) / step).long() + 1
        spread = np.sqrt(2.0) * 0.5 * (tile - 1) / min(cam.fx, cam.fy) / block_size if self.BAND_CONSERVATIVE else 0.0
        keys = []
        for k in range(int(n.max())):
            on = n > k
            s = a0[on] + (a1[on] - a0[on]) * k / (n[on] - 1).double()
            c = origin + s[:, None] * rays[on]
            r = (s * spread)[:, None]
            lo, hi = torch.floor(c - r).long(), torch.floor(c + r).long()
            span = int((hi - lo).max()) + 1
            for di in range(span):
                for dj in range(span):
                    for dq in range(span):
                        b = lo + torch.tensor([di, dj, dq], device=tdev)
                        ok = torch.all(b <= hi, dim=1)
                        b = b[ok] + _KEY_BIAS
                        keys.append((b[:, 0] * _KEY_SPAN + b[:, 1]) * _KEY_SPAN + b[:, 2])
        return torch.unique(torch.cat(keys)).cpu().numpy()

    def weights_for(
        self, variance: np.ndarray | None, depth: np.ndarray | None = None, *, points: int = 0
    ) -> np.ndarray | None:
        """The per-pixel weights of this volume's weighting for a variance map (None = uniform).

        ``depth`` (the depth map the variance belongs to, metres) is needed with the relative
        settings (the default) and the weighting "variance"; ``points`` is the number of sparse
        measurements the frame had (they set its uninformed pixels' weight, `FusionConfig.fallback_for`).
        """
        if self.config.weighting == "uniform" or variance is None:
            return None
        cfg = self.config
        return weights_from_variance(
            variance,
            sigma_ref=cfg.sigma_ref,
            depth=depth,
            max_relative_sigma=cfg.max_relative_sigma,
            relative_sigma_ref=cfg.relative_sigma_ref,
            fallback_weight=cfg.fallback_for(points),
        )

    def integrate_posterior(
        self, posterior: "DepthPosterior", T_world_camera: np.ndarray, *, rgb: np.ndarray | None = None
    ) -> IntegrationStats:
        """Fuses a `DepthPosterior`'s mean, weighted as ``config.weighting`` says from its variance."""
        return self.integrate(
            posterior.mean,
            T_world_camera,
            rgb=rgb,
            weights=self.weights_for(posterior.variance, posterior.mean, points=len(getattr(posterior, "sparse", ()))),
            variance=posterior.variance if self.config.integrate_variance else None,
        )

    # ------------------------------------------------------------------ extraction
    def _check_nonempty(self) -> None:
        if self.frames_integrated == 0:
            raise EmptyInputError("fusion", "at least one integrated frame", "an empty volume")

    def voxels(self) -> dict[str, np.ndarray]:
        """The observed voxels (accumulated weight > 0).

        Returns:
            ``coords`` (M, 3) world positions of the voxels' sample points (metres), ``tsdf``
            (M,) truncated signed distance / ``config.tsdf_scale`` in [-1, 1], ``weight`` (M,) accumulated
            weights, with colour ``color`` (M, 3) float in 0..1 and with
            ``config.integrate_variance`` ``variance`` (M,) m^2.
        """
        self._check_nonempty()
        hashmap = self.vbg.hashmap()
        buf = hashmap.active_buf_indices()
        coords, idx = self.vbg.voxel_coordinates_and_flattened_indices(buf)
        weight = self.vbg.attribute("weight").reshape((-1,))[idx]
        keep = weight > 0
        out = {
            "coords": coords[keep].cpu().numpy().astype(np.float64),
            "tsdf": self.vbg.attribute("tsdf").reshape((-1,))[idx][keep].cpu().numpy().astype(np.float64),
            "weight": weight[keep].cpu().numpy().astype(np.float64),
        }
        if self.config.integrate_color:
            out["color"] = (
                self.vbg.attribute("color").reshape((-1, 3))[idx][keep].cpu().numpy().astype(np.float64) / 255
            )
        if self.config.integrate_variance:
            out["variance"] = self.vbg.attribute("variance").reshape((-1,))[idx][keep].cpu().numpy().astype(np.float64)
        return out

    def extract_mesh(self, *, allow_empty: bool = False) -> "trimesh.Trimesh":
        """The zero level set as a `trimesh.Trimesh` (metres, world frame) with vertex colours.

        Args:
            allow_empty: Return a mesh without faces (instead of raising) when no surface passes
                ``weight_threshold`` (e.g. after few frames with low weights).

        Raises:
            EmptyInputError: if nothing was integrated, or (without ``allow_empty``) no surface
                passes ``weight_threshold``.
        """
        import trimesh

        self._check_nonempty()
        mesh = self.vbg.extract_triangle_mesh(float(self.config.weight_threshold)).cpu()
        if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0 or mesh.triangle.indices.shape[0] == 0:
            if allow_empty:
                return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
            raise EmptyInputError("fusion", f"a surface with weight > {self.config.weight_threshold}", "no triangles")
        vertices = mesh.vertex.positions.numpy().astype(np.float64)
        faces = mesh.triangle.indices.numpy().astype(np.int64)
        colors = None
        if "colors" in mesh.vertex:
            colors = np.clip(np.rint(mesh.vertex.colors.numpy() * 255.0), 0, 255).astype(np.uint8)
        return trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)

    CHUNK_BLOCKS = 4
    """Edge of an incremental-extraction chunk, in blocks (4 blocks of 8 voxels of 2 cm: 64 cm)."""

    def extract_mesh_incremental(self, *, allow_empty: bool = False) -> "trimesh.Trimesh":
        """The same surface as `extract_mesh`, re-extracting only the chunks changed since the last call.

        The volume is cut into cubic chunks of `CHUNK_BLOCKS` blocks. A marching-cubes cell
        belongs to the block of its lowest voxel and needs the voxels of the next block along
        each axis, so a changed block changes the cells of its own chunk and of the chunks of
        its 7 lower neighbours. Those chunks' blocks and a one-block halo are copied into a
        temporary grid and meshed by Open3D; every other chunk keeps its cached triangles.
        The first call meshes the whole volume. The result is the surface `extract_mesh` gives
        (the same triangles), as a triangle soup: vertices are not shared between triangles.

        Args:
            allow_empty: Return a mesh without faces (instead of raising) when no surface passes
                ``weight_threshold``.

        Raises:
            EmptyInputError: if nothing was integrated, or (without ``allow_empty``) no surface
                passes ``weight_threshold``.
        """
        import torch

        self._check_nonempty()
        o3d, o3c = self._o3d, self._o3c
        res, C = int(self.config.block_resolution), int(self.CHUNK_BLOCKS)
        with self._threads():
            if self._chunks is None:
                chunks = None  # everything
                grid = self.vbg
            else:
                dirty = np.unique(np.concatenate(self._dirty)) if self._dirty else np.zeros(0, np.int64)
                if dirty.size == 0:
                    return self._assemble(allow_empty)
                b = _keys_to_blocks(dirty).astype(np.int64)
                offsets = np.array([[i, j, k] for i in (0, -1) for j in (0, -1) for k in (0, -1)])
                chunk_coords = np.unique(np.floor_divide((b[:, None, :] + offsets[None]).reshape(-1, 3), C), axis=0)
                chunks = _blocks_to_keys(chunk_coords)
                span = np.stack(np.meshgrid(*[np.arange(C + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
                candidates = np.unique(_blocks_to_keys((chunk_coords[:, None, :] * C + span[None]).reshape(-1, 3)))
                blocks = o3c.Tensor(_keys_to_blocks(candidates), device=self._device)
                buf, found = self.vbg.hashmap().find(blocks)
                found_np = found.cpu().numpy().astype(bool).reshape(-1)
                src = torch.as_tensor(
                    buf.cpu().numpy().astype(np.int64).reshape(-1)[found_np], device=self._torch_device
                )
                grid = o3d.t.geometry.VoxelBlockGrid(
                    self._attributes,
                    tuple(o3c.float32 for _ in self._attributes),
                    tuple(3 if a == "color" else 1 for a in self._attributes),
                    float(self.config.voxel_size),
                    res,
                    max(1, int(found_np.sum())),
                    self._device,
                )
                if found_np.any():
                    sub = o3c.Tensor(_keys_to_blocks(candidates[found_np]), device=self._device)
                    dst_buf, _ = grid.hashmap().activate(sub)
                    dst = torch.as_tensor(dst_buf.cpu().numpy().astype(np.int64).reshape(-1), device=self._torch_device)
                    for name in self._attributes:
                        _to_torch(grid.attribute(name))[dst] = _to_torch(self.vbg.attribute(name))[src]
            mesh = grid.extract_triangle_mesh(float(self.config.weight_threshold)).cpu()
        if "positions" in mesh.vertex and mesh.vertex.positions.shape[0] and mesh.triangle.indices.shape[0]:
            vertices = mesh.vertex.positions.numpy().astype(np.float64)
            faces = mesh.triangle.indices.numpy().astype(np.int64)
            tri = vertices[faces]  # (m, 3, 3)
            if "colors" in mesh.vertex:
                col = np.clip(np.rint(mesh.vertex.colors.numpy() * 255.0), 0, 255).astype(np.uint8)[faces]
            else:
                col = np.full(tri.shape, 128, np.uint8)
            owner_voxel = np.floor(tri.mean(axis=1) / float(self.config.voxel_size)).astype(np.int64)
            owner = _blocks_to_keys(np.floor_divide(np.floor_divide(owner_voxel, res), C))
        else:
            tri, col, owner = np.zeros((0, 3, 3)), np.zeros((0, 3, 3), np.uint8), np.zeros(0, np.int64)
        if chunks is None:
            self._chunks = {}
        else:
            for key in chunks:
                self._chunks.pop(int(key), None)
            keep = np.isin(owner, chunks)
            tri, col, owner = tri[keep], col[keep], owner[keep]
        order = np.argsort(owner, kind="stable")
        tri, col, owner = tri[order], col[order], owner[order]
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if owner.size else np.zeros(0, np.int64)
        for a, b_ in zip(starts, np.r_[starts[1:], owner.size].astype(np.int64)):
            self._chunks[int(owner[a])] = (tri[a:b_], col[a:b_])
        self._dirty = []
        return self._assemble(allow_empty)

    def _assemble(self, allow_empty: bool) -> "trimesh.Trimesh":
        import trimesh

        parts = list(self._chunks.values()) if self._chunks else []
        if not parts:
            if allow_empty:
                return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
            raise EmptyInputError("fusion", f"a surface with weight > {self.config.weight_threshold}", "no triangles")
        tri = np.concatenate([p[0] for p in parts]).reshape(-1, 3)
        col = np.concatenate([p[1] for p in parts]).reshape(-1, 3)
        faces = np.arange(tri.shape[0], dtype=np.int64).reshape(-1, 3)
        return trimesh.Trimesh(tri, faces, vertex_colors=col, process=False)

    def extract_point_cloud(self, *, allow_empty: bool = False) -> ColoredCloud:
        """Surface points of the volume as a `ColoredCloud`.

        Each point takes the values of the voxel nearest to it: the confidence is that voxel's
        accumulated weight divided by ``weight_cap`` (in [0, 1]); the variance is the voxel's
        fused depth variance (m^2) with ``config.integrate_variance``, else NaN (unknown). The
        viewing depth is not defined for a fused point (``depth`` is NaN).

        Args:
            allow_empty: Return a cloud without points (instead of raising) when no surface
                passes ``weight_threshold``.

        Raises:
            EmptyInputError: if nothing was integrated, or (without ``allow_empty``) no surface
                passes ``weight_threshold``.
        """
        self._check_nonempty()
        pcd = self.vbg.extract_point_cloud(float(self.config.weight_threshold)).cpu()
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            if allow_empty:
                return ColoredCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0), np.zeros(0))
            raise EmptyInputError("fusion", f"a surface with weight > {self.config.weight_threshold}", "no points")
        pts = pcd.point.positions.numpy().astype(np.float64)
        n = pts.shape[0]
        if "colors" in pcd.point:
            colors = np.clip(np.rint(pcd.point.colors.numpy() * 255.0), 0, 255).astype(np.uint8)
        else:
            colors = np.full((n, 3), 128, np.uint8)
        flat = self._nearest_voxels(pts)
        weight = self.vbg.attribute("weight").cpu().numpy().reshape(-1)[flat].astype(np.float64)
        conf = np.clip(weight / self.config.weight_cap, 0.0, 1.0)
        if self.config.integrate_variance:
            var = self.vbg.attribute("variance").cpu().numpy().reshape(-1)[flat].astype(np.float64)
        else:
            var = np.full(n, np.nan)
        return ColoredCloud(pts, colors, var, conf, np.full(n, np.nan))

    def _nearest_voxels(self, points: np.ndarray) -> np.ndarray:
        """(N,) flat buffer indices of the voxels nearest to (N, 3) world points (on extracted surfaces).

        A voxel's sample point is at ``voxel_size * index``; Open3D stores a block's voxels at
        ``buffer_index * res^3 + (z * res + y) * res + x``. Points whose nearest voxel's block
        does not exist fall back to a nearest-neighbour search over the observed voxels.
        """
        res = int(self.config.block_resolution)
        vi = np.rint(points / float(self.config.voxel_size)).astype(np.int64)
        blocks = np.floor_divide(vi, res)
        local = vi - blocks * res
        keys = _blocks_to_keys(blocks)
        uniq, inverse = np.unique(keys, return_inverse=True)
        buf, found = self.vbg.hashmap().find(self._o3c.Tensor(_keys_to_blocks(uniq), device=self._device))
        buf = buf.cpu().numpy().astype(np.int64).reshape(-1)[inverse]
        found = found.cpu().numpy().astype(bool).reshape(-1)[inverse]
        flat = buf * res**3 + (local[:, 2] * res + local[:, 1]) * res + local[:, 0]
        if not found.all():
            from scipy.spatial import cKDTree

            hashmap = self.vbg.hashmap()
            coords, idx = self.vbg.voxel_coordinates_and_flattened_indices(hashmap.active_buf_indices())
            _, near = cKDTree(coords.cpu().numpy()).query(points[~found])
            flat[~found] = idx.cpu().numpy().astype(np.int64)[near]
        return flat

    def save_mesh(self, path: str | Path) -> Path:
        """Extracts the mesh and writes it (PLY, GLB or OBJ by suffix) atomically."""
        return save_mesh(self.extract_mesh(), path)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """Writes the volume atomically: ``path`` (``.npz``, Open3D's ``VoxelBlockGrid.save``) and,
        beside it, ``<stem>.json`` with the camera, the config and the frame count.

        Returns:
            The ``.npz`` path.
        """
        path = Path(path)
        if path.suffix.lower() != ".npz":
            raise InvalidInputError("path", "a .npz file name", str(path))
        meta = {
            "camera": [
                self.camera.fx,
                self.camera.fy,
                self.camera.cx,
                self.camera.cy,
                self.camera.width,
                self.camera.height,
            ],
            "config": asdict(self.config),
            "frames_integrated": self.frames_integrated,
        }
        with atomic_path(path) as tmp:
            self.vbg.save(str(tmp))
        write_json(path.with_suffix(".json"), meta)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "TSDFFusion":
        """Reads a volume written by `save` (the ``.npz`` and its ``.json``).

        Raises:
            DataFormatError: if a file is missing or not a saved volume.
        """
        o3d = require("open3d")

        path = Path(path)
        meta_path = path.with_suffix(".json")
        for p in (path, meta_path):
            if not p.is_file():
                raise DataFormatError(p, "file of a saved TSDF volume not found")
        try:
            meta = json.loads(meta_path.read_text())
            fx, fy, cx, cy, width, height = meta["camera"]
            camera = PinholeCamera(float(fx), float(fy), float(cx), float(cy), int(width), int(height))
            config = FusionConfig(**meta["config"])
            vbg = o3d.t.geometry.VoxelBlockGrid.load(str(path))
        except (KeyError, TypeError, ValueError, RuntimeError, OSError) as exc:
            raise DataFormatError(path, f"not a saved gpdepth3d TSDF volume: {exc}") from None
        if config.device != "CPU:0":
            vbg = vbg.to(o3d.core.Device(config.device))
        fusion = cls(camera, config, _vbg=vbg)
        fusion.frames_integrated = int(meta["frames_integrated"])
        return fusion


# ---------------------------------------------------------------------- compiled CPU kernels
@nb.njit(cache=True, nogil=True)
def _masked_frame(
    depth, weights, variance, depth_min, depth_max
):  # pragma: no cover - compiled; tested through integrate
    """The pixels a frame fuses, in one pass (float64 inputs of one shape; ``variance`` may be (0, 0)).

    A pixel is fused when its depth is finite, in (depth_min, depth_max), its weight > 0 and
    (with a variance) its variance finite and >= 0. Returns float32 depth, weight and variance
    (0 where not fused; the variance (0, 0) without one), the number of negative or non-finite
    depths, the number of pixels fused, and whether any weight is negative or not finite.
    """
    h, w = depth.shape
    has_var = variance.shape[0] > 0
    d32 = np.zeros((h, w), np.float32)
    w32 = np.zeros((h, w), np.float32)
    v32 = np.zeros((h, w) if has_var else (0, 0), np.float32)
    n_bad = 0
    pixels = 0
    bad_weights = False
    for i in range(h):
        for j in range(w):
            d = depth[i, j]
            wt = weights[i, j]
            if not (np.isfinite(wt) and wt >= 0):
                bad_weights = True
            if not (np.isfinite(d) and d >= 0):
                n_bad += 1
                continue
            if has_var and not (np.isfinite(variance[i, j]) and variance[i, j] >= 0):
                continue
            if d > depth_min and d < depth_max and wt > 0:
                d32[i, j] = d
                w32[i, j] = wt
                if has_var:
                    v32[i, j] = variance[i, j]
                pixels += 1
    return d32, w32, v32, n_bad, pixels, bad_weights


@nb.njit(cache=True, nogil=True)
def _update_voxels(
    blocks,
    buf,
    res,
    voxel_size,
    R_cw,
    t_cw,
    fx,
    fy,
    cx,
    cy,
    depth,
    wpix,
    color,
    var,
    trunc,
    scale,
    cap,
    tsdf,
    weight,
    col,
    vvox,
):  # pragma: no cover - compiled; tested against the torch update
    """The projective TSDF update of every voxel of the given blocks (see the module docstring).

    ``blocks`` (M, 3) block coordinates, ``buf`` (M,) their buffer indices; a voxel (x, y, z)
    of block b sits at ``(b * res + (x, y, z)) * voxel_size`` and is stored at
    ``buf * res^3 + (z * res + y) * res + x`` (Open3D's layout). ``color`` / ``var`` of size 0
    skip those attributes. ``trunc`` (H, W) is each pixel's truncation, ``scale`` the distance the
    stored signed distances are divided by. Returns the number of voxel updates.
    """
    h, w = depth.shape
    has_color = color.shape[0] > 0
    has_var = var.shape[0] > 0
    n = 0
    r3 = res * res * res
    # camera coordinates of voxel (x, y, z) of a block: the voxel (0, y, z) plus x steps along ex
    ex = R_cw[:, 0] * voxel_size
    for m in range(blocks.shape[0]):
        base = buf[m] * r3
        o0 = blocks[m, 0] * res
        o1 = blocks[m, 1] * res
        o2 = blocks[m, 2] * res
        for z in range(res):
            for y in range(res):
                # the block's voxel (0, y, z) in the camera frame
                gx, gy, gz = o0 * voxel_size, (o1 + y) * voxel_size, (o2 + z) * voxel_size
                qx = R_cw[0, 0] * gx + R_cw[0, 1] * gy + R_cw[0, 2] * gz + t_cw[0]
                qy = R_cw[1, 0] * gx + R_cw[1, 1] * gy + R_cw[1, 2] * gz + t_cw[1]
                qz = R_cw[2, 0] * gx + R_cw[2, 1] * gy + R_cw[2, 2] * gz + t_cw[2]
                for x in range(res):
                    pz = qz + x * ex[2]
                    if pz <= 1e-6:
                        continue
                    inv = 1.0 / pz
                    u = np.rint(fx * (qx + x * ex[0]) * inv + cx)
                    v = np.rint(fy * (qy + x * ex[1]) * inv + cy)
                    if u < 0 or v < 0 or u >= w or v >= h:
                        continue
                    iu = int(u)
                    iv = int(v)
                    reading = depth[iv, iu]
                    wn = wpix[iv, iu]
                    if reading <= 0 or wn <= 0:
                        continue
                    tau = trunc[iv, iu]
                    sdf = reading - pz
                    if sdf < -tau:
                        continue
                    if sdf > tau:
                        sdf = tau
                    sdf /= scale
                    idx = base + (z * res + y) * res + x
                    wold = weight[idx]
                    wsum = wold + wn
                    tsdf[idx] = (tsdf[idx] * wold + sdf * wn) / wsum
                    if has_color:
                        for c in range(3):
                            col[3 * idx + c] = (col[3 * idx + c] * wold + color[iv, iu, c] * wn) / wsum
                    if has_var:
                        vvox[idx] = (vvox[idx] * wold + var[iv, iu] * wn) / wsum
                    weight[idx] = min(wsum, cap)
                    n += 1
    return n


@nb.njit(cache=True, nogil=True)
def _band_blocks(
    depth, fx, fy, cx, cy, R, t, trunc, step, block_size, tile, conservative
):  # pragma: no cover - compiled
    """(M, 3) int64 coordinates of the blocks the truncation band of a depth frame reaches, in
    key order (x, then y, then z).

    The image is cut into ``tile`` x ``tile`` pixel tiles; the ray through a tile's centre is
    sampled from the smallest (valid depth - trunc) of its pixels to the largest (depth + trunc)
    (``trunc`` (H, W) per pixel), at most ``step``
    metres apart; with ``conservative`` each sample also marks every block within the distance
    the tile's other pixel rays can be from it at that depth. The samples' blocks are marked in
    a dense grid over the bounding box of the rays' end samples (the samples in between lie
    between them; one block of margin for rounding), read out in order (no sort, no hash).
    """
    h, w = depth.shape
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    t0, t1, t2 = t[0] / block_size, t[1] / block_size, t[2] / block_size
    th, tw = (h + tile - 1) // tile, (w + tile - 1) // tile
    # pixel centres of a tile lie within (tile - 1) / 2 pixels of its centre in u and v: at depth
    # s their rays are within sqrt(2) * s * (tile - 1) / 2 / f metres of the centre ray
    spread = np.sqrt(2.0) * 0.5 * (tile - 1) / min(fx, fy) / block_size if conservative else 0.0
    # per tile: the ray's direction (blocks per metre of depth), its band [a0, a1], samples n (0: no depth)
    ray = np.empty((th, tw, 3))
    band = np.empty((th, tw, 2))
    count = np.zeros((th, tw), np.int64)
    for ty in range(th):
        v0, v1 = ty * tile, min(h, ty * tile + tile)
        for tx in range(tw):
            u0, u1 = tx * tile, min(w, tx * tile + tile)
            dmin, dmax = np.inf, -1.0
            for v in range(v0, v1):
                for u in range(u0, u1):
                    d = depth[v, u]
                    if d > 0:
                        dmin = min(dmin, d - trunc[v, u])
                        dmax = max(dmax, d + trunc[v, u])
            if dmax < 0:
                continue
            rx = (0.5 * (u0 + u1 - 1) - cx) / fx
            ry = (0.5 * (v0 + v1 - 1) - cy) / fy
            d0 = (R[0, 0] * rx + R[0, 1] * ry + R[0, 2]) / block_size
            d1 = (R[1, 0] * rx + R[1, 1] * ry + R[1, 2]) / block_size
            d2 = (R[2, 0] * rx + R[2, 1] * ry + R[2, 2]) / block_size
            a0 = max(dmin, 1e-3)
            a1 = dmax
            n = int(np.ceil((a1 - a0) / step)) + 1
            ray[ty, tx, 0], ray[ty, tx, 1], ray[ty, tx, 2] = d0, d1, d2
            band[ty, tx, 0], band[ty, tx, 1] = a0, a1
            count[ty, tx] = n
            for k in (0, n - 1):
                s = a0 + (a1 - a0) * k / (n - 1)
                r = s * spread
                c0, c1, c2 = t0 + s * d0, t1 + s * d1, t2 + s * d2
                lo[0], hi[0] = min(lo[0], int(np.floor(c0 - r)) - 1), max(hi[0], int(np.floor(c0 + r)) + 1)
                lo[1], hi[1] = min(lo[1], int(np.floor(c1 - r)) - 1), max(hi[1], int(np.floor(c1 + r)) + 1)
                lo[2], hi[2] = min(lo[2], int(np.floor(c2 - r)) - 1), max(hi[2], int(np.floor(c2 + r)) + 1)
    if lo[0] > hi[0]:
        return np.zeros((0, 3), np.int64)
    nx, ny, nz = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    grid = np.zeros((nx, ny, nz), np.bool_)
    for ty in range(th):
        for tx in range(tw):
            n = count[ty, tx]
            if n == 0:
                continue
            d0, d1, d2 = ray[ty, tx, 0], ray[ty, tx, 1], ray[ty, tx, 2]
            a0, a1 = band[ty, tx, 0], band[ty, tx, 1]
            for k in range(n):
                s = a0 + (a1 - a0) * k / (n - 1)
                r = s * spread  # the tile's other rays are within r of this sample (blocks)
                c0, c1, c2 = t0 + s * d0, t1 + s * d1, t2 + s * d2
                for i in range(int(np.floor(c0 - r)), int(np.floor(c0 + r)) + 1):
                    for j in range(int(np.floor(c1 - r)), int(np.floor(c1 + r)) + 1):
                        for q in range(int(np.floor(c2 - r)), int(np.floor(c2 + r)) + 1):
                            grid[i - lo[0], j - lo[1], q - lo[2]] = True
    total = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if grid[i, j, k]:
                    total += 1
    out = np.zeros((total, 3), np.int64)
    m = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if grid[i, j, k]:
                    out[m, 0], out[m, 1], out[m, 2] = i + lo[0], j + lo[1], k + lo[2]
                    m += 1
    return out


def _to_torch(tensor: Any) -> Any:
    """A zero-copy torch view of an Open3D tensor (writes go to the Open3D buffer)."""
    import torch.utils.dlpack

    return torch.utils.dlpack.from_dlpack(tensor.to_dlpack())


MESH_FORMATS = (".ply", ".glb", ".obj")


def save_mesh(mesh: Any, path: str | Path) -> Path:
    """Writes a `trimesh.Trimesh` as PLY, GLB or OBJ (chosen by the suffix) atomically.

    Raises:
        InvalidInputError: for another suffix or something that is not a trimesh mesh.
        EmptyInputError: for a mesh without faces.
    """
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_FORMATS:
        raise InvalidInputError("path", f"a file name ending in one of {MESH_FORMATS}", str(path))
    if not isinstance(mesh, trimesh.Trimesh):
        raise InvalidInputError("mesh", "a trimesh.Trimesh", type(mesh).__name__)
    if len(mesh.faces) == 0:
        raise EmptyInputError("mesh", "at least one triangle", "no faces")
    data = mesh.export(file_type=suffix[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return path
