"""Tests of gpdepth3d.mapping: SLAM map points, the incremental Mapper, mesh metrics, fuse_command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, EmptyInputError, InvalidInputError, ShapeError
from gpdepth3d.fusion import FusionConfig
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.mapping import (
    Mapper,
    MapperConfig,
    fuse_command,
    merge_sparse,
    mesh_metrics,
    sparse_from_map_points,
)
from gpdepth3d.measurements import SparseDepth

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
            gp=DepthGPConfig.residual(engine="exact"),
            fusion=FusionConfig(voxel_size=0.04, truncation=0.12),
        )
        mapper = Mapper(cam, config)
        rng = np.random.default_rng(0)
        for f in frames:
            pts, _ = cam.backproject(f.depth)
            pts = pts[rng.choice(len(pts), 150, replace=False)]
            world = pts @ f.pose[:3, :3].T + f.pose[:3, 3]
            res = mapper.add_frame(f.rgb, f.pose, mde_depth=_standin_mde(f.depth), map_points_world=world,
                                   map_points_sigma=0.01)
            gt = project_points(cam.backproject(f.depth)[0], mapper.work_camera).to_depth_map()
            ok = gt > 0
            err_mde = np.median(np.abs(res.mde[ok] - gt[ok]))
            err_gp = np.median(np.abs(res.depth[ok] - gt[ok]))
            assert err_gp < 0.5 * err_mde
            assert len(res.sparse) > 100 and np.all(np.isfinite(res.variance))
            assert set(res.timings) == {"mde", "triangulate", "refine", "fuse"}
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
            working_scale=0.25, max_points=80, gp=DepthGPConfig.residual(engine="exact"), fusion=FusionConfig(voxel_size=0.05, truncation=0.15)
        )
        mapper = Mapper(cam, config, mde=front_end)
        first = mapper.add_frame(frames[0].rgb, frames[0].pose)
        assert len(first.sparse) == 0  # nothing to triangulate against yet
        second = mapper.add_frame(frames[1].rgb, frames[1].pose)
        assert 10 < len(second.sparse) <= 80
        assert np.all(np.isfinite(second.sparse.sigma)) and np.all(second.sparse.sigma > 0)
        assert calls == [(480, 640, 3)] * 2
        # the refined depth moved from the constant stand-in towards the triangulated depths
        assert np.std(second.depth) > 0.01

    def test_mde_only_mode(self, shared_data):
        f = _frames(shared_data, (0,))[0]
        mapper = Mapper(f.camera, MapperConfig(refine=False, triangulate=False, working_scale=0.25,
                                               fusion=FusionConfig(voxel_size=0.04, truncation=0.12)))
        res = mapper.add_frame(f.rgb, f.pose, mde_depth=f.depth)
        assert res.posterior is None and np.all(np.isnan(res.variance))
        assert mapper.fusion.config.weighting == "uniform"

    def test_errors(self, tmp_path: Path):
        mapper = Mapper(CAM, MapperConfig(triangulate=False, gp=DepthGPConfig.residual(engine="exact")))
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
        with pytest.raises(EmptyInputError):
            mapper.add_frame(rgb, np.eye(4), mde_depth=np.zeros((60, 80)))
        assert mapper.frames == 0


class TestFuseCommand:
    @pytest.mark.slow
    def test_writes_meshes_and_metrics(self, shared_data, tmp_path: Path):
        model = shared_data.parent / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip(f"FastDepth model not found at {model}")
        pytest.importorskip("ai_edge_litert")
        out = tmp_path / "fuse"
        summary = fuse_command(shared_data / "7scenes", out, model=model, frames=3, working_scale=0.25, voxel_size=0.05,
                               truncation=0.15, sigma_ref=1.0, metric_samples=5000, engine="exact")
        names = sorted(p.name for p in out.iterdir())
        assert names == ["mesh_gp_uniform.ply", "mesh_gp_variance.ply", "mesh_gt.ply", "mesh_mde.ply", "metrics.json"]
        on_disk = json.loads((out / "metrics.json").read_text())
        assert on_disk["frames"] == 3 == summary["frames"]
        for variant in ("mde", "gp_uniform", "gp_variance"):
            m = on_disk["metrics"][variant]
            assert 0 <= m["precision"] <= 1 and 0 <= m["recall"] <= 1 and m["chamfer"] > 0
