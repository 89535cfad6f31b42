"""Tests of gpdepth3d.pipelines.mapping_run: a user's posed sequence opened, mapped, written and reloaded."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import check_pose
from gpdepth3d.errors import DataFormatError, InvalidInputError, OutputError, ShapeError
from gpdepth3d.pipelines.mapping_run import map_sequence, open_posed_sequence, write_map
from gpdepth3d.mapping.cloud import ColoredCloud
from gpdepth3d.mapping.mapper import Mapper
from gpdepth3d.io.poses import Trajectory, write_tum_trajectory


@pytest.fixture()
def seven(shared_data: Path, tmp_path: Path) -> Path:
    """Eight 7-Scenes frames in a user's layout: rgb/ and depth/ named by time, a TUM trajectory."""
    return _user_layout(shared_data, tmp_path, spacing=5)


def _user_layout(shared_data: Path, tmp_path: Path, spacing: int) -> Path:
    """Eight 7-Scenes frames ``spacing`` frames apart, laid out as `seven`."""
    src = shared_data / "7scenes"
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    poses, ts = [], []
    for k in range(8):
        t = 1000.0 + k / 30.0
        shutil.copy(src / f"frame-{spacing * k:06d}.color.jpg", tmp_path / "rgb" / f"{t:.6f}.jpg")
        shutil.copy(src / f"frame-{spacing * k:06d}.depth.png", tmp_path / "depth" / f"{t:.6f}.png")
        poses.append(np.loadtxt(src / f"frame-{spacing * k:06d}.pose.txt"))
        ts.append(t)
    write_tum_trajectory(tmp_path / "traj.txt", Trajectory(np.stack(poses), np.array(ts)))
    return tmp_path


def _open(seven: Path, **kw):
    return open_posed_sequence(
        seven / "rgb",
        seven / "traj.txt",
        "525,525,320,240",
        depth=seven / "depth",
        depth_invalid=65535,
        depth_intrinsics="585,585,320,240",
        **kw,
    )


@pytest.fixture(scope="module")
def fastdepth():
    from conftest import shared_data_dir
    from gpdepth3d.mde import load_frontend

    models = shared_data_dir().parent / "models"
    if not (models / "fast_depth_224.tflite").is_file():
        pytest.skip("FastDepth model not found")
    return load_frontend("fastdepth", models_dir=models)


class TestOpen:
    def test_tum_by_timestamp(self, seven: Path, shared_data: Path):
        inputs = _open(seven)
        assert inputs.pose_format == "tum" and len(inputs.sequence) == 8 and inputs.map_points is None
        f = inputs.sequence.frame(3)
        np.testing.assert_allclose(
            f.pose, check_pose(np.loadtxt(shared_data / "7scenes" / "frame-000015.pose.txt")), atol=1e-6
        )
        assert f.depth is not None and f.depth.shape == (480, 640)

    def test_errors(self, seven: Path):
        with pytest.raises(InvalidInputError, match="intrinsics"):
            open_posed_sequence(seven / "rgb", seven / "traj.txt")
        with pytest.raises(InvalidInputError, match="pose_format"):
            _open(seven, pose_format="euroc")
        with pytest.raises(ShapeError, match="8 images"):
            open_posed_sequence(
                seven / "rgb", seven / "traj.txt", "525,525,320,240", depth=str(seven / "depth" / "1000.0*.png")
            )
        first = sorted((seven / "rgb").iterdir())[0]
        first.rename(first.with_name("2000.000000.jpg"))
        with pytest.raises(DataFormatError, match=r"2000.000000.jpg: no pose within 0.02 s \(1 of 8"):
            _open(seven)


class TestMapSequence:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_map_write_reload(self, seven: Path, fastdepth, tmp_path: Path, monkeypatch):
        (seven / "rgb" / "1000.100000.jpg").write_bytes(b"broken")  # frame 3: not a readable JPEG
        result = map_sequence(_open(seven), mde=fastdepth)
        assert result.frames == 8 and result.frames_fused == 7
        assert len(result.frame_errors) == 1 and "1000.100000" in result.frame_errors[0]
        assert result.mapper.work_camera.width == 320
        for name in ("map", "mde"):
            m = result.metrics[name]
            assert m is not None and 0 < m["fscore"] <= 1 and m["threshold"] == 0.05
        assert len(result.mesh.faces) > 0 and len(result.cloud) > 0
        assert np.all(np.isfinite(result.cloud.sigma)) and np.all(result.cloud.sigma >= 0)
        out = tmp_path / "out"
        written = write_map(result, out)
        assert sorted(p.name for p in written) == sorted(
            ["mesh.ply", "cloud.ply", "mapper.json", "keyframes.npz", "volume.npz", "volume.json", "metrics.json"]
        )
        back = Mapper.load(out)
        assert sorted(back.keyframes) == sorted(result.mapper.keyframes) and len(back.keyframes) == 7
        cloud = ColoredCloud.load_ply(out / "cloud.ply")
        np.testing.assert_allclose(cloud.sigma, result.cloud.sigma, rtol=1e-6)
        summary = json.loads((out / "metrics.json").read_text())
        assert summary["metrics"]["map"]["fscore"] == pytest.approx(result.metrics["map"]["fscore"])
        assert summary["frames_fused"] == 7 and "1000.100000" in summary["frame_errors"][0]
        assert len(back.mesh().faces) > 0

        # a second write that fails half-way (the cloud's writer) leaves the first set as it was
        before = {p.name: p.read_bytes() for p in out.iterdir() if not p.name.startswith(".")}

        def broken(self, path):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(ColoredCloud, "save_ply", broken)
        result.frame_errors.append("a change the metrics would show")
        with pytest.raises(OutputError):
            write_map(result, out)
        assert {p.name: p.read_bytes() for p in out.iterdir() if not p.name.startswith(".")} == before

    def test_stride_limit_and_no_depth(self, seven: Path, fastdepth, tmp_path: Path):
        inputs = open_posed_sequence(seven / "rgb", seven / "traj.txt", "525,525,320,240")
        result = map_sequence(inputs, mde=fastdepth, stride=2, max_frames=3, working_width=160)
        assert result.frames == 3 and result.metrics is None and result.mapper.work_camera.width == 160
        assert sorted(result.mapper.keyframes) == [0, 2, 4]
        for bad in ({"stride": 0}, {"max_frames": 0}, {"working_width": 1.5}, {"threshold": -1.0}):
            with pytest.raises(InvalidInputError, match=next(iter(bad))):
                map_sequence(inputs, mde=fastdepth, **bad)


class TestPoseCheckStopsTheRun:
    def test_rule(self):
        from gpdepth3d.errors import CalibrationError
        from gpdepth3d.pipelines.mapping_run import check_poses_agree

        check_poses_agree([True, True, False, False])  # half: a run with fast turns goes on
        check_poses_agree([True, True] + [False] * 6, final=True)
        check_poses_agree([True] * 5, final=False)  # too early to judge
        check_poses_agree([True, True, True, False])  # a short run: its first frames often fail (short baseline)
        with pytest.raises(CalibrationError, match="5 of 6 frames failing the pose check: likely inverted"):
            check_poses_agree([True] * 5 + [False], "kitti")
        with pytest.raises(CalibrationError, match="w-first") as info:
            check_poses_agree([True] * 8, "tum", final=False)
        assert "map --force" in str(info.value) and "\n" not in str(info.value)

    @pytest.mark.slow
    def test_inverted_poses_stop_the_run_unless_forced(self, shared_data: Path, tmp_path: Path, fastdepth):
        """Frames 20 apart (about 0.7 s of a hand-held walk): inverted relative motions are too far off to
        triangulate. Over a few centimetres, as `seven`'s frames 5 apart, the track check cannot tell them."""
        from gpdepth3d.errors import CalibrationError
        from gpdepth3d.io.poses import invert_pose, read_trajectory

        seven = _user_layout(shared_data, tmp_path, spacing=20)

        traj = read_trajectory(seven / "traj.txt")
        inverted = Trajectory(np.stack([invert_pose(T) for T in traj.poses]), traj.timestamps)
        write_tum_trajectory(seven / "inverted.txt", inverted)
        inputs = open_posed_sequence(seven / "rgb", seven / "inverted.txt", "525,525,320,240")
        with pytest.raises(CalibrationError, match="failing the pose check: likely inverted poses"):
            map_sequence(inputs, mde=fastdepth, working_width=160)
        result = map_sequence(inputs, mde=fastdepth, working_width=160, force=True)
        assert result.frames_fused == 8


class TestColmapInputs:
    def test_model_gives_poses_camera_and_map_points(self, seven: Path, tmp_path: Path):
        import pycolmap

        from gpdepth3d.io.poses import invert_pose, read_trajectory

        poses = read_trajectory(seven / "traj.txt").poses
        names = sorted(p.name for p in (seven / "rgb").iterdir())
        rng = np.random.default_rng(0)
        pc = np.column_stack([rng.uniform(-0.5, 0.5, 25), rng.uniform(-0.4, 0.4, 25), rng.uniform(1.5, 3.0, 25)])
        points = pc @ poses[0][:3, :3].T + poses[0][:3, 3]
        rec = pycolmap.Reconstruction()
        cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 525.0, 640, 480)
        cam.params = [525.0, 525.0, 320.5, 240.5]
        rec.add_camera_with_trivial_rig(cam)
        order = [3, 0, 5]  # three of the eight images, in another order (ids are not the sequence order)
        for image_id, k in enumerate(order, start=1):
            T_cw = invert_pose(poses[k])
            p = points @ T_cw[:3, :3].T + T_cw[:3, 3]
            uv = p[:, :2] / p[:, 2:] * 525.0 + [320.5, 240.5]
            img = pycolmap.Image(name=names[k], keypoints=uv, camera_id=1, image_id=image_id)
            rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(T_cw[:3]))
        for j, x in enumerate(points[:20]):  # five points stay unobserved
            track = pycolmap.Track()
            for image_id in (1, 2, 3):
                track.add_element(image_id, j)
            rec.add_point3D(x, track, np.array([1, 2, 3], np.uint8))
        (tmp_path / "sparse").mkdir()
        rec.write_binary(str(tmp_path / "sparse"))
        images = [seven / "rgb" / names[k] for k in sorted(order)]
        inputs = open_posed_sequence(images, tmp_path / "sparse")
        assert inputs.pose_format == "colmap"
        seq = inputs.sequence
        assert seq.camera.fx == 525.0 and seq.camera.cx == 320.0  # COLMAP's pixel-corner origin moved to centres
        np.testing.assert_allclose(seq.poses, poses[sorted(order)], atol=1e-6)
        assert [len(m) for m in inputs.map_points] == [20, 20, 20]
        np.testing.assert_allclose(np.sort(inputs.map_points[0][:, 0]), np.sort(points[:20, 0]), atol=1e-9)
        with pytest.raises(DataFormatError, match="no pose of that name"):
            open_posed_sequence(seven / "rgb", tmp_path / "sparse")


def test_sensor_depth_reference_is_the_resized_depth_of_the_same_camera():
    """The map's reference depth is `resize_depth` of the sensor depth when the frame's camera is the one the
    working camera was resized from (the reference `fuse_sequence` fuses); another camera's depth is projected."""
    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.datasets.base import Frame
    from gpdepth3d.mapping.frame_inputs import resize_depth
    from gpdepth3d.pipelines.mapping_run import _sensor_depth_at

    rng = np.random.default_rng(0)
    camera = PinholeCamera(100.0, 100.0, 39.5, 29.5, 80, 60)
    work = camera.resized(40, 30)
    depth = rng.uniform(1.0, 3.0, (60, 80))
    depth[rng.random((60, 80)) < 0.3] = 0.0
    frame = Frame(name="f", rgb=np.zeros((60, 80, 3), np.uint8), camera=camera, depth=depth, pose=np.eye(4))
    got = _sensor_depth_at(frame, camera, work)
    assert got.shape == (30, 40)
    np.testing.assert_array_equal(got, resize_depth(depth, (30, 40)))

    other = PinholeCamera(120.0, 120.0, 39.5, 29.5, 80, 60)  # a frame seen by another camera: lifted, projected
    flat = Frame(name="g", rgb=frame.rgb, camera=other, depth=np.full((60, 80), 2.0), pose=np.eye(4))
    projected = _sensor_depth_at(flat, camera, work)
    assert projected.shape == (30, 40)
    assert np.allclose(projected[projected > 0], 2.0) and (projected > 0).mean() > 0.5
    assert (projected[0] == 0).all()  # the narrower field of view leaves the border empty
