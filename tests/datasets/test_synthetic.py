"""Tests of the built-in synthetic scene generator (gpdepth3d.datasets.synthetic)."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.camera import check_pose, transform_points
from gpdepth3d.errors import EmptyInputError, InvalidInputError, ShapeError
from gpdepth3d.measurements import LidarCalibration, project_points
from gpdepth3d.datasets.synthetic import (
    HDL64_ELEVATIONS_DEG,
    LidarModel,
    MDESimulation,
    SyntheticFrame,
    build_scene,
    default_camera,
    make_scene,
    pose_from_position_yaw_pitch,
    scan_lidar,
    sequence,
    simulate_mde,
)

NOISE_FREE = LidarModel(noise=0.0)
COARSE = LidarModel(azimuth_step_deg=0.5)  # fewer rays where the LiDAR is not what is tested


def _pixels(sparse):
    return set(zip(sparse.v.astype(int).tolist(), sparse.u.astype(int).tolist()))


class TestMakeScene:
    @pytest.mark.parametrize("kind, shape", [("street", (96, 320)), ("room", (120, 160))])
    def test_fields_and_shapes(self, kind, shape, street_frame, room_frame):
        f = street_frame if kind == "street" else room_frame
        assert isinstance(f, SyntheticFrame)
        assert f.rgb.shape == shape + (3,) and f.rgb.dtype == np.uint8
        assert f.depth_gt.shape == shape and f.mde.shape == shape
        assert f.camera.shape == shape and f.lidar.image_size == shape
        check_pose(f.T_world_camera)
        check_pose(f.T_camera_lidar)
        assert np.all(np.isfinite(f.mde)) and np.all(f.mde > 0)
        assert np.all(f.depth_gt >= 0) and np.all(f.depth_gt <= f.max_depth)
        assert f.kind == kind and f.seed == 0 and f.index == 0

    def test_notes_say_simulated(self, street_frame):
        assert "SIMULATED" in street_frame.notes
        assert "mde: SIMULATED monocular depth" in street_frame.notes
        assert "simulated" in make_scene.__doc__.lower() or "SIMULATED" in make_scene.__doc__

    def test_deterministic_for_a_seed(self):
        a = make_scene(3, width=64, height=24, lidar=COARSE)
        b = make_scene(3, width=64, height=24, lidar=COARSE)
        for name in ("rgb", "depth_gt", "mde", "lidar_points", "T_world_camera"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(a.lidar.uv, b.lidar.uv)
        np.testing.assert_array_equal(a.lidar.depth, b.lidar.depth)

    def test_seeds_differ(self):
        a = make_scene(1, width=64, height=24, lidar=COARSE)
        b = make_scene(2, width=64, height=24, lidar=COARSE)
        assert not np.array_equal(a.depth_gt, b.depth_gt)
        assert not np.array_equal(a.rgb, b.rgb)

    def test_sizes_are_arguments(self):
        f = make_scene(0, kind="room", width=40, height=30, lidar=COARSE)
        assert f.rgb.shape == (30, 40, 3) and f.camera.width == 40 and f.camera.height == 30
        assert len(f.lidar) > 0

    def test_street_has_sky_without_depth_room_is_closed(self, street_frame, room_frame):
        sky = street_frame.depth_gt == 0
        assert 0 < sky.mean() < 0.3
        assert sky[:5].any() and not sky[-5:].any()  # sky at the top, ground at the bottom
        assert np.all(room_frame.depth_gt > 0)
        assert 0.3 < room_frame.depth_gt.min() and room_frame.depth_gt.max() < 10.0

    def test_images_are_textured(self, street_frame, room_frame):
        for f in (street_frame, room_frame):
            assert np.all(f.rgb.reshape(-1, 3).std(axis=0) > 10)
            assert len(np.unique(f.rgb.reshape(-1, 3), axis=0)) > 500

    def test_ground_depth_matches_geometry(self, street_frame):
        # Road pixels: the camera is 1.65 m above a flat ground, looking level, so z = 1.65 fy / (v - cy).
        cam = street_frame.camera
        v = cam.height - 1
        u = cam.width // 2
        expected = 1.65 * cam.fy / (v - cam.cy)
        assert street_frame.depth_gt[v, u] == pytest.approx(expected, rel=1e-9)

    @pytest.mark.parametrize(
        "kwargs, argument",
        [
            ({"kind": "forest"}, "kind"),
            ({"width": 4}, "width"),
            ({"height": 10.5}, "height"),
            ({"width": True}, "width"),
        ],
    )
    def test_bad_arguments(self, kwargs, argument):
        with pytest.raises(InvalidInputError) as info:
            make_scene(0, **kwargs)
        assert info.value.argument == argument

    @pytest.mark.parametrize("seed", [-1, 1.5, "0", None])
    def test_bad_seed(self, seed):
        with pytest.raises(InvalidInputError):
            make_scene(seed)


class TestLidar:
    @pytest.mark.parametrize("kind", ["street", "room"])
    def test_noise_free_lidar_equals_depth_gt(self, kind):
        f = make_scene(0, kind=kind, lidar=NOISE_FREE)
        rows, cols = f.lidar.v.astype(int), f.lidar.u.astype(int)
        assert len(f.lidar) > 500
        np.testing.assert_allclose(f.lidar.depth, f.depth_gt[rows, cols], atol=1e-6, rtol=0)

    def test_points_only_where_a_beam_hits(self, street_frame):
        f = street_frame
        rows, cols = f.lidar.v.astype(int), f.lidar.u.astype(int)
        assert np.all(f.depth_gt[rows, cols] > 0)  # never in the sky
        # Every raw return lies on one of the 64 beams ...
        p = f.lidar_points
        elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        beams = np.asarray(HDL64_ELEVATIONS_DEG)
        assert np.abs(elevation[:, None] - beams[None]).min(axis=1).max() < 1e-9
        # Beams between +2 deg and the image's lowest ray (about -16 deg at the corners) are seen.
        lowest = -np.degrees(np.arctan((f.camera.height - 0.5 - f.camera.cy) / f.camera.fy))
        assert len(np.unique(np.round(elevation, 6))) >= np.sum(beams > lowest)
        # ... and every measured pixel is the projection of a raw return.
        raw = project_points(transform_points(f.T_camera_lidar, p), f.camera)
        assert _pixels(f.lidar) <= _pixels(raw)
        # The top beam is at +2 deg: the image rows above it (the upper 35 %) carry no measurement.
        top_row = f.camera.cy - f.camera.fy * np.tan(np.radians(2.0))
        assert f.lidar.v.min() >= np.floor(top_row) - 1
        assert 0.05 < len(f.lidar) / f.depth_gt.size < 0.7

    def test_raw_mode_is_the_projected_scan(self):
        lidar = LidarModel(noise=0.0, snap_to_pixel_centres=False, offset=(0.0, -0.08, -0.27))
        f = make_scene(0, lidar=lidar)
        calib = LidarCalibration(np.hstack([f.K, np.zeros((3, 1))]), f.T_camera_lidar)
        expected = calib.project(f.lidar_points[f.lidar_points[:, 0] > 0], f.camera.shape)
        expected = expected.subset(expected.depth <= f.max_depth)
        np.testing.assert_array_equal(f.lidar.uv, expected.uv)
        np.testing.assert_allclose(f.lidar.depth, expected.depth, rtol=1e-12)
        # The LiDAR sits 8 cm above and 27 cm behind the camera.
        np.testing.assert_allclose(f.T_camera_lidar[:3, 3], [0.0, -0.08, -0.27], atol=1e-12)
        # Raw z-depths differ from the pixel-centre depth by sub-pixel offsets only (on most pixels).
        gt = f.depth_gt[f.lidar.v.astype(int), f.lidar.u.astype(int)]
        rel = np.abs(f.lidar.depth - gt) / gt
        assert np.median(rel) < 0.02

    def test_noise_level(self):
        f = make_scene(0, width=160, height=48, lidar=LidarModel(noise=0.05, azimuth_step_deg=0.2))
        gt = f.depth_gt[f.lidar.v.astype(int), f.lidar.u.astype(int)]
        assert np.std(f.lidar.depth - gt) == pytest.approx(0.05, rel=0.1)
        assert np.all(np.isnan(f.lidar.sigma))  # sigma left to the model default

    def test_vlp16_is_sparser(self, room_frame):
        f = make_scene(0, kind="room", lidar=LidarModel.vlp16(noise=0.0))
        assert 0 < len(f.lidar) < len(room_frame.lidar) / 2

    @pytest.mark.parametrize(
        "kwargs",
        [
            {"elevations_deg": ()},
            {"elevations_deg": (95.0,)},
            {"azimuth_step_deg": 0.0},
            {"noise": -0.1},
            {"min_range": float("nan")},
            {"offset": (0.0, 1.0)},
        ],
    )
    def test_bad_model(self, kwargs):
        with pytest.raises(InvalidInputError):
            LidarModel(**kwargs)

    def test_scan_lidar_directly(self):
        scene = build_scene(0, kind="room")
        cam = default_camera("room", width=32, height=24)
        T = pose_from_position_yaw_pitch((0.0, -2.0, 1.4))
        depth, _ = scene.render(cam, T)
        sparse, pts, T_cl = scan_lidar(scene, cam, T, NOISE_FREE, depth, np.random.default_rng(0))
        assert pts.shape[1] == 3 and len(sparse) > 0
        np.testing.assert_allclose(sparse.depth, depth[sparse.v.astype(int), sparse.u.astype(int)], atol=1e-9)


class TestSimulateMDE:
    @pytest.mark.parametrize("kind", ["street", "room"])
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_error_in_documented_range(self, kind, seed):
        size = dict(width=96, height=32) if kind == "street" else dict(width=64, height=48)
        f = make_scene(seed, kind=kind, lidar=COARSE, **size)
        valid = f.depth_gt > 0
        rel = (f.mde[valid] - f.depth_gt[valid]) / f.depth_gt[valid]
        rel_rms = float(np.sqrt(np.mean(rel**2)))
        assert 0.10 <= rel_rms <= 0.30
        # Most of the error is the global scale: aligning it removes much of the error.
        s = np.median(f.depth_gt[valid] / f.mde[valid])
        rel_aligned = (s * f.mde[valid] - f.depth_gt[valid]) / f.depth_gt[valid]
        assert np.sqrt(np.mean(rel_aligned**2)) < 0.7 * rel_rms

    def test_perfect_simulation_returns_gt(self):
        gt = np.full((20, 30), 4.0)
        gt[5:10, 5:10] = 2.0
        gt[0, :] = 0.0
        sim = MDESimulation(scale=1.0, blur_sigma=0.0, field_amplitude=0.0, noise=0.0)
        out = simulate_mde(gt, sim, np.random.default_rng(0), fill_depth=50.0)
        np.testing.assert_allclose(out[1:], gt[1:], rtol=1e-12)
        np.testing.assert_allclose(out[0], 50.0)

    def test_nearest_fill_without_fill_depth(self):
        gt = np.full((20, 30), 4.0)
        gt[:, 20:] = 8.0
        gt[:, 18:22] = 0.0  # a hole between the two depths
        gt[0, 0] = np.nan
        sim = MDESimulation(scale=1.0, blur_sigma=0.0, field_amplitude=0.0, noise=0.0)
        out = simulate_mde(gt, sim, np.random.default_rng(0))
        np.testing.assert_allclose(out[:, :18], 4.0)
        np.testing.assert_allclose(out[:, 18:20], 4.0)  # nearest is the left side
        np.testing.assert_allclose(out[:, 20:], 8.0)
        with pytest.raises(EmptyInputError):
            simulate_mde(np.zeros((4, 4)), sim, np.random.default_rng(0))
        with pytest.raises(ShapeError):
            simulate_mde(np.ones(4), sim, np.random.default_rng(0))

    def test_scale_error_only(self):
        gt = np.linspace(1.0, 5.0, 600).reshape(20, 30)
        sim = MDESimulation(scale=1.3, blur_sigma=0.0, field_amplitude=0.0, noise=0.0)
        np.testing.assert_allclose(simulate_mde(gt, sim, np.random.default_rng(0), fill_depth=9.0), 1.3 * gt)

    def test_field_is_smooth_and_sized(self):
        gt = np.full((60, 80), 5.0)
        sim = MDESimulation(scale=1.0, blur_sigma=0.0, field_amplitude=0.1, field_lengthscale=0.25, noise=0.0)
        log_err = np.log(simulate_mde(gt, sim, np.random.default_rng(1), fill_depth=9.0) / gt)
        assert np.std(log_err) == pytest.approx(0.1, rel=0.05)
        assert np.abs(np.diff(log_err, axis=1)).max() < 0.02  # low frequency: tiny pixel-to-pixel change

    @pytest.mark.parametrize(
        "kwargs", [{"scale": 0.0}, {"blur_sigma": -1.0}, {"field_amplitude": float("inf")}, {"field_lengthscale": 0.0}]
    )
    def test_bad_simulation(self, kwargs):
        with pytest.raises(InvalidInputError):
            MDESimulation(**kwargs)


class TestSequence:
    def test_frames_and_poses(self):
        frames = list(sequence(0, n_frames=3, width=64, height=24, lidar=COARSE))
        assert [f.index for f in frames] == [0, 1, 2]
        np.testing.assert_allclose(frames[1].T_world_camera[:3, 3] - frames[0].T_world_camera[:3, 3], [0, 1, 0])
        first = make_scene(0, width=64, height=24, lidar=COARSE)
        np.testing.assert_array_equal(frames[0].depth_gt, first.depth_gt)
        np.testing.assert_array_equal(frames[0].mde, first.mde)
        assert not np.array_equal(frames[1].mde, frames[0].mde)

    @pytest.mark.parametrize("kind", ["street", "room"])
    def test_static_scene_is_consistent_across_frames(self, kind):
        f0, f1 = list(sequence(0, kind=kind, n_frames=2, width=80, height=40, lidar=COARSE))
        points, _ = f0.camera.backproject(f0.depth_gt)
        world = transform_points(f0.T_world_camera, points)
        in_1 = transform_points(np.linalg.inv(f1.T_world_camera), world)
        uv, z = f1.camera.project(in_1)
        seen = (z > 0.1) & f1.camera.in_image(uv)
        scene = build_scene(0, kind=kind)
        rendered = scene.depth_at(f1.camera, f1.T_world_camera, uv[seen])
        agree = np.abs(rendered - z[seen]) < 1e-6 * z[seen]
        assert seen.mean() > 0.5 and agree.mean() > 0.85  # the rest is occluded in frame 1

    @pytest.mark.parametrize("kwargs", [{"n_frames": 0}, {"n_frames": 2.0}, {"step": float("nan")}])
    def test_bad_arguments(self, kwargs):
        with pytest.raises(InvalidInputError):
            next(sequence(0, **kwargs))


class TestSceneGeometry:
    def test_culling_does_not_change_hits(self):
        scene = build_scene(0)
        cam = default_camera("street", width=64, height=24)
        T = pose_from_position_yaw_pitch((1.8, 0.0, 1.65))
        u, v = cam.pixel_grid()
        d = np.stack([(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy, np.ones(u.size)], 1) @ T[:3, :3].T
        t1, i1, n1 = scene.cast(T[:3, 3], d)
        t2, i2, n2 = scene.cast(np.broadcast_to(T[:3, 3], d.shape).copy(), d)
        np.testing.assert_array_equal(i1, i2)
        np.testing.assert_array_equal(t1, t2)
        np.testing.assert_array_equal(n1, n2)

    def test_box_hit_from_outside_and_inside(self):
        from gpdepth3d.datasets.synthetic import _box

        box = _box((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), (1, 1, 1), "plain", yaw=0.0)
        t, n = box.intersect(np.array([[-5.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-5.0, 3.0, 0.0]]), np.eye(3)[[0, 1, 0]])
        np.testing.assert_allclose(t[:2], [4.0, 1.0])
        assert np.isinf(t[2])
        np.testing.assert_allclose(n[0], [-1, 0, 0])
        np.testing.assert_allclose(n[1], [0, -1, 0])  # exit face, normal facing the origin

    def test_turned_box(self):
        from gpdepth3d.datasets.synthetic import _box

        box = _box((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), (1, 1, 1), "plain", yaw=np.pi / 4)
        t, _ = box.intersect(np.array([[-5.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
        np.testing.assert_allclose(t, [5.0 - np.sqrt(2.0)])


class TestCameraAndPose:
    def test_default_camera(self):
        cam = default_camera("street")
        assert cam.shape == (96, 320) and cam.fx == pytest.approx(0.581 * 320)
        assert default_camera("room").shape == (120, 160)
        with pytest.raises(InvalidInputError):
            default_camera("moon")

    def test_pose_conventions(self):
        T = check_pose(pose_from_position_yaw_pitch((1.0, 2.0, 3.0)))
        np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)  # optical axis along +y (north)
        np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # image down is world down
        np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
        T = check_pose(pose_from_position_yaw_pitch((0, 0, 0), yaw_deg=90.0))
        np.testing.assert_allclose(T[:3, 2], [-1, 0, 0], atol=1e-12)  # turned left: looks west
        T = check_pose(pose_from_position_yaw_pitch((0, 0, 0), pitch_deg=30.0))
        assert T[2, 2] == pytest.approx(np.sin(np.radians(30.0)))
