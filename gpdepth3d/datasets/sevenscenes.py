"""Microsoft 7-Scenes RGB-D sequences (and TUM-like folders laid out the same way)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError, InvalidInputError
from ..io import load_depth, load_rgb, read_matrix
from ..io.poses import load_pose
from ..measurements import project_points
from .base import DatasetReader, Frame

DEFAULT_INTRINSICS = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
"""The depth camera's K when the folder has no ``camera-intrinsics.txt`` (the dataset's default)."""

COLOUR_INTRINSICS = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
"""The colour camera's K (7-Scenes gives none; the Kinect v1's usual colour calibration, f = 525). A bundle adjustment of
the colour images with self-calibrated intrinsics stays at these values."""


class SevenScenes(DatasetReader):
    """Reads a 7-Scenes sequence folder, with the depth registered to the colour image.

    Layout: ``frame-XXXXXX.color.jpg`` (640x480 RGB), ``frame-XXXXXX.depth.png`` (uint16 mm,
    65535 = invalid, 0 = invalid), ``frame-XXXXXX.pose.txt`` (4x4 T_world_camera), optional
    ``camera-intrinsics.txt`` (3x3 K of the *depth* camera; default fx = fy = 585, cx = 320,
    cy = 240).

    The Kinect's colour and depth images are raw, unregistered images of two cameras with
    different fields of view (depth f = 585, colour f ~ 525). With ``register`` (the default)
    each frame's depth is lifted with the depth camera's K and re-projected into the colour
    camera (``colour_K``; the closest depth wins a pixel, pixels nothing lands on are 0), so
    ``depth[v, u]`` is the depth of ``rgb[v, u]`` and ``camera`` is the colour camera: what a
    depth-completion or mapping user of the RGB needs. The two cameras are taken to share the
    pose (the Kinect's ~2.5 cm colour-depth baseline is not modelled). The registered depth
    covers the central ~90 % of the colour image's width and height (the colour camera sees
    more); its edges line up with the image's, which the raw depth's do not.
    ``register=False`` gives the raw depth with the depth camera's K (``camera``), as stored.

    Args:
        root: The sequence folder.
        register: Register the depth to the colour image (see above).
        colour_K: 3x3 intrinsics of the colour camera at 640 x 480 (default `COLOUR_INTRINSICS`).
    """

    def __init__(self, root: str | Path, *, register: bool = True, colour_K: np.ndarray | None = None):
        super().__init__(root)
        self.names = sorted(p.name[: -len(".color.jpg")] for p in self.root.glob("frame-*.color.jpg"))
        if not self.names:
            raise DataFormatError(self.root, "no frame-*.color.jpg files: not a 7-Scenes sequence folder")
        if not isinstance(register, (bool, np.bool_)):
            raise InvalidInputError("register", "True or False", register)
        k_path = self.root / "camera-intrinsics.txt"
        self.K = read_matrix(k_path, (3, 3), "intrinsics") if k_path.is_file() else DEFAULT_INTRINSICS
        colour_K = COLOUR_INTRINSICS if colour_K is None else np.asarray(colour_K, dtype=np.float64)
        if colour_K.shape != (3, 3) or not np.all(np.isfinite(colour_K)):
            raise InvalidInputError("colour_K", "a finite 3x3 intrinsics matrix", colour_K)
        self.colour_K = colour_K
        self.register = bool(register)

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
            pose = load_pose(pose_path)
        h, w = rgb.shape[:2]
        depth_camera = PinholeCamera.from_K(self.K, w, h)
        if not self.register:
            return Frame(name=name, rgb=rgb, camera=depth_camera, depth=depth, pose=pose)
        camera = PinholeCamera.from_K(self.colour_K, w, h)
        points, _ = depth_camera.backproject(depth)
        return Frame(name=name, rgb=rgb, camera=camera, depth=project_points(points, camera).to_depth_map(), pose=pose)
