"""Tests of gpdepth3d.datasets.posed: a user's own posed sequence (images, poses, intrinsics, depth)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.datasets import SevenScenes
from gpdepth3d.datasets.posed import PosedSequence, list_files, match_depth, read_intrinsics
from gpdepth3d.errors import CalibrationError, DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.io.poses import associate_poses, read_trajectory


def _write_sequence(folder: Path, n: int = 3, size=(40, 30)) -> np.ndarray:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * 0.1
    for i in range(n):
        cv2.imwrite(str(folder / "rgb" / f"{i:05d}.png"), rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
        d = np.full((size[1], size[0]), 1500 + 100 * i, np.uint16)
        d[0, 0] = 0
        d[1, 1] = 9999
        cv2.imwrite(str(folder / "depth" / f"{i:05d}.png"), d)
    return poses


class TestPosedSequence:
    def test_frames(self, tmp_path: Path):
        poses = _write_sequence(tmp_path)
        seq = PosedSequence(tmp_path / "rgb", poses, "50,51,19.5,14.5", depth=tmp_path / "depth", depth_invalid=9999)
        assert len(seq) == 3 and seq.names == ["00000", "00001", "00002"]
        f = seq[2]
        assert f.rgb.shape == (30, 40, 3) and f.camera == PinholeCamera(50, 51, 19.5, 14.5, 40, 30)
        np.testing.assert_allclose(f.pose, poses[2])
        assert f.depth[5, 5] == pytest.approx(1.7) and f.depth[0, 0] == 0 and f.depth[1, 1] == 0
        seq2 = PosedSequence(str(tmp_path / "rgb" / "*.png"), poses, [50, 51, 19.5, 14.5], depth_scale=2e-4)
        assert seq2[0].depth is None and len(seq2) == 3

    def test_counts_and_missing(self, tmp_path: Path):
        poses = _write_sequence(tmp_path)
        with pytest.raises(ShapeError, match=r"one pose per image \(3 images\).*2 poses"):
            PosedSequence(tmp_path / "rgb", poses[:2], "50,50,20,15")
        (tmp_path / "depth" / "00002.png").unlink()
        with pytest.raises(ShapeError, match=r"00002.png has none.*2 depth files"):
            PosedSequence(tmp_path / "rgb", poses, "50,50,20,15", depth=tmp_path / "depth")
        with pytest.raises(DataFormatError, match="images: folder not found"):
            PosedSequence(tmp_path / "nope", poses, "50,50,20,15")
        with pytest.raises(DataFormatError, match="no files"):
            PosedSequence(str(tmp_path / "rgb" / "*.jpg"), poses, "50,50,20,15")
        bad = poses.copy()
        bad[1, :3, :3] *= 2
        with pytest.raises(CalibrationError, match="00001.png"):
            PosedSequence(tmp_path / "rgb", bad, "50,50,20,15")
        with pytest.raises(InvalidInputError, match="depth_invalid"):
            PosedSequence(tmp_path / "rgb", poses, "50,50,20,15", depth_invalid=70000)
        with pytest.raises(InvalidInputError, match="depth_intrinsics"):
            PosedSequence(tmp_path / "rgb", poses, "50,50,20,15", depth_intrinsics="50,50,20,15")

    def test_bad_frame_named_on_read(self, tmp_path: Path):
        poses = _write_sequence(tmp_path)
        (tmp_path / "rgb" / "00001.png").write_bytes(b"not a png")
        seq = PosedSequence(tmp_path / "rgb", poses, "50,50,20,15")
        assert seq[0].rgb.shape == (30, 40, 3)
        with pytest.raises(DataFormatError, match="00001.png"):
            seq[1]
        assert seq[2].name == "00002"
        with pytest.raises(InvalidInputError):
            seq["00002"]  # type: ignore[index]
        assert seq.load("00002").name == "00002"
        with pytest.raises(InvalidInputError, match="name"):
            seq.load("00009")

    def test_intrinsics(self, tmp_path: Path):
        K = np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]])
        np.savetxt(tmp_path / "K.txt", K)
        assert read_intrinsics(tmp_path / "K.txt", 640, 480).K.tolist() == K.tolist()
        (tmp_path / "f.txt").write_text("500 501 320 240\n")
        assert read_intrinsics(str(tmp_path / "f.txt"), 640, 480) == PinholeCamera(500, 501, 320, 240, 640, 480)
        assert read_intrinsics("500, 501, 320, 240", 640, 480) == PinholeCamera(500, 501, 320, 240, 640, 480)
        (tmp_path / "bad.txt").write_text("1 2 3\n")
        with pytest.raises(DataFormatError, match="9 numbers"):
            read_intrinsics(tmp_path / "bad.txt", 640, 480)
        with pytest.raises(DataFormatError, match="neither a K file"):
            read_intrinsics("missing_K.txt", 640, 480)
        with pytest.raises(CalibrationError):
            read_intrinsics("500,501,320", 640, 480)
        with pytest.raises(CalibrationError):
            read_intrinsics("-500,501,320,240", 640, 480)

    def test_match_depth(self):
        images = [Path("a.color.jpg"), Path("b.color.jpg")]
        assert match_depth(images, [Path("b.depth.png"), Path("a.depth.png")]) == [
            Path("a.depth.png"),
            Path("b.depth.png"),
        ]
        assert match_depth(images, [Path("x.png"), Path("y.png")]) == [Path("x.png"), Path("y.png")]


class TestRealSequences:
    def test_hololens(self, shared_data: Path):
        d = shared_data / "hololens"
        seq = PosedSequence(d / "images", read_trajectory(d / "poses_images.txt").poses, d / "K.txt", depth=d / "depth")
        assert len(seq) == 94
        f = seq[10]
        assert f.name == "00043" and f.rgb.shape == (360, 540, 3)
        assert 0.5 < np.median(f.depth[f.depth > 0]) < 7 and f.camera.fx == pytest.approx(495.5678, abs=1e-3)
        np.testing.assert_allclose(f.pose, np.loadtxt(d / "poses_images.txt")[10].reshape(4, 4), atol=1e-4)

    def test_seven_scenes_layout_equals_its_reader(self, shared_data: Path):
        d = shared_data / "7scenes"
        images = list_files(d, (".png", ".jpg"), "color", "images")
        assert len(images) == 60 and images[0].name == "frame-000000.color.jpg"
        poses = associate_poses(read_trajectory(d), [p.name for p in images])
        seq = PosedSequence(
            d, poses, "525,525,320,240", depth=d, depth_invalid=65535, depth_intrinsics=d / "camera-intrinsics.txt"
        )
        ours, ref = seq[7], SevenScenes(d)[7]
        assert ours.name == ref.name and ours.camera == ref.camera
        np.testing.assert_array_equal(ours.depth, ref.depth)
        np.testing.assert_allclose(ours.pose, ref.pose)


class TestMatchDepthRules:
    def test_same_stem_and_times(self):
        images = [Path("0001.png"), Path("0002.png")]
        assert match_depth(images, [Path("0002.npy"), Path("0001.npy")]) == [Path("0001.npy"), Path("0002.npy")]
        rgb = [Path("1305031102.175304.png"), Path("1305031102.211214.png")]
        depth = [Path("1305031102.160407.png"), Path("1305031102.194330.png"), Path("1305031102.226738.png")]
        assert match_depth(rgb, depth) == [depth[0], depth[2]]  # the nearest in time, 15 ms each
        with pytest.raises(ShapeError, match=r"matched by name, time or order"):
            match_depth(rgb, depth, max_time_difference=0.001)
