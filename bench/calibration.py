"""How far to trust the default model's standard deviation: the shape of its errors in sigmas, and its ranking.

+-2 sigma coverage (the issue's target, `bench/default_model.py`, `bench/kitti_paper.py`) can be right while
the errors' distribution is far from the posterior's. For the default `DepthGPConfig()`, and beside it the same
model without the local calibration of its variance (``calibration.reach=None``, `gpdepth3d.gp.local_calibration`;
stored under ``without_local_calibration`` in each case), this reports, pooled over the frames' ground-truth pixels
(`gpdepth3d.metrics.calibration_metrics`):

- coverage at 1 / 2 / 3 sigma (a Gaussian: 68.3 / 95.4 / 99.7 %) and the median |error| / sigma (0.674);
- the ranking: AUSE (area under the RMSE's sparsification error, 0 = sigma orders the errors perfectly) and
  the RMSE left after removing the 10 % / 30 % of pixels with the largest sigma, beside the oracle that
  removes the largest errors (what a robot gains by discarding its least certain pixels).

Data: kitti_tiny as the paper's protocol prepares it (RT-MonoDepth-S, GP at 1/3 resolution, 20 % of the LiDAR
pixels held out as ground truth), uniform densities 1/64, 1/16, 1/4 and all; 7-Scenes (FastDepth, 320 x 240,
every 3rd shared frame, uniform Kinect samples) at 50 / 200 / 500 points, and on the same frames real SLAM points
with their own sigma (the library's triangulation from the 8 posed frames before and the 4 after; also with a flat
10 % sigma and with none). Writes
``bench/results/calibration.json`` (atomically) and prints a table.

    python bench/calibration.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _kitti_speed import REPO, machine  # noqa: E402

KEYS = ("coverage_1sigma", "coverage_2sigma", "coverage_3sigma", "median_abs_z", "ause")
CONFIGS = (({}, None), ({"calibration": {"reach": None}}, "without_local_calibration"))
"""The default, and the default without the local calibration of its variance (`gpdepth3d.gp.local_calibration`)."""


def _store(out: dict, case: str, key: str | None, row: dict) -> None:
    """The default's row as the case, the other configs' rows under their key inside it."""
    if key is None:
        out[case] = {**row, **out.get(case, {})}
    else:
        out.setdefault(case, {})[key] = row


def _summary(means, variances, gts) -> dict:
    """`calibration_metrics` pooled over frames, and the RMSE after removing the least certain pixels."""
    from gpdepth3d.metrics import SPARSIFICATION_FRACTIONS, calibration_metrics, sparsification

    mean = np.concatenate([m.ravel() for m in means])
    var = np.concatenate([v.ravel() for v in variances])
    gt = np.concatenate([t.ravel() for t in gts])
    row = {k: v for k, v in calibration_metrics(mean, var, gt).items() if k in KEYS}
    v = gt > 0
    err = mean[v] - gt[v]
    rmse = float(np.sqrt(np.mean(err**2)))
    by_std, oracle = sparsification(np.abs(err), var[v])
    row["rmse_mm"] = 1e3 * rmse
    for share in (0.1, 0.3):
        i = int(np.flatnonzero(np.isclose(SPARSIFICATION_FRACTIONS, share))[0])
        row[f"rmse_mm_without_{share:.0%}_by_sigma"] = 1e3 * rmse * float(by_std[i])
        row[f"rmse_mm_without_{share:.0%}_oracle"] = 1e3 * rmse * float(oracle[i])
    return row


def kitti(data: Path, models: Path) -> dict:
    from gpdepth3d import DepthCompleter, DepthGPConfig
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.evaluation.kitti_protocol import KittiProtocolConfig, draw_input, lidar_frames, prepare_kitti_frame
    from gpdepth3d.mde import load_frontend

    mde = load_frontend("rtmonodepth", models_dir=models)
    protocol = KittiProtocolConfig()
    setups = [
        prepare_kitti_frame(name, rgb, lidar, mde, factor=protocol.factor, holdout=protocol.holdout, rng=i)
        for i, (name, rgb, lidar) in enumerate(lidar_frames(open_dataset(data / "kitti_tiny")))
    ]
    out = {}
    for label, density in (("1/64", 1 / 64), ("1/16", 1 / 16), ("1/4", 1 / 4), ("all", 1.0)):
        for config, key in CONFIGS:
            means, variances, gts = [], [], []
            for i, setup in enumerate(setups):
                sparse = draw_input("uniform", density, setup.lidar.available, rng=np.random.default_rng([7, i]))
                post = DepthCompleter(DepthGPConfig().replace(**config))(setup.mde_grid, sparse)
                means.append(post.mean)
                variances.append(post.variance)
                gts.append(setup.lidar.gt_grid)
            _store(out, f"kitti_tiny {label}", key, _summary(means, variances, gts))
    return out


def seven_scenes(data: Path, models: Path) -> dict:
    import gpdepth3d as g
    from gpdepth3d.mde import load_frontend

    fastdepth = load_frontend("fastdepth", models_dir=models)
    inputs = []
    for fr in list(g.open_dataset(data / "7scenes"))[::3]:
        small = fr.resized(0.5)
        inputs.append((fr.name, np.asarray(fastdepth(small.rgb), dtype=np.float64), small.depth))
    out = {}
    for n in (50, 200, 500):
        for config, key in CONFIGS:
            means, variances, gts = [], [], []
            completer = g.DepthCompleter(g.DepthGPConfig().replace(**config))
            for i, (name, mde, gt) in enumerate(inputs):
                sp = g.sample_uniform(gt, n=n, rng=np.random.default_rng(1000 * i + n))  # as bench/default_model.py
                post = completer(mde, sp, frame=name)
                means.append(post.mean)
                variances.append(post.variance)
                gts.append(gt)
            _store(out, f"7scenes {n} points", key, _summary(means, variances, gts))
    return out


def seven_scenes_triangulated(data: Path, models: Path, step: int = 3) -> dict:
    """Real SLAM points with their own sigma: the library's multi-view triangulation of every ``step``-th 7-Scenes
    frame from the 8 posed frames before it and the 4 after (the Mapper's window and lag), scored on every
    Kinect pixel at 320 x 240."""
    import gpdepth3d as g
    from gpdepth3d.mapping.points.triangulation import triangulate_frames
    from gpdepth3d.mde import load_frontend

    fastdepth = load_frontend("fastdepth", models_dir=models)
    frames = list(g.open_dataset(data / "7scenes"))
    inputs = []
    for r in range(0, len(frames), step):
        first = max(0, r - 8)
        window = frames[first : r + 5]
        sp = triangulate_frames(
            [f.rgb for f in window], [f.pose for f in window], frames[r].camera, reference=r - first
        )
        small = frames[r].resized(0.5)
        inputs.append((frames[r].name, np.asarray(fastdepth(small.rgb), dtype=np.float64), small.depth, sp))
    out = {}
    # the triangulation's sigma; the same points with a flat 10 % of their depth; with none (the model's sigma_meas)
    variants = (
        ("", lambda sp: sp),
        (", flat 10 % sigma", lambda sp: sp.with_sigma(0.1 * sp.depth)),
        (", no sigma", lambda sp: sp.with_sigma(np.nan)),
    )
    for suffix, given in variants:
        for config, key in CONFIGS:
            completer = g.DepthCompleter(g.DepthGPConfig().replace(**config))
            posts = [(completer(mde, given(sp), frame=name), gt) for name, mde, gt, sp in inputs]
            row = _summary([p.mean for p, _ in posts], [p.variance for p, _ in posts], [gt for _, gt in posts])
            row["points_per_frame"] = float(np.mean([len(sp) for *_, sp in inputs]))
            _store(out, "7scenes triangulated" + suffix, key, row)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("GPDEPTH3D_DATA", REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "calibration.json")
    args = parser.parse_args(argv)
    models = args.models or args.data.parent / "models"
    from gpdepth3d import PosteriorWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PosteriorWarning)
        cases = {
            **seven_scenes(args.data, models),
            **seven_scenes_triangulated(args.data, models),
            **kitti(args.data, models),
        }
    print(
        f"{'case':38s} {'RMSE':>6s}  cov 1/2/3 sigma      median|z|  AUSE   RMSE without 10 % / 30 % by sigma (oracle)"
    )
    for name, case in cases.items():
        for label, r in ((name, case), ("  without local calib.", case["without_local_calibration"])):
            print(
                f"{label:38s} {r['rmse_mm']:6.0f}  {100 * r['coverage_1sigma']:4.1f} / {100 * r['coverage_2sigma']:4.1f} / "
                f"{100 * r['coverage_3sigma']:5.2f}   {r['median_abs_z']:.3f}    {r['ause']:.3f}  "
                f"{r['rmse_mm_without_10%_by_sigma']:5.0f} / {r['rmse_mm_without_30%_by_sigma']:5.0f} "
                f"({r['rmse_mm_without_10%_oracle']:.0f} / {r['rmse_mm_without_30%_oracle']:.0f})"
            )
    from gpdepth3d.io import write_json

    args.output.parent.mkdir(parents=True, exist_ok=True)
    print(
        f"wrote {write_json(args.output, {**machine(), 'config': 'DepthGPConfig()', 'compared': 'DepthGPConfig(calibration=CalibrationConfig(reach=None))', 'cases': cases}, indent=1)}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
