"""Tests of gpdepth3d.mapping.tsdf.fusion: per-pixel weighted TSDF integration, extraction, export, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import (
    CalibrationError,
    DataFormatError,
    EmptyInputError,
    InvalidInputError,
    ProblemTooLargeError,
    ShapeError,
)
from gpdepth3d.mapping.tsdf.fusion import FusionConfig, TSDFFusion, save_mesh, weights_from_variance
from gpdepth3d.mapping.tsdf.blocks import blocks_to_keys

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

    def test_relative_sigma_cut_and_fallback(self):
        # depth 2 m: sigma 0.2 m (10 %) and 0.4 m (20 %) informed, 0.41 m and 0.6 m (> 20 %) get the fallback weight
        var = np.array([[0.04, 0.16, 0.41**2, 0.36]])
        depth = np.full(var.shape, 2.0)
        w = weights_from_variance(var, sigma_ref=0.1, depth=depth, max_relative_sigma=0.2)
        np.testing.assert_allclose(w, [[0.2, 1 / 17, 0.0, 0.0]])
        w = weights_from_variance(var, sigma_ref=0.1, depth=depth, max_relative_sigma=0.2, fallback_weight=0.3)
        np.testing.assert_allclose(w, [[0.2, 1 / 17, 0.3, 0.3]])
        # relative reference: sigma / depth 0.05 weighs 0.5 at any depth
        rel = weights_from_variance(var, sigma_ref=0.1, depth=depth, relative_sigma_ref=0.05)
        np.testing.assert_allclose(rel, 1 / (1 + np.array([[0.01, 0.04, 0.41**2 / 4, 0.09]]) / 0.05**2))
        far = weights_from_variance(var * 9, sigma_ref=0.1, depth=depth * 3, relative_sigma_ref=0.05)
        np.testing.assert_allclose(far, rel)
        # without the cut the same formula everywhere
        np.testing.assert_allclose(weights_from_variance(var, sigma_ref=0.1)[0, 2:], [1 / (1 + 0.41**2 / 0.01), 1 / 37])
        with pytest.raises(InvalidInputError, match="depth"):
            weights_from_variance(var, sigma_ref=0.1, max_relative_sigma=0.2)
        with pytest.raises(ShapeError, match="depth"):
            weights_from_variance(var, sigma_ref=0.1, depth=np.ones((2, 2)), max_relative_sigma=0.2)
        with pytest.raises(InvalidInputError, match="max_relative_sigma"):
            weights_from_variance(var, sigma_ref=0.1, depth=depth, max_relative_sigma=0.0)
        with pytest.raises(InvalidInputError, match="fallback_weight"):
            weights_from_variance(var, sigma_ref=0.1, depth=depth, max_relative_sigma=0.2, fallback_weight=1.5)

    def test_weights_for_applies_the_config_and_the_frames_points(self):
        var = np.array([[0.01, 0.36]])
        depth = np.full(var.shape, 2.0)
        from gpdepth3d.mapping.mapper_config import MAPPER_FUSION

        cfg = FusionConfig()
        assert (cfg.max_relative_sigma, cfg.relative_sigma_ref, cfg.fallback_weight) == (0.2, None, 0.5)
        assert MAPPER_FUSION == FusionConfig(relative_sigma_ref=0.05)
        rel = TSDFFusion(CAM, MAPPER_FUSION)
        # informed pixel: sigma / depth 0.05 -> 0.5; uninformed: the fallback, which the frame's points lower
        np.testing.assert_allclose(rel.weights_for(var, depth, points=0), [[0.5, 0.5]])
        np.testing.assert_allclose(rel.weights_for(var, depth, points=10), [[0.5, 0.5 * np.exp(-1)]])
        assert rel.weights_for(var, depth, points=400)[0, 1] == 0.0
        # in metres (the default): sigma 0.1 m -> 0.5
        np.testing.assert_allclose(TSDFFusion(CAM).weights_for(var, depth, points=400), [[0.5, 0.0]])
        assert cfg.fallback_for(0) == 0.5 and cfg.fallback_for(5) > cfg.fallback_for(6)
        with pytest.raises(InvalidInputError, match="points"):
            cfg.fallback_for(-1)
        absolute = FusionConfig(max_relative_sigma=None, relative_sigma_ref=None)
        np.testing.assert_allclose(TSDFFusion(CAM, absolute).weights_for(var), [[0.5, 1 / 37]])
        assert TSDFFusion(CAM, FusionConfig(weighting="uniform")).weights_for(var) is None
        with pytest.raises(InvalidInputError, match="depth"):
            TSDFFusion(CAM).weights_for(var)

    def test_config_validation(self):
        for bad in (0.0, -0.1, np.nan, True):
            with pytest.raises(InvalidInputError, match="max_relative_sigma"):
                FusionConfig(max_relative_sigma=bad)
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
            assert fusion.integrate(_plane(PLANE_Z), _shift(x), rgb=rgb).voxels > 0
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
        cfg = FusionConfig(
            voxel_size=0.02,
            truncation=0.06,
            weight_threshold=0.0,
            sigma_ref=0.1,
            relative_sigma_ref=None,
            max_relative_sigma=None,
        )
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
        with pytest.raises(EmptyInputError):
            fusion.integrate(-_plane(), np.eye(4))  # negative depths are masked: nothing left
        with pytest.raises(EmptyInputError):
            fusion.integrate(np.zeros(CAM.shape), np.eye(4))
        with pytest.raises(EmptyInputError):
            fusion.integrate(_plane(9.0), np.eye(4))  # beyond depth_max
        with pytest.raises(EmptyInputError):
            fusion.integrate(_plane(), np.eye(4), weights=np.zeros(CAM.shape))
        assert fusion.frames_integrated == 0
        with pytest.raises(InvalidInputError):
            TSDFFusion("camera")  # type: ignore[arg-type]


class TestTruncationFromVariance:
    """``truncation_sigma``: each pixel's truncation follows its depth sigma."""

    def test_pixel_truncation_and_validation(self):
        cfg = FusionConfig(voxel_size=0.02, truncation=0.08, truncation_sigma=2.0, truncation_max=0.3)
        var = np.array([[0.0, 0.05**2, 0.1**2], [0.5**2, np.nan, -1.0]])
        np.testing.assert_allclose(
            cfg.pixel_truncation(var, var.shape), [[0.08, 0.1, 0.2], [0.3, 0.08, 0.08]], rtol=1e-6
        )
        assert cfg.pixel_truncation(None, (2, 3)).tolist() == [[np.float32(0.08)] * 3] * 2
        assert cfg.tsdf_scale == 0.3 and FusionConfig(truncation=0.08).tsdf_scale == 0.08
        off = FusionConfig(voxel_size=0.02, truncation=0.08)  # the default: fixed truncation, variance or not
        np.testing.assert_array_equal(off.pixel_truncation(var, var.shape), np.full(var.shape, np.float32(0.08)))
        with pytest.raises(ShapeError):
            cfg.pixel_truncation(var, (3, 2))
        for bad in (
            dict(truncation_sigma=-1.0),
            dict(truncation_sigma=np.nan),
            dict(truncation_sigma=1.0, truncation_max=0.05),
        ):
            with pytest.raises(InvalidInputError):
                FusionConfig(voxel_size=0.02, truncation=0.08, **bad)
        FusionConfig(voxel_size=0.02, truncation=0.5)  # truncation_max only matters with truncation_sigma > 0

    def test_uncertain_pixels_fall_back_by_the_frames_points(self):
        # left half a plane at 1.5 m with sigma 0.1 m (7 %), right half one at 1.8 m with sigma 0.4 m
        # (22 %, uninformed): a frame with many points leaves the right half out, one without points
        # fuses it with the fallback weight; without the cut both halves by their variance
        depth, var = _plane(1.5), np.full(CAM.shape, 0.01)
        depth[:, CAM.width // 2 :] = 1.8
        var[:, CAM.width // 2 :] = 0.16

        def surfaces(cut, points):
            fusion = TSDFFusion(
                CAM, FusionConfig(voxel_size=0.02, truncation=0.06, max_relative_sigma=cut, weight_threshold=0.01)
            )
            fusion.integrate(depth, np.eye(4), weights=fusion.weights_for(var, depth, points=points), variance=var)
            z = fusion.extract_mesh().vertices[:, 2]
            return bool(np.abs(z - 1.5).min() < 0.01), bool(np.abs(z - 1.8).min() < 0.01)

        assert surfaces(0.2, 400) == (True, False)
        assert surfaces(0.2, 0) == (True, True)
        assert surfaces(None, 400) == (True, True)
        assert surfaces(0.25, 400) == (True, True)
        # a frame with every pixel above the cut and many points has nothing to fuse
        fusion = TSDFFusion(CAM)
        with pytest.raises(EmptyInputError):
            fusion.integrate(
                _plane(1.8), np.eye(4), weights=fusion.weights_for(np.full(CAM.shape, 0.16), _plane(1.8), points=400)
            )

    @pytest.mark.parametrize("sigma_far, expected", [(0.3, 1.461), (0.4, 1.437)])
    def test_disagreeing_frames_meet_at_their_weighted_mean(self, sigma_far, expected):
        # two readings of a plane 30 cm apart (1.311 m, sigma 0.3 m; 1.611 m, sigma_far): with the
        # truncation following sigma one surface at the mean weighted by 1 / (1 + var / sigma_ref^2);
        # with the fixed 8 cm truncation two surfaces, at each reading
        def fused(k):
            fusion = TSDFFusion(
                CAM,
                FusionConfig(
                    voxel_size=0.02,
                    truncation=0.08,
                    truncation_sigma=k,
                    truncation_max=0.4,
                    sigma_ref=0.3,
                    weight_threshold=0.3,
                    max_relative_sigma=None,
                    relative_sigma_ref=None,
                ),
            )
            for z, s in ((1.311, 0.3), (1.611, sigma_far)):
                v = np.full(CAM.shape, s**2)
                fusion.integrate(_plane(z), np.eye(4), weights=fusion.weights_for(v), variance=v)
            vert = fusion.extract_mesh().vertices
            return vert[(np.abs(vert[:, 0]) < 0.3) & (np.abs(vert[:, 1]) < 0.2), 2]

        w = 1 / (1 + np.array([0.3, sigma_far]) ** 2 / 0.3**2)
        assert (w @ [1.311, 1.611]) / w.sum() == pytest.approx(expected, abs=1e-3)
        z = fused(1.0)
        assert np.all(np.abs(z - expected) < 2e-3)
        z_fixed = fused(0.0)
        assert np.abs(z_fixed - 1.311).min() < 1e-3 and np.abs(z_fixed - 1.611).min() < 1e-3

    def test_band_and_update_match_torch_and_reach_the_wide_band(self):
        rng = np.random.default_rng(21)
        cfg = FusionConfig(
            voxel_size=0.02, truncation=0.06, truncation_sigma=1.5, truncation_max=0.3, integrate_variance=True
        )
        compiled, reference = TSDFFusion(CAM, cfg), TSDFFusion(CAM, cfg)
        reference._update = reference._update_torch  # type: ignore[method-assign]
        reference._band_keys = compiled._band_keys  # the same blocks: compare the update alone
        bs = cfg.voxel_size * cfg.block_resolution
        for i in range(3):
            T = _shift(0.05 * i, 0.02 * i)
            u_grid = np.arange(CAM.width)[None, :] * np.ones((CAM.height, 1))
            d = 1.2 + 0.5 * rng.random() + 0.2 * np.sin(u_grid / 5.0)
            var = (0.02 + 0.25 * u_grid / CAM.width) ** 2  # truncation 6 cm on the left to 30 cm on the right
            trunc = cfg.pixel_truncation(var, d.shape)
            assert trunc.min() == np.float32(0.06) and trunc.max() == np.float32(0.3)
            d32 = d.astype(np.float32)
            ours, ref = compiled._band_keys(d32, T, trunc), compiled._band_keys_torch(d32, T, trunc)
            assert np.intersect1d(ours, ref).size >= 0.995 * max(ours.size, ref.size)
            np.testing.assert_array_equal(compiled.block_keys(d, T, var), ours)
            assert ours.size > compiled._band_keys(d32, T).size  # wider than the fixed band
            v, u = np.nonzero(d32 > 0)
            rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones(u.size)], 1)
            offs = np.linspace(-1.0, 1.0, 33)[None, :, None] * trunc[v, u][:, None, None]
            pts = (rays[:, None, :] * (d32[v, u][:, None, None] + offs)).reshape(-1, 3)
            assert np.isin(np.unique(_keys_of(pts @ T[:3, :3].T + T[:3, 3], bs)), ours).mean() > 0.9
            kw = dict(
                weights=fusion_weights(var), variance=var, rgb=rng.integers(0, 255, CAM.shape + (3,), dtype=np.uint8)
            )
            n1, n2 = compiled.integrate(d, T, **kw).voxels, reference.integrate(d, T, **kw).voxels
            # torch computes in float32: voxels within rounding of a half pixel or of a band end differ
            assert abs(n1 - n2) <= 0.003 * n2 and n1 > 1000
        a, b = _sorted_voxels(compiled), _sorted_voxels(reference)
        ka = {c: i for i, c in enumerate(map(tuple, np.round(a["coords"], 4)))}
        pairs = np.array([(ka[c], j) for j, c in enumerate(map(tuple, np.round(b["coords"], 4))) if c in ka])
        assert len(pairs) >= 0.998 * max(len(ka), len(b["coords"]))
        for k in ("tsdf", "weight", "variance"):
            # the wide band keeps more voxels unclipped, where the other pixel of a half-pixel tie
            # (float32 vs float64 projection) gives another value: ~1 % of the voxels after 3 frames
            assert np.isclose(a[k][pairs[:, 0]], b[k][pairs[:, 1]], rtol=1e-5, atol=1e-5).mean() > 0.98, k
        assert 0.5 < np.abs(a["tsdf"]).max() <= 1.0 + 1e-6  # stored / truncation_max (float32 truncations)

    def test_reset_and_reintegrate_equals_from_scratch(self):
        rng = np.random.default_rng(5)
        cfg = FusionConfig(
            voxel_size=0.02, truncation=0.06, truncation_sigma=1.0, truncation_max=0.25, integrate_variance=True
        )
        depths = [1.4 + 0.3 * rng.random(CAM.shape) for _ in range(3)]
        variances = [rng.uniform(0.0, 0.3, CAM.shape) ** 2 for _ in range(3)]
        poses = [_shift(0.1 * i) for i in range(3)]
        fusion = TSDFFusion(CAM, cfg)
        stats = [
            fusion.integrate(d, T, variance=v, weights=fusion_weights(v)) for d, T, v in zip(depths, poses, variances)
        ]
        moved = list(poses)
        moved[1] = _shift(0.16, 0.03)
        affected = np.union1d(stats[1].block_keys, fusion.block_keys(depths[1], moved[1], variances[1]))
        fusion.reset_blocks(affected)
        for d, T, v in zip(depths, moved, variances):
            fusion.integrate(d, T, variance=v, weights=fusion_weights(v), blocks=affected)
        scratch = TSDFFusion(CAM, cfg)
        for d, T, v in zip(depths, moved, variances):
            scratch.integrate(d, T, variance=v, weights=fusion_weights(v))
        a, b = _sorted_voxels(fusion), _sorted_voxels(scratch)
        assert a["coords"].shape == b["coords"].shape
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])


def fusion_weights(var: np.ndarray) -> np.ndarray:
    return weights_from_variance(var, sigma_ref=0.1)


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
        break_writes("gpdepth3d.mapping.tsdf.storage")
        with pytest.raises(OSError):
            save_mesh(mesh, tmp_path / "m.glb")
        assert list(tmp_path.iterdir()) == []


def _sorted_voxels(fusion: TSDFFusion) -> dict[str, np.ndarray]:
    vox = fusion.voxels()
    order = np.lexsort(vox["coords"].T)
    return {k: v[order] for k, v in vox.items()}


class TestRobustness:
    def test_negative_and_nan_depths_are_masked_and_counted(self):
        depth = _plane()
        depth[0, :5] = -0.07  # a GP mean that dipped below zero next to an outlier
        depth[1, :3] = np.nan
        depth[2, :2] = np.inf
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06))
        stats = fusion.integrate(depth, np.eye(4))
        assert stats.invalid_pixels == 10
        assert stats.pixels == CAM.width * CAM.height - 10
        assert stats.voxels > 0 and stats.block_keys.size > 0
        clean = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06))
        mask = np.isfinite(depth) & (depth > 0)
        clean.integrate(np.where(mask, depth, 0.0), np.eye(4))
        a, b = _sorted_voxels(fusion), _sorted_voxels(clean)
        np.testing.assert_array_equal(a["tsdf"], b["tsdf"])

    def test_pixels_out_of_range_unweighted_or_without_variance_are_not_fused(self):
        rng = np.random.default_rng(5)
        depth = _plane() + rng.uniform(-0.05, 0.05, CAM.shape)
        depth[3, :4] = 0.05  # below depth_min
        depth[4, :3] = 6.0  # beyond depth_max
        depth[5, 0] = -1.0  # invalid, counted
        weights = rng.uniform(0.2, 1.0, CAM.shape)
        weights[6, :5] = 0.0
        variance = np.full(CAM.shape, 1e-4, np.float32)
        variance[7, :2] = np.nan
        variance[8, :6] = -1.0
        cfg = FusionConfig(voxel_size=0.02, truncation=0.06, integrate_variance=True, depth_max=5.0)
        fusion = TSDFFusion(CAM, cfg)
        stats = fusion.integrate(depth.astype(np.float32), np.eye(4), weights=weights, variance=variance)
        kept = (
            (depth > cfg.depth_min) & (depth < cfg.depth_max) & (weights > 0) & np.isfinite(variance) & (variance >= 0)
        )
        assert stats.invalid_pixels == 1 and stats.pixels == kept.sum() == CAM.width * CAM.height - 21
        # the same voxels as the frame with those pixels set to no depth
        clean = TSDFFusion(CAM, cfg)
        clean.integrate(
            np.where(kept, depth, 0.0).astype(np.float32),
            np.eye(4),
            weights=weights,
            variance=np.where(kept, variance, 0.0),
        )
        a, b = _sorted_voxels(fusion), _sorted_voxels(clean)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
        weights[9, 9] = np.nan
        with pytest.raises(InvalidInputError, match="weights"):
            fusion.integrate(depth, np.eye(4), weights=weights, variance=variance)

    def test_empty_mesh_allowed(self):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, weight_threshold=5.0))
        fusion.integrate(_plane(), np.eye(4), weights=np.full(CAM.shape, 0.1))
        with pytest.raises(EmptyInputError):
            fusion.extract_mesh()
        assert len(fusion.extract_mesh(allow_empty=True).faces) == 0


class TestMemoryGuard:
    @pytest.mark.parametrize("voxel", [1e-5, 1e-4, 1e-3])
    def test_a_voxel_that_would_exhaust_memory_is_refused_up_front(self, voxel, monkeypatch):
        import resource
        import time

        import gpdepth3d.mapping.tsdf.fusion as fusion_module

        monkeypatch.setattr(fusion_module, "memory_limit", lambda: 2**30)  # a 1 GiB machine
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=voxel, truncation=0.06, block_count=64))
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        with pytest.raises(ProblemTooLargeError, match=f"voxel_size: .*got {voxel} m"):
            fusion.integrate(_plane(), np.eye(4))
        assert time.perf_counter() - t0 < 1.0
        assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100_000  # KiB: nothing large was allocated
        assert fusion.frames_integrated == 0

    def test_sizes_that_fit_pass_and_a_huge_initial_grid_is_refused(self, monkeypatch):
        import gpdepth3d.mapping.tsdf.fusion as fusion_module

        monkeypatch.setattr(fusion_module, "memory_limit", lambda: 2**30)
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.01, truncation=0.04))
        assert fusion.integrate(_plane(), np.eye(4)).voxels > 0
        with pytest.raises(ProblemTooLargeError, match="block_count"):
            TSDFFusion(CAM, FusionConfig(voxel_size=0.01, truncation=0.04, block_count=10**6))
        assert 0 < fusion_module.memory_limit() and fusion.block_bytes == 8**3 * 4 * 5


class TestReintegration:
    @pytest.mark.parametrize("color", [True, False])
    def test_reset_and_reintegrate_equals_from_scratch(self, color):
        rng = np.random.default_rng(3)
        cfg = FusionConfig(
            voxel_size=0.02, truncation=0.06, integrate_variance=True, integrate_color=color, weight_cap=2.5
        )
        depths = [1.4 + 0.3 * rng.random(CAM.shape) for _ in range(4)]
        variances = [rng.uniform(0.001, 0.02, CAM.shape) for _ in range(4)]
        rgbs = [rng.integers(0, 255, CAM.shape + (3,), dtype=np.uint8) for _ in range(4)]
        poses = [_shift(0.1 * i) for i in range(4)]
        fusion = TSDFFusion(CAM, cfg)
        stats = [
            fusion.integrate(d, T, variance=v, rgb=c, weights=1 / (1 + v))
            for d, T, v, c in zip(depths, poses, variances, rgbs)
        ]
        moved = list(poses)
        moved[1] = _shift(0.13, 0.02)
        affected = np.union1d(stats[1].block_keys, fusion.block_keys(depths[1], moved[1]))
        assert fusion.reset_blocks(affected) >= np.unique(stats[1].block_keys).size  # plus new ones other frames made
        for d, T, v, c in zip(depths, moved, variances, rgbs):
            fusion.integrate(d, T, variance=v, rgb=c, weights=1 / (1 + v), blocks=affected)
        scratch = TSDFFusion(CAM, cfg)
        for d, T, v, c in zip(depths, moved, variances, rgbs):
            scratch.integrate(d, T, variance=v, rgb=c, weights=1 / (1 + v))
        a, b = _sorted_voxels(fusion), _sorted_voxels(scratch)
        assert a.keys() == b.keys() and a["coords"].shape == b["coords"].shape
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
        # and the moved frame really changed the volume
        unmoved = TSDFFusion(CAM, cfg)
        for d, T, v, c in zip(depths, poses, variances, rgbs):
            unmoved.integrate(d, T, variance=v, rgb=c, weights=1 / (1 + v))
        assert _sorted_voxels(unmoved)["coords"].shape != a["coords"].shape or not np.array_equal(
            _sorted_voxels(unmoved)["tsdf"], a["tsdf"]
        )

    def test_variance_needed_and_carried_to_points(self):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, integrate_variance=True))
        with pytest.raises(InvalidInputError):
            fusion.integrate(_plane(), np.eye(4))
        var = np.full(CAM.shape, 0.04)
        fusion.integrate(_plane(), np.eye(4), variance=var)
        fusion.integrate(_plane(), _shift(0.02), variance=np.full(CAM.shape, 0.01), weights=np.full(CAM.shape, 3.0))
        cloud = fusion.extract_point_cloud()
        # weighted mean of the variances (1 * 0.04 + 3 * 0.01) / 4 where both frames saw the voxel
        assert np.all(np.isfinite(cloud.variance))
        assert np.median(cloud.variance) == pytest.approx(0.0175, rel=1e-4)
        with pytest.raises(ShapeError):
            fusion.integrate(_plane(), np.eye(4), variance=var[:-1])


class TestPersistence:
    def test_save_load_round_trip(self, tmp_path: Path):
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, integrate_variance=True))
        fusion.integrate(
            _plane(), np.eye(4), variance=np.full(CAM.shape, 0.01), rgb=np.full(CAM.shape + (3,), 90, np.uint8)
        )
        path = fusion.save(tmp_path / "map" / "volume.npz")
        assert sorted(p.name for p in path.parent.iterdir()) == ["volume.json", "volume.npz"]
        loaded = TSDFFusion.load(path)
        assert loaded.config == fusion.config and loaded.camera == fusion.camera and loaded.frames_integrated == 1
        a, b = _sorted_voxels(fusion), _sorted_voxels(loaded)
        np.testing.assert_array_equal(a["coords"], b["coords"])  # the same observed voxels
        np.testing.assert_allclose(b["tsdf"], a["tsdf"], rtol=0, atol=1.01 / 32767)  # fixed point
        np.testing.assert_allclose(b["weight"], a["weight"], rtol=2.0**-11)  # half precision
        np.testing.assert_allclose(b["variance"], a["variance"], rtol=2.0**-10)  # a half-precision sigma
        np.testing.assert_allclose(b["color"], a["color"], rtol=0, atol=0.5 / 255)  # 8 bits
        meta = json.loads(path.with_suffix(".json").read_text())
        assert meta["format"] == "gpdepth3d-blocks-1" and meta["blocks"] == fusion.vbg.hashmap().size()
        with np.load(path) as d:  # only the allocated blocks, sorted by key
            keys = blocks_to_keys(d["blocks"])
            assert d["blocks"].shape == (fusion.vbg.hashmap().size(), 3) and np.all(np.diff(keys) > 0)
        with np.load(path) as d, np.load(loaded.save(tmp_path / "again" / "volume.npz")) as e:
            assert d.files == e.files and all(np.array_equal(d[k], e[k]) for k in d.files)  # saved again: the same
        from scipy.spatial import cKDTree

        before, after = fusion.extract_mesh(), loaded.extract_mesh()
        assert len(after.faces) == len(before.faces)
        assert cKDTree(before.vertices).query(after.vertices)[0].max() < 1e-5  # metres
        # the loaded volume keeps integrating
        loaded.integrate(_plane(), _shift(0.05), variance=np.full(CAM.shape, 0.01))
        assert len(loaded.extract_mesh().faces) > 100
        with pytest.raises(InvalidInputError):
            fusion.save(tmp_path / "volume.vbg")
        with pytest.raises(DataFormatError):
            TSDFFusion.load(tmp_path / "missing.npz")
        (tmp_path / "bad.npz").write_bytes(b"not a zip")
        (tmp_path / "bad.json").write_text((tmp_path / "map" / "volume.json").read_text())
        with pytest.raises(DataFormatError):
            TSDFFusion.load(tmp_path / "bad.npz")


class TestThreads:
    def test_cpu_threads_restored_and_validated(self):
        import torch

        before = torch.get_num_threads()
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06, cpu_threads=1))
        fusion.integrate(_plane(), np.eye(4))
        assert torch.get_num_threads() == before
        with pytest.raises(InvalidInputError):
            FusionConfig(cpu_threads=-1)
        with pytest.raises(InvalidInputError):
            FusionConfig(cpu_threads=1.5)


def _centroids(mesh) -> np.ndarray:
    c = np.asarray(mesh.vertices)[np.asarray(mesh.faces)].mean(axis=1)
    return c[np.lexsort(c.T)]


class TestIncrementalMesh:
    def test_same_surface_as_full_extraction(self):
        rng = np.random.default_rng(5)
        cfg = FusionConfig(voxel_size=0.02, truncation=0.06, block_resolution=4)
        fusion = TSDFFusion(CAM, cfg)
        with pytest.raises(EmptyInputError):
            fusion.extract_mesh_incremental()
        poses = [_shift(0.0), _shift(0.3), _shift(0.6, 0.1), _shift(1.5)]
        stats = []
        for i, T in enumerate(poses):
            depth = (
                1.2 + 0.4 * rng.random() + 0.05 * np.sin(np.arange(CAM.width) / 7.0)[None, :] * np.ones((CAM.height, 1))
            )
            stats.append(fusion.integrate(depth, T, rgb=np.full(CAM.shape + (3,), 40 * i, np.uint8)))
            inc, full = fusion.extract_mesh_incremental(), fusion.extract_mesh()
            assert len(inc.faces) == len(full.faces) > 100
            np.testing.assert_allclose(_centroids(inc), _centroids(full), atol=1e-9)
        # nothing changed: the cached surface; a reset plus re-integration: updated
        assert len(fusion.extract_mesh_incremental().faces) == len(full.faces)
        fusion.reset_blocks(stats[3].block_keys)
        inc, full = fusion.extract_mesh_incremental(allow_empty=True), fusion.extract_mesh()
        np.testing.assert_allclose(_centroids(inc), _centroids(full), atol=1e-9)
        # colours come along
        assert inc.visual.vertex_colors.shape[0] == len(inc.vertices)


class TestCompiledUpdate:
    """The CPU's compiled voxel update and band search against the torch implementation (CUDA's).

    The camera's principal point is off the half pixel and the poses rotate, so that (almost) no
    voxel projects exactly onto a half pixel: float32 (torch) and float64 (here) round such ties
    either way.
    """

    CAM = PinholeCamera(120.0, 121.0, 39.37, 29.61, 80, 60)

    @staticmethod
    def _frames(rng):
        import cv2

        poses = []
        for k, (x, y) in enumerate([(0.0113, 0.0031), (0.0712, 0.0207), (-0.0493, 0.0411)]):
            T = _shift(x, y)
            T[:3, :3] = cv2.Rodrigues(np.array([0.013 * k + 0.002, -0.07 * k + 0.003, 0.021 * k]))[0]
            poses.append(T)
        depths = []
        cam = TestCompiledUpdate.CAM
        for _ in poses:
            d = 1.3 + 0.6 * rng.random() + 0.2 * np.sin(np.arange(cam.width) / 5.0)[None, :] * np.ones((cam.height, 1))
            d[rng.random(cam.shape) < 0.05] = 0.0  # holes
            depths.append(d)
        return poses, depths

    def test_band_blocks_are_the_torch_ones_and_cover_the_band(self):
        rng = np.random.default_rng(11)
        poses, depths = self._frames(rng)
        cfg = FusionConfig(voxel_size=0.02, truncation=0.08, block_resolution=4)
        fusion = TSDFFusion(self.CAM, cfg)
        cam, bs = self.CAM, cfg.voxel_size * cfg.block_resolution
        for d, T in zip(depths, poses):
            d32 = d.astype(np.float32)
            ours, ref = fusion._band_keys(d32, T), fusion._band_keys_torch(d32, T)
            assert np.all(np.diff(ours) > 0)  # sorted, unique
            # the same samples (float rounding may put one on either side of a block face)
            common = np.intersect1d(ours, ref).size
            assert common >= 0.995 * max(ours.size, ref.size) and ours.size > 50
            # the band itself: every valid pixel's ray densely through [d - trunc, d + trunc]
            v, u = np.nonzero(d32 > 0)
            rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(u.size)], 1)
            offs = np.linspace(-cfg.truncation, cfg.truncation, 33)
            pts = (rays[:, None, :] * (d32[v, u][:, None, None] + offs[None, :, None])).reshape(-1, 3)
            dense = np.unique(_keys_of(pts @ T[:3, :3].T + T[:3, 3], bs))
            assert np.isin(dense, ours).mean() > 0.9  # tiles' centre rays: slivers at block faces are missed
            fusion.BAND_CONSERVATIVE = True
            wide, wide_ref = fusion._band_keys(d32, T), fusion._band_keys_torch(d32, T)
            fusion.BAND_CONSERVATIVE = False
            assert np.isin(dense, wide).mean() > 0.995 and np.isin(ours, wide).all()
            assert np.intersect1d(wide, wide_ref).size >= 0.995 * max(wide.size, wide_ref.size)
        assert fusion._band_keys(np.zeros(self.CAM.shape, np.float32), np.eye(4)).size == 0
        assert fusion._band_keys_torch(np.zeros(self.CAM.shape, np.float32), np.eye(4)).size == 0

    @pytest.mark.parametrize("color, variance", [(True, True), (False, False)])
    def test_voxels_match_the_torch_update(self, color, variance):
        rng = np.random.default_rng(12)
        poses, depths = self._frames(rng)
        cfg = FusionConfig(
            voxel_size=0.02, truncation=0.06, integrate_color=color, integrate_variance=variance, weight_cap=2.5
        )
        cam = self.CAM
        compiled, reference = TSDFFusion(cam, cfg), TSDFFusion(cam, cfg)
        reference._update = reference._update_torch  # type: ignore[method-assign]
        reference._band_keys = compiled._band_keys  # the same blocks for both: compare the update alone
        for d, T in zip(depths, poses):
            kw = dict(
                rgb=rng.integers(0, 255, cam.shape + (3,), dtype=np.uint8), weights=rng.uniform(0.2, 1.0, cam.shape)
            )
            if variance:
                kw["variance"] = rng.uniform(0.001, 0.02, cam.shape)
            n1, n2 = compiled.integrate(d, T, **kw).voxels, reference.integrate(d, T, **kw).voxels
            assert abs(n1 - n2) <= 0.001 * n2 and n1 > 1000
        a, b = _sorted_voxels(compiled), _sorted_voxels(reference)
        assert a.keys() == b.keys()
        # the same voxels observed, with the same values, up to voxels whose projection lies
        # within float32 rounding of a half pixel
        ca, cb = {tuple(c) for c in np.round(a["coords"], 4)}, {tuple(c) for c in np.round(b["coords"], 4)}
        assert len(ca ^ cb) <= 0.002 * len(cb)
        ka = {c: i for i, c in enumerate(map(tuple, np.round(a["coords"], 4)))}
        pairs = np.array([(ka[c], j) for j, c in enumerate(map(tuple, np.round(b["coords"], 4))) if c in ka])
        assert len(pairs) >= 0.998 * len(cb)
        for k in a:
            close = np.isclose(a[k][pairs[:, 0]], b[k][pairs[:, 1]], rtol=1e-5, atol=1e-5).reshape(len(pairs), -1)
            assert np.all(close, axis=1).mean() > 0.995, k


def _keys_of(points: np.ndarray, block_size: float) -> np.ndarray:
    from gpdepth3d.mapping.tsdf.blocks import blocks_to_keys

    return blocks_to_keys(np.floor(points / block_size).astype(np.int64))
