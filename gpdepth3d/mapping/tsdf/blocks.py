"""The voxel blocks of a TSDF volume: its Open3D `VoxelBlockGrid`, block keys, block look-up, torch views.

A block is ``block_resolution``^3 voxels; block (i, j, k) holds the voxels of world coordinates
``[i, i + 1) * voxel_size * block_resolution`` (likewise j, k). A block is named by one int64 key
(`blocks_to_keys`), so that sets of blocks are plain sorted arrays. The grid and its hash map are
Open3D's: https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ...extras import require

if TYPE_CHECKING:  # pragma: no cover
    from .fusion_config import FusionConfig

KEY_BIAS, KEY_SPAN = 1 << 20, 1 << 21
"""A block coordinate c in [-KEY_BIAS, KEY_BIAS) is stored as c + KEY_BIAS, KEY_SPAN values per axis."""


def blocks_to_keys(blocks: np.ndarray) -> np.ndarray:
    """(M, 3) integer block coordinates to (M,) int64 keys (one number per block, sorted as x, y, z)."""
    b = np.asarray(blocks, dtype=np.int64) + KEY_BIAS
    return (b[:, 0] * KEY_SPAN + b[:, 1]) * KEY_SPAN + b[:, 2]


def keys_to_blocks(keys: np.ndarray) -> np.ndarray:
    """(M,) int64 keys to (M, 3) int32 block coordinates."""
    k = np.asarray(keys, dtype=np.int64)
    b = np.stack([k // (KEY_SPAN * KEY_SPAN), (k // KEY_SPAN) % KEY_SPAN, k % KEY_SPAN], axis=1) - KEY_BIAS
    return b.astype(np.int32)


def grid_attributes(config: "FusionConfig") -> tuple[str, ...]:
    """Names of the float32 voxel attributes a volume with ``config`` stores ("color" has 3 channels)."""
    names = ["tsdf", "weight"]
    if config.integrate_color:
        names.append("color")
    if config.integrate_variance:
        names.append("variance")
    return tuple(names)


def new_grid(config: "FusionConfig", block_count: int, device: Any) -> Any:
    """An empty Open3D `VoxelBlockGrid` with ``config``'s attributes and voxels, room for ``block_count`` blocks."""
    o3d = require("open3d")
    o3c = require("open3d.core")
    names = grid_attributes(config)
    return o3d.t.geometry.VoxelBlockGrid(
        names,
        tuple(o3c.float32 for _ in names),
        tuple(3 if name == "color" else 1 for name in names),
        float(config.voxel_size),
        int(config.block_resolution),
        int(block_count),
        device,
    )


def find_blocks(vbg: Any, keys: np.ndarray, device: Any) -> tuple[np.ndarray, np.ndarray]:
    """(M,) int64 buffer indices and (M,) bool "exists" of the blocks ``keys`` in the grid ``vbg``."""
    o3c = require("open3d.core")
    buf, found = vbg.hashmap().find(o3c.Tensor(keys_to_blocks(keys), device=device))
    return buf.cpu().numpy().astype(np.int64).reshape(-1), found.cpu().numpy().astype(bool).reshape(-1)


def to_torch(tensor: Any) -> Any:
    """A zero-copy torch view of an Open3D tensor (writes go to the Open3D buffer)."""
    import torch.utils.dlpack

    return torch.utils.dlpack.from_dlpack(tensor.to_dlpack())


def torch_device(device: Any) -> str:
    """The torch device ("cpu" or "cuda:N") of an Open3D device."""
    o3c = require("open3d.core")
    if device.get_type() == o3c.Device.DeviceType.CUDA:
        return f"cuda:{device.get_id()}"
    return "cpu"
