"""KITTI readers: a raw-drive snippet (``kitti_tiny``) and object-benchmark frames (``kitti_object``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError
from ..io import load_npz_arrays, load_rgb, read_matrix
from ..io.poses import read_kitti_poses
from ..measurements import LidarCalibration, SparseDepth, load_velodyne
from .base import DatasetReader, Frame


class KittiTiny(DatasetReader):
    """Reads a KITTI raw drive snippet with LiDAR already projected into camera 02.

    Layout: ``image_02/*.png`` RGB; ``velodyne_02/*.npz`` key ``velodyne_depth`` (float32 H x W
    metres, 0 = no point); ``cam.txt`` 3x3 K; ``poses.txt`` one 3x4 row-major T_world_camera per
    line for every frame of the drive (line i belongs to frame number i, the image file stem); optional ``calib_cam_to_cam.txt`` and
    ``calib_velo_to_cam.txt`` (used to recover LiDAR beams for the scan-line protocol).
    There is no dense ground truth: evaluate by holding out LiDAR points
    (`gpdepth3d.sampling.holdout_split`).
    """

    def __init__(self, root: str | Path):
        super().__init__(root)
        img_dir = self.root / "image_02"
        self.names = sorted(p.stem for p in img_dir.glob("*.png")) if img_dir.is_dir() else []
        if not self.names:
            raise DataFormatError(img_dir, "no PNG images: not a kitti_tiny folder")
        self.K = read_matrix(self.root / "cam.txt", (3, 3), "intrinsics cam.txt")
        self.poses: np.ndarray | None = None
        pose_path = self.root / "poses.txt"
        if pose_path.is_file():
            self.poses = read_kitti_poses(pose_path).poses
        self.calibration: LidarCalibration | None = None
        if (self.root / "calib_cam_to_cam.txt").is_file() and (self.root / "calib_velo_to_cam.txt").is_file():
            self.calibration = LidarCalibration.from_kitti(self.root, camera=2)

    def load(self, name: str) -> Frame:
        """The frame ``name`` with its projected LiDAR as ``sparse``."""
        rgb = load_rgb(self._require(self.root / "image_02" / f"{name}.png", "image"))
        path = self._require(self.root / "velodyne_02" / f"{name}.npz", "projected LiDAR")
        d = np.asarray(load_npz_arrays(path, ["velodyne_depth"], "projected LiDAR")["velodyne_depth"], dtype=np.float64)
        if d.shape != rgb.shape[:2]:
            raise DataFormatError(path, f"LiDAR map {d.shape} != image {rgb.shape[:2]}")
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
        h, w = rgb.shape[:2]
        pose = None
        if self.poses is not None:
            index = int(name) if name.isdigit() else self.names.index(name)
            if index >= len(self.poses):
                raise DataFormatError(self.root / "poses.txt", f"no pose line for frame {name}")
            pose = self.poses[index]
        return Frame(
            name=name,
            rgb=rgb,
            camera=PinholeCamera.from_K(self.K, w, h),
            sparse=SparseDepth.from_depth_map(d),
            pose=pose,
            calibration=self.calibration,
        )


class KittiObject(DatasetReader):
    """Reads KITTI object-benchmark frames: ``N.png``, ``N.bin`` (Velodyne), ``calib_N.txt``.

    The LiDAR scan is projected into the image with ``P2``, ``R0_rect`` and ``Tr_velo_to_cam``
    (closest point per pixel) and returned as ``sparse``; the raw points as ``lidar``. No
    ground truth.
    """

    def __init__(self, root: str | Path):
        super().__init__(root)
        self.names = sorted(p.stem for p in self.root.glob("*.png") if (self.root / f"{p.stem}.bin").is_file())
        if not self.names:
            raise DataFormatError(self.root, "no N.png with N.bin pairs: not a kitti_object folder")

    def load(self, name: str) -> Frame:
        """The frame ``name`` with its projected LiDAR as ``sparse``."""
        rgb = load_rgb(self._require(self.root / f"{name}.png", "image"))
        calib = LidarCalibration.from_kitti(self._require(self.root / f"calib_{name}.txt", "calibration"), camera=2)
        points = load_velodyne(self.root / f"{name}.bin")
        h, w = rgb.shape[:2]
        front = points[:, 0] > 0  # behind the car nothing projects
        sparse = calib.project(points[front], (h, w))
        K = calib.P[:, :3]
        try:
            camera = PinholeCamera.from_K(K / K[2, 2], w, h)
        except Exception as exc:  # CalibrationError: report as a file problem
            raise DataFormatError(self.root / f"calib_{name}.txt", f"bad P2: {exc}") from None
        return Frame(name=name, rgb=rgb, camera=camera, sparse=sparse, calibration=calib, lidar=points)
