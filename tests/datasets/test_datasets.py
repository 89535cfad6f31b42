"""Tests of the dataset readers on the real data in ../shared/data (skipped when absent)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.datasets import (
    Frame,
    IbimsSample,
    KittiObject,
    KittiTiny,
    SevenScenes,
    VioSparse,
    detect_format,
    open_dataset,
)
from gpdepth3d.errors import DataFormatError, InvalidInputError


def _folder(shared_data: Path, name: str) -> Path:
    p = shared_data / name
    if not p.is_dir():
        pytest.skip(f"{p} not found")
    return p


class TestSevenScenes:
    def test_frame(self, shared_data):
        ds = SevenScenes(_folder(shared_data, "7scenes"))
        assert len(ds) == 60 and ds.names[0] == "frame-000000"
        f = ds[0]
        assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
        assert f.depth.shape == (480, 640)
        valid = f.depth > 0
        # registered to the colour camera (f = 525), which sees more than the depth camera (f = 585)
        assert 0.5 < valid.mean() < 0.85 and 0.5 < np.median(f.depth[valid]) < 5  # metres, indoors
        assert f.depth.max() < 10  # 65535 (invalid) is not a depth
        assert f.camera.fx == 525 and f.camera.cx == 320
        np.testing.assert_allclose(f.pose[:3, :3] @ f.pose[:3, :3].T, np.eye(3), atol=1e-3)
        assert f.sparse is None
        raw = SevenScenes(_folder(shared_data, "7scenes"), register=False)[0]
        assert raw.camera.fx == 585 and 0.85 < (raw.depth > 0).mean() <= 1
        np.testing.assert_array_equal(raw.pose, f.pose)
        np.testing.assert_array_equal(raw.rgb, f.rgb)

    def test_registration_geometry(self, shared_data):
        """Every raw depth pixel, lifted with the depth camera's K, lands in the colour image at a
        pixel whose registered depth is its own or a closer one (z-buffer); the same 3-D points
        come back from the registered depth with the colour camera's K."""
        folder = _folder(shared_data, "7scenes")
        f, raw = SevenScenes(folder)[5], SevenScenes(folder, register=False)[5]
        points, _ = raw.camera.backproject(raw.depth)
        uv, z = f.camera.project(points)
        iu = np.rint(uv).astype(int)
        inside = (iu[:, 0] >= 0) & (iu[:, 0] < 640) & (iu[:, 1] >= 0) & (iu[:, 1] < 480)
        reg = f.depth[iu[inside, 1], iu[inside, 0]]
        assert np.all(reg > 0) and np.all(reg <= z[inside] + 1e-9)
        assert np.mean(np.isclose(reg, z[inside])) > 0.5  # compressed 585 -> 525: ~0.8 of them win their pixel
        back, _ = f.camera.backproject(f.depth)
        # the registered points are a subset of the raw points (same 3-D positions up to the pixel rounding)
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(points).query(back)
        assert np.median(dist) < 0.003 and np.percentile(dist, 99) < 0.01

    def test_registration_aligns_edges(self, shared_data):
        """The registered depth's edges lie on the image's edges; the raw depth's do not (the
        correlation of the two gradient magnitudes; measured 0.11 vs 0.00 over 30 frames)."""
        import cv2

        folder = _folder(shared_data, "7scenes")

        def correlation(frame):
            grey = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
            g_img = cv2.GaussianBlur(
                np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)), (0, 0), 1.5
            )
            valid = frame.depth > 0
            log_d = np.log(np.where(valid, frame.depth, 1.0)).astype(np.float32)
            g_d = np.hypot(cv2.Sobel(log_d, cv2.CV_32F, 1, 0), cv2.Sobel(log_d, cv2.CV_32F, 0, 1))
            g_d[cv2.erode(valid.astype(np.uint8), np.ones((5, 5))) == 0] = 0
            g_d = cv2.GaussianBlur(g_d, (0, 0), 1.5)
            inner = cv2.erode(valid.astype(np.uint8), np.ones((9, 9))) > 0
            return np.corrcoef(g_img[inner], g_d[inner])[0, 1]

        reg = [correlation(SevenScenes(folder)[i]) for i in range(0, 60, 10)]
        raw = [correlation(SevenScenes(folder, register=False)[i]) for i in range(0, 60, 10)]
        assert np.mean(reg) > np.mean(raw) + 0.05

    def test_bad_options(self, shared_data):
        folder = _folder(shared_data, "7scenes")
        with pytest.raises(InvalidInputError, match="register"):
            SevenScenes(folder, register="yes")
        with pytest.raises(InvalidInputError, match="colour_K"):
            SevenScenes(folder, colour_K=np.eye(2))

    def test_resized(self, shared_data):
        f = SevenScenes(_folder(shared_data, "7scenes"))[0].resized(0.5)
        assert f.rgb.shape == (240, 320, 3) and f.depth.shape == (240, 320)
        assert f.camera.width == 320 and f.camera.fx == pytest.approx(262.5)
        with pytest.raises(InvalidInputError):
            f.resized(0)

    def test_corrupt_files(self, shared_data, tmp_path):
        src = _folder(shared_data, "7scenes")
        for suffix in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(src / f"frame-000000.{suffix}", tmp_path / f"frame-000000.{suffix}")
        (tmp_path / "frame-000000.pose.txt").write_text("1 2 3\n")
        ds = SevenScenes(tmp_path)
        with pytest.raises(DataFormatError, match="pose"):
            ds[0]
        (tmp_path / "frame-000000.pose.txt").unlink()
        (tmp_path / "frame-000000.depth.png").write_bytes(b"garbage")
        with pytest.raises(DataFormatError):
            ds[0]
        (tmp_path / "frame-000000.depth.png").unlink()
        with pytest.raises(DataFormatError, match="not found"):
            ds[0]
        with pytest.raises(DataFormatError):
            SevenScenes(tmp_path / "nothing")
        with pytest.raises(DataFormatError):
            SevenScenes(tmp_path / "frame-000000.color.jpg")  # a file, not a folder


class TestKittiTiny:
    def test_frame(self, shared_data):
        ds = KittiTiny(_folder(shared_data, "kitti_tiny"))
        assert len(ds) == 7
        f = ds[1]
        assert f.rgb.shape == (375, 1242, 3) and f.depth is None
        assert 15000 < len(f.sparse) < 25000 and 3 < np.median(f.sparse.depth) < 40
        assert f.camera.fx == pytest.approx(721.5377)
        assert f.pose.shape == (4, 4) and f.calibration is not None
        # consecutive poses of a moving car: translation changes, rotation stays proper
        assert not np.allclose(f.pose[:3, 3], ds[0].pose[:3, 3])
        assert np.linalg.det(f.pose[:3, :3]) == pytest.approx(1.0, abs=1e-3)

    def test_bad_npz(self, shared_data, tmp_path):
        src = _folder(shared_data, "kitti_tiny")
        shutil.copytree(src / "image_02", tmp_path / "image_02")
        (tmp_path / "velodyne_02").mkdir()
        shutil.copy(src / "cam.txt", tmp_path / "cam.txt")
        np.savez(tmp_path / "velodyne_02" / "0000000000.npz", other=np.zeros(3))
        ds = KittiTiny(tmp_path)
        with pytest.raises(DataFormatError, match="velodyne_depth"):
            ds[0]
        with pytest.raises(DataFormatError, match="not found"):
            ds[1]


class TestPoseCheckIsShared:
    """The KITTI-tiny and 7-Scenes readers refuse the same non-rigid pose (one reader each: gpdepth3d.io.poses)."""

    def test_scaled_pose_refused_by_both(self, shared_data, tmp_path):
        src = _folder(shared_data, "kitti_tiny")
        kt = tmp_path / "kitti_tiny"
        shutil.copytree(src, kt)
        rows = np.loadtxt(kt / "poses.txt", ndmin=2)
        rows[2, [0, 5, 10]] *= 2.0  # frame 2: a rotation scaled by 2 (det 8)
        np.savetxt(kt / "poses.txt", rows)
        with pytest.raises(DataFormatError, match="line 3: not a rigid transform"):
            KittiTiny(kt)
        seven = tmp_path / "7scenes"
        seven.mkdir()
        src7 = _folder(shared_data, "7scenes")
        for suffix in (".color.jpg", ".depth.png", ".pose.txt"):
            shutil.copy(src7 / f"frame-000000{suffix}", seven / f"frame-000000{suffix}")
        T = np.loadtxt(seven / "frame-000000.pose.txt")
        T[:3, :3] *= 2.0
        np.savetxt(seven / "frame-000000.pose.txt", T)
        with pytest.raises(DataFormatError, match="not a rigid transform"):
            SevenScenes(seven)[0]

    def test_truncated_colour_image(self, shared_data, tmp_path):
        seven = tmp_path / "7scenes"
        seven.mkdir()
        src7 = _folder(shared_data, "7scenes")
        for suffix in (".color.jpg", ".depth.png", ".pose.txt"):
            shutil.copy(src7 / f"frame-000000{suffix}", seven / f"frame-000000{suffix}")
        jpg = seven / "frame-000000.color.jpg"
        jpg.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])
        with pytest.raises(DataFormatError, match="truncated JPEG"):
            SevenScenes(seven)[0]


class TestKittiObject:
    def test_frame(self, shared_data):
        ds = KittiObject(_folder(shared_data, "kitti_object"))
        assert len(ds) == 3
        f = ds[0]
        assert f.rgb.ndim == 3 and f.lidar.shape[1] == 4
        assert 5000 < len(f.sparse) < 40000
        assert f.sparse.image_size == f.shape and 2 < np.median(f.sparse.depth) < 50
        assert f.camera.fx == pytest.approx(707.0493)


class TestIbims:
    def test_frame(self, shared_data):
        ds = IbimsSample(_folder(shared_data, "ibims_sample"), sparse_count=1000)
        assert ds.sparse_counts == [10, 100, 1000]
        f = ds[0]
        assert f.camera is None and f.depth.shape == (480, 640)
        assert 900 <= len(f.sparse) <= 1000
        # the given samples are samples of the ground truth
        np.testing.assert_allclose(f.sparse.depth, f.depth[f.sparse.v.astype(int), f.sparse.u.astype(int)], rtol=1e-5)

    def test_missing_count(self, shared_data):
        with pytest.raises(DataFormatError):
            IbimsSample(_folder(shared_data, "ibims_sample"), sparse_count=7)


class TestVio:
    def test_frame(self, shared_data):
        ds = VioSparse(_folder(shared_data, "vio_sparse"))
        assert len(ds) == 8
        f = ds[0]
        pts = ds.load_points(ds.names[0])
        assert 50 < len(f.sparse) <= len(pts)
        assert f.camera.fx == pytest.approx(577.591)
        # projecting the points back lands them in the image at their depth
        uv, z = f.camera.project(pts)
        assert np.all(f.sparse.depth >= z[z > 0].min() - 1e-9)

    def test_bad_points(self, shared_data, tmp_path):
        src = _folder(shared_data, "vio_sparse")
        (tmp_path / "color").mkdir()
        (tmp_path / "depth_sparse").mkdir()
        shutil.copy(src / "color" / "color_000000.png", tmp_path / "color" / "color_000000.png")
        (tmp_path / "depth_sparse" / "depth_sparse_000000.txt").write_text("1 2 3\n")
        with pytest.raises(DataFormatError, match="id X Y Z"):
            VioSparse(tmp_path)[0]


class TestOpenDataset:
    @pytest.mark.parametrize(
        "name,cls",
        [
            ("7scenes", SevenScenes),
            ("kitti_tiny", KittiTiny),
            ("kitti_object", KittiObject),
            ("ibims_sample", IbimsSample),
            ("vio_sparse", VioSparse),
        ],
    )
    def test_detect(self, shared_data, name, cls):
        folder = _folder(shared_data, name)
        assert detect_format(folder) == name
        ds = open_dataset(folder)
        assert isinstance(ds, cls) and isinstance(ds[0], Frame)
        assert sum(1 for _ in zip(range(2), ds)) == min(2, len(ds))
        with pytest.raises(IndexError):
            ds[len(ds)]

    def test_unknown(self, tmp_path):
        with pytest.raises(DataFormatError, match="unknown"):
            detect_format(tmp_path)
        with pytest.raises(DataFormatError):
            open_dataset(tmp_path, "nyu")
