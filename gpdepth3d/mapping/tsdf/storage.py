"""Files of the TSDF fusion: a saved volume (``.npz`` + ``.json``) and meshes (PLY, GLB, OBJ), written atomically.

A volume is Open3D's ``VoxelBlockGrid.save`` archive
(https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html) with,
beside it, ``<stem>.json``: ``camera`` [fx, fy, cx, cy, width, height], ``config`` (the
`FusionConfig` fields) and ``frames_integrated``.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ...camera import PinholeCamera
from ...errors import DataFormatError, EmptyInputError, InvalidInputError
from ...extras import require
from ...io import atomic_path, write_json
from .fusion_config import FusionConfig

MESH_FORMATS = (".ply", ".glb", ".obj")


def write_volume(path: str | Path, vbg: Any, camera: PinholeCamera, config: FusionConfig, frames: int) -> Path:
    """Writes the grid ``vbg`` to ``path`` (``.npz``) and its camera, config and frame count beside it.

    Returns:
        The ``.npz`` path.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise InvalidInputError("path", "a .npz file name", str(path))
    meta = {
        "camera": [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height],
        "config": asdict(config),
        "frames_integrated": frames,
    }
    with atomic_path(path) as tmp:
        vbg.save(str(tmp))
    write_json(path.with_suffix(".json"), meta)
    return path


def read_volume(path: str | Path) -> tuple[PinholeCamera, FusionConfig, Any, dict]:
    """Reads a volume written by `write_volume`: its camera, config, grid (on ``config.device``) and
    the parsed ``.json`` (``frames_integrated``).

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
    return camera, config, vbg, meta


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
