"""The TSDF volume (`TSDFFusion`): posed depth frames fused with per-pixel weights into an Open3D `VoxelBlockGrid`.

Open3D's stock ``VoxelBlockGrid.integrate`` gives every pixel the weight 1. Here each pixel
carries its own weight (`gpdepth3d.mapping.tsdf.fusion_weights`) and, with a variance, its own
truncation (`gpdepth3d.mapping.tsdf.fusion_config`); the projective voxel update of KinectFusion
(Newcombe et al. 2011) with those weights is `gpdepth3d.mapping.tsdf.kernels`, compiled on the
CPU and in torch on zero-copy DLPack views of the grid's buffers on CUDA (``FusionConfig.device``).
The blocks to allocate are found by sampling every valid pixel's ray through the truncation band
(Open3D's ``compute_unique_block_coordinates`` samples the band too sparsely for truncations of
several blocks and would leave band voxels un-updated). Grid:
https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html.

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

Extraction (meshes, surface points, voxels) is `gpdepth3d.mapping.tsdf.extraction`; the files
(`TSDFFusion.save`, `save_mesh`) are `gpdepth3d.mapping.tsdf.storage`.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from ...camera import PinholeCamera, check_pose
from ...errors import EmptyInputError, InvalidInputError, ProblemTooLargeError, ShapeError, describe
from ...extras import require
from ...limits import memory_limit
from ..cloud import ColoredCloud
from .fusion_config import FusionConfig
from .fusion_weights import weights_from_variance
from .blocks import find_blocks, grid_attributes, keys_to_blocks, new_grid, to_torch, torch_device
from .extraction import MeshChunks, grid_mesh, observed_voxels, surface_cloud
from .storage import read_volume, save_mesh, write_volume
from .kernels import band_keys_cpu, band_keys_torch, masked_frame, update_cpu, update_torch

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

    from ...completion.complete import DepthPosterior

__all__ = ["FusionConfig", "IntegrationStats", "TSDFFusion", "save_mesh", "weights_from_variance"]


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


class TSDFFusion:
    """A TSDF volume that integrates posed depth frames with per-pixel weights.

    Example:
        >>> fusion = TSDFFusion(camera, FusionConfig(voxel_size=0.02))  # doctest: +SKIP
        >>> fusion.integrate(depth, T_world_camera, rgb=rgb, weights=w)  # doctest: +SKIP
        >>> fusion.save_mesh("room.glb")  # doctest: +SKIP
    """

    BAND_TILE = 3
    """Pixels per side of the tiles whose centre rays sample the truncation band (`_band_keys`)."""

    BAND_CONSERVATIVE = False
    """`_band_keys`: also take every block the tile's other pixel rays may reach (see there)."""

    CHUNK_BLOCKS = 4
    """Edge of an incremental-extraction chunk, in blocks (4 blocks of 8 voxels of 2 cm: 64 cm)."""

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
        self.vbg = _vbg if _vbg is not None else new_grid(self.config, self.config.block_count, self._device)
        self._torch_device = torch_device(self._device)
        self.frames_integrated = 0
        self._mesh_chunks = MeshChunks()  # the incremental extraction's cache and changed blocks

    @property
    def _attributes(self) -> tuple[str, ...]:
        return grid_attributes(self.config)

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
        d, w, var = self._checked_frame(depth, weights, variance)
        trunc = cfg.pixel_truncation(variance, d.shape)
        self._check_band_memory(d, trunc)
        d, w, var32, n_bad, pixels, bad_weights = masked_frame(
            np.ascontiguousarray(d, dtype=np.float64), w, var, float(cfg.depth_min), float(cfg.depth_max)
        )
        if bad_weights:
            raise InvalidInputError("weights", "finite weights >= 0", "negative or non-finite weights")
        if pixels == 0:
            raise EmptyInputError(
                "depth", f"at least one pixel with depth in ({cfg.depth_min}, {cfg.depth_max}) m and weight > 0", "none"
            )
        color = self._frame_color(rgb, d.shape) if cfg.integrate_color else None
        with self._threads():
            keys = self._band_keys(d, T, trunc)
            if blocks is not None:
                keys = np.intersect1d(keys, np.asarray(blocks, dtype=np.int64), assume_unique=False)
            n = 0
            if keys.size:
                n = self._update(keys, d, w, color, var32 if cfg.integrate_variance else None, T, trunc)
        self._mesh_chunks.mark(keys)
        self.frames_integrated += 1
        return IntegrationStats(voxels=n, pixels=pixels, invalid_pixels=n_bad, block_keys=keys)

    def _checked_frame(
        self, depth: np.ndarray, weights: np.ndarray | None, variance: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`integrate`'s depth (as given), float64 weights and variance ((0, 0) when not integrated), checked."""
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
        if self.config.integrate_variance:
            if variance is None:
                raise InvalidInputError("variance", "an (H, W) variance map (config.integrate_variance is on)", None)
            var = np.ascontiguousarray(variance, dtype=np.float64)
            if var.shape != d.shape:
                raise ShapeError("variance", f"the shape of depth {d.shape}", describe(var))
        return d, w, var

    def _frame_color(self, rgb: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
        """(H, W, 3) float32 colour to fuse, 0..255 (mid-grey without an image)."""
        if rgb is None:
            return np.full(shape + (3,), 128.0, np.float32)
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] < 3:
            raise ShapeError("rgb", "an (H, W, 3) RGB image", describe(rgb))
        self.camera.check_image(rgb, "rgb")
        # Open3D's extraction divides the stored colour by 255.
        color = rgb[..., :3].astype(np.float32)
        if not np.issubdtype(rgb.dtype, np.integer):
            color = color * 255.0
        return color

    @property
    def block_bytes(self) -> int:
        """Bytes one voxel block holds (float32 channels of ``block_resolution``^3 voxels)."""
        channels = 2 + 3 * bool(self.config.integrate_color) + bool(self.config.integrate_variance)
        return int(self.config.block_resolution) ** 3 * 4 * channels

    def _check_band_memory(self, depth: np.ndarray, trunc: np.ndarray) -> None:
        """Refuses a frame whose truncation band would need more than `gpdepth3d.limits.memory_limit` (blocks, search grid).

        Estimate: the frame's surface area (each pixel's footprint ``d^2 / (fx fy)``) in blocks,
        times the blocks the band spans along a ray, plus the dense grid `band_blocks` marks them in.
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
                f"{limit / 2**30:.1f} GiB (`gpdepth3d.limits.memory_limit`), got {self.config.voxel_size} m: about "
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

    # ------------------------------------------------------------------ blocks
    def _activate(self, keys: np.ndarray) -> Any:
        """Buffer indices of the blocks ``keys``, allocating (zeroed) the missing ones."""
        blocks = self._o3c.Tensor(keys_to_blocks(keys), device=self._device)
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
            to_torch(self.vbg.attribute(name))[buf_idx] = 0.0

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
        """The voxel update of one frame over the blocks ``keys`` (`gpdepth3d.mapping.tsdf.kernels`).

        On the CPU a compiled loop (`update_cpu`, numba) visits every voxel of the blocks once;
        on CUDA the same update runs as torch tensor operations (`_update_torch`).
        """
        if trunc is None:
            trunc = np.full(d.shape, self.config.truncation, np.float32)
        if self._torch_device != "cpu":
            return self._update_torch(keys, d, w, color, var, T, trunc)
        buf = self._activate(keys).cpu().numpy().astype(np.int64).reshape(-1)
        blocks = keys_to_blocks(keys).astype(np.int64)
        cfg = self.config
        voxels = (int(cfg.block_resolution), float(cfg.voxel_size))
        frame = (d, w, color, var, trunc)
        return update_cpu(self.vbg, blocks, buf, self.camera, frame, T, voxels, cfg.tsdf_scale, cfg.weight_cap)

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
        cfg = self.config
        buf_indices = self._activate(keys)
        if trunc is None:
            trunc = np.full(d.shape, cfg.truncation, np.float32)
        frame = (d, w, color, var, trunc)
        return update_torch(
            self.vbg, buf_indices, self.camera, frame, T, cfg.tsdf_scale, cfg.weight_cap, self._torch_device
        )

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
        buf, found = find_blocks(self.vbg, keys, self._device)
        idx = torch.as_tensor(buf[found], device=self._torch_device)
        self._zero(idx)
        self._mesh_chunks.mark(keys)
        return int(idx.numel())

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
        the frame's bounding box (`band_blocks`, no sort); on CUDA torch computes the same
        samples and keeps the unique keys.
        """
        if self._torch_device != "cpu":
            return self._band_keys_torch(depth, T, trunc)
        cfg = self.config
        if trunc is None:
            trunc = np.full(np.shape(depth), cfg.truncation, np.float32)
        sizes = (cfg.voxel_size, cfg.voxel_size * cfg.block_resolution)
        return band_keys_cpu(depth, T, trunc, self.camera, sizes, int(self.BAND_TILE), bool(self.BAND_CONSERVATIVE))

    def _band_keys_torch(self, depth: np.ndarray, T: np.ndarray, trunc: np.ndarray | None = None) -> np.ndarray:
        """`_band_keys` with torch (CUDA, and the CPU reference in the tests): the same samples."""
        cfg = self.config
        if trunc is None:
            trunc = np.full(np.shape(depth), cfg.truncation, np.float32)
        sizes = (cfg.voxel_size, float(cfg.voxel_size * cfg.block_resolution))
        tile, wide = int(self.BAND_TILE), self.BAND_CONSERVATIVE
        return band_keys_torch(depth, T, trunc, self.camera, sizes, tile, wide, self._torch_device)

    # ------------------------------------------------------------------ weights
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
        return observed_voxels(self.vbg, self.config)

    def extract_mesh(self, *, allow_empty: bool = False) -> "trimesh.Trimesh":
        """The zero level set as a `trimesh.Trimesh` (metres, world frame) with vertex colours.

        Args:
            allow_empty: Return a mesh without faces (instead of raising) when no surface passes
                ``weight_threshold`` (e.g. after few frames with low weights).

        Raises:
            EmptyInputError: if nothing was integrated, or (without ``allow_empty``) no surface
                passes ``weight_threshold``.
        """
        self._check_nonempty()
        return grid_mesh(self.vbg, self.config, allow_empty)

    def extract_mesh_incremental(self, *, allow_empty: bool = False) -> "trimesh.Trimesh":
        """The same surface as `extract_mesh`, re-extracting only the chunks changed since the last call.

        The volume is cut into cubic chunks of `CHUNK_BLOCKS` blocks (`extraction.MeshChunks`);
        the first call meshes the whole volume. The result is the surface `extract_mesh` gives
        (the same triangles), as a triangle soup: vertices are not shared between triangles.

        Args:
            allow_empty: Return a mesh without faces (instead of raising) when no surface passes
                ``weight_threshold``.

        Raises:
            EmptyInputError: if nothing was integrated, or (without ``allow_empty``) no surface
                passes ``weight_threshold``.
        """
        self._check_nonempty()
        with self._threads():
            return self._mesh_chunks.mesh(self.vbg, self.config, self._device, self.CHUNK_BLOCKS, allow_empty)

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
        return surface_cloud(self.vbg, self.config, self._device, allow_empty)

    # ------------------------------------------------------------------ persistence
    def save_mesh(self, path: str | Path) -> Path:
        """Extracts the mesh and writes it (PLY, GLB or OBJ by suffix) atomically."""
        return save_mesh(self.extract_mesh(), path)

    def save(self, path: str | Path) -> Path:
        """Writes the volume atomically: ``path`` (``.npz``, Open3D's ``VoxelBlockGrid.save``) and,
        beside it, ``<stem>.json`` with the camera, the config and the frame count.

        Returns:
            The ``.npz`` path.
        """
        return write_volume(path, self.vbg, self.camera, self.config, self.frames_integrated)

    @classmethod
    def load(cls, path: str | Path) -> "TSDFFusion":
        """Reads a volume written by `save` (the ``.npz`` and its ``.json``).

        Raises:
            DataFormatError: if a file is missing or not a saved volume.
        """
        camera, config, vbg, meta = read_volume(path)
        fusion = cls(camera, config, _vbg=vbg)
        fusion.frames_integrated = int(meta["frames_integrated"])
        return fusion
