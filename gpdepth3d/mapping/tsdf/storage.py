"""Files of the TSDF fusion: a saved volume (``.npz`` + ``.json``) and meshes (PLY, GLB, OBJ), written atomically.

A volume is one compressed ``.npz`` of its allocated blocks, sorted by block key
(`gpdepth3d.mapping.tsdf.blocks`): ``blocks`` (M, 3) int32 block coordinates and one array per
voxel attribute, (M, r, r, r[, 3]) for blocks of r^3 voxels in Open3D's voxel order, in
`gpdepth3d.mapping.compact_arrays`' forms: ``tsdf`` fixed point, ``weight`` half precision,
``color`` uint8, ``sigma`` (the square root of the variance attribute) half precision. Beside it,
``<stem>.json``: ``camera`` [fx, fy, cx, cy, width, height], ``config`` (the `FusionConfig`
fields), ``frames_integrated``, ``format`` (`VOLUME_FORMAT`) and ``blocks``. Both files are one
output set (`gpdepth3d.io.output_set`). Volumes written before this format (Open3D's
``VoxelBlockGrid.save`` archive, https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html)
still load.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from ...camera import PinholeCamera
from ...errors import DataFormatError, EmptyInputError, InvalidInputError
from ...extras import require
from ...io import atomic_path, npz_writer, output_set, write_json
from ..compact_arrays import FIXED_STEPS, read_npz_members, sigma_of, to_fixed, to_half
from .fusion_config import FusionConfig
from .extraction import canonical_mesh
from .blocks import blocks_to_keys, grid_attributes, keys_to_blocks, new_grid, to_torch, torch_device

MESH_FORMATS = (".ply", ".glb", ".obj")
VOLUME_FORMAT = "gpdepth3d-blocks-1"
"""``format`` of a volume's ``.json`` in the block format above (absent: Open3D's archive)."""


def write_volume(path: str | Path, vbg: Any, camera: PinholeCamera, config: FusionConfig, frames: int) -> Path:
    """Writes the allocated blocks of the grid ``vbg`` to ``path`` (``.npz``) and its camera, config
    and frame count beside it, as one output set.

    Returns:
        The ``.npz`` path.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise InvalidInputError("path", "a .npz file name", str(path))
    arrays = volume_arrays(vbg, config)
    meta = {
        "camera": [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height],
        "config": asdict(config),
        "frames_integrated": frames,
        "format": VOLUME_FORMAT,
        "blocks": int(arrays["blocks"].shape[0]),
    }
    with output_set(path.with_suffix(""), members=[path.name, path.with_suffix(".json").name]):
        with atomic_path(path) as tmp:
            npz_writer(**arrays)(tmp)
        write_json(path.with_suffix(".json"), meta)
    return path


def volume_arrays(vbg: Any, config: FusionConfig) -> dict[str, np.ndarray]:
    """The arrays of the saved form of ``vbg``'s allocated blocks (the module docstring), sorted by block key."""
    o3c = require("open3d.core")
    buf = vbg.hashmap().active_buf_indices().to(o3c.int64)
    blocks = vbg.hashmap().key_tensor()[buf].cpu().numpy().astype(np.int32).reshape(-1, 3)
    order = np.argsort(blocks_to_keys(blocks), kind="stable")
    idx = o3c.Tensor(buf.cpu().numpy()[order])
    out = {"blocks": blocks[order]}
    for name in grid_attributes(config):
        values = vbg.attribute(name).cpu()[idx].numpy()
        if name == "tsdf":
            out[name] = to_fixed(values[..., 0])
        elif name == "weight":
            out[name] = to_half(values[..., 0])
        elif name == "color":
            out[name] = np.clip(np.rint(values), 0, 255).astype(np.uint8)
        else:  # the variance, m^2
            out["sigma"] = sigma_of(values[..., 0])
    return out


def read_volume(path: str | Path) -> tuple[PinholeCamera, FusionConfig, Any, dict]:
    """Reads a volume written by `write_volume` (or by earlier versions): its camera, config, grid
    (on ``config.device``) and the parsed ``.json`` (``frames_integrated``).

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
        if meta.get("format") == VOLUME_FORMAT:
            vbg = grid_from_arrays(path, config)
        else:  # Open3D's archive (volumes of earlier versions)
            vbg = o3d.t.geometry.VoxelBlockGrid.load(str(path))
            if config.device != "CPU:0":
                vbg = vbg.to(o3d.core.Device(config.device))
    except (KeyError, TypeError, ValueError, RuntimeError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"not a saved gpdepth3d TSDF volume: {exc}") from None
    return camera, config, vbg, meta


def grid_from_arrays(path: Path, config: FusionConfig) -> Any:
    """An Open3D grid on ``config.device`` holding the blocks of a volume ``.npz`` in the block format."""
    o3c = require("open3d.core")
    res = int(config.block_resolution)
    names = grid_attributes(config)
    members = read_npz_members(path, ["blocks", *("sigma" if n == "variance" else n for n in names)])
    blocks = members["blocks"].astype(np.int32).reshape(-1, 3)
    stored = {n: members["sigma" if n == "variance" else n] for n in names}
    m = blocks.shape[0]
    if np.unique(blocks_to_keys(blocks)).size != m:
        raise ValueError("a block is stored twice")
    device = o3c.Device(config.device)
    grid = new_grid(config, max(int(config.block_count), m), device)
    if m == 0:
        return grid
    buf, _ = grid.hashmap().activate(o3c.Tensor(keys_to_blocks(blocks_to_keys(blocks)), device=device))
    tdev = torch_device(device)
    dst_np = buf.cpu().numpy().astype(np.int64).reshape(-1)
    order = np.argsort(dst_np, kind="stable")
    in_order = tdev == "cpu" and np.array_equal(dst_np[order], np.arange(m))  # a fresh grid fills slots 0..m-1
    for name, a in stored.items():
        channels = 3 if name == "color" else 1
        if a.shape != (m, res, res, res) + ((3,) if channels == 3 else ()):
            raise ValueError(f"{name}: shape {a.shape} is not that of {m} blocks of {res}^3 voxels")
        a = a[order] if in_order else a  # the stored blocks in the order of their buffer slots
        # Open3D's CPU tensors share their memory with .numpy(): decoded straight into the grid
        out = grid.attribute(name).numpy()[:m].reshape(a.shape) if in_order else np.empty(a.shape, np.float32)
        if name == "tsdf":
            np.multiply(a, np.float32(1.0 / FIXED_STEPS), out=out)  # from_fixed, decoded in place
        elif name == "variance":
            np.square(a, out=out, dtype=np.float32)  # variance_of
        else:
            out[...] = a
        if not in_order:
            import torch

            values = torch.as_tensor(out.reshape(m, res, res, res, channels), device=tdev)
            to_torch(grid.attribute(name))[torch.as_tensor(dst_np, device=tdev)] = values
    return grid


def save_mesh(mesh: Any, path: str | Path) -> Path:
    """Writes a `trimesh.Trimesh` as PLY, GLB or OBJ (chosen by the suffix) atomically, in the
    canonical form of `gpdepth3d.mapping.tsdf_extraction.canonical_mesh` (shared vertices, one
    order: the same surface gives the same bytes).

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
    data = canonical_mesh(mesh).export(file_type=suffix[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return path
