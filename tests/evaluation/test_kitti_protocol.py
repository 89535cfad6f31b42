"""The paper's KITTI protocol: hand-made sampling cases and one cheap end-to-end run on kitti_tiny."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpdepth3d.errors import EmptyInputError, InvalidInputError, ShapeError
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.evaluation.kitti_protocol import (
    KITTI_PROTOCOLS,
    PAPER_KITTI_RMSE_MM,
    KittiMethods,
    KittiProtocolConfig,
    density_label,
    draw_input,
    evaluate_kitti_frame,
    full_table,
    holdout_lidar,
    lidar_frames,
    paper_table,
    plot_kitti,
    prepare_kitti_frame,
    run_kitti_protocol,
    summarize_kitti,
)
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.sampling import PAPER_DENSITIES


def _pixels(sparse: SparseDepth) -> set[tuple[int, int]]:
    return {(int(v), int(u)) for v, u in zip(sparse.v, sparse.u)}


def _random_lidar(shape=(60, 90), share=0.3, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(2.0, 60.0, shape)
    d[rng.random(shape) > share] = 0.0
    return d


class TestHoldoutLidar:
    def test_closest_point_per_block(self):
        """The grid keeps the nearest LiDAR point of each 3x3 block, ignoring empty pixels."""
        d = np.zeros((6, 6))
        d[0, 0], d[1, 2], d[2, 1] = 10.0, 4.0, 7.0  # block (0, 0): closest 4
        d[4, 4] = 9.0  # block (1, 1): single point
        d[0, 3] = np.nan  # block (0, 1): invalid only -> empty
        split = holdout_lidar(d, factor=3, holdout=0.5, rng=0)
        grid = split.gt_grid + split.available.to_depth_map((2, 2))
        np.testing.assert_array_equal(grid, [[4.0, 0.0], [0.0, 9.0]])
        assert split.n_grid == 2

    def test_disjoint_and_complete(self):
        d = _random_lidar()
        split = holdout_lidar(d, factor=3, holdout=0.2, rng=1)
        held = {(int(r), int(c)) for r, c in zip(*np.nonzero(split.gt_grid))}
        pool = _pixels(split.available)
        assert not held & pool
        assert len(held) + len(pool) == split.n_grid
        assert len(held) == round(0.2 * split.n_grid)

    def test_full_resolution_ground_truth_is_every_point_of_held_out_blocks(self):
        d = _random_lidar()
        split = holdout_lidar(d, factor=3, holdout=0.25, rng=2)
        rows, cols = np.nonzero(d > 0)
        in_held = split.gt_grid[rows // 3, cols // 3] > 0
        np.testing.assert_array_equal(split.gt_full[rows[in_held], cols[in_held]], d[rows[in_held], cols[in_held]])
        assert np.all(split.gt_full[rows[~in_held], cols[~in_held]] == 0)
        assert np.count_nonzero(split.gt_full) == in_held.sum()
        # no input point lies in a block that holds full-resolution ground truth
        gr, gc = np.nonzero(split.gt_full)
        assert not _pixels(split.available) & {(int(r) // 3, int(c) // 3) for r, c in zip(gr, gc)}
        # each grid ground-truth pixel is the minimum of its block's full-resolution points
        for r, c in zip(*np.nonzero(split.gt_grid)):
            block = split.gt_full[3 * r : 3 * r + 3, 3 * c : 3 * c + 3]
            assert split.gt_grid[r, c] == block[block > 0].min()

    def test_trailing_rows_are_cropped(self):
        d = _random_lidar((61, 92))
        split = holdout_lidar(d, factor=3)
        assert split.gt_grid.shape == (20, 30) and split.gt_full.shape == (60, 90)

    def test_seeded(self):
        d = _random_lidar()
        a, b = holdout_lidar(d, rng=5), holdout_lidar(d, rng=5)
        np.testing.assert_array_equal(a.gt_full, b.gt_full)
        assert not np.array_equal(a.gt_grid, holdout_lidar(d, rng=6).gt_grid)

    def test_bad_input(self):
        with pytest.raises(ShapeError, match="lidar_depth"):
            holdout_lidar(np.zeros((4, 4, 1)))
        with pytest.raises(EmptyInputError, match="lidar_depth"):
            holdout_lidar(np.zeros((30, 30)))
        with pytest.raises(InvalidInputError, match="holdout"):
            holdout_lidar(_random_lidar(), holdout=1.0)
        with pytest.raises(ShapeError):
            holdout_lidar(_random_lidar(), factor=0)


class TestDrawInput:
    @pytest.fixture
    def pool(self) -> SparseDepth:
        return holdout_lidar(_random_lidar((90, 120), share=0.6), factor=3, rng=0).available

    @pytest.mark.parametrize("density", PAPER_DENSITIES)
    def test_uniform_counts(self, pool, density):
        sparse = draw_input("uniform", density, pool, rng=0)
        assert len(sparse) == max(1, round(density * len(pool)))
        assert _pixels(sparse) <= _pixels(pool)

    def test_horizontal_band_geometry_and_count(self, pool):
        h = pool.image_size[0]
        inside = int(np.sum(pool.v >= h / 2))
        for density in (1 / 64, 1 / 4, 1.0):
            sparse = draw_input("hband", density, pool, rng=0, hband=(0.5, 1.0))
            assert np.all(sparse.v >= h / 2)  # rows 15..29 of a 30-row grid
            assert len(sparse) == min(max(1, round(density * len(pool))), inside)
        top = draw_input("hband", 1.0, pool, hband=(0.0, 0.2))
        assert np.all(top.v < 0.2 * h) and len(top) == int(np.sum((pool.v + 0.5) / h < 0.2))

    def test_vertical_band_geometry(self, pool):
        w = pool.image_size[1]
        sparse = draw_input("vband", 1.0, pool, vband=(0.0, 0.5))
        assert np.all(sparse.u < w / 2) and len(sparse) == int(np.sum(pool.u < w / 2))
        right = draw_input("vband", 1 / 8, pool, vband=(0.75, 1.0))
        assert np.all(right.u >= 0.75 * w - 0.5)

    def test_unknown_protocol(self, pool):
        with pytest.raises(InvalidInputError, match="protocol"):
            draw_input("scanlines", 0.5, pool)
        with pytest.raises(InvalidInputError, match="density"):
            draw_input("uniform", 0.0, pool)


class TestConfig:
    def test_defaults_are_the_papers(self):
        cfg = KittiProtocolConfig()
        assert cfg.factor == 3 and cfg.densities == PAPER_DENSITIES and cfg.protocols == KITTI_PROTOCOLS
        assert "held out" in cfg.gt_description() and "20%" in cfg.gt_description()

    @pytest.mark.parametrize(
        "kwargs",
        [
            {"factor": 0},
            {"factor": 2.5},
            {"holdout": 0.0},
            {"densities": (0.5, 1.5)},
            {"densities": ()},
            {"protocols": ("diagonal",)},
            {"methods": ("midas",)},
            {"hband": (0.6, 0.4)},
        ],
    )
    def test_bad_options(self, kwargs):
        with pytest.raises(InvalidInputError):
            KittiProtocolConfig(**kwargs)

    def test_density_labels(self):
        assert [density_label(d) for d in PAPER_DENSITIES] == ["1/64", "1/32", "1/16", "1/8", "1/4", "1/2", "3/4", "1x"]
        assert density_label(0.3) == "0.3"
        assert set(PAPER_KITTI_RMSE_MM) == {"mde", "1/64", "1/16", "1/4", "1x"}


class TestSyntheticEndToEnd:
    """Hand-made frame: a constant-depth wall, an MDE off by a factor 1.5, exact LiDAR."""

    def test_rows_metrics_and_tables(self, tmp_path):
        rng = np.random.default_rng(0)
        H, W = 36, 60
        lidar = np.where(rng.random((H, W)) < 0.5, 10.0, 0.0)
        rgb = np.zeros((H, W, 3), np.uint8)

        def mde(image):
            return np.full(image.shape[:2], 15.0)

        cfg = KittiProtocolConfig(
            densities=(1 / 4, 1.0), protocols=("uniform", "hband"), methods=("mde", "ip_basic", "gp_paper")
        )
        methods = KittiMethods(paper=DepthGPConfig.paper(), engine=EngineConfig(name="exact"))
        rows = run_kitti_protocol([("wall", rgb, lidar)], mde, cfg, methods=methods)
        assert len(rows) == 2 * 2 * 3 * 2
        by = {(r["protocol"], r["label"], r["method"], r["resolution"]): r for r in rows}
        for res in ("grid", "full"):
            assert by[("uniform", "1x", "mde", res)]["rmse"] == pytest.approx(5000.0)
            assert by[("uniform", "1x", "ip_basic", res)]["rmse"] == pytest.approx(0.0, abs=1e-6)
            assert math.isnan(by[("uniform", "1x", "mde", res)]["nll"])
            assert by[("uniform", "1x", "gp_paper", res)]["rmse"] < 5000.0
            assert np.isfinite(by[("uniform", "1x", "gp_paper", res)]["coverage_2sigma"])
        assert by[("uniform", "1x", "mde", "full")]["n_gt"] > by[("uniform", "1x", "mde", "grid")]["n_gt"]
        assert all("held out" in r["gt"] for r in rows)
        summary = summarize_kitti(rows)
        assert len(summary) == len(rows)  # one frame
        table = paper_table(summary)
        assert "| 1/4 |" in table and "2252" in table and "3951" in table and "5000" in table
        assert "gp_paper" in full_table(summary)
        png = plot_kitti(summary, tmp_path / "plot")
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    def test_frame_errors(self):
        with pytest.raises(ShapeError, match="lidar_depth"):
            prepare_kitti_frame("x", np.zeros((30, 30, 3), np.uint8), np.ones((30, 31)), lambda im: np.ones((30, 30)))
        with pytest.raises(ShapeError, match="mde"):
            prepare_kitti_frame("x", np.zeros((30, 30, 3), np.uint8), np.ones((30, 30)), lambda im: np.ones((10, 10)))
        with pytest.raises(EmptyInputError, match="frames"):
            run_kitti_protocol([], lambda im: im)
        with pytest.raises(InvalidInputError, match="method"):
            setup = prepare_kitti_frame(
                "x", np.zeros((30, 30, 3), np.uint8), np.ones((30, 30)), lambda im: np.ones((30, 30))
            )
            KittiMethods().run("midas", setup, setup.lidar.available, "grid")


def test_kitti_tiny_one_frame_end_to_end(shared_data):
    """One kitti_tiny frame, RT-MonoDepth-S, uniform 1/16 and 1x: the GP with all the LiDAR beats the MDE alone."""
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.mde import load_frontend

    models = shared_data.parent / "models"
    if not (models / "rtmonodepth_s_ms_640_192.onnx").is_file() or not (shared_data / "kitti_tiny").is_dir():
        pytest.skip("kitti_tiny or the RT-MonoDepth-S model not found")
    pytest.importorskip("onnxruntime")
    dataset = open_dataset(shared_data / "kitti_tiny")
    name, rgb, lidar = next(iter(lidar_frames(dataset)))
    assert rgb.shape == (375, 1242, 3) and lidar.shape == (375, 1242)
    cfg = KittiProtocolConfig(densities=(1 / 16, 1.0), protocols=("uniform",), methods=("mde", "ip_basic", "gp_paper"))
    setup = prepare_kitti_frame(name, rgb, lidar, load_frontend("rtmonodepth", models_dir=models), rng=0)
    assert setup.grid_shape == (125, 414) and setup.full_shape == (375, 1242)
    assert 0.15 < np.count_nonzero(setup.lidar.gt_grid) / setup.lidar.n_grid < 0.25
    rows = evaluate_kitti_frame(setup, cfg, rng=0)
    by = {(r["label"], r["method"], r["resolution"]): r for r in rows}
    for res in ("grid", "full"):
        mde = by[("1x", "mde", res)]
        assert 2000 < mde["rmse"] < 9000  # README: ~5.3 m against the projected LiDAR
        assert by[("1x", "gp_paper", res)]["rmse"] < mde["rmse"]
        assert by[("1x", "gp_paper", res)]["min_mean"] > 0
        assert by[("1x", "ip_basic", res)]["mae"] < mde["mae"]  # all the LiDAR: interpolation beats the MDE
    assert by[("1/16", "mde", "grid")]["n_points"] == round(setup.lidar.available.depth.size / 16)
