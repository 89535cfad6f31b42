"""Frames with the sparse 3-D points of a visual-inertial SLAM system (``vio_sparse``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError
from ..io import load_rgb
from ..measurements import project_points
from .base import DatasetReader, Frame

VIO_INTRINSICS = (577.591, 578.73, 318.905, 242.684)  # fx, fy, cx, cy of the vio_sparse frames


class VioSparse(DatasetReader):
    """Reads ``color/color_XXXXXX.png`` and ``depth_sparse/depth_sparse_XXXXXX.txt``.

    Each text line is ``id X Y Z``: a triangulated SLAM feature in the camera frame (metres);
    the points are projected with the intrinsics (closest per pixel) into ``Frame.sparse``. No
    ground truth.

    Args:
        root: The folder.
        intrinsics: (fx, fy, cx, cy) in pixels of the 640x480 images.
    """

    def __init__(self, root: str | Path, *, intrinsics: tuple[float, float, float, float] = VIO_INTRINSICS):
        super().__init__(root)
        color = self.root / "color"
        self.names = sorted(p.stem[len("color_") :] for p in color.glob("color_*.png")) if color.is_dir() else []
        if not self.names:
            raise DataFormatError(color, "no color_*.png images: not a vio_sparse folder")
        self.intrinsics = tuple(float(x) for x in intrinsics)

    def load_points(self, name: str) -> np.ndarray:
        """(N, 3) camera-frame points of frame ``name`` (metres)."""
        path = self._require(self.root / "depth_sparse" / f"depth_sparse_{name}.txt", "sparse points")
        try:
            table = np.loadtxt(path, ndmin=2)
        except ValueError as exc:
            raise DataFormatError(path, f"expected lines 'id X Y Z': {exc}") from None
        if table.size == 0:
            return np.zeros((0, 3))
        if table.shape[1] != 4:
            raise DataFormatError(path, f"expected 4 columns 'id X Y Z', got {table.shape[1]}")
        return table[:, 1:4]

    def load(self, name: str) -> Frame:
        """The frame ``name`` (e.g. ``"000000"``) with its projected SLAM points."""
        rgb = load_rgb(self.root / "color" / f"color_{name}.png")
        h, w = rgb.shape[:2]
        fx, fy, cx, cy = self.intrinsics
        camera = PinholeCamera(fx, fy, cx, cy, w, h)
        sparse = project_points(self.load_points(name), camera)
        return Frame(name=name, rgb=rgb, camera=camera, sparse=sparse)
