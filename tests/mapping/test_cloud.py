"""Tests of gpdepth3d.mapping.cloud: back-projection, confidence, filtering, transforms, PLY export."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.mapping.cloud import (
    DEFAULT_RHO_REF,
    ColoredCloud,
    MaskedDepthWarning,
    backproject_depth,
    backproject_posterior,
    confidence_from_variance,
)
from gpdepth3d.errors import CalibrationError, EmptyInputError, InvalidDepthError, InvalidInputError, ShapeError

CAM = PinholeCamera(40.0, 42.0, 15.5, 11.0, 32, 24)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)
    return R


def _pose(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = _rot(rng.normal(size=3), 0.7)
    T[:3, 3] = rng.normal(size=3)
    return T


def _frame(seed: int = 0):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(1.0, 4.0, CAM.shape)
    rgb = rng.integers(0, 256, CAM.shape + (3,)).astype(np.uint8)
    var = rng.uniform(0.0, 0.09, CAM.shape)
    return depth, rgb, var


class TestConfidence:
    def test_formula(self):
        z = np.array([1.0, 2.0, 10.0, 2.0])
        sigma = np.array([0.05, 0.1, 0.5, 0.0]) * np.array([1, 1, 1, 1])
        c = confidence_from_variance(sigma**2, z)
        # sigma / z = 0.05 = rho_ref for the first three -> 0.5; zero variance -> 1
        np.testing.assert_allclose(c, [0.5, 0.5, 0.5, 1.0])
        rho = 0.2
        np.testing.assert_allclose(
            confidence_from_variance(np.array([(rho * 3.0) ** 2]), np.array([3.0])),
            1 / (1 + (rho / DEFAULT_RHO_REF) ** 2),
        )

    def test_monotone_and_nan(self):
        var = np.linspace(0, 1, 50)
        c = confidence_from_variance(var, np.full(50, 2.0))
        assert np.all(np.diff(c) < 0) and c[0] == 1.0
        assert confidence_from_variance(np.array([np.nan]), np.array([1.0]))[0] == 1.0

    def test_errors(self):
        with pytest.raises(ShapeError):
            confidence_from_variance(np.ones(3), np.ones(4))
        with pytest.raises(InvalidInputError):
            confidence_from_variance(np.ones(3), np.ones(3), rho_ref=0.0)


class TestBackproject:
    def test_round_trip_project(self):
        depth, rgb, var = _frame()
        depth[3, 4] = 0.0
        depth[5, 6] = np.nan
        cloud = backproject_depth(depth, rgb, CAM, variance=var)
        assert len(cloud) == depth.size - 2
        uv, z = CAM.project(cloud.points)
        valid = np.isfinite(depth) & (depth > 0)
        u, v = CAM.pixel_grid()
        np.testing.assert_allclose(uv[:, 0], u[valid], atol=1e-9)
        np.testing.assert_allclose(uv[:, 1], v[valid], atol=1e-9)
        np.testing.assert_allclose(z, depth[valid], atol=1e-12)
        np.testing.assert_array_equal(cloud.colors, rgb[valid])
        np.testing.assert_allclose(cloud.variance, var[valid])
        np.testing.assert_allclose(cloud.confidence, confidence_from_variance(var[valid], depth[valid]))
        np.testing.assert_allclose(cloud.relative_sigma, np.sqrt(var[valid]) / depth[valid])

    def test_world_transform(self):
        depth, rgb, var = _frame(1)
        T = _pose(1)
        cam_cloud = backproject_depth(depth, rgb, CAM, variance=var)
        world = backproject_depth(depth, rgb, CAM, variance=var, T_world_camera=T)
        np.testing.assert_allclose(world.points, cam_cloud.points @ T[:3, :3].T + T[:3, 3], atol=1e-12)
        back = world.transformed(np.linalg.inv(T))
        np.testing.assert_allclose(back.points, cam_cloud.points, atol=1e-9)
        np.testing.assert_allclose(world.depth, cam_cloud.depth)  # depth is kept for sigma / depth

    def test_depth_range_and_stride(self):
        depth, rgb, _ = _frame(2)
        cloud = backproject_depth(depth, rgb, CAM, min_depth=2.0, max_depth=3.0, stride=2)
        assert np.all((cloud.depth > 2.0) & (cloud.depth <= 3.0))
        uv, _ = CAM.project(cloud.points)
        assert np.all(np.rint(uv) % 2 == 0)
        assert np.all(np.isnan(cloud.variance)) and np.all(cloud.confidence == 1.0)

    def test_posterior(self):
        from gpdepth3d.completion.complete import complete
        from gpdepth3d.gp.model import DepthGPConfig
        from gpdepth3d.measurements import SparseDepth

        depth, rgb, _ = _frame(3)
        sparse = SparseDepth.from_arrays([4.0, 20.0], [5.0, 15.0], [2.0, 2.5], CAM.shape)
        post = complete(depth, sparse, config=DepthGPConfig.residual(), engine=EngineConfig(name="exact"))
        cloud = backproject_posterior(post, rgb, CAM)
        assert len(cloud) == depth.size
        np.testing.assert_allclose(cloud.depth, post.mean.ravel())
        np.testing.assert_allclose(cloud.variance, post.variance.ravel())
        # points at the measurements are the most confident
        best = np.argmax(cloud.confidence)
        assert (int(best) // CAM.width, int(best) % CAM.width) in {(5, 4), (15, 20)}

    def test_negative_and_nan_depths_masked_and_counted(self):
        # a GP mean that dipped below zero next to an outlier point, plus NaN / inf pixels
        depth, rgb, var = _frame(4)
        depth[0, :3] = -0.066
        depth[1, :2] = np.nan
        depth[2, 0] = np.inf
        with pytest.warns(MaskedDepthWarning, match=r"3 pixels with negative depth \(minimum -0.066 m\)"):
            cloud = backproject_depth(depth, rgb, CAM, variance=var)
        assert len(cloud) == depth.size - 6
        assert np.all(cloud.depth > 0) and np.all(np.isfinite(cloud.points))

    def test_errors(self):
        depth, rgb, var = _frame()
        with pytest.raises(ShapeError):
            backproject_depth(depth, rgb[:-1], CAM)
        with pytest.raises(ShapeError):
            backproject_depth(depth[:, :-1], rgb[:, :-1], CAM)
        with pytest.raises(ShapeError):
            backproject_depth(depth, rgb, CAM, variance=var[:-1])
        with pytest.raises(EmptyInputError):
            backproject_depth(np.zeros(CAM.shape), rgb, CAM)
        with pytest.raises(EmptyInputError):
            backproject_depth(depth, rgb, CAM, variance=np.full(CAM.shape, np.nan))
        with pytest.warns(MaskedDepthWarning), pytest.raises(EmptyInputError):
            backproject_depth(-depth, rgb, CAM)  # every pixel masked: nothing left
        bad = np.eye(4)
        bad[:3, :3] *= 2.0
        with pytest.raises(CalibrationError):
            backproject_depth(depth, rgb, CAM, T_world_camera=bad)
        with pytest.raises(InvalidInputError):
            backproject_posterior(depth, rgb, CAM)


class TestColoredCloud:
    def _cloud(self) -> ColoredCloud:
        depth, rgb, var = _frame(4)
        return backproject_depth(depth, rgb, CAM, variance=var)

    def test_filter(self):
        cloud = self._cloud()
        f = cloud.filter(min_confidence=0.6)
        assert 0 < len(f) < len(cloud) and np.all(f.confidence >= 0.6)
        g = cloud.filter(max_relative_sigma=0.05)
        assert np.all(g.relative_sigma <= 0.05)
        assert len(g) == int(np.sum(cloud.relative_sigma <= 0.05))
        h = cloud.filter(max_sigma=0.1)
        assert np.all(h.sigma <= 0.1) and len(h) == int(np.sum(cloud.sigma <= 0.1))
        with pytest.raises(InvalidInputError):
            cloud.filter(min_confidence=1.5)
        with pytest.raises(InvalidInputError):
            cloud.filter(max_relative_sigma=0.0)

    def test_validation(self):
        with pytest.raises(ShapeError):
            ColoredCloud(np.zeros((3, 3)), np.zeros((2, 3), np.uint8), np.zeros(3), np.ones(3))
        with pytest.raises(InvalidInputError):
            ColoredCloud(np.zeros((3, 3)), np.zeros((3, 3), np.uint8), np.zeros(3), np.full(3, 2.0))
        with pytest.raises(InvalidDepthError):
            ColoredCloud(np.full((3, 3), np.nan), np.zeros((3, 3), np.uint8), np.zeros(3), np.ones(3))

    def test_concatenate(self):
        a = self._cloud()
        b = a.concatenate(a)
        assert len(b) == 2 * len(a)
        np.testing.assert_array_equal(b.colors[len(a) :], a.colors)

    def test_to_open3d_and_trimesh(self):
        cloud = self._cloud()
        pcd = cloud.to_open3d()
        np.testing.assert_allclose(pcd.point.positions.numpy(), cloud.points, rtol=1e-6)
        np.testing.assert_allclose(pcd.point.colors.numpy(), cloud.colors / 255.0, atol=1e-6)
        np.testing.assert_allclose(pcd.point.confidence.numpy()[:, 0], cloud.confidence, rtol=1e-6)
        tm = cloud.to_trimesh()
        np.testing.assert_allclose(tm.vertices, cloud.points)
        np.testing.assert_array_equal(tm.colors[:, :3], cloud.colors)
        np.testing.assert_allclose(tm.metadata["confidence"], cloud.confidence)

    def test_ply_round_trip_open3d_and_trimesh(self, tmp_path: Path):
        import open3d as o3d
        import trimesh

        cloud = self._cloud()
        path = cloud.save_ply(tmp_path / "cloud.ply")
        pcd = o3d.t.io.read_point_cloud(str(path))
        np.testing.assert_allclose(pcd.point.positions.numpy(), cloud.points, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(pcd.point.colors.numpy(), cloud.colors)
        np.testing.assert_allclose(pcd.point.confidence.numpy()[:, 0], cloud.confidence, rtol=1e-6)
        np.testing.assert_allclose(pcd.point.sigma.numpy()[:, 0], cloud.sigma, rtol=1e-6)

        tm = trimesh.load(path)
        assert isinstance(tm, trimesh.PointCloud)
        np.testing.assert_allclose(tm.vertices, cloud.points, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(tm.colors)[:, :3], cloud.colors)
        raw = tm.metadata["_ply_raw"]["vertex"]["data"]
        np.testing.assert_allclose(raw["confidence"].ravel(), cloud.confidence, rtol=1e-6)
        np.testing.assert_allclose(raw["sigma"].ravel(), cloud.sigma, rtol=1e-6)

        back = ColoredCloud.load_ply(path)
        np.testing.assert_allclose(back.points, cloud.points, atol=1e-6)
        np.testing.assert_array_equal(back.colors, cloud.colors)
        np.testing.assert_allclose(back.confidence, cloud.confidence, rtol=1e-6)
        np.testing.assert_allclose(back.variance, cloud.variance, rtol=1e-5)

    def test_export_errors_leave_no_file(self, tmp_path: Path, break_writes):
        cloud = self._cloud()
        with pytest.raises(EmptyInputError):
            cloud.subset(np.zeros(len(cloud), bool)).save_ply(tmp_path / "empty.ply")
        with pytest.raises(InvalidInputError):
            cloud.save_ply(tmp_path / "cloud.txt")

        break_writes("gpdepth3d.mapping.cloud")
        with pytest.raises(OSError):
            cloud.save_ply(tmp_path / "broken.ply")
        assert list(tmp_path.iterdir()) == []
