"""The keyframe store of a map (`Keyframe`) and the files a saved map is made of.

A saved map is a folder: the TSDF volume (``volume.npz`` + ``volume.json``, `TSDFFusion.save`),
the keyframe store (``keyframes.npz``, `save_keyframes`) and the mapper's camera, settings and
frame counts (``mapper.json``, `write_map_meta`). `Mapper.save` writes them as one output set
(`gpdepth3d.io.output_set`, base name `MAP_SET`), so that a reader sees the old map or the new
one; `Mapper.load` first finishes a commit a kill interrupted, or removes the temporaries of a
writer killed before its commit (`recover_map_folder`). Maps saved by earlier versions of the
library load (missing keys take defaults, older array forms are read as they were written).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError, OutputError
from ..gp.model import DepthGPConfig
from ..io import clean_output_set, save_npz, write_json
from .compact_arrays import read_npz_members, sigma_of, to_half, variance_of
from .tsdf.fusion_config import FusionConfig
from .mapper_config import MapperConfig
from .points.refinding import RefindConfig
from .points.triangulation_config import TriangulationConfig

MAP_FILES = ("mapper.json", "keyframes.npz", "volume.npz")
"""The files of a saved map's folder that `Mapper.load` needs (``volume.json`` goes with ``volume.npz``)."""
MAP_SET = "map"
"""Base name of the output set of a saved map's files (its commit journal is ``.map.<8 hex>.journal``)."""


@dataclass
class Keyframe:
    """One fused frame as the keyframe store keeps it (everything at the working resolution).

    Attributes:
        keyframe_id: Its id.
        T_world_camera: 4x4 pose it is fused with.
        depth: (h, w) float32 fused depth, metres (0 = none).
        variance: (h, w) float32 depth variance, m^2 (NaN when not refining).
        rgb: (h, w, 3) uint8 colour.
        block_keys: (M,) int64 keys of the TSDF blocks it reached.
        points: Sparse measurements it was refined with (they set its fallback weight,
            `FusionConfig.fallback_for`).
    """

    keyframe_id: int
    T_world_camera: np.ndarray
    depth: np.ndarray
    variance: np.ndarray
    rgb: np.ndarray
    block_keys: np.ndarray
    points: int = 0


def save_keyframes(path: str | Path, keyframes: dict[int, Keyframe], shape: tuple[int, int]) -> Path:
    """Writes a keyframe store to one compressed ``.npz`` atomically (``shape``: the (h, w) of an empty store's arrays).

    Depths are stored in half precision and variances as half-precision sigmas
    (`gpdepth3d.mapping.compact_arrays`: relative error <= 2^-11, far below any depth's own).
    """
    ids = list(keyframes)
    kfs = [keyframes[k] for k in ids]
    h, w = shape
    keys = [kf.block_keys for kf in kfs]
    return save_npz(
        path,
        ids=np.array(ids, dtype=np.int64),
        poses=np.stack([kf.T_world_camera for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
        depth=to_half(np.stack([kf.depth for kf in kfs]) if kfs else np.zeros((0, h, w), np.float32)),
        sigma=sigma_of(np.stack([kf.variance for kf in kfs]) if kfs else np.zeros((0, h, w), np.float32)),
        rgb=np.stack([kf.rgb for kf in kfs]) if kfs else np.zeros((0, h, w, 3), np.uint8),
        block_keys=np.concatenate(keys) if keys else np.zeros(0, np.int64),
        block_counts=np.array([k.size for k in keys], dtype=np.int64),
        points=np.array([kf.points for kf in kfs], dtype=np.int64),
    )


def load_keyframes(path: str | Path) -> dict[int, Keyframe]:
    """Reads a keyframe store `save_keyframes` wrote, in its order (stores of earlier versions: float32
    ``variance`` instead of ``sigma``; without ``points``: 0 each).

    Raises:
        DataFormatError: if the file is not a keyframe store.
    """
    keyframes = {}
    try:
        with np.load(path, allow_pickle=False) as d:
            files = set(d.files)
        names = ["ids", "poses", "depth", "rgb", "block_counts", "block_keys"]
        names += ["sigma" if "sigma" in files else "variance"] + (["points"] if "points" in files else [])
        m = read_npz_members(path, names)  # each member decompressed once
        ids, poses, depth, rgb, counts = (m[k] for k in ("ids", "poses", "depth", "rgb", "block_counts"))
        keys = m["block_keys"].astype(np.int64)
        variance = variance_of(m["sigma"]) if "sigma" in m else m["variance"]
        points = m.get("points", np.zeros(len(ids), np.int64))
        if not (len(poses) == len(depth) == len(variance) == len(rgb) == len(counts) == len(points) == len(ids)):
            raise ValueError("arrays of different lengths")
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        for i, kid in enumerate(ids):
            keyframes[int(kid)] = Keyframe(
                int(kid),
                poses[i].astype(np.float64),
                depth[i].astype(np.float32),
                variance[i].astype(np.float32),
                rgb[i].astype(np.uint8),
                keys[offsets[i] : offsets[i + 1]],
                int(points[i]),
            )
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"not a saved keyframe store: {exc}") from None
    return keyframes


def write_map_meta(path: str | Path, camera: PinholeCamera, config: MapperConfig, *, frames: int, next_id: int) -> Path:
    """Writes a map's ``mapper.json`` atomically: the RGB camera, the `MapperConfig`, frames fused, next keyframe id."""
    c = camera
    meta = {
        "camera": [c.fx, c.fy, c.cx, c.cy, c.width, c.height],
        "config": asdict(config),
        "frames": frames,
        "next_id": next_id,
    }
    return write_json(path, meta)


def read_map_meta(path: str | Path, config: MapperConfig | None = None) -> tuple[PinholeCamera, MapperConfig, dict]:
    """Reads a map's ``mapper.json``: (its camera, ``config`` or else the saved `MapperConfig`, the whole record).

    Raises:
        DataFormatError: if the file is not what `write_map_meta` writes.
    """
    try:
        meta = json.loads(Path(path).read_text())
        fx, fy, cx, cy, width, height = meta["camera"]
        camera = PinholeCamera(float(fx), float(fy), float(cx), float(cy), int(width), int(height))
        if config is None:
            config = config_from_dict(meta["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(path, f"not a saved gpdepth3d map: {exc}") from None
    return camera, config, meta


def config_from_dict(saved: dict) -> MapperConfig:
    """A `MapperConfig` from its ``asdict`` form (as ``mapper.json`` holds it; older maps' missing fields default)."""
    return MapperConfig(
        gp=DepthGPConfig.from_dict(saved["gp"]),
        fusion=FusionConfig(**saved["fusion"]),
        triangulation=TriangulationConfig(**_tuples(saved["triangulation"])),
        refind=RefindConfig(**saved.get("refind", {})),
        **{k: v for k, v in saved.items() if k not in ("gp", "fusion", "triangulation", "refind")},
    )


def check_map_folder(folder: str | Path) -> Path:
    """The folder of a saved map as a `Path`, or `DataFormatError` naming the first of `MAP_FILES` missing."""
    folder = Path(folder)
    for name in MAP_FILES:
        if not (folder / name).is_file():
            raise DataFormatError(folder / name, "file of a saved map not found")
    return folder


def recover_map_folder(folder: str | Path) -> int:
    """Finishes a commit of a map's files a kill interrupted and removes the temporaries of killed writers.

    Returns:
        How many leftovers were finished or removed.

    Raises:
        DataFormatError: an interrupted commit cannot be finished (e.g. a read-only folder): the
            folder then holds part of two maps.
    """
    names = [*MAP_FILES, "volume.json"]
    try:
        count = clean_output_set(Path(folder) / MAP_SET, names)
        return count + clean_output_set(Path(folder) / "volume", ["volume.npz", "volume.json"])
    except OutputError as exc:
        raise DataFormatError(folder, f"an interrupted save of this map cannot be finished: {exc}") from None


def _tuples(d: dict) -> dict:
    """JSON lists back to tuples (frozen config fields)."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
