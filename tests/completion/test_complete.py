"""Tests of gpdepth3d.completion.complete: input rules, build_problem, complete(), DepthCompleter, DepthPosterior."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gpdepth3d.completion.complete import (
    DepthCompleter,
    DepthPosterior,
    PosteriorWarning,
    build_problem,
    check_mde_depth,
    complete,
)
from gpdepth3d.errors import DataFormatError, EmptyInputError, InvalidDepthError, ShapeError
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.io import load_depth
from gpdepth3d.measurements import SparseDepth, downsample_depth
from gpdepth3d.metrics import calibration_metrics, depth_metrics
from gpdepth3d.gp.engine import EngineConfig

EXACT = DepthGPConfig.paper()
RESIDUAL = DepthGPConfig.residual()
EXACT_ENGINE = EngineConfig(name="exact")


def small_inputs(h=8, w=10, seed=0):
    rng = np.random.default_rng(seed)
    mde = rng.uniform(2.0, 4.0, size=(h, w))
    sparse = SparseDepth(np.array([1.0, 7.0, 4.0]), np.array([2.0, 5.0, 7.0]), np.array([3.0, 2.5, 3.5]), (h, w))
    return mde, sparse


class TestCheckMdeDepth:
    def test_invalid_pixels_become_zero(self):
        d = np.array([[1.0, np.nan], [np.inf, 0.0], [-np.inf, 2.0]])
        out, valid = check_mde_depth(d)
        np.testing.assert_array_equal(out, [[1.0, 0.0], [0.0, 0.0], [0.0, 2.0]])
        np.testing.assert_array_equal(valid, [[True, False], [False, False], [False, True]])
        out, _ = check_mde_depth(np.full((2, 2), 3, dtype=np.uint16))  # integer maps are accepted
        assert out.dtype == np.float64

    @pytest.mark.parametrize(
        "d, error",
        [
            (np.ones(5), ShapeError),
            (np.ones((1, 5)), ShapeError),
            (np.ones((3, 3, 1)), ShapeError),
            (np.full((3, 3), "a"), ShapeError),
            (np.ones((3, 3), dtype=complex), ShapeError),
            (np.array([[1.0, -0.5], [1.0, 1.0]]), InvalidDepthError),
        ],
    )
    def test_errors(self, d, error):
        with pytest.raises(error):
            check_mde_depth(d)

    def test_errors_count_the_bad_depths_and_name_the_first_outside_the_range(self):
        d = np.array([[1.0, -0.5, -np.inf, np.nan], [-2.0, 3e6, 1.0, 1e-7]])  # -inf and NaN: no depth, not negative
        with pytest.raises(InvalidDepthError, match="2 negative"):
            check_mde_depth(d)
        d = np.array([[1.0, np.inf, 1e-7, 2.0], [3e6, 1.0, 5e-7, 1.0]])  # inf: no depth, not outside
        with pytest.raises(InvalidDepthError, match=r"3 outside, e\.g\. 1e-07"):
            check_mde_depth(d)


class TestBuildProblem:
    def test_balanced(self):
        mde, sparse = small_inputs()
        problem, grid, scale, align = build_problem(mde, sparse, EXACT)
        assert scale == pytest.approx(np.median(mde)) and align.scale == 1.0
        np.testing.assert_allclose(problem.prior_mean, mde.mean())
        s_dl, s_m = 0.05 * scale, 0.001 * scale
        r, c = 2, 1  # the first point: MDE and measurement combine by precision
        p = 1 / s_dl**2 + 1 / s_m**2
        assert problem.precision[r, c] == pytest.approx(p)
        assert problem.obs[r, c] == pytest.approx((mde[r, c] / s_dl**2 + 3.0 / s_m**2) / p)
        assert problem.kernel.outputscale == pytest.approx(scale)

    def test_residual_aligns_the_prior(self):
        mde, _ = small_inputs()
        rows, cols = np.array([1, 3, 6, 7]), np.array([2, 8, 4, 0])
        sparse = SparseDepth(cols.astype(float), rows.astype(float), 1.25 * mde[rows, cols], mde.shape)
        problem, _, _, align = build_problem(mde, sparse, RESIDUAL)
        assert align.scale == pytest.approx(1.25)
        np.testing.assert_allclose(problem.prior_mean, 1.25 * mde)
        assert np.count_nonzero(problem.precision) == 4

    def test_points_at_another_resolution_keep_the_closest(self):
        mde = np.full((4, 6), 3.0)
        # Two points at twice the resolution fall into MDE pixel (1, 2): the nearer one is used.
        sparse = SparseDepth(np.array([4.0, 5.0]), np.array([2.0, 3.0]), np.array([2.0, 1.5]), (8, 12))
        problem, grid, _, _ = build_problem(mde, sparse, RESIDUAL)
        assert len(grid) == 1 and grid.depth[0] == 1.5 and grid.image_size == (4, 6)
        assert problem.obs[1, 2] == 1.5

    def test_errors(self):
        mde, sparse = small_inputs()
        with pytest.raises(ShapeError, match="aspect"):
            build_problem(mde, SparseDepth.empty((8, 20)), EXACT)  # another aspect ratio
        with pytest.raises(ShapeError):
            build_problem(mde, {"u": [1]}, EXACT)  # type: ignore[arg-type]
        with pytest.raises(EmptyInputError):
            build_problem(np.zeros((8, 10)), SparseDepth.empty((8, 10)), EXACT)
        with pytest.raises(EmptyInputError):
            build_problem(np.full((8, 10), np.nan), SparseDepth.empty((16, 20)), RESIDUAL)
        with pytest.raises(ShapeError):
            build_problem(mde, sparse, EXACT, output_shape=(0, 5))


class TestComplete:
    def test_shapes_and_fields(self):
        mde, sparse = small_inputs()
        post = complete(mde, sparse, config=EXACT, engine=EXACT_ENGINE)
        assert isinstance(post, DepthPosterior)
        assert post.mean.shape == post.variance.shape == post.mde.shape == post.shape == (8, 10)
        np.testing.assert_allclose(post.std, np.sqrt(post.variance))
        assert set(post.timings) >= {"setup", "solve"} and post.config == EXACT
        np.testing.assert_array_equal(post.mde, mde)

    def test_upsampled_output(self):
        mde, sparse = small_inputs()
        post = complete(mde, sparse, config=RESIDUAL, engine=EXACT_ENGINE, output_shape=(16, 20))
        assert post.mean.shape == post.variance.shape == post.mde.shape == (16, 20)
        assert np.all(np.isfinite(post.mean)) and np.all(post.variance > 0)

    def test_without_variance(self):
        mde, sparse = small_inputs()
        post = complete(mde, sparse, config=EXACT, engine=EXACT_ENGINE, variance=False)
        assert np.all(np.isnan(post.variance))
        np.testing.assert_allclose(post.mean, complete(mde, sparse, config=EXACT, engine=EXACT_ENGINE).mean)

    def test_measurements_are_honoured(self):
        mde, sparse = small_inputs()
        for cfg in (EXACT, RESIDUAL):
            post = complete(mde, sparse, config=cfg, engine=EXACT_ENGINE)
            at = post.mean[sparse.v.astype(int), sparse.u.astype(int)]
            np.testing.assert_allclose(at, sparse.depth, rtol=0.02)

    def test_empty_sparse_balanced_follows_the_mde(self):
        mde, _ = small_inputs()
        post = complete(mde, SparseDepth.empty(mde.shape), config=EXACT, engine=EXACT_ENGINE)
        rel = (post.mean - mde) / mde
        assert np.sqrt(np.mean(rel**2)) < 0.05
        assert np.corrcoef(post.mean.ravel(), mde.ravel())[0, 1] > 0.9
        scale = np.median(mde)
        assert np.all(post.variance < (0.05 * scale) ** 2)  # each pixel has an MDE observation

    def test_empty_sparse_residual_is_the_prior(self):
        mde, _ = small_inputs()
        post = complete(mde, SparseDepth.empty(mde.shape), config=RESIDUAL, engine=EXACT_ENGINE)
        np.testing.assert_allclose(post.mean, mde)
        scale = np.median(mde)
        np.testing.assert_allclose(post.variance, (RESIDUAL.outputscale * scale) ** 2)
        assert post.alignment.scale == 1.0

    @pytest.mark.parametrize("cfg", [EXACT, RESIDUAL], ids=["balanced", "residual"])
    def test_no_valid_mde_with_measurements(self, cfg):
        _, sparse = small_inputs()
        mde = np.full((8, 10), np.nan)
        post = complete(mde, sparse, config=cfg, engine=EXACT_ENGINE)
        assert np.all(np.isfinite(post.mean)) and np.all(post.variance > 0)
        assert post.depth_scale == pytest.approx(np.median(sparse.depth))
        at = post.mean[sparse.v.astype(int), sparse.u.astype(int)]
        np.testing.assert_allclose(at, sparse.depth, rtol=0.01)
        np.testing.assert_array_equal(post.mde, 0.0)
        far = post.mean[0, 9]
        assert 2.5 <= far <= 3.5  # far from the points: the prior (mean / median of the points)

    def test_same_result_from_the_completer(self):
        mde, sparse = small_inputs()
        completer = DepthCompleter(RESIDUAL, engine=EXACT_ENGINE)
        a = completer(mde, sparse)
        b = completer.complete(mde, sparse)
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.mean, complete(mde, sparse, config=RESIDUAL, engine=EXACT_ENGINE).mean)
        assert DepthCompleter().config == DepthGPConfig()

    def test_synthetic_street(self, tiny_street_frame):
        f = tiny_street_frame
        mde_m = depth_metrics(f.mde, f.depth_gt)
        for cfg in (EXACT, RESIDUAL):
            post = complete(
                f.mde, f.lidar.subset(np.arange(0, len(f.lidar), 3)), config=cfg, engine=EXACT_ENGINE, variance=False
            )
            assert depth_metrics(post.mean, f.depth_gt)["rmse"] < mde_m["rmse"]

    def test_gaussian_presets_say_when_the_mde_scale_is_off_and_when_depths_go_below_zero(self):
        # the paper's model is Gaussian in metres: an MDE in millimetres against points in metres
        # is reported; an MDE in kilometres leaves pixels between the points at or below 0 m,
        # which are counted (frame named) and not clipped
        mde, sparse = small_inputs()
        with pytest.warns(
            PosteriorWarning, match=r"frame 7: the MDE's scale disagrees with the points by a factor of 0\.00"
        ):
            post = complete(mde * 1000.0, sparse, config=EXACT, engine=EXACT_ENGINE, frame="7")
        assert len(post.warnings) == 1 and "factor of" in post.warnings[0]
        with pytest.warns(PosteriorWarning) as record:
            post = complete(mde * 1e-3, sparse, config=EXACT, engine=EXACT_ENGINE, frame="8")
        low = int(np.count_nonzero(post.mean <= 0))
        assert low > 0 and post.mean.min() < 0  # the model's mean, not clipped
        messages = [str(r.message) for r in record]
        assert any(m.startswith(f"frame 8: {low} pixels (") and "<= 0 m" in m for m in messages)
        assert any("factor of 1166" in m for m in messages)
        # a well-scaled frame says nothing
        with warnings.catch_warnings():
            warnings.simplefilter("error", PosteriorWarning)
            post = complete(mde, sparse, config=EXACT, engine=EXACT_ENGINE)
        assert post.warnings == ()
        assert np.all(post.mean > 0)


class TestDepthPosteriorSaveLoad:
    def test_round_trip(self, tmp_path):
        mde, sparse = small_inputs()
        post = complete(mde, sparse, config=RESIDUAL, engine=EXACT_ENGINE)
        written = post.save(tmp_path / "post", png=True)
        assert [p.name for p in written] == ["post.npz", "post_mean.png", "post_std.png"]
        assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
            "post.npz",
            "post_mean.png",
            "post_std.png",
        ]
        assert not any(p.name.startswith(".") or p.is_symlink() for p in tmp_path.iterdir())  # plain files only
        back = DepthPosterior.load(written[0], config=RESIDUAL)
        np.testing.assert_allclose(back.mean, post.mean, rtol=1e-6)
        np.testing.assert_allclose(back.variance, post.variance, rtol=1e-6)
        np.testing.assert_allclose(back.mde, post.mde, rtol=1e-6)
        np.testing.assert_allclose(back.sparse.depth, post.sparse.depth, rtol=1e-6)
        assert back.sparse.image_size == post.sparse.image_size
        assert back.depth_scale == post.depth_scale and back.alignment.scale == post.alignment.scale
        np.testing.assert_allclose(load_depth(written[1]), post.mean, atol=0.5 / 256)
        np.testing.assert_allclose(load_depth(written[2]), post.std, atol=0.5 / 256)
        assert load_depth(written[0]).shape == (8, 10)  # the npz opens as a depth map (its mean)
        assert back.K is None  # none was given

    def test_round_trip_keeps_the_intrinsics(self, tmp_path):
        from dataclasses import replace

        mde, sparse = small_inputs()
        K = np.array([[9.0, 0.0, 4.5], [0.0, 9.0, 3.5], [0.0, 0.0, 1.0]])
        post = replace(complete(mde, sparse, config=RESIDUAL, engine=EXACT_ENGINE), K=K)
        back = DepthPosterior.load(post.save(tmp_path / "post")[0], config=RESIDUAL)
        np.testing.assert_array_equal(back.K, K)

    def test_round_trip_keeps_the_config_the_rejections_and_the_warnings(self, tmp_path):
        """The file carries the config that made it (not a default), the rejected points and the warnings."""
        mde, sparse = small_inputs()
        depth = sparse.depth.copy()
        depth[0] *= 0.05  # one gross outlier
        cfg = DepthGPConfig(lengthscale=5.0, nugget=0.03)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            post = complete(
                mde, SparseDepth(sparse.u, sparse.v, depth, sparse.image_size), config=cfg, engine=EXACT_ENGINE
            )
        assert post.solve is not None and post.solve.route in ("grid", "woodbury", "neumann", "dense")
        written = post.save(tmp_path / "post")
        back = DepthPosterior.load(written[0])
        assert back.config == post.config and back.config != DepthGPConfig() and back.config.lengthscale == 5.0
        np.testing.assert_array_equal(back.rejected, post.rejected)
        assert back.warnings == post.warnings and back.solve is None
        assert DepthPosterior.load(written[0], config=RESIDUAL).config == RESIDUAL  # an explicit config wins
        np.savez(tmp_path / "bad.npz", **{**dict(np.load(written[0])), "config_json": np.array('{"nu": 7}')})
        with pytest.raises(DataFormatError, match="nu"):
            DepthPosterior.load(tmp_path / "bad.npz")

    def test_load_errors(self, tmp_path):
        with pytest.raises(DataFormatError):
            DepthPosterior.load(tmp_path / "missing.npz")
        np.savez(tmp_path / "other.npz", depth=np.ones((2, 2)))
        with pytest.raises(DataFormatError):
            DepthPosterior.load(tmp_path / "other.npz")
        for content in (b"not a zip", b"PK\x03\x04 truncated zip"):
            (tmp_path / "junk.npz").write_bytes(content)
            with pytest.raises(DataFormatError):
                DepthPosterior.load(tmp_path / "junk.npz")


@pytest.mark.shared_data
class TestSevenScenesCrop:
    def test_gp_residual_beats_the_mde(self, seven_scenes_frame, shared_data):
        """Real data: FastDepth on a 7-Scenes frame, 200 Kinect depths as measurements."""
        pytest.importorskip("ai_edge_litert", reason="FastDepth needs ai-edge-litert (the tflite extra)")
        import cv2

        from gpdepth3d.mde import FastDepthTFLite
        from gpdepth3d.mde.align import align_to_sparse

        model = shared_data.parent / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip(f"FastDepth model not found at {model}")
        f = seven_scenes_frame
        mde = cv2.resize(FastDepthTFLite(model)(f.rgb), (160, 120), interpolation=cv2.INTER_AREA)
        gt = downsample_depth(f.depth, 4)  # 120x160, closest depth per 4x4 block
        mde, gt = mde[12:108, 16:144], gt[12:108, 16:144]  # 96x128 crop
        rows, cols = np.nonzero(gt > 0)
        pick = np.random.default_rng(0).choice(rows.size, 200, replace=False)
        sparse = SparseDepth(cols[pick].astype(float), rows[pick].astype(float), gt[rows[pick], cols[pick]], gt.shape)
        held_out = gt.copy()
        held_out[rows[pick], cols[pick]] = 0.0
        post = complete(mde, sparse, config=RESIDUAL, engine=EXACT_ENGINE)
        aligned, _ = align_to_sparse(mde, sparse)
        rmse_gp = depth_metrics(post.mean, held_out)["rmse"]
        rmse_aligned = depth_metrics(aligned, held_out)["rmse"]
        rmse_mde = depth_metrics(mde, held_out)["rmse"]
        assert rmse_gp < 0.8 * rmse_aligned and rmse_gp < 0.8 * rmse_mde
        cal = calibration_metrics(post.mean, post.variance, held_out)
        assert cal["coverage_2sigma"] > 0.75
