"""Tests of gpdepth3d.io.poses: pose helpers, TUM / ORB-SLAM3 / KITTI / COLMAP readers, the inverted-pose check."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.io.poses import (
    InvertedPoseWarning,
    associate_poses,
    detect_pose_format,
    load_pose,
    read_flat_poses,
    read_pose_files,
    read_trajectory,
    Trajectory,
    check_pose_orientation,
    invert_pose,
    pose_from_tq,
    read_colmap_model,
    read_kitti_poses,
    read_tum_trajectory,
    tq_from_pose,
    write_tum_trajectory,
)

CAM = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _random_pose(rng) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def _seven_scenes_poses(shared_data: Path, n: int = 10) -> np.ndarray:
    folder = shared_data / "7scenes"
    return np.stack([np.loadtxt(folder / f"frame-{5 * i:06d}.pose.txt") for i in range(n)])


class TestPoseHelpers:
    def test_known_quaternion(self):
        # 90 degrees about z: x -> y
        T = pose_from_tq([1.0, 2.0, 3.0], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
        np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
        Tw = pose_from_tq([1.0, 2.0, 3.0], [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], order="wxyz")
        np.testing.assert_allclose(T, Tw, atol=1e-12)

    def test_round_trips(self):
        rng = np.random.default_rng(0)
        poses = np.stack([_random_pose(rng) for _ in range(20)])
        for T in poses:
            for order in ("xyzw", "wxyz"):
                t, q = tq_from_pose(T, order=order)
                np.testing.assert_allclose(pose_from_tq(t, q, order=order), T, atol=1e-12)
            np.testing.assert_allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)
            np.testing.assert_allclose(invert_pose(T), np.linalg.inv(T), atol=1e-12)
        ts = np.stack([tq_from_pose(T)[0] for T in poses])
        qs = np.stack([tq_from_pose(T)[1] for T in poses])
        np.testing.assert_allclose(pose_from_tq(ts, qs), poses, atol=1e-12)

    def test_errors(self):
        with pytest.raises(CalibrationError):
            pose_from_tq([0, 0, 0], [0, 0, 0, 2.0])
        with pytest.raises(ShapeError):
            pose_from_tq([0, 0, 0], [0, 0, 1.0])
        with pytest.raises(ShapeError):
            pose_from_tq(np.zeros((2, 3)), [0, 0, 0, 1.0])
        with pytest.raises(InvalidInputError):
            pose_from_tq([0, 0, 0], [0, 0, 0, 1.0], order="zyxw")  # type: ignore[arg-type]
        with pytest.raises(CalibrationError):
            invert_pose(2 * np.eye(4))


class TestTUM:
    def test_orbslam3_keyframe_file(self, tmp_path: Path):
        # ORB-SLAM3 writes KeyFrameTrajectory.txt in TUM format (timestamp tx ty tz qx qy qz qw)
        text = (
            "1341847980.722988 0.000000 0.000000 0.000000 0.000000 0.000000 0.000000 1.000000\n"
            "1341847982.998783 0.1000 -0.0500 0.2500 0.0000000 0.7071068 0.0000000 0.7071068\n"
        )
        path = tmp_path / "KeyFrameTrajectory.txt"
        path.write_text(text)
        traj = read_tum_trajectory(path)
        assert len(traj) == 2
        np.testing.assert_allclose(traj.timestamps, [1341847980.722988, 1341847982.998783])
        np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(traj.poses[1][:3, 3], [0.1, -0.05, 0.25])
        # 90 degrees about y: the camera's z axis (viewing direction) points along world +x
        np.testing.assert_allclose(traj.poses[1][:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-6)
        assert traj.nearest(1341847983.0) == 1
        with pytest.raises(InvalidInputError):
            traj.nearest(1341847990.0)

    def test_round_trip_real_poses(self, shared_data: Path, tmp_path: Path):
        poses = _seven_scenes_poses(shared_data)
        traj = Trajectory(poses, np.arange(len(poses)) / 30.0)
        path = write_tum_trajectory(tmp_path / "traj.txt", traj)
        back = read_tum_trajectory(path)
        np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)
        np.testing.assert_allclose(traj.poses, poses, atol=1e-3)  # 7-Scenes' rotations are orthonormal to ~1e-4
        np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
        assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]

    def test_errors(self, tmp_path: Path):
        with pytest.raises(DataFormatError):
            read_tum_trajectory(tmp_path / "missing.txt")
        bad = tmp_path / "bad.txt"
        bad.write_text("0 1 2\n")
        with pytest.raises(DataFormatError):
            read_tum_trajectory(bad)
        with pytest.raises(InvalidInputError):
            write_tum_trajectory(tmp_path / "x.txt", np.eye(4))  # type: ignore[arg-type]
        with pytest.raises(ShapeError):
            Trajectory(np.eye(4))
        with pytest.raises(CalibrationError):
            Trajectory(2 * np.eye(4)[None])


class TestKITTI:
    def test_read(self, shared_data: Path, tmp_path: Path):
        poses = _seven_scenes_poses(shared_data, 5)
        path = tmp_path / "00.txt"
        path.write_text("\n".join(" ".join(f"{x:.9e}" for x in T[:3].ravel()) for T in poses) + "\n")
        traj = read_kitti_poses(path)
        np.testing.assert_allclose(traj.poses, Trajectory(poses).poses, atol=1e-8)
        assert np.all(np.isnan(traj.timestamps))
        bad = tmp_path / "bad.txt"
        bad.write_text("1 2 3\n")
        with pytest.raises(DataFormatError):
            read_kitti_poses(bad)


def _write_colmap(
    folder: Path, poses: np.ndarray, points: np.ndarray, model: str = "PINHOLE", binary: bool = True
) -> None:
    import pycolmap

    rec = pycolmap.Reconstruction()
    params = [525.0, 525.0, 320.0, 240.0] if model == "PINHOLE" else [525.0, 320.0, 240.0, 0.1]
    cam = pycolmap.Camera.create_from_model_name(1, model, 525.0, 640, 480)
    cam.params = params
    rec.add_camera_with_trivial_rig(cam)
    observations = []
    for i, T in enumerate(poses):
        T_cw = invert_pose(T)
        pc = points @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv = pc[:, :2] / pc[:, 2:] * 525.0 + [320.0, 240.0]  # COLMAP pixel coordinates (corner at 0)
        img = pycolmap.Image(name=f"frame{i}.png", keypoints=uv, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(T_cw[:3]))
        observations.append(uv)
    for j, p in enumerate(points):
        track = pycolmap.Track()
        for i in range(len(poses)):
            track.add_element(i + 1, j)
        rec.add_point3D(p, track, np.array([10, 20, 30], np.uint8))
    folder.mkdir(parents=True)
    (rec.write_binary if binary else rec.write_text)(str(folder))


class TestColmap:
    @pytest.mark.parametrize("binary", [True, False])
    def test_round_trip_with_real_poses(self, shared_data: Path, tmp_path: Path, binary: bool):
        poses = _seven_scenes_poses(shared_data, 3)
        rng = np.random.default_rng(0)
        # points 1.5-3 m in front of the first camera
        pc = np.column_stack([rng.uniform(-0.5, 0.5, 30), rng.uniform(-0.4, 0.4, 30), rng.uniform(1.5, 3.0, 30)])
        points = pc @ poses[0][:3, :3].T + poses[0][:3, 3]
        _write_colmap(tmp_path / "sparse", poses, points, binary=binary)
        model = read_colmap_model(tmp_path / "sparse")
        assert model.cameras[1] == PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
        np.testing.assert_allclose(model.trajectory().poses, Trajectory(poses).poses, atol=1e-6)
        order = np.argsort(model.point_ids)
        np.testing.assert_allclose(model.points[order], points, atol=1e-9)
        assert np.all(model.track_lengths == 3) and np.all(model.colors == [10, 20, 30])
        first = model.image_by_name("frame0.png")
        mp = model.map_points(first)
        assert mp.shape == (30, 3)
        # the keypoints sit where gpdepth3d's camera projects the map points with the read pose
        pcam = (
            mp @ invert_pose(model.images[first].T_world_camera)[:3, :3].T
            + invert_pose(model.images[first].T_world_camera)[:3, 3]
        )
        uv, _ = model.cameras[1].project(pcam)
        np.testing.assert_allclose(uv, model.images[first].uv, atol=1e-6)
        with pytest.raises(InvalidInputError):
            model.map_points(99)
        with pytest.raises(InvalidInputError):
            model.image_by_name("nope.png")

    @pytest.mark.parametrize("binary", [True, False])
    def test_a_zero_quaternion_is_refused_naming_the_image(self, tmp_path: Path, binary: bool):
        import struct

        points = np.array([[0.0, 0.0, 2.0]] * 3) + np.arange(3)[:, None] * 0.1
        poses = np.stack([np.eye(4), np.eye(4)])
        poses[1, 0, 3] = 0.1
        _write_colmap(tmp_path / "m", poses, points, binary=binary)
        read_colmap_model(tmp_path / "m")  # unit quaternions: read
        if binary:
            data = bytearray((tmp_path / "m" / "images.bin").read_bytes())
            data[12 : 12 + 32] = struct.pack("<4d", 0.0, 0.0, 0.0, 0.0)  # the first image's qw qx qy qz
            (tmp_path / "m" / "images.bin").write_bytes(bytes(data))
        else:
            text = (tmp_path / "m" / "images.txt").read_text().splitlines()
            rows = [i for i, ln in enumerate(text) if ln and not ln.startswith("#")][::2]
            f = text[rows[0]].split()
            text[rows[0]] = " ".join(f[:1] + ["0", "0", "0", "0"] + f[5:])
            (tmp_path / "m" / "images.txt").write_text("\n".join(text) + "\n")
        with pytest.raises(DataFormatError, match=r"image frame\d\.png: quaternion 0 0 0 0 of norm 0"):
            read_colmap_model(tmp_path / "m")

    def test_distortion_and_errors(self, tmp_path: Path):
        points = np.array([[0.0, 0.0, 2.0]] * 3) + np.arange(3)[:, None] * 0.1
        _write_colmap(tmp_path / "radial", np.eye(4)[None], points, model="SIMPLE_RADIAL")
        with pytest.raises(CalibrationError):
            read_colmap_model(tmp_path / "radial")
        model = read_colmap_model(tmp_path / "radial", ignore_distortion=True)
        assert model.cameras[1].fx == 525.0
        with pytest.raises(DataFormatError):
            read_colmap_model(tmp_path / "missing")
        (tmp_path / "empty").mkdir()
        with pytest.raises(DataFormatError):
            read_colmap_model(tmp_path / "empty")


class TestInvertedPoseCheck:
    def test_real_frame(self, seven_scenes_frame):
        f = seven_scenes_frame
        pts, _ = f.camera.backproject(f.depth)
        rng = np.random.default_rng(0)
        pts = pts[rng.choice(len(pts), 500, replace=False)]
        world = pts @ f.T_world_camera[:3, :3].T + f.T_world_camera[:3, 3]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ok = check_pose_orientation(world, f.T_world_camera, f.camera, frame=0)
        assert not ok.inverted and ok.visible == 1.0 and ok.points == 500
        with pytest.warns(InvertedPoseWarning, match=r"frame 7: .*\d+% of 500 map points.*100% under its inverse"):
            bad = check_pose_orientation(world, invert_pose(f.T_world_camera), f.camera, frame=7)
        assert bad.inverted and bad.visible_inverse == 1.0 and bad.visible < 0.1
        # too few points are not judged; NaN points are ignored
        few = check_pose_orientation(world[:5], invert_pose(f.T_world_camera), f.camera)
        assert not few.inverted and few.points == 5
        with_nan = np.vstack([world, np.full((3, 3), np.nan)])
        assert check_pose_orientation(with_nan, f.T_world_camera, f.camera, warn=False).points == 500
        with pytest.raises(ShapeError):
            check_pose_orientation(world[:, :2], f.T_world_camera, f.camera)


# ---------------------------------------------------------------------- checks of TUM files, any format, association
def _tum_text(ts, poses) -> str:
    lines = []
    for t, T in zip(ts, poses):
        tr, q = tq_from_pose(T)
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in (*tr, *q)))
    return "\n".join(lines) + "\n"


class TestTUMChecks:
    @pytest.mark.parametrize("q", ["0 0 0 2", "0 0 0 0.5", "0 0 0 0", "0.5 0.5 0.5 0.6"])
    def test_quaternion_not_unit_refused(self, tmp_path: Path, q: str):
        path = tmp_path / "t.txt"
        path.write_text(f"# header\n0.0 0 0 0 0 0 0 1\n1.0 1 2 3 {q}\n")
        with pytest.raises(DataFormatError, match=r"line 3: quaternion of norm"):
            read_tum_trajectory(path)

    def test_rounded_quaternion_is_normalised(self, tmp_path: Path):
        path = tmp_path / "t.txt"
        path.write_text("0.0 0 0 0 0.0000 0.7071 0.0000 0.7071\n")  # norm 0.99999, 4 digits as TUM writes
        T = read_tum_trajectory(path).poses[0]
        np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-9)

    def test_duplicate_timestamps_refused(self, tmp_path: Path):
        path = tmp_path / "t.txt"
        path.write_text("0.5 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n0.5 1 0 0 0 0 0 1\n")
        with pytest.raises(DataFormatError, match=r"lines 1 and 3: the same timestamp 0.5"):
            read_tum_trajectory(path)
        with pytest.raises(InvalidInputError, match="unique"):
            Trajectory(np.tile(np.eye(4), (2, 1, 1)), np.array([1.0, 1.0]))

    @pytest.mark.parametrize("t", [float("nan"), float("inf"), "a", None, True])
    def test_nearest_bad_time(self, t):
        traj = Trajectory(np.tile(np.eye(4), (2, 1, 1)), np.array([0.0, 1.0]))
        with pytest.raises(InvalidInputError, match="timestamp"):
            traj.nearest(t)  # type: ignore[arg-type]

    def test_bad_lines(self, tmp_path: Path):
        path = tmp_path / "t.txt"
        for text, match in [
            ("0 0 0 0 0 0 0\n", "expected 8 numbers"),
            ("0 0 0 nan 0 0 0 1\n", "NaN"),
            ("0 0 0 x 0 0 0 1\n", "not numbers"),
            ("# only a comment\n", "no poses"),
        ]:
            path.write_text(text)
            with pytest.raises(DataFormatError, match=match):
                read_tum_trajectory(path)


class TestFlatPoses:
    def test_real_hololens_file(self, shared_data: Path):
        path = shared_data / "hololens" / "poses_images.txt"
        traj = read_flat_poses(path)
        assert len(traj) == 94 and np.all(np.isnan(traj.timestamps)) and traj.names == ()
        np.testing.assert_allclose(traj.poses, np.loadtxt(path).reshape(-1, 4, 4), atol=1e-4)
        assert detect_pose_format(path) == "rows"
        np.testing.assert_array_equal(read_trajectory(path).poses, traj.poses)

    def test_write_then_read(self, tmp_path: Path):
        rng = np.random.default_rng(1)
        poses = np.stack([_random_pose(rng) for _ in range(5)])
        path = tmp_path / "poses.txt"
        path.write_text("# flattened 4x4\n" + "\n".join(" ".join(f"{x:.12g}" for x in T.ravel()) for T in poses) + "\n")
        np.testing.assert_allclose(read_flat_poses(path).poses, poses, atol=1e-10)

    def test_errors(self, tmp_path: Path):
        path = tmp_path / "poses.txt"
        path.write_text(" ".join(["1"] * 16) + "\n")
        with pytest.raises(DataFormatError, match="line 1: not a rigid transform"):
            read_flat_poses(path)
        path.write_text(" ".join(["0"] * 12) + "\n")
        with pytest.raises(DataFormatError, match="expected 16 numbers"):
            read_flat_poses(path)
        with pytest.raises(DataFormatError):
            read_flat_poses(tmp_path / "missing.txt")


class TestKittiRealFile:
    def test_real_kitti_tiny(self, shared_data: Path):
        path = shared_data / "kitti_tiny" / "poses.txt"
        traj = read_kitti_poses(path)
        rows = np.loadtxt(path)
        assert len(traj) == rows.shape[0] == 474
        np.testing.assert_allclose(traj.poses[:, :3, :].reshape(-1, 12), rows, atol=1e-5)
        assert detect_pose_format(path) == "kitti"
        np.testing.assert_allclose(read_trajectory(path).poses, traj.poses)


class TestPoseFiles:
    def test_real_seven_scenes(self, shared_data: Path):
        folder = shared_data / "7scenes"
        traj = read_pose_files(folder)
        files = sorted(folder.glob("*.pose.txt"))
        assert len(traj) == len(files) == 60
        assert traj.names[:2] == ("frame-000000", "frame-000005")
        np.testing.assert_allclose(traj.poses, np.stack([np.loadtxt(f) for f in files]), atol=1e-3)
        assert detect_pose_format(folder) == "files"

    def test_write_then_read(self, tmp_path: Path):
        rng = np.random.default_rng(2)
        poses = np.stack([_random_pose(rng) for _ in range(3)])
        for i, T in enumerate(poses):
            np.savetxt(tmp_path / f"img{i}.txt", T)
        traj = read_trajectory(tmp_path, "files")
        assert traj.names == ("img0", "img1", "img2")
        np.testing.assert_allclose(traj.poses, poses, atol=1e-12)
        np.testing.assert_allclose(associate_poses(traj, ["img2.png", "img0.png"]), poses[[2, 0]], atol=1e-12)

    def test_errors(self, tmp_path: Path):
        with pytest.raises(DataFormatError, match="no pose files"):
            read_pose_files(tmp_path)
        (tmp_path / "a.txt").write_text("1 0 0\n0 1 0\n")
        with pytest.raises(DataFormatError, match="a.txt"):
            read_pose_files(tmp_path)
        with pytest.raises(DataFormatError, match="not found"):
            read_pose_files(tmp_path / "missing")

    def test_one_file_forms(self, tmp_path: Path):
        """`load_pose` (the 7-Scenes reader's and the folder reader's one parser): 4x4, 3x4 rows, comments."""
        T = _random_pose(np.random.default_rng(3))
        (tmp_path / "c.txt").write_text("# pose\n" + "\n".join(" ".join(f"{v:.17g}" for v in r) for r in T[:3]) + "\n")
        np.testing.assert_allclose(load_pose(tmp_path / "c.txt"), T, atol=1e-12)
        scaled = T.copy()
        scaled[:3, :3] *= 2.0
        np.savetxt(tmp_path / "s.txt", scaled)
        with pytest.raises(DataFormatError, match="s.txt.*not a rigid transform"):
            load_pose(tmp_path / "s.txt")
        (tmp_path / "n.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n")
        with pytest.raises(DataFormatError, match="n.txt"):
            load_pose(tmp_path / "n.txt")


class TestAnyFormat:
    def test_each_format_written_then_read(self, shared_data: Path, tmp_path: Path):
        poses = _seven_scenes_poses(shared_data, 4)
        ref = Trajectory(poses).poses
        ts = 1305031102.0 + np.arange(4) / 30.0
        written = {
            "tum": write_tum_trajectory(tmp_path / "tum.txt", Trajectory(poses, ts)),
            "kitti": tmp_path / "kitti.txt",
            "rows": tmp_path / "rows.txt",
            "files": tmp_path / "files",
            "colmap": tmp_path / "sparse",
        }
        written["kitti"].write_text("\n".join(" ".join(f"{x:.12e}" for x in T[:3].ravel()) for T in ref) + "\n")
        written["rows"].write_text("\n".join(" ".join(f"{x:.12e}" for x in T.ravel()) for T in ref) + "\n")
        written["files"].mkdir()
        for i, T in enumerate(ref):
            np.savetxt(written["files"] / f"frame-{i:06d}.pose.txt", T)
        rng = np.random.default_rng(0)
        pc = np.column_stack([rng.uniform(-0.5, 0.5, 20), rng.uniform(-0.4, 0.4, 20), rng.uniform(1.5, 3.0, 20)])
        _write_colmap(written["colmap"], ref, pc @ ref[0][:3, :3].T + ref[0][:3, 3])
        images = {
            "tum": [f"{t:.6f}.png" for t in ts],
            "kitti": [f"{i:06d}.png" for i in range(4)],
            "rows": [f"{i:06d}.png" for i in range(4)],
            "files": [f"frame-{i:06d}.color.jpg" for i in range(4)],
            "colmap": [f"frame{i}.png" for i in range(4)],
        }
        for fmt, path in written.items():
            assert detect_pose_format(path) == fmt
            traj = read_trajectory(path)
            np.testing.assert_allclose(traj.poses, ref, atol=1e-6, err_msg=fmt)
            np.testing.assert_allclose(
                associate_poses(traj, images[fmt][::-1] if fmt in ("files", "colmap", "tum") else images[fmt]),
                ref[::-1] if fmt in ("files", "colmap", "tum") else ref,
                atol=1e-6,
                err_msg=fmt,
            )
        with pytest.raises(InvalidInputError, match="format"):
            read_trajectory(written["tum"], "euroc")

    def test_detect_errors(self, tmp_path: Path):
        path = tmp_path / "x.txt"
        path.write_text("1 2 3 4 5\n")
        with pytest.raises(DataFormatError, match="8 numbers a line"):
            detect_pose_format(path)
        with pytest.raises(DataFormatError):
            detect_pose_format(tmp_path / "missing.txt")


class TestAssociate:
    def test_timestamps(self):
        poses = np.tile(np.eye(4), (3, 1, 1))
        poses[:, 0, 3] = [0.0, 1.0, 2.0]
        traj = Trajectory(poses, np.array([10.0, 10.1, 10.2]))
        got = associate_poses(traj, ["10.101000.png", "10.000000.png"])
        np.testing.assert_allclose(got[:, 0, 3], [1.0, 0.0])
        with pytest.raises(DataFormatError, match=r"11.500000.png: no pose within 0.02 s \(1 of 2"):
            associate_poses(traj, ["10.101000.png", "11.500000.png"])
        # images named by a plain number are matched by order, not as times
        np.testing.assert_allclose(associate_poses(traj, ["0003.png", "0007.png", "0011.png"]), traj.poses)

    def test_order_and_errors(self):
        traj = Trajectory(np.tile(np.eye(4), (3, 1, 1)))
        with pytest.raises(ShapeError, match=r"3 poses"):
            associate_poses(traj, ["a.png", "b.png"])
        with pytest.raises(InvalidInputError, match="timestamps"):
            associate_poses(traj, ["1.5.png"] * 3, by="timestamp")
        with pytest.raises(InvalidInputError, match="names"):
            associate_poses(traj, ["a.png"] * 3, by="name")
        with pytest.raises(InvalidInputError, match="by"):
            associate_poses(traj, ["a.png"] * 3, by="time")
        named = Trajectory(np.tile(np.eye(4), (2, 1, 1)), names=("a", "b"))
        with pytest.raises(DataFormatError, match=r"c.png: no pose of that name \(1 of 2"):
            associate_poses(named, ["a.png", "c.png"])
        with pytest.raises(ShapeError):
            Trajectory(np.tile(np.eye(4), (2, 1, 1)), names=("a",))
