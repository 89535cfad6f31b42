"""Tests of gpdepth3d.fusion: per-pixel weighted TSDF integration, extraction, export, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, EmptyInputError, InvalidDepthError, InvalidInputError, ShapeError
from gpdepth3d.fusion import FusionConfig, TSDFFusion, save_mesh, weights_from_variance

CAM = PinholeCamera(120.0, 120.0, 39.5, 29.5, 80, 60)
PLANE_Z = 1.511  # not on a voxel boundary


def _shift(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[1, 3] = x, y
    return T


def _plane(z: float = PLANE_Z) -> np.ndarray:
    return np.full(CAM.shape, z)


class TestWeights:
    def test_formula(self):
        var = np.array([[0.0, 0.01, 0.04], [np.nan, -1.0, np.inf]])
        w = weights_from_variance(var, sigma_ref=0.1)
        np.testing.assert_allclose(w[0], [1.0, 0.5, 0.2])
        np.testing.assert_array_equal(w[1], [0.0, 0.0, 0.0])
        with pytest.raises(InvalidInputError):
            weights_from_variance(var, sigma_ref=0.0)

    def test_config_validation(self):
        with pytest.raises(InvalidInputError):
            FusionConfig(voxel_size=0.05, truncation=0.01)
        with pytest.raises(InvalidInputError):
            FusionConfig(weighting="median")
        with pytest.raises(InvalidInputError):
            FusionConfig(depth_min=3.0, depth_max=2.0)
        with pytest.raises(InvalidInputError):
            FusionConfig(voxel_size=-1.0)


class TestIntegrate:
    def test_plane_mesh_on_surface_with_colour(self):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06))
        rgb = np.zeros(CAM.shape + (3,), np.uint8)
        rgb[..., 0] = 200
        rgb[..., 2] = 30
        for x in (-0.05, 0.0, 0.05):
            assert fusion.integrate(_plane(PLANE_Z), _shift(x), rgb=rgb) > 0
        mesh = fusion.extract_mesh()
        assert len(mesh.faces) > 100
        np.testing.assert_allclose(mesh.vertices[:, 2], PLANE_Z, atol=2e-3)
        # the mesh spans the field of view at that depth
        assert mesh.vertices[:, 0].max() - mesh.vertices[:, 0].min() > 0.9
        np.testing.assert_array_equal(np.unique(mesh.visual.vertex_colors[:, :3], axis=0), [[200, 0, 30]])
        cloud = fusion.extract_point_cloud()
        np.testing.assert_allclose(cloud.points[:, 2], PLANE_Z, atol=2e-3)
        assert np.all(cloud.colors == [200, 0, 30])
        assert np.all((cloud.confidence > 0) & (cloud.confidence <= 1))

    def test_per_pixel_weights_reach_the_voxels(self):
        # left half of the image weighs 0.25, right half 1: voxels seen by each half carry it
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, weight_threshold=0.0))
        w = np.ones(CAM.shape)
        w[:, : CAM.width // 2] = 0.25
        fusion.integrate(_plane(), np.eye(4), weights=w)
        vox = fusion.voxels()
        x_over_z = vox["coords"][:, 0] / vox["coords"][:, 2]
        u = CAM.fx * x_over_z + CAM.cx
        left, right = u < CAM.width / 2 - 2, u > CAM.width / 2 + 1
        assert left.sum() > 100 and right.sum() > 100
        np.testing.assert_allclose(vox["weight"][left], 0.25)
        np.testing.assert_allclose(vox["weight"][right], 1.0)

    @pytest.mark.parametrize("w_near, expected", [(1.0, 1.555), (3.0, 1.5325)])
    def test_weighted_average_moves_the_surface(self, w_near, expected):
        # two readings of a plane (1.51 m with weight w_near, 1.60 m with weight 1): the fused
        # surface lies at their weighted mean
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.2))
        fusion.integrate(_plane(1.51), np.eye(4), weights=np.full(CAM.shape, w_near))
        fusion.integrate(_plane(1.60), np.eye(4), weights=np.ones(CAM.shape))
        z = fusion.extract_mesh().vertices[:, 2]
        assert abs(np.median(z) - expected) < 2e-3

    def test_weight_cap(self):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, weight_cap=2.5))
        for _ in range(5):
            fusion.integrate(_plane(), np.eye(4))
        assert fusion.voxels()["weight"].max() == pytest.approx(2.5)
        assert fusion.frames_integrated == 5

    def test_posterior_weighting(self):
        from types import SimpleNamespace

        var = np.full(CAM.shape, 0.01)
        var[:, :40] = 0.09
        post = SimpleNamespace(mean=_plane(), variance=var)
        cfg = FusionConfig(voxel_size=0.02, truncation=0.06, weight_threshold=0.0, sigma_ref=0.1)
        weighted = TSDFFusion(CAM, cfg)
        weighted.integrate_posterior(post, np.eye(4))
        uniform = TSDFFusion(CAM, FusionConfig(**{**cfg.__dict__, "weighting": "uniform"}))
        uniform.integrate_posterior(post, np.eye(4))
        np.testing.assert_allclose(np.unique(np.round(weighted.voxels()["weight"], 6)), [0.1, 0.5])
        np.testing.assert_allclose(np.unique(uniform.voxels()["weight"]), [1.0])

    def test_real_frames_mesh_near_surface(self, shared_data):
        from scipy.spatial import cKDTree

        from gpdepth3d.datasets.sevenscenes import SevenScenes

        reader = SevenScenes(shared_data / "7scenes")
        frames = [reader[i].resized(0.25) for i in (0, 2, 4)]
        cam = frames[0].camera
        fusion = TSDFFusion(cam, FusionConfig(voxel_size=0.02, truncation=0.06, depth_max=4.0))
        for f in frames:
            fusion.integrate(f.depth, f.pose, rgb=f.rgb)
        mesh = fusion.extract_mesh()
        pts, _ = cam.backproject(frames[0].depth)
        T = frames[0].pose
        world = pts @ T[:3, :3].T + T[:3, 3]
        dist, _ = cKDTree(world).query(mesh.vertices)
        assert np.median(dist) < 0.02
        assert len(mesh.vertices) > 2000

    def test_errors(self):
        fusion = TSDFFusion(CAM, FusionConfig())
        with pytest.raises(EmptyInputError):
            fusion.extract_mesh()
        bad = np.eye(4)
        bad[:3, :3] *= 1.5
        with pytest.raises(CalibrationError):
            fusion.integrate(_plane(), bad)
        with pytest.raises(CalibrationError):
            fusion.integrate(_plane(), np.eye(3))
        with pytest.raises(ShapeError):
            fusion.integrate(np.ones((59, 80)), np.eye(4))
        with pytest.raises(ShapeError):
            fusion.integrate(_plane(), np.eye(4), rgb=np.zeros((60, 81, 3), np.uint8))
        with pytest.raises(ShapeError):
            fusion.integrate(_plane(), np.eye(4), weights=np.ones((60, 81)))
        with pytest.raises(InvalidInputError):
            fusion.integrate(_plane(), np.eye(4), weights=-np.ones(CAM.shape))
        with pytest.raises(InvalidDepthError):
            fusion.integrate(-_plane(), np.eye(4))
        with pytest.raises(EmptyInputError):
            fusion.integrate(np.zeros(CAM.shape), np.eye(4))
        with pytest.raises(EmptyInputError):
            fusion.integrate(_plane(9.0), np.eye(4))  # beyond depth_max
        with pytest.raises(EmptyInputError):
            fusion.integrate(_plane(), np.eye(4), weights=np.zeros(CAM.shape))
        assert fusion.frames_integrated == 0
        with pytest.raises(InvalidInputError):
            TSDFFusion("camera")  # type: ignore[arg-type]


class TestExport:
    @pytest.fixture(scope="class")
    def mesh(self):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.03, truncation=0.09))
        rgb = np.full(CAM.shape + (3,), 90, np.uint8)
        fusion.integrate(_plane(), np.eye(4), rgb=rgb)
        fusion.integrate(_plane(), _shift(0.05), rgb=rgb)
        return fusion.extract_mesh()

    @pytest.mark.parametrize("suffix", [".ply", ".glb", ".obj"])
    def test_round_trip(self, mesh, tmp_path: Path, suffix):
        import trimesh

        path = save_mesh(mesh, tmp_path / f"m{suffix}")
        loaded = trimesh.load(path, force="mesh")
        assert len(loaded.faces) == len(mesh.faces)
        np.testing.assert_allclose(np.sort(loaded.vertices[:, 2]).mean(), mesh.vertices[:, 2].mean(), atol=1e-4)
        if suffix == ".ply":
            np.testing.assert_array_equal(loaded.visual.vertex_colors[:, :3], mesh.visual.vertex_colors[:, :3])

    def test_errors_leave_no_file(self, mesh, tmp_path: Path, break_writes):
        import trimesh

        with pytest.raises(InvalidInputError):
            save_mesh(mesh, tmp_path / "m.stl")
        with pytest.raises(InvalidInputError):
            save_mesh("not a mesh", tmp_path / "m.ply")
        with pytest.raises(EmptyInputError):
            save_mesh(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), tmp_path / "m.ply")
        break_writes("gpdepth3d.fusion")
        with pytest.raises(OSError):
            save_mesh(mesh, tmp_path / "m.glb")
        assert list(tmp_path.iterdir()) == []
