"""Microsoft 7-Scenes RGB-D sequences (and TUM-like folders laid out the same way)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError
from ..io import load_depth, load_rgb
from .base import DatasetReader, Frame, checked_pose, read_matrix

DEFAULT_INTRINSICS = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


class SevenScenes(DatasetReader):
    """Reads a 7-Scenes sequence folder.

    Layout: ``frame-XXXXXX.color.jpg`` (640x480 RGB), ``frame-XXXXXX.depth.png`` (uint16 mm,
    65535 = invalid, 0 = invalid), ``frame-XXXXXX.pose.txt`` (4x4 T_world_camera), optional
    ``camera-intrinsics.txt`` (3x3 K of the depth camera; default fx = fy = 585, cx = 320,
    cy = 240). Note: the Kinect's colour and depth images are *not* perfectly registered, so
    the ground truth is slightly misaligned with the RGB (a few pixels at edges); the same K is
    used for both.

    Args:
        root: The sequence folder.
    """

    def __init__(self, root: str | Path):
        super().__init__(root)
        self.names = sorted(p.name[: -len(".color.jpg")] for p in self.root.glob("frame-*.color.jpg"))
        if not self.names:
            raise DataFormatError(self.root, "no frame-*.color.jpg files: not a 7-Scenes sequence folder")
        k_path = self.root / "camera-intrinsics.txt"
        self.K = read_matrix(k_path, (3, 3), "intrinsics") if k_path.is_file() else DEFAULT_INTRINSICS

    def load(self, name: str) -> Frame:
        """The frame ``name`` (e.g. ``"frame-000000"``) with depth (metres) and pose."""
        rgb = load_rgb(self._require(self.root / f"{name}.color.jpg", "colour image"))
        depth = load_depth(
            self._require(self.root / f"{name}.depth.png", "depth image"), png_scale=1e-3, invalid_value=65535
        )
        if depth.shape != rgb.shape[:2]:
            raise DataFormatError(self.root / f"{name}.depth.png", f"depth {depth.shape} != image {rgb.shape[:2]}")
        pose = None
        pose_path = self.root / f"{name}.pose.txt"
        if pose_path.is_file():
            pose = checked_pose(read_matrix(pose_path, (4, 4), "pose"), pose_path)
        h, w = rgb.shape[:2]
        camera = PinholeCamera.from_K(self.K, w, h)
        return Frame(name=name, rgb=rgb, camera=camera, depth=depth, pose=pose)
