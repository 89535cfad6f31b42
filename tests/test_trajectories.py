"""Tests of gpdepth3d.mapping.trajectories: pose helpers, TUM / ORB-SLAM3 / KITTI / COLMAP readers, the inverted-pose check."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.mapping.trajectories import (
    InvertedPoseWarning,
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


def _write_colmap(folder: Path, poses: np.ndarray, points: np.ndarray, model: str = "PINHOLE", binary: bool = True) -> None:
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
        pcam = mp @ invert_pose(model.images[first].T_world_camera)[:3, :3].T + invert_pose(model.images[first].T_world_camera)[:3, 3]
        uv, _ = model.cameras[1].project(pcam)
        np.testing.assert_allclose(uv, model.images[first].uv, atol=1e-6)
        with pytest.raises(InvalidInputError):
            model.map_points(99)
        with pytest.raises(InvalidInputError):
            model.image_by_name("nope.png")

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
