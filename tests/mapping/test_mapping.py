"""Tests of gpdepth3d.mapping: SLAM map points, the incremental Mapper, mesh metrics, `gpdepth3d fuse`."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, DataFormatError, EmptyInputError, InvalidInputError, ShapeError
from gpdepth3d.mapping.tsdf.fusion import FusionConfig
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import CalibrationConfig, DepthGPConfig
from gpdepth3d.mapping import Mapper, MapperConfig, merge_sparse, project_map_points, sparse_from_map_points
from gpdepth3d.cli.fuse import fuse_command
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.mapping.points.triangulation import TriangulationConfig
from gpdepth3d.metrics import mesh_metrics

CAM = PinholeCamera(100.0, 100.0, 39.5, 29.5, 80, 60)


def _pose(seed: int) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rng.normal(size=3) * 0.3)[0]
    T[:3, 3] = rng.normal(size=3)
    return T


class TestSparseHelpers:
    def test_map_points_project_to_their_depth(self):
        rng = np.random.default_rng(0)
        uv = np.stack([rng.integers(0, 80, 50), rng.integers(0, 60, 50)], 1).astype(float)
        z = rng.uniform(1, 5, 50)
        pts_cam = CAM.backproject_pixels(uv, z)
        T = _pose(1)
        world = pts_cam @ T[:3, :3].T + T[:3, 3]
        behind = world[:5] - 10 * (T[:3, :3] @ [0, 0, 1])  # points behind the camera are dropped
        sparse = sparse_from_map_points(np.vstack([world, behind]), T, CAM, sigma=0.02)
        expected = SparseDepth.from_arrays(uv[:, 0], uv[:, 1], z, CAM.shape).rasterize()
        assert len(sparse) == len(expected)
        order_s = np.lexsort((sparse.u, sparse.v))
        order_e = np.lexsort((expected.u, expected.v))
        np.testing.assert_allclose(sparse.depth[order_s], expected.depth[order_e], atol=1e-9)
        np.testing.assert_allclose(sparse.sigma, 0.02)
        with pytest.raises(ShapeError):
            sparse_from_map_points(world[:, :2], T, CAM)
        with pytest.raises(CalibrationError):
            sparse_from_map_points(world, T * 2, CAM)

    def test_merge_keeps_closest(self):
        a = SparseDepth.from_arrays([1.0, 5.0], [1.0, 2.0], [2.0, 3.0], (10, 10), 0.1)
        b = SparseDepth.from_arrays([1.0], [1.0], [1.5], (10, 10), 0.2)
        m = merge_sparse(a, b, image_size=(10, 10))
        assert len(m) == 2
        np.testing.assert_allclose(sorted(m.depth), [1.5, 3.0])
        assert len(merge_sparse(image_size=(10, 10))) == 0
        with pytest.raises(ShapeError):
            merge_sparse(a, SparseDepth.from_arrays([1.0], [1.0], [1.0], (5, 5)), image_size=(10, 10))


class TestMeshMetrics:
    def test_identical_and_shifted(self):
        import trimesh

        box = trimesh.creation.box((1.0, 1.0, 1.0))
        same = mesh_metrics(box, box, samples=5000)
        assert same["chamfer"] < 0.03 and same["precision"] > 0.99 and same["recall"] > 0.99
        shifted = box.copy()
        shifted.apply_translation([0.0, 0.0, 0.2])
        m = mesh_metrics(shifted, box, samples=5000, threshold=0.05)
        assert m["precision"] < 0.9 and m["recall"] < 0.9
        # a sub-mesh is precise but incomplete
        half = box.submesh([np.arange(6)], append=True)
        h = mesh_metrics(half, box, samples=5000)
        assert h["precision"] > 0.99 and h["recall"] < 0.7
        assert h["accuracy"] < h["completeness"]
        with pytest.raises(EmptyInputError):
            mesh_metrics(trimesh.Trimesh(), box)


ROOT = Path(__file__).resolve().parents[2]


def _frames(shared_data: Path, indices):
    from gpdepth3d.datasets.sevenscenes import SevenScenes

    reader = SevenScenes(shared_data / "7scenes")
    return [reader[i] for i in indices]


def _standin_mde(depth: np.ndarray) -> np.ndarray:
    """STAND-IN MDE for tests: the Kinect depth degraded (hole-filled, blurred, 12 % too far)."""
    import cv2
    from scipy.ndimage import distance_transform_edt

    valid = depth > 0
    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    filled = depth[ri, ci]
    return 1.12 * cv2.GaussianBlur(filled.astype(np.float32), (0, 0), 6).astype(np.float64)


class TestMapper:
    def test_map_points_refine_towards_truth(self, shared_data):
        from gpdepth3d.measurements import project_points

        frames = _frames(shared_data, (0, 3))
        cam = frames[0].camera
        config = MapperConfig(
            triangulate=False,
            working_scale=0.25,
            gp=DepthGPConfig.residual(),
            fusion=FusionConfig(voxel_size=0.04, truncation=0.12),
        )
        mapper = Mapper(cam, config)
        rng = np.random.default_rng(0)
        for f in frames:
            pts, _ = cam.backproject(f.depth)
            pts = pts[rng.choice(len(pts), 150, replace=False)]
            world = pts @ f.pose[:3, :3].T + f.pose[:3, 3]
            res = mapper.add_frame(
                f.rgb, f.pose, mde_depth=_standin_mde(f.depth), map_points_world=world, map_points_sigma=0.01
            )
            gt = project_points(cam.backproject(f.depth)[0], mapper.work_camera).to_depth_map()
            ok = gt > 0
            err_mde = np.median(np.abs(res.mde[ok] - gt[ok]))
            err_gp = np.median(np.abs(res.depth[ok] - gt[ok]))
            assert err_gp < 0.5 * err_mde
            assert len(res.sparse) > 100 and np.all(np.isfinite(res.variance))
            assert set(res.timings) == {"mde", "points", "gp", "fusion", "total"}
            assert res.fused and res.error is None and res.map_points.given == 150 and not res.pose_check.inverted
        mesh = mapper.mesh()
        assert len(mesh.faces) > 100
        cloud = mapper.point_cloud()
        assert len(cloud) > 100

    def test_triangulation_front_end_and_baseline(self, shared_data):
        frames = _frames(shared_data, (40, 44))
        cam = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
        calls = []

        def front_end(rgb):
            calls.append(rgb.shape)
            return np.full((120, 160), 2.0)  # any resolution of the same aspect ratio

        config = MapperConfig(
            working_scale=0.25,
            max_points=80,
            gp=DepthGPConfig.residual(),
            fusion=FusionConfig(voxel_size=0.05, truncation=0.15),
            triangulation=TriangulationConfig(detector="orb"),
        )
        mapper = Mapper(cam, config, mde=front_end)
        first = mapper.add_frame(frames[0].rgb, frames[0].pose)
        assert len(first.sparse) == 0  # nothing to triangulate against yet
        second = mapper.add_frame(frames[1].rgb, frames[1].pose)
        assert 10 < len(second.sparse) <= 80
        assert np.all(np.isfinite(second.sparse.sigma)) and np.all(second.sparse.sigma > 0)
        assert calls == [(480, 640, 3)] * 2
        # the refined depth moved from the constant stand-in towards the triangulated depths
        iu = np.rint(second.sparse.uv * 0.25).astype(int).clip(0, [159, 119])
        at_points = second.depth[iu[:, 1], iu[:, 0]]
        assert np.median(np.abs(at_points - second.sparse.depth)) < 0.5 * np.median(np.abs(2.0 - second.sparse.depth))

    def test_mde_only_mode(self, shared_data):
        f = _frames(shared_data, (0,))[0]
        mapper = Mapper(
            f.camera,
            MapperConfig(
                refine=False,
                triangulate=False,
                working_scale=0.25,
                fusion=FusionConfig(voxel_size=0.04, truncation=0.12),
            ),
        )
        res = mapper.add_frame(f.rgb, f.pose, mde_depth=f.depth)
        assert res.posterior is None and np.all(np.isnan(res.variance))
        assert mapper.fusion.config.weighting == "uniform"

    def test_errors(self, tmp_path: Path):
        mapper = Mapper(CAM, MapperConfig(triangulate=False, gp=DepthGPConfig.residual()))
        rgb = np.zeros((60, 80, 3), np.uint8)
        with pytest.raises(EmptyInputError):
            mapper.mesh()
        with pytest.raises(InvalidInputError):
            mapper.add_frame(rgb, np.eye(4))  # no MDE and no front-end
        with pytest.raises(ShapeError):
            mapper.add_frame(np.zeros((61, 80, 3), np.uint8), np.eye(4), mde_depth=np.ones((60, 80)))
        with pytest.raises(ShapeError):
            mapper.add_frame(rgb, np.eye(4), mde_depth=np.ones((60, 60)))
        bad = np.eye(4)
        bad[0, 1] = 0.5
        with pytest.raises(CalibrationError):
            mapper.add_frame(rgb, bad, mde_depth=np.ones((60, 80)))
        with pytest.raises(InvalidInputError):
            Mapper(CAM, mde="fastdepth")  # type: ignore[arg-type]
        with pytest.raises(InvalidInputError):
            MapperConfig(working_scale=2.0)
        for bad_id in ("a", float("nan"), 1.5, True, object()):
            with pytest.raises(InvalidInputError, match="keyframe_id"):
                mapper.add_frame(rgb, np.eye(4), mde_depth=np.ones((60, 80)), keyframe_id=bad_id)
        for bad_sigma in ("x", -1.0, float("nan"), np.ones((2, 2)), [0.1, "y"]):
            with pytest.raises(InvalidInputError, match="map_points_sigma"):
                mapper.add_frame(
                    rgb,
                    np.eye(4),
                    mde_depth=np.ones((60, 80)),
                    map_points_world=np.ones((2, 3)),
                    map_points_sigma=bad_sigma,
                )
        assert mapper.frames == 0 and not mapper.pending  # refused before anything was added
        empty = mapper.add_frame(rgb, np.eye(4), mde_depth=np.zeros((60, 80)))  # data, not an error
        assert not empty.fused and empty.error.startswith("frame 0: ") and mapper.failures == [empty.error]
        assert mapper.frames == 0 and not mapper.keyframes


class TestFuseCommand:
    @pytest.mark.slow
    def test_writes_meshes_and_metrics(self, shared_data, tmp_path: Path):
        model = shared_data.parent / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip(f"FastDepth model not found at {model}")
        pytest.importorskip("ai_edge_litert")
        out = tmp_path / "fuse"
        # 4 frames: with 3 the tracker triangulates no point, every pixel keeps the GP prior's sigma (> 20 %
        # of depth, FusionConfig.max_relative_sigma) and the variance-weighted mesh is empty (reported, not written)
        summary = fuse_command(
            shared_data / "7scenes",
            out,
            mde=str(model),
            frames=4,
            working_scale=0.25,
            voxel_size=0.05,
            truncation=0.15,
            sigma_ref=1.0,
            metric_samples=5000,
        )
        names = sorted(p.name for p in out.iterdir())
        assert names == ["mesh_gp_uniform.ply", "mesh_gp_variance.ply", "mesh_gt.ply", "mesh_mde.ply", "metrics.json"]
        on_disk = json.loads((out / "metrics.json").read_text())
        assert on_disk["frames"] == 4 == summary["frames"]
        for variant in ("mde", "gp_uniform", "gp_variance"):
            m = on_disk["metrics"][variant]
            assert 0 <= m["precision"] <= 1 and 0 <= m["recall"] <= 1 and m["chamfer"] > 0


def _kinect_sparse(frame, camera: PinholeCamera, n: int, seed: int) -> SparseDepth:
    """n Kinect depth samples of a frame as measurements (sigma 1 cm)."""
    rng = np.random.default_rng(seed)
    v, u = np.nonzero(frame.depth > 0)
    i = rng.choice(len(u), n, replace=False)
    return SparseDepth.from_arrays(u[i].astype(float), v[i].astype(float), frame.depth[v[i], u[i]], camera.shape, 0.01)


def _world_points(frame, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts, _ = frame.camera.backproject(frame.depth)
    pts = pts[rng.choice(len(pts), n, replace=False)]
    return pts @ frame.pose[:3, :3].T + frame.pose[:3, 3]


def _small_config(**overrides) -> MapperConfig:
    # weights from sigma in metres (these tests' GP is the residual one, less certain in relative terms)
    base = dict(
        triangulate=False,
        working_scale=0.25,
        fusion=FusionConfig(voxel_size=0.04, truncation=0.12, relative_sigma_ref=None),
    )
    return MapperConfig(**{**base, **overrides})


def _sorted_voxels(fusion) -> dict:
    vox = fusion.voxels()
    order = np.lexsort(vox["coords"].T)
    return {k: v[order] for k, v in vox.items()}


class _NegativeCompleter:
    """A completer whose posterior mean dips below zero and has NaNs (what an outlier can do)."""

    def __init__(self):
        from gpdepth3d.completion.complete import DepthCompleter

        self.inner = DepthCompleter(DepthGPConfig.residual(), engine=EngineConfig(name="exact"))

    def complete(self, mde, sparse, *, output_shape=None):
        from dataclasses import replace as dc_replace

        post = self.inner.complete(mde, sparse, output_shape=output_shape)
        mean = post.mean.copy()
        mean[:2, :3] = -0.066
        mean[5, 5] = np.nan
        return dc_replace(post, mean=mean)


class TestRobustness:
    def test_outlier_map_point_does_not_crash(self, shared_data):
        # the case: one map point at 0.15 m where the surface is ~1.85 m, claimed sigma 2 mm
        f = _frames(shared_data, (0,))[0]
        cam = f.camera
        v, u = np.nonzero(np.abs(f.depth - 1.85) < 0.02)
        ray = cam.backproject_pixels(np.array([[u[0], v[0]]], float), np.array([0.15]))
        outlier = ray @ f.pose[:3, :3].T + f.pose[:3, 3]
        world = np.vstack([_world_points(f, 150, 0), outlier])
        sigma = np.r_[np.full(150, 0.01), 0.002]
        mapper = Mapper(cam, _small_config())
        res = mapper.add_frame(
            f.rgb, f.pose, mde_depth=_standin_mde(f.depth), map_points_world=world, map_points_sigma=sigma
        )
        assert res.fused and res.error is None
        assert np.all(np.isfinite(res.depth)) and res.depth.min() >= 0
        assert res.map_points.given == 151 and res.map_points.outside == 0
        mapper.mesh()  # one frame may not pass the weight threshold yet: a mesh without faces, not an error
        mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth), map_points_world=world, map_points_sigma=sigma)
        assert len(mapper.mesh().faces) > 100 and len(mapper.point_cloud()) > 100

    def test_negative_and_nan_mean_masked_and_counted(self, shared_data):
        f = _frames(shared_data, (0,))[0]
        mapper = Mapper(f.camera, _small_config(held_out=0.0), completer=_NegativeCompleter())
        res = mapper.add_frame(
            f.rgb, f.pose, mde_depth=_standin_mde(f.depth), sparse=_kinect_sparse(f, f.camera, 100, 0)
        )
        assert res.fused and res.masked_pixels == 7 and not res.mde_fallback and res.held_out is None
        assert res.depth[0, 0] == 0 and res.depth[5, 5] == 0 and np.all(np.isfinite(res.depth))
        assert any("7 pixels" in w for w in res.warnings)
        assert mapper.keyframes[0].depth[0, 0] == 0

    def test_a_refinement_worse_than_the_rescaled_mde_falls_back_to_it(self, shared_data):
        # the broken posterior (negative and NaN means) predicts the held-out points worse than the MDE
        # rescaled by one median: the frame is fused as that MDE, with its variance, and says so
        f = _frames(shared_data, (0,))[0]
        mapper = Mapper(f.camera, _small_config(), completer=_NegativeCompleter())
        mde = _standin_mde(f.depth)
        res = mapper.add_frame(f.rgb, f.pose, mde_depth=mde, sparse=_kinect_sparse(f, f.camera, 100, 0))
        assert res.fused and res.mde_fallback and res.held_out.held_out == 20 and res.posterior is None
        assert res.masked_pixels == 0 and np.all(res.variance >= 0)
        np.testing.assert_allclose(res.depth[res.mde > 0], (res.mde * res.held_out.mde_scale)[res.mde > 0], rtol=1e-5)
        assert any("held-out points worse than the MDE" in w for w in res.warnings)
        assert res.fallback_weight == mapper.fusion.config.fallback_for(0)

    def test_the_held_out_gp_runs_on_the_coarse_grid_and_the_frame_on_the_full_one(self, shared_data):
        from gpdepth3d.mapping.mde_check import held_out_shape

        f = _frames(shared_data, (0,))[0]
        completer = _NegativeCompleter()
        shapes = []

        def recording(mde, sparse, *, output_shape=None):
            shapes.append((len(sparse), tuple(output_shape)))
            return _NegativeCompleter.complete(completer, mde, sparse, output_shape=output_shape)

        completer.complete = recording
        mapper = Mapper(f.camera, _small_config(), completer=completer)
        res = mapper.add_frame(
            f.rgb, f.pose, mde_depth=_standin_mde(f.depth), sparse=_kinect_sparse(f, f.camera, 100, 0)
        )
        work = mapper.work_camera.shape
        assert shapes[0] == (80, held_out_shape(work)) and res.held_out.held_out == 20
        assert shapes[1:] == ([] if res.mde_fallback else [(100, work)])

    def test_bad_frames_are_recorded_and_the_sequence_goes_on(self, shared_data):
        frames = _frames(shared_data, (0, 1, 2, 3))
        cam = frames[0].camera
        calls = []

        def flaky(rgb):
            calls.append(1)
            if len(calls) == 2:
                raise RuntimeError("front-end hiccup")
            depth = _standin_mde(frames[len(calls) - 1].depth)
            if len(calls) == 3:
                depth = np.zeros_like(depth)  # an empty frame
            if len(calls) == 4:
                depth[:100] = np.nan  # NaN depths
            return depth

        mapper = Mapper(cam, _small_config(), mde=flaky)
        sparse = [_kinect_sparse(f, cam, 80, i) for i, f in enumerate(frames)]
        sparse[2] = None  # frame 2: nothing at all
        results = [mapper.add_frame(f.rgb, f.pose, sparse=s) for f, s in zip(frames, sparse)]
        assert [r.fused for r in results] == [True, False, False, True]
        assert results[1].error == "frame 1: mde: RuntimeError: front-end hiccup"
        assert results[2].error.startswith("frame 2: gp: ")
        assert mapper.failures == [results[1].error, results[2].error]
        assert sorted(mapper.keyframes) == [0, 3] and mapper.frames == 2
        assert len(mapper.mesh().faces) > 100

    def test_inverted_pose_and_points_outside_are_reported(self, shared_data):
        from gpdepth3d.io.poses import InvertedPoseWarning, invert_pose

        f = _frames(shared_data, (0,))[0]
        world = _world_points(f, 200, 1)
        mapper = Mapper(f.camera, _small_config())
        with pytest.warns(InvertedPoseWarning, match="frame 0: "):
            res = mapper.add_frame(f.rgb, invert_pose(f.pose), mde_depth=_standin_mde(f.depth), map_points_world=world)
        assert res.pose_check.inverted and res.pose_check.visible_inverse == 1.0
        assert res.map_points.used < 50 and res.map_points.outside + res.map_points.behind > 150
        assert any("looks inverted" in w for w in res.warnings) and any("outside the image" in w for w in res.warnings)
        # the flagged frame is reported by name and not fused; the run goes on
        assert (
            not res.fused
            and res.error.startswith("frame 0: pose check: CalibrationError")
            and mapper.failures == [res.error]
        )
        assert 0 not in mapper.keyframes and mapper.frames == 0
        forced = Mapper(f.camera, replace(_small_config(), fuse_inverted_poses=True))
        with pytest.warns(InvertedPoseWarning):
            res = forced.add_frame(f.rgb, invert_pose(f.pose), mde_depth=_standin_mde(f.depth), map_points_world=world)
        assert res.fused and res.error is None
        # a correct pose: map points with NaN rows and some outside the image are counted, not silently dropped
        cam_pts = np.array([[5.0, 0.0, 1.0], [0.0, 0.0, -1.0], [np.nan, 0.0, 1.0]])
        extra = cam_pts @ f.pose[:3, :3].T + f.pose[:3, 3]
        res = mapper.add_frame(
            f.rgb, f.pose, mde_depth=_standin_mde(f.depth), map_points_world=np.vstack([world, extra])
        )
        assert (res.map_points.outside, res.map_points.behind, res.map_points.nonfinite) == (1, 1, 1)
        assert not res.pose_check.inverted

    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_a_pose_the_feature_tracks_contradict_is_reported(self, shared_data):
        # own triangulation, no map points: an inverted pose, or another frame's, in the middle of a real
        # sequence leaves (almost) none of its tracks agreeing with it; that frame is warned about by name.
        # Exact poses are not, and neither are poses each off by 2 cm and 2 degrees (a SLAM back-end's)
        import importlib.util

        from gpdepth3d.mapping.frame_points import POSE_TRACK_SHARE
        from gpdepth3d.io.poses import InvertedPoseWarning, invert_pose

        spec = importlib.util.spec_from_file_location("bench", ROOT / "bench" / "mapping_sequences.py")
        bench = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(bench)
        frames = _frames(shared_data, range(0, 14))
        foreign = _frames(shared_data, [40])[0].pose
        config = MapperConfig(working_scale=0.25)  # the tracker's defaults: window 8, lag 4

        def run(poses):
            mapper = Mapper(frames[0].camera, config)
            results = []
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                for f, pose in zip(frames, poses):
                    r = mapper.add_frame(f.rgb, pose, mde_depth=_standin_mde(f.depth))
                    results += [r] if r is not None else []
                results += mapper.flush()
            tracked = [str(w.message) for w in caught if issubclass(w.category, InvertedPoseWarning)]
            return {r.keyframe_id: r for r in results}, tracked

        exact = [f.pose for f in frames]
        clean, tracked = run(exact)
        assert tracked == [] and not any("feature tracks" in w for r in clean.values() for w in r.warnings)
        assert all(len(clean[k].sparse) >= 60 for k in range(3, 14))  # every clean frame triangulates
        _, tracked = run(bench.perturb_poses(exact, 2.0, 2.0, seed=0))
        assert tracked == []
        for name, pose in (("inverted", invert_pose(exact[7])), ("foreign", foreign)):
            bad, tracked = run(exact[:7] + [pose] + exact[8:])
            assert any(m.startswith("frame 7: only ") and "feature tracks agree" in m for m in tracked), name
            message = [w for w in bad[7].warnings if "feature tracks agree" in w]
            assert len(message) == 1
            agree, seen = (int(x) for x in re.match(r"frame 7: only (\d+) of (\d+) ", message[0]).groups())
            assert seen >= 50 and agree < POSE_TRACK_SHARE * seen, name

    def test_project_map_points_counts(self):
        pts = CAM.backproject_pixels(np.array([[10.0, 10.0], [10.0, 10.0], [50.0, 20.0]]), np.array([2.0, 3.0, 2.5]))
        pts = np.vstack([pts, [[100.0, 0.0, 1.0]], [[0.0, 0.0, -2.0]], [[np.inf, 0.0, 1.0]]])
        sparse, stats = project_map_points(pts, np.eye(4), CAM, sigma=np.arange(1.0, 7.0))
        assert (stats.given, stats.nonfinite, stats.behind, stats.outside, stats.used) == (6, 1, 1, 1, 2)
        np.testing.assert_allclose(sorted(sparse.depth), [2.0, 2.5])
        np.testing.assert_allclose(sparse.sigma[np.argsort(sparse.depth)], [1.0, 3.0])
        with pytest.raises(ShapeError):
            project_map_points(pts, np.eye(4), CAM, sigma=np.ones(4))


def _assert_stored_voxels_close(a: dict, b: dict, refused: bool = False) -> None:
    """The voxels ``b`` of a saved and loaded volume are those of ``a`` within what the saved forms keep
    (`gpdepth3d.mapping.compact_arrays`); ``refused``: ``b`` was partly re-fused from stored keyframes."""
    assert a.keys() == b.keys()
    if refused:  # a band edge may move by a voxel where a depth moved by its rounding
        ka, kb = (np.ascontiguousarray(np.rint(x["coords"] * 1000).astype(np.int64)) for x in (a, b))
        common, ia, ib = np.intersect1d(ka.view("V24").ravel(), kb.view("V24").ravel(), return_indices=True)
        assert common.size >= 0.999 * max(len(ka), len(kb))
        a, b = {k: v[ia] for k, v in a.items()}, {k: v[ib] for k, v in b.items()}
    np.testing.assert_array_equal(a["coords"], b["coords"])
    # a depth's rounding (<= 2^-11 of it: ~1 mm at 2 m) moves a signed distance by up to ~1 mm / truncation
    atol = {"tsdf": 0.02, "color": 2 / 255} if refused else {"tsdf": 1.01 / 32767, "color": 0.5 / 255}
    rtol = 5e-3 if refused else 1e-3
    for k in a:
        if k == "coords":
            continue
        close = np.isclose(b[k], a[k], rtol=rtol, atol=atol.get(k, 0.0)) | (np.isnan(a[k]) & np.isnan(b[k]))
        if refused:  # voxels at a band edge gain or lose a frame; the rest agree
            assert close.mean() >= 0.99, (k, close.mean())
        else:
            assert close.all(), (k, np.flatnonzero(~close)[:5])


class TestLoopClosure:
    def _run(self, frames, poses, config, sparse):
        mapper = Mapper(frames[0].camera, config)
        for i, (f, T) in enumerate(zip(frames, poses)):
            r = mapper.add_frame(f.rgb, T, mde_depth=_standin_mde(f.depth), sparse=sparse[i])
            assert r.fused
        return mapper

    @pytest.mark.parametrize("truncation_sigma", [0.0, 1.0])
    def test_update_poses_equals_fusing_from_scratch(self, shared_data, tmp_path: Path, truncation_sigma):
        import cv2

        frames = _frames(shared_data, (0, 4, 8, 30, 34))
        # with the truncation from the variance the moved frame's band is found from its stored variance
        fusion = FusionConfig(voxel_size=0.04, truncation=0.12, truncation_sigma=truncation_sigma, truncation_max=0.4)
        config = _small_config(gp=DepthGPConfig.residual(), fusion=fusion)
        sparse = [_kinect_sparse(f, f.camera, 80, i) for i, f in enumerate(frames)]
        poses = [f.pose for f in frames]
        mapper = self._run(frames, poses, config, sparse)
        mesh_before = mapper.mesh()
        moved = poses[3].copy()
        moved[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0] @ moved[:3, :3]
        moved[:3, 3] += [0.1, 0.0, 0.0]
        new_poses = list(poses)
        new_poses[3] = moved
        assert mapper.update_poses({0: poses[0]}).moved == ()  # nothing moved: nothing done
        update = mapper.update_poses({3: moved, 1: poses[1]})
        assert update.moved == (3,) and 3 in update.reintegrated and update.blocks > 0
        assert update.blocks < 0.8 * mapper.fusion.vbg.hashmap().size()  # only the blocks the moved frame reached
        scratch = self._run(frames, new_poses, config, sparse)
        a, b = _sorted_voxels(mapper.fusion), _sorted_voxels(scratch.fusion)
        assert a.keys() == b.keys() and a["coords"].shape == b["coords"].shape
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        assert not np.array_equal(mesh_before.vertices.shape, mapper.mesh().vertices.shape) or not np.allclose(
            np.sort(mesh_before.vertices, axis=0), np.sort(mapper.mesh().vertices, axis=0)
        )
        with pytest.raises(InvalidInputError):
            mapper.update_poses({99: moved})
        with pytest.raises(CalibrationError):
            mapper.update_poses({3: 2 * moved})

        # save and load: the same volume and keyframes; the loaded map goes on updating and fusing
        mapper.save(tmp_path / "map")
        assert sorted(p.name for p in (tmp_path / "map").iterdir()) == [
            "keyframes.npz",
            "mapper.json",
            "volume.json",
            "volume.npz",
        ]
        loaded = Mapper.load(tmp_path / "map")
        _assert_stored_voxels_close(a, _sorted_voxels(loaded.fusion))
        assert sorted(loaded.keyframes) == sorted(mapper.keyframes)
        assert loaded.config.gp == mapper.config.gp
        np.testing.assert_allclose(loaded.keyframes[3].T_world_camera, moved, atol=1e-12)  # snapped by check_pose
        loaded.update_poses({3: poses[3]})
        mapper.update_poses({3: poses[3]})
        # re-fused from the stored keyframes (half-precision depths): the same voxels, values within the storage's error
        _assert_stored_voxels_close(_sorted_voxels(mapper.fusion), _sorted_voxels(loaded.fusion), refused=True)
        r = loaded.add_frame(frames[0].rgb, poses[0], mde_depth=_standin_mde(frames[0].depth), sparse=sparse[0])
        assert r.fused and r.keyframe_id == 5
        with pytest.raises(InvalidInputError):
            loaded.add_frame(frames[0].rgb, poses[0], mde_depth=_standin_mde(frames[0].depth), keyframe_id=3)
        with pytest.raises(DataFormatError):
            Mapper.load(tmp_path / "nothing")

    def test_point_cloud_carries_variance(self, shared_data):
        frames = _frames(shared_data, (0, 2))
        sparse = [_kinect_sparse(f, f.camera, 80, i) for i, f in enumerate(frames)]
        mapper = self._run(frames, [f.pose for f in frames], _small_config(gp=DepthGPConfig.residual()), sparse)
        cloud = mapper.point_cloud()
        assert len(cloud) > 100 and np.all(np.isfinite(cloud.variance)) and np.all(cloud.variance > 0)
        stored = np.concatenate([kf.variance.ravel() for kf in mapper.keyframes.values()])
        # a voxel's variance is a weighted mean of the keyframes' pixel variances
        assert stored.min() - 1e-9 <= cloud.variance.min() and cloud.variance.max() <= stored.max() + 1e-9

    def test_without_store(self, shared_data):
        f = _frames(shared_data, (0,))[0]
        mapper = Mapper(f.camera, _small_config(keep_keyframes=False))
        mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth))
        assert mapper.keyframes == {}
        with pytest.raises(InvalidInputError):
            mapper.update_poses({0: f.pose})


class TestFuseAsTheReadmeSays:
    @pytest.mark.slow
    def test_readme_line_completes_all_60_frames(self, shared_data, tmp_path: Path, monkeypatch):
        """`gpdepth3d fuse --data ../shared/data/7scenes --output fuse_out`, exactly as the README writes it
        (run from the repository root; only the output folder is moved into tmp_path)."""
        from gpdepth3d.cli import main

        repo = Path(__file__).resolve().parents[2]
        if shared_data.resolve() != (repo.parent / "shared" / "data").resolve():
            pytest.skip("the README's relative paths need the data at ../shared/data")
        if not (repo.parent / "shared" / "models" / "fast_depth_224.tflite").is_file():
            pytest.skip("FastDepth model not found at ../shared/models/fast_depth_224.tflite")
        pytest.importorskip("ai_edge_litert")
        monkeypatch.chdir(repo)
        out = tmp_path / "fuse_out"
        assert main(["fuse", "--data", "../shared/data/7scenes", "--output", str(out)]) == 0
        summary = json.loads((out / "metrics.json").read_text())
        assert summary["frames"] == 60 and summary["frames_fused"] == 60 and summary["frame_errors"] == []
        assert summary["empty_meshes"] == [] and len(summary["meshes_written"]) == 4
        assert summary["config"]["mapper"]["gp"]["calibration"]["reach"] is None  # MAPPER_GP
        for variant in ("mde", "gp_uniform", "gp_variance"):
            m = summary["metrics"][variant]
            assert 0 < m["fscore"] <= 1 and m["chamfer"] > 0

    @pytest.mark.slow
    def test_few_frames_report_an_empty_mesh_instead_of_failing(self, shared_data, tmp_path: Path):
        model = shared_data.parent / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip(f"FastDepth model not found at {model}")
        pytest.importorskip("ai_edge_litert")
        # one frame whose variance weights (sigma_ref 1 mm) stay below the weight threshold: the
        # variance-weighted mesh is empty, reported, not written; the others are written
        summary = fuse_command(
            shared_data / "7scenes",
            tmp_path,
            mde=str(model),
            frames=1,
            working_scale=0.25,
            voxel_size=0.05,
            truncation=0.15,
            sigma_ref=0.001,
            metric_samples=2000,
        )
        assert summary["frames_fused"] == 1
        assert "gp_variance" in summary["empty_meshes"] and summary["metrics"]["gp_variance"] is None
        assert all(Path(p).is_file() for p in summary["meshes_written"])
        assert not (tmp_path / "mesh_gp_variance.ply").exists()


class TestVioSparse:
    def test_points_outside_the_image_are_counted(self, shared_data):
        """vio_sparse's SLAM points (camera frame): about a third project outside the image; they are counted."""
        files = sorted((shared_data / "vio_sparse" / "depth_sparse").glob("*.txt"))
        if not files:
            pytest.skip("vio_sparse not found")
        cam = PinholeCamera(577.591, 578.73, 318.905, 242.684, 640, 480)
        given = outside = used = 0
        for f in files:
            pts = np.loadtxt(f)[:, 1:4]
            sparse, stats = project_map_points(pts, np.eye(4), cam)
            assert stats.given == len(pts) and stats.used == len(sparse)
            assert stats.used <= stats.given - stats.nonfinite - stats.behind - stats.outside
            uv, _ = cam.project(pts)
            assert stats.outside == int(np.sum((pts[:, 2] > 1e-3) & ~cam.in_image(uv)))
            given, outside, used = given + stats.given, outside + stats.outside, used + stats.used
        assert 0.25 < outside / given < 0.5 and used > 0.5 * (given - outside)


class TestFixedLag:
    """The Mapper's fixed lag: a frame is triangulated from earlier and later views, then fused."""

    def _config(self, **kw) -> MapperConfig:
        base = dict(
            working_scale=0.25,
            window=3,
            lag=2,
            gp=DepthGPConfig.residual(),
            fusion=FusionConfig(voxel_size=0.04, truncation=0.12),
        )
        return MapperConfig(**{**base, **kw})

    def test_frames_come_back_after_lag_calls_with_points_from_both_sides(self, shared_data):
        from gpdepth3d.mapping import SEVEN_SCENES_RGB_K

        frames = _frames(shared_data, range(40, 46))
        cam = PinholeCamera.from_K(SEVEN_SCENES_RGB_K, 640, 480)
        mapper = Mapper(cam, self._config())
        results = []
        for i, f in enumerate(frames):
            r = mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth), keyframe_id=10 + i)
            if i < 2:
                assert r is None and mapper.pending == tuple(range(10, 11 + i))
            else:
                assert r.keyframe_id == 10 + i - 2 and mapper.pending == (10 + i - 1, 10 + i)
                results.append(r)
            assert set(mapper.timings[-1]) == {"mde", "points", "gp", "fusion", "total"}
        with pytest.raises(InvalidInputError):  # a waiting frame's id is taken too
            mapper.add_frame(frames[0].rgb, frames[0].pose, mde_depth=_standin_mde(frames[0].depth), keyframe_id=15)
        assert mapper.pending == (14, 15)
        rest = mapper.flush()
        assert [r.keyframe_id for r in rest] == [14, 15] and mapper.pending == () and mapper.flush() == []
        results += rest
        assert [r.keyframe_id for r in results] == list(range(10, 16)) and all(r.fused for r in results)
        assert sorted(mapper.keyframes) == list(range(10, 16)) and mapper.frames == 6
        # every frame has triangulated points, the first one too (it has later views), near the Kinect depth
        for r, f in zip(results, frames):
            assert len(r.sparse) > 30, r.keyframe_id
            lifted = cam.backproject_pixels(r.sparse.uv, r.sparse.depth)
            uv, z = f.camera.project(lifted)
            inside = f.camera.in_image(uv)
            iu = np.rint(uv[inside]).astype(int)
            k = f.depth[iu[:, 1], iu[:, 0]]
            ok = k > 0
            assert np.median(np.abs(z[inside][ok] - k[ok]) / k[ok]) < 0.12, r.keyframe_id
        assert len(mapper.mesh().faces) > 100

    def test_lag_zero_is_immediate_and_a_failed_frame_keeps_its_turn(self, shared_data):
        frames = _frames(shared_data, range(40, 44))
        calls = []

        def flaky(rgb):
            calls.append(1)
            if len(calls) == 2:
                raise RuntimeError("front-end hiccup")
            return _standin_mde(frames[len(calls) - 1].depth)

        lagged = Mapper(frames[0].camera, self._config(lag=1), mde=flaky)
        out = [lagged.add_frame(f.rgb, f.pose) for f in frames] + lagged.flush()
        assert out[0] is None and [r.keyframe_id for r in out[1:]] == [0, 1, 2, 3]
        assert [r.fused for r in out[1:]] == [True, False, True, True]
        assert out[2].error == "frame 1: mde: RuntimeError: front-end hiccup" and lagged.failures == [out[2].error]
        immediate = Mapper(frames[0].camera, self._config(lag=0))
        r = immediate.add_frame(frames[0].rgb, frames[0].pose, mde_depth=_standin_mde(frames[0].depth))
        assert r.keyframe_id == 0 and r.fused and immediate.pending == () and immediate.flush() == []

    def test_update_poses_of_a_waiting_frame(self, shared_data):
        frames = _frames(shared_data, range(40, 44))
        mapper = Mapper(frames[0].camera, self._config())
        for f in frames[:3]:
            mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth))
        assert mapper.pending == (1, 2)
        moved = frames[2].pose.copy()
        moved[:3, 3] += [0.02, 0.0, 0.0]
        update = mapper.update_poses({2: moved})
        assert update.moved == ()  # not in the volume yet: nothing to re-integrate
        mapper.flush()
        np.testing.assert_allclose(mapper.keyframes[2].T_world_camera, moved, atol=1e-9)
        with pytest.raises(InvalidInputError):
            mapper.update_poses({7: moved})

    def test_config(self):
        for bad in (-1, 1.5, True):
            with pytest.raises(InvalidInputError):
                MapperConfig(lag=bad)
        with pytest.raises(InvalidInputError):
            MapperConfig(fuse_depth="mode")  # type: ignore[arg-type]
        assert MapperConfig().lag == 4 and MapperConfig().window == 8 and MapperConfig().fuse_depth == "median"

    def test_gp_is_the_default_model_with_the_stationary_variance(self, monkeypatch, tmp_path):
        """The fusion's cut and weights were chosen on the stationary GP's variance (MapperConfig.gp, with the
        mapper's longer length scale); `gpdepth3d fuse` refines with the same GP unless told otherwise."""
        from gpdepth3d.cli import main
        from gpdepth3d.gp.model import DepthGPConfig
        from gpdepth3d.mapping.mapper_config import MAPPER_GP

        mapper_gp = DepthGPConfig(lengthscale=64.0, calibration=CalibrationConfig(reach=None))
        assert MapperConfig().gp == MAPPER_GP == mapper_gp
        seen = []

        class Stop(Exception):
            pass

        def capture(*args, gp=None, **kwargs):
            seen.append(gp)
            raise Stop

        monkeypatch.setattr("gpdepth3d.pipelines.fuse_run.MapperConfig", capture)
        monkeypatch.setattr("gpdepth3d.mde.load_frontend", lambda *a, **k: None)
        for argv, expected in (([], None), (["--gp.calibration.reach", "1.5"], 1.5)):
            main(["fuse", "--data", str(tmp_path), "--output", str(tmp_path / "out"), *argv])  # stops at the config
            assert seen[-1].calibration.reach == expected
            assert seen[-1].replace(calibration={"reach": None}) == MAPPER_GP


class TestFusedDepth:
    def test_median_of_the_log_normal_posterior(self):
        from types import SimpleNamespace

        from gpdepth3d.mapping import fused_depth

        rng = np.random.default_rng(0)
        mu, v = rng.normal(0.5, 0.2, (6, 7)), rng.uniform(0.0, 0.3, (6, 7))  # log depth: mean, variance
        mean, var = np.exp(mu + v / 2), (np.exp(v) - 1) * np.exp(2 * mu + v)  # the log-normal's moments
        post = SimpleNamespace(mean=mean, variance=var, config=DepthGPConfig())
        np.testing.assert_allclose(fused_depth(post), np.exp(mu), rtol=1e-12)  # the median: exp(mu)
        np.testing.assert_array_equal(fused_depth(post, "mean"), mean)
        gaussian = SimpleNamespace(mean=mean, variance=var, config=DepthGPConfig.residual())
        np.testing.assert_array_equal(fused_depth(gaussian), mean)
        mean[0, 0], mean[0, 1] = -0.1, np.nan  # left for the fusion to mask
        out = fused_depth(post)
        assert out[0, 0] == -0.1 and np.isnan(out[0, 1])
        with pytest.raises(InvalidInputError):
            fused_depth(post, "mode")  # type: ignore[arg-type]

    def test_mapper_fuses_the_median(self, shared_data):
        from gpdepth3d.mapping import fused_depth

        f = _frames(shared_data, (0,))[0]
        for estimate in ("median", "mean"):
            # held_out off: the stand-in MDE is the Kinect depth blurred, rescaled it can beat the GP
            mapper = Mapper(f.camera, _small_config(fuse_depth=estimate, held_out=0.0))
            res = mapper.add_frame(
                f.rgb, f.pose, mde_depth=_standin_mde(f.depth), sparse=_kinect_sparse(f, f.camera, 60, 0)
            )
            expected = fused_depth(res.posterior, estimate)
            np.testing.assert_allclose(res.depth, expected.astype(np.float32), rtol=1e-6)
            if estimate == "median":
                assert np.all(res.depth <= res.posterior.mean + 1e-6) and np.any(res.depth < 0.999 * res.posterior.mean)


class TestMapScale:
    """`map_scale`: a frame's measurements against the keyframes already fused."""

    @staticmethod
    def _scene(n_keyframes: int = 5):
        """Keyframes looking at a tilted plane from nearby poses (depth maps exact, variance 1 %)."""
        from gpdepth3d.mapping import Keyframe

        cam = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
        normal, offset = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0]), 2.0  # n . x = offset (world)

        def depth_map(T):
            u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
            rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
            rw = rays @ T[:3, :3].T
            return (offset - normal @ T[:3, 3]) / (rw @ normal)  # z along each ray: z = t for rays with z = 1

        stored = []
        for k in range(n_keyframes):
            T = np.eye(4)
            T[:3, 3] = [0.05 * k, 0.02 * k, 0.0]
            d = depth_map(T).astype(np.float32)
            stored.append(
                Keyframe(k, T, d, (0.01 * d) ** 2, np.zeros(cam.shape + (3,), np.uint8), np.zeros(0, np.int64))
            )
        T = np.eye(4)
        T[:3, 3] = [0.12, 0.05, 0.0]
        return cam, stored, T, depth_map(T)

    def test_recovers_a_common_scale_error(self):
        from dataclasses import replace as dc_replace

        from gpdepth3d.mapping import map_scale

        cam, stored, T, truth = self._scene()
        rng = np.random.default_rng(0)
        u, v = rng.integers(0, cam.width, 200), rng.integers(0, cam.height, 200)
        for factor in (1.0, 1.2, 0.85):
            sparse = SparseDepth.from_arrays(u.astype(float), v.astype(float), factor * truth[v, u], cam.shape, 0.02)
            log_s, used = map_scale(sparse, T, cam, stored, cam)
            assert used == 5 and log_s == pytest.approx(np.log(factor), abs=0.01)
        # only the most recent keyframes; too few of them, too few points, unsure keyframes: no result
        assert map_scale(sparse, T, cam, stored, cam, recent=2) == (0.0, 0)
        assert map_scale(sparse.subset(np.arange(10)), T, cam, stored, cam) == (0.0, 0)
        unsure = [dc_replace(kf, variance=(0.5 * kf.depth) ** 2) for kf in stored]
        assert map_scale(sparse, T, cam, unsure, cam) == (0.0, 0)

    def test_median_helper_is_numpys_median(self):
        from gpdepth3d.mapping.map_scale import fast_median

        rng = np.random.default_rng(3)
        for n in (1, 2, 5, 20, 301):
            x = rng.normal(size=n)
            assert fast_median(x) == np.median(x)

    def test_mapper_pulls_a_frames_points_halfway_to_the_map(self, shared_data):
        frames = _frames(shared_data, (0, 1, 2, 3, 4))
        cam = frames[0].camera
        sparse = [_kinect_sparse(f, cam, 150, i) for i, f in enumerate(frames)]
        results = {}
        for weight in (0.0, 0.5):
            mapper = Mapper(cam, _small_config(triangulate=True, lag=0, map_scale_weight=weight, local_map_frames=0))
            mapper._points.triangulate = lambda rgb, T, kid: scaled[kid]  # the frame's "triangulated" points
            scaled = {
                i: s if i < 4 else SparseDepth(s.u, s.v, 1.3 * s.depth, s.image_size, 1.3 * s.sigma)
                for i, s in enumerate(sparse)
            }
            for i, f in enumerate(frames):
                results[weight, i] = mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth))
        assert all(results[0.0, i].map_scale == 1.0 for i in range(5))
        assert [results[0.5, i].map_scale for i in range(3)] == [1.0] * 3  # fewer than 3 keyframes before them
        assert results[0.5, 4].map_scale == pytest.approx(np.sqrt(1.3), rel=0.03)  # halfway, in log
        np.testing.assert_allclose(
            np.sort(results[0.5, 4].sparse.depth), np.sort(1.3 * sparse[4].depth / results[0.5, 4].map_scale), rtol=1e-9
        )
        with pytest.raises(InvalidInputError):
            MapperConfig(map_scale_weight=1.5)
        with pytest.raises(InvalidInputError):
            MapperConfig(map_scale_keyframes=0)
        for bad in (0.0, -0.1, float("nan")):
            with pytest.raises(InvalidInputError):
                MapperConfig(map_scale_max_sigma=bad)

    def test_scale_disagreement_goes_into_the_fused_variance(self, shared_data):
        """``scale_variance``: a frame whose points disagree with the map by a factor s is fused
        with its posterior variance plus w (1 - w) (log s)^2 depth^2 (w the default map_scale_weight); ``map_scale_max_sigma``
        reaches `map_scale` (no keyframe pixel is certain enough with a tiny one: no correction)."""
        frames = _frames(shared_data, (0, 1, 2, 3, 4))
        cam = frames[0].camera
        sparse = [_kinect_sparse(f, cam, 150, i) for i, f in enumerate(frames)]
        scaled = {
            i: s if i < 4 else SparseDepth(s.u, s.v, 1.3 * s.depth, s.image_size, 1.3 * s.sigma)
            for i, s in enumerate(sparse)
        }
        results = {}
        for key, kw in (("on", {}), ("off", dict(scale_variance=False)), ("strict", dict(map_scale_max_sigma=1e-6))):
            # held_out off: the stand-in MDE is the Kinect depth blurred, rescaled it can beat the GP
            mapper = Mapper(cam, _small_config(triangulate=True, lag=0, held_out=0.0, **kw))
            mapper._points.triangulate = lambda rgb, T, kid: scaled[kid]
            for i, f in enumerate(frames):
                results[key, i] = mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth))
        assert MapperConfig().scale_variance and MapperConfig().map_scale_max_sigma == 0.15
        w = MapperConfig().map_scale_weight
        on, off = results["on", 4], results["off", 4]
        assert on.map_scale == pytest.approx(1.3**w, rel=0.03) and off.map_scale == on.map_scale
        np.testing.assert_allclose(off.variance, off.posterior.variance.astype(np.float32), rtol=1e-6)
        for i in (3, 4):
            r = results["on", i]
            log_s = np.log(r.map_scale) / w  # the frame's disagreement with the map; a share w of it corrected
            np.testing.assert_allclose(
                r.variance, r.posterior.variance + w * (1 - w) * log_s**2 * r.depth**2, rtol=1e-5
            )
        assert np.nanmedian(on.variance / on.posterior.variance) > 1.05  # a real share, not rounding
        for i in range(3):  # no map scale (fewer than 3 keyframes before them): no extra variance
            np.testing.assert_allclose(
                results["on", i].variance, results["on", i].posterior.variance.astype(np.float32), rtol=1e-6
            )
        assert results["strict", 4].map_scale == 1.0
        np.testing.assert_allclose(
            results["strict", 4].variance, results["strict", 4].posterior.variance.astype(np.float32), rtol=1e-6
        )


class TestUncertainPixels:
    """`FusionConfig.max_relative_sigma` and ``fallback_weight`` in the Mapper: pixels less certain than 20 % of
    their depth (no point informs them) are fused with the fallback weight, which the frame's points lower."""

    @staticmethod
    def _mapper(rel_sigma_left: float, rel_sigma_right: float, **fusion):
        from types import SimpleNamespace

        class Completer:  # a posterior on a plane at 1.5 m with a chosen relative sigma per image half
            def complete(self, mde, measurements, output_shape):
                var = np.full(output_shape, (rel_sigma_left * 1.5) ** 2)
                var[:, output_shape[1] // 2 :] = (rel_sigma_right * 1.5) ** 2
                return SimpleNamespace(mean=np.full(output_shape, 1.5), variance=var, config=None)

        cfg = MapperConfig(
            triangulate=False, fusion=FusionConfig(voxel_size=0.02, truncation=0.06, weight_threshold=0.01, **fusion)
        )
        return Mapper(CAM, cfg, completer=Completer())

    def test_uninformed_pixels_fall_back_unless_the_frame_has_points(self):
        rgb = np.zeros(CAM.shape + (3,), np.uint8)
        points = SparseDepth.from_arrays(np.arange(40.0), np.full(40, 5.0), np.full(40, 1.5), CAM.shape, 0.01)
        x_extent, fallback = {}, {}
        for case, kwargs in (("points", dict(sparse=points)), ("none", {})):
            mapper = self._mapper(0.1, 0.3)
            res = mapper.add_frame(rgb, np.eye(4), mde_depth=np.full(CAM.shape, 1.5), **kwargs)
            assert res.fused and res.error is None
            x = mapper.mesh().vertices[:, 0]
            x_extent[case], fallback[case] = (x.min(), x.max()), res.fallback_weight
        # the camera sees x in [-0.59, 0.61] m at 1.5 m: with 40 points the right half is left to other
        # frames; without any point the frame falls back to its (MDE) depth there, at half weight, and says so
        assert x_extent["points"][0] < -0.5 and x_extent["points"][1] < 0.05 and fallback["points"] < 0.01
        assert x_extent["none"][0] < -0.5 and x_extent["none"][1] > 0.5 and fallback["none"] == 0.5
        assert any("no points: fused as the MDE" in w for w in res.warnings)

    def test_frame_with_nothing_certain_and_no_fallback_is_kept_not_failed(self):
        rgb = np.zeros(CAM.shape + (3,), np.uint8)
        mapper = self._mapper(0.3, 0.3, fallback_weight=0.0)
        res = mapper.add_frame(rgb, np.eye(4), mde_depth=np.full(CAM.shape, 1.5), keyframe_id=7)
        assert res.fused and res.error is None and mapper.failures == []
        assert any("nothing fused" in w for w in res.warnings)
        assert 7 in mapper.keyframes and mapper.keyframes[7].block_keys.size == 0
        assert mapper.fusion.frames_integrated == 0
        T = np.eye(4)
        T[0, 3] = 0.1
        assert mapper.update_poses({7: T}).moved == (7,)  # re-integrating it fuses nothing, raises nothing

    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_cut_pixels_are_the_inaccurate_ones_on_7scenes(self, shared_data):
        """With FastDepth and the Mapper's own points (defaults, 320 x 240), the pixels the cut leaves
        out are the MDE's shape alone: farther from the Kinect depth than the pixels it fuses (60
        frames: median |error| 0.235 vs 0.126 m), and the default tracker and ``max_points`` give
        frames more points than 400 corners or the old cap of 300 could."""
        from gpdepth3d.mde.tflite import FastDepthTFLite
        from gpdepth3d.measurements import project_points

        model = shared_data.parent / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip(f"FastDepth model not found at {model}")
        pytest.importorskip("ai_edge_litert")
        frames = _frames(shared_data, range(0, 12))
        cam = frames[0].camera
        mapper = Mapper(cam, MapperConfig(working_scale=0.5), mde=FastDepthTFLite(model))
        results = [mapper.add_frame(f.rgb, f.pose, keyframe_id=i) for i, f in enumerate(frames)] + mapper.flush()
        results = [r for r in results if r is not None]
        assert len(results) == 12 and all(r.fused for r in results)
        cut = mapper.fusion.config.max_relative_sigma
        assert cut == 0.2
        err = {"kept": [], "cut": []}
        for r in results:
            f = frames[r.keyframe_id]
            pts, _ = f.camera.backproject(f.depth)
            gt = project_points(pts, mapper.work_camera).to_depth_map()
            above = np.sqrt(r.variance) > cut * r.depth
            ok = (gt > 0) & (r.depth > 0)
            err["kept"].append(np.abs(r.depth - gt)[ok & ~above])
            err["cut"].append(np.abs(r.depth - gt)[ok & above])
        kept, dropped = np.concatenate(err["kept"]), np.concatenate(err["cut"])
        assert 0.03 < dropped.size / (dropped.size + kept.size) < 0.6
        assert np.median(dropped) > 1.3 * np.median(kept)
        # 800 KLT corners and up to 450 points: frames 0-11 get up to 450 (with 400 corners at most 360, with
        # the old cap 300)
        assert max(len(r.sparse) for r in results) > 400
