"""Dataset readers: each yields `Frame` records (rgb, camera, ground-truth depth, sparse, pose).

`open_dataset` recognises a folder's layout; the readers can also be used directly.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataFormatError
from .base import DatasetReader as DatasetReader
from .base import Frame as Frame
from .ibims import IbimsSample as IbimsSample
from .kitti import KittiObject as KittiObject
from .kitti import KittiTiny as KittiTiny
from .sevenscenes import SevenScenes as SevenScenes
from .vio import VioSparse as VioSparse

READERS = {
    "7scenes": SevenScenes,
    "kitti_tiny": KittiTiny,
    "kitti_object": KittiObject,
    "ibims_sample": IbimsSample,
    "vio_sparse": VioSparse,
}


def detect_format(root: str | Path) -> str:
    """Name of the dataset layout found in ``root`` (a key of `READERS`)."""
    root = Path(root)
    if not root.is_dir():
        raise DataFormatError(root, "dataset folder not found")
    if any(root.glob("frame-*.color.jpg")):
        return "7scenes"
    if (root / "image_02").is_dir() and (root / "velodyne_02").is_dir():
        return "kitti_tiny"
    if (root / "gt.npz").is_file() and (root / "image.png").is_file():
        return "ibims_sample"
    if (root / "color").is_dir() and (root / "depth_sparse").is_dir():
        return "vio_sparse"
    if any(root.glob("*.bin")) and any(root.glob("calib_*.txt")):
        return "kitti_object"
    raise DataFormatError(root, f"unknown dataset layout (known: {', '.join(READERS)})")


def open_dataset(root: str | Path, kind: str | None = None) -> DatasetReader:
    """Opens a dataset folder with the reader of ``kind`` (default: detected from its files)."""
    kind = kind or detect_format(root)
    if kind not in READERS:
        raise DataFormatError(root, f"unknown dataset kind {kind!r} (known: {', '.join(READERS)})")
    return READERS[kind](root)
