"""Measures the default model (`DepthGPConfig()`, log-residual) against its targets on real data.

* 7-Scenes (../shared/data/7scenes), FastDepth at 320x240, uniform samples of the Kinect depth
  (50 / 200 / 500 points), scored on the dense Kinect depth: RMSE, +-2 sigma coverage, and the
  same with 5 % of the points replaced by gross outliers (depth x U(0.1, 3), the sigma of a good
  point): RMSE rise, points rejected, smallest posterior mean.
* 7-Scenes bound: what a *smooth* correction of FastDepth can reach at all. The true log residual
  log(Kinect / FastDepth) at every pixel, averaged over valid pixels with a Gaussian of sigma = 4 /
  8 / 12 px (the points' spacing is 10.5 / 16.6 px at 500 / 200 uniform points), and the same
  averaged with an RGB-guided (joint bilateral) weight exp(-|rgb - rgb'|^2 / (2 * 10^2)).
* vio_sparse: real SLAM points, 20 % of them held out (seeded) as ground truth; the default model
  against FastDepth scaled to the other 80 % (robust median ratio).
* ibims_sample: the 3-20 m hall at 320x240, 50 / 200 / 500 uniform samples of the laser scan (3
  seeds): the default against the same model with its s fixed (``screen.raise_outputscale=False``).
* speed: the default model (mean + variance) on kitti_tiny frame 0 at 1/3 and full resolution at
  the paper's densities 1/64, 1/16, 1/4 and 1, beside IP-Basic on the same input in the same run.
* parts: what each part of the default model earns (docs/model.md): RMSE and +-2 sigma of the default and
  of the default with one part off (depth-aware correlation, slope, edge term, outlier screen, raised s,
  local calibration) or exact (every pixel instead of the lattice), pooled over the same 7-Scenes frames
  (50 / 200 / 500 points; 200 with 5 % gross outliers) and over kitti_tiny at 1/3 (RT-MonoDepth-S, the paper's protocol: 20 % of the
  LiDAR held out, 1/16 and all of the rest as input).

One DepthCompleter per protocol, as a sequence (warm-started fits). Writes
bench/results/default_model.json and prints a table.

    python bench/default_model.py [--data ../shared/data] [--stride 3]
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import gpdepth3d as g
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import ScreenConfig
from gpdepth3d.io import write_json
from gpdepth3d.mde import load_frontend
from gpdepth3d.sampling import gross_outliers

ROOT = Path(__file__).resolve().parents[1]


def seven_scenes(data: Path, stride: int, fastdepth) -> dict:
    frames = list(g.open_dataset(data / "7scenes"))[::stride]
    inputs = []
    for fr in frames:
        small = fr.resized(0.5)
        inputs.append((fr.name, np.asarray(fastdepth(small.rgb), dtype=np.float64), small.depth, small.rgb))
    out = {"bound": seven_scenes_bound(inputs)}
    for n in (50, 200, 500):
        for share in (0.0, 0.05):
            completer = g.DepthCompleter()
            rows = []
            for i, (name, mde, gt, _) in enumerate(inputs):
                rng = np.random.default_rng(1000 * i + n)
                sp = g.sample_uniform(gt, n=n, rng=rng)
                if share:
                    sp = gross_outliers(sp, share, rng=rng)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", g.PosteriorWarning)
                    t = time.perf_counter()
                    post = completer(mde, sp, frame=name)
                    seconds = time.perf_counter() - t
                v = gt > 0
                err = post.mean[v] - gt[v]
                rows.append(
                    {
                        "frame": name,
                        "rmse_mm": 1000 * float(np.sqrt(np.mean(err**2))),
                        "mde_rmse_mm": 1000 * float(np.sqrt(np.mean((mde[v] - gt[v]) ** 2))),
                        "coverage_2sigma": float(np.mean(np.abs(err) <= 2 * post.std[v])),
                        "rejected": post.n_rejected,
                        "min_mean_m": float(post.mean.min()),
                        "seconds": seconds,
                        "lengthscale": post.config.lengthscale,
                        "outputscale": post.config.outputscale,
                    }
                )
            out[f"{n}_points_outliers_{share:.2f}"] = {
                "rmse_mm": float(np.mean([r["rmse_mm"] for r in rows])),
                "mde_rmse_mm": float(np.mean([r["mde_rmse_mm"] for r in rows])),
                "coverage_2sigma": float(np.mean([r["coverage_2sigma"] for r in rows])),
                "rejected_mean": float(np.mean([r["rejected"] for r in rows])),
                "min_mean_m": float(min(r["min_mean_m"] for r in rows)),
                "median_seconds": float(np.median([r["seconds"] for r in rows])),
                "frames": rows,
            }
    return out


def _smoothed(values: np.ndarray, valid: np.ndarray, sigma: float, guide: np.ndarray | None = None) -> np.ndarray:
    """Average of ``values`` over valid pixels with a Gaussian spatial weight (and a guide's colour weight)."""
    import cv2

    if guide is None:
        num = cv2.GaussianBlur(np.where(valid, values, 0.0), (0, 0), sigma)
        return num / np.maximum(cv2.GaussianBlur(valid.astype(np.float64), (0, 0), sigma), 1e-9)
    h, w = values.shape
    rad = int(2 * sigma)
    pad = lambda a: np.pad(a, ((rad, rad), (rad, rad)) + ((0, 0),) * (a.ndim - 2), mode="edge")  # noqa: E731
    vals, ok, gd = pad(np.where(valid, values, 0.0)), pad(valid.astype(np.float64)), pad(guide.astype(np.float64))
    num, den = np.zeros((h, w)), np.zeros((h, w))
    for dy in range(-rad, rad + 1, 2):  # every 2nd offset: the weights are smooth at this sigma
        for dx in range(-rad, rad + 1, 2):
            sl = (slice(rad + dy, rad + dy + h), slice(rad + dx, rad + dx + w))
            colour = np.exp(-np.sum((gd[sl] - guide) ** 2, axis=2) / (2 * 10.0**2))
            weight = np.exp(-(dx * dx + dy * dy) / (2 * sigma * sigma)) * colour * ok[sl]
            num += weight * vals[sl]
            den += weight
    return num / np.maximum(den, 1e-9)


def seven_scenes_bound(inputs: list) -> dict:
    """RMSE of FastDepth corrected by the *true* log residual, smoothed (see the module docstring)."""
    out = {}
    for sigma in (4.0, 8.0, 12.0):
        for guided in (False, True):
            if guided and sigma == 4.0:
                continue
            errs = []
            for _, mde, gt, rgb in inputs:
                v = gt > 0
                resid = np.log(np.where(v, gt, 1.0) / mde)
                est = mde * np.exp(_smoothed(resid, v, sigma, rgb.astype(np.float64) if guided else None))
                errs.append(1000 * float(np.sqrt(np.mean((est[v] - gt[v]) ** 2))))
            out[f"sigma_{sigma:.0f}px{'_rgb_guided' if guided else ''}_rmse_mm"] = float(np.mean(errs))
    return out


def vio(data: Path, fastdepth) -> dict:
    completer = g.DepthCompleter()
    rows = []
    for i, fr in enumerate(g.open_dataset(data / "vio_sparse")):
        mde = np.asarray(fastdepth(fr.rgb), dtype=np.float64)
        sp = fr.sparse.rasterize(mde.shape)
        rng = np.random.default_rng(i)
        test = np.zeros(len(sp), dtype=bool)
        test[rng.permutation(len(sp))[: max(1, len(sp) // 5)]] = True
        train, held = sp.subset(~test), sp.subset(test)
        rr, cc = held.v.astype(int), held.u.astype(int)
        scale = float(np.median(train.depth / mde[train.v.astype(int), train.u.astype(int)]))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", g.PosteriorWarning)
            post = completer(mde, train, frame=fr.name)
        err = post.mean[rr, cc] - held.depth
        rows.append(
            {
                "frame": fr.name,
                "points": len(train),
                "held_out": len(held),
                "rmse_mm": 1000 * float(np.sqrt(np.mean(err**2))),
                "scaled_mde_rmse_mm": 1000 * float(np.sqrt(np.mean((scale * mde[rr, cc] - held.depth) ** 2))),
                "mde_rmse_mm": 1000 * float(np.sqrt(np.mean((mde[rr, cc] - held.depth) ** 2))),
                "within_2sigma": int(np.sum(np.abs(err) <= 2 * post.std[rr, cc])),
                "rejected": post.n_rejected,
            }
        )
    held = sum(r["held_out"] for r in rows)
    pooled = lambda key: (
        1000
        * float(  # noqa: E731 - RMSE pooled over all held-out points
            np.sqrt(sum((r[key] / 1000) ** 2 * r["held_out"] for r in rows) / held)
        )
    )
    return {
        "rmse_mm": pooled("rmse_mm"),
        "scaled_mde_rmse_mm": pooled("scaled_mde_rmse_mm"),
        "mde_rmse_mm": pooled("mde_rmse_mm"),
        "coverage_2sigma": sum(r["within_2sigma"] for r in rows) / held,
        "held_out_points": held,
        "frames": rows,
    }


def ibims(data: Path, fastdepth, seeds: int = 3) -> dict:
    """The iBims hall (3-20 m) at 320 x 240, uniform samples of the laser scan (seeds 0..seeds-1):
    the default against the same model with s fixed (``screen.raise_outputscale=False``)."""
    frame = g.open_dataset(data / "ibims_sample")[0].resized(0.5)
    mde = np.asarray(fastdepth(frame.rgb), dtype=np.float64)
    gt = frame.depth
    v = gt > 0
    out = {"mde_rmse_mm": 1000 * float(np.sqrt(np.mean((mde[v] - gt[v]) ** 2)))}
    for n in (50, 200, 500):
        for name, config in (
            ("default", g.DepthGPConfig()),
            ("s_fixed", g.DepthGPConfig(screen=ScreenConfig(raise_outputscale=False))),
        ):
            se, cover, s = [], [], []
            for seed in range(seeds):
                sp = g.sample_uniform(gt, n=n, rng=np.random.default_rng(seed))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", g.PosteriorWarning)
                    post = g.complete(mde, sp, config=config)
                err = post.mean[v] - gt[v]
                se.append(float(np.mean(err**2)))
                cover.append(float(np.mean(np.abs(err) <= 2 * post.std[v])))
                s.append(post.config.outputscale)
            out[f"{n}_points_{name}"] = {
                "rmse_mm": 1000 * float(np.sqrt(np.mean(se))),
                "coverage_2sigma": float(np.mean(cover)),
                "outputscale": s,
            }
    return out


def speed(data: Path, rtmonodepth, repeats: int = 3) -> dict:
    """Seconds per frame (mean + variance, best of ``repeats`` after one warm-up) of the default model
    on kitti_tiny frame 0 at 1/3 and full resolution for each density, beside IP-Basic on the same input."""
    from gpdepth3d.evaluation.baselines import ip_basic

    frame = g.open_dataset(data / "kitti_tiny")[0]
    out = {}
    for label, factor in (("1/3", 1 / 3), ("full", 1.0)):
        small = frame.resized(factor) if factor != 1.0 else frame
        mde = np.asarray(rtmonodepth(small.rgb), dtype=np.float64)
        points = frame.sparse.rasterize(mde.shape)
        for density in (1 / 64, 1 / 16, 1 / 4, 1.0):
            sp = g.sample_uniform(points, density=density, rng=0)
            completer = g.DepthCompleter()
            timings = []
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", g.PosteriorWarning)
                for _ in range(repeats + 1):
                    t = time.perf_counter()
                    post = completer(mde, sp)
                    timings.append((time.perf_counter() - t, post.timings))
            best = min(timings[1:], key=lambda x: x[0])
            ip = []
            for _ in range(repeats):
                t = time.perf_counter()
                ip_basic(sp, mde.shape)
                ip.append(time.perf_counter() - t)
            out[f"{label} {mde.shape[0]}x{mde.shape[1]} density {density:.4f}"] = {
                "points": len(sp),
                "seconds": best[0],
                "stages": best[1],
                "ip_basic_seconds": min(ip),
            }
    return out


PARTS = {
    "default": {},
    "no depth-aware correlation": {"assembly": {"depth_lengthscale": None}},
    "no slope": {"slope": {"prior_sigma": None}},
    "no edge term": {"assembly": {"edge_sigma": 0.0}},
    "no outlier screen": {"screen": {"outlier_threshold": None}},
    "s fixed": {"screen": {"raise_outputscale": False}},
    "no local calibration": {"calibration": {"reach": None}},
    "every pixel (no lattice)": {"engine": {"lattice_stride": 1}},
}
"""The default and each variant of `parts`: `DepthGPConfig.replace` changes, "engine" an `EngineConfig`'s."""


def _pooled(posts_and_gt: list) -> dict:
    """RMSE (mm) and +-2 sigma coverage pooled over the ground-truth pixels of several frames."""
    err, inside = [], []
    for post, gt in posts_and_gt:
        v = gt > 0
        e = post.mean[v] - gt[v]
        err.append(e)
        inside.append(np.abs(e) <= 2 * post.std[v])
    err = np.concatenate(err)
    return {
        "rmse_mm": 1000 * float(np.sqrt(np.mean(err**2))),
        "coverage_2sigma": float(np.mean(np.concatenate(inside))),
    }


def parts(data: Path, stride: int, fastdepth, rtmonodepth) -> dict:
    """Each part of the default model switched off (or made exact) in turn; see the module docstring."""
    from gpdepth3d.evaluation.kitti_protocol import draw_input, lidar_frames, prepare_kitti_frame

    cases = {}
    frames = list(g.open_dataset(data / "7scenes"))[::stride]
    seven = [(np.asarray(fastdepth(f.resized(0.5).rgb), dtype=np.float64), f.resized(0.5).depth) for f in frames]
    for n in (50, 200, 500):
        cases[f"7scenes {n} points"] = [
            (mde, g.sample_uniform(gt, n=n, rng=1000 * i + n), gt) for i, (mde, gt) in enumerate(seven)
        ]
    rngs = [np.random.default_rng(1000 * i + 200) for i in range(len(seven))]
    cases["7scenes 200 points, 5 % gross outliers"] = [
        (mde, gross_outliers(g.sample_uniform(gt, n=200, rng=rng), 0.05, rng=rng), gt)
        for (mde, gt), rng in zip(seven, rngs)
    ]
    kitti = [
        prepare_kitti_frame(name, rgb, lidar, rtmonodepth, factor=3, holdout=0.2, rng=0)
        for name, rgb, lidar in lidar_frames(g.open_dataset(data / "kitti_tiny"))
    ]
    for label, density in (("1/16", 1 / 16), ("all", 1.0)):
        cases[f"kitti_tiny {label}"] = [
            (s.mde_grid, draw_input("uniform", density, s.lidar.available, rng=i), s.lidar.gt_grid)
            for i, s in enumerate(kitti)
        ]
    out = {}
    for variant, changes in PARTS.items():
        config = g.DepthGPConfig().replace(**{k: v for k, v in changes.items() if k != "engine"})
        engine = EngineConfig(**changes.get("engine", {}))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", g.PosteriorWarning)
            out[variant] = {
                case: _pooled([(g.DepthCompleter(config, engine=engine)(mde, sp), gt) for mde, sp, gt in inputs])
                for case, inputs in cases.items()
            }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--stride", type=int, default=3, help="every stride-th 7-Scenes frame (60 in all)")
    parser.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "default_model.json")
    args = parser.parse_args()
    fastdepth = load_frontend("fastdepth", models_dir=args.data.parent / "models")
    result = {"config": repr(g.DepthGPConfig()), "7scenes": seven_scenes(args.data, args.stride, fastdepth)}
    result["vio_sparse"] = vio(args.data, fastdepth)
    result["ibims"] = ibims(args.data, fastdepth)
    rtmonodepth = load_frontend("rtmonodepth", models_dir=args.data.parent / "models")
    result["speed_kitti"] = speed(args.data, rtmonodepth)
    result["parts"] = parts(args.data, args.stride, fastdepth, rtmonodepth)
    write_json(args.output, result)
    print("7-Scenes (FastDepth, 320x240): RMSE mm / +-2 sigma / rejected / min mean / median s")
    for key, r in result["7scenes"].items():
        if key == "bound":
            continue
        print(
            f"  {key:28s} {r['rmse_mm']:6.0f} (MDE {r['mde_rmse_mm']:.0f})  {r['coverage_2sigma']:.3f}  "
            f"{r['rejected_mean']:5.1f}  {r['min_mean_m']:.2f}  {r['median_seconds']:.3f}"
        )
    print("7-Scenes bound: FastDepth corrected by the true log residual, smoothed:")
    for key, mm in result["7scenes"]["bound"].items():
        print(f"  {key:32s} {mm:6.0f} mm")
    v = result["vio_sparse"]
    print(
        f"vio_sparse (20 % of {v['held_out_points']} points held out): GP {v['rmse_mm']:.0f} mm, FastDepth "
        f"scaled {v['scaled_mde_rmse_mm']:.0f} mm, FastDepth {v['mde_rmse_mm']:.0f} mm, +-2 sigma {v['coverage_2sigma']:.3f}"
    )
    b = result["ibims"]
    print(f"iBims hall (FastDepth alone {b['mde_rmse_mm']:.0f} mm): RMSE mm / +-2 sigma / s, default vs s fixed")
    for n in (50, 200, 500):
        d, f = b[f"{n}_points_default"], b[f"{n}_points_s_fixed"]
        print(
            f"  {n:4d} points  {d['rmse_mm']:6.0f}  {d['coverage_2sigma']:.3f}  {np.round(d['outputscale'], 2)}"
            f"  |  {f['rmse_mm']:6.0f}  {f['coverage_2sigma']:.3f}"
        )
    print("speed, kitti_tiny frame 0 (mean + variance, best of 3 after a warm-up): points / default / IP-Basic")
    for key, r in result["speed_kitti"].items():
        print(f"  {key:32s} {r['points']:6d}  {1000 * r['seconds']:8.1f} ms  {1000 * r['ip_basic_seconds']:7.1f} ms")
    print("parts of the default model: RMSE mm / +-2 sigma, pooled")
    for variant, row in result["parts"].items():
        print(
            f"  {variant:28s} "
            + "  ".join(f"{c}: {r['rmse_mm']:5.0f} {100 * r['coverage_2sigma']:4.1f}" for c, r in row.items())
        )
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
