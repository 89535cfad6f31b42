"""Benchmark of mapping on 7-Scenes with the library's own triangulated points: mesh F-score,
per-frame depth RMSE, sigma coverage of the points, points per frame, triangulation time.

Usage::

    python bench/fusion.py [--data ../shared/data/7scenes] [--model ../shared/models/fast_depth_224.tflite]
                           [--frames 60] [--threads 1] [--window N] [--lag N] [--fuse-depth median|mean] [--detector klt]
                           [--gp default|residual] [--tri FIELD=VALUE ...] [--gp-set FIELD=VALUE ...]
                           [--out PATH]

``--gp residual`` uses ``DepthGPConfig.residual()`` instead of the Mapper's default; ``--tri``
overrides `TriangulationConfig` fields (e.g. ``--tri variance_factor=False``), ``--gp-set`` fields of
the GP model (e.g. ``--gp-set "align='none'"``).

Pipeline per frame (`gpdepth3d.mapping.Mapper`, refinement and fusion at 320 x 240, voxel 2 cm,
truncation 8 cm, depth_max 5 m):

* MDE: FastDepth (int8 TFLite, real network) on the RGB image.
* Sparse points: the Mapper's own triangulation (`gpdepth3d.mapping.points.triangulation`): with the default
  ``detector="klt"`` a `TrackTriangulator` follows corners frame to frame and triangulates each
  track from every view it was seen in among the ``--window`` frames before and the ``--lag``
  frames after the frame (the Mapper's fixed lag), with the sequence's poses (no ground truth);
  per-point sigma from pixel noise and pose uncertainty.
* Refinement: the Mapper's GP, ``MAPPER_GP`` (the library's default model with the stationary GP's
  variance, ``DepthGPConfig(calibration=CalibrationConfig(reach=None))``; whatever it is at the time of the run, it is
  written into the JSON; ``--gp-set "calibration={'reach': 1.5}"`` gives the library default's variance).
* Fusion: variance-weighted TSDF of the posterior median (the Mapper's volume and
  ``fuse_depth``); MDE-only with uniform weights as the
  baseline; the reference mesh is fused from the Kinect depth with the depth camera's
  intrinsics (f = 585). The colour camera is taken as f = 525 (`SEVEN_SCENES_RGB_K`).

Measured:

* mesh metrics against the reference mesh (`mesh_metrics`, 50k samples, 5 cm): F-score etc.;
* per-frame depth RMSE (and median |error|) of the GP mean and of FastDepth alone against the
  Kinect depth registered to the colour camera (lift with the depth camera, project, z-buffer),
  averaged over frames, and their ratio;
* the points' +-2 sigma coverage against the Kinect depth (each point lifted with the colour
  camera and projected into the depth camera): over all frames, over the first and last half
  and over even / odd frames (hold-outs: the sigma model's constants were set on the whole
  sequence; the halves show whether they carry over);
* points per frame (frames without points), median per-frame |bias| of the points;
* seconds per `Mapper.add_frame` call of each stage (mean and median; "points" is the tracking
  step and the triangulation; with the Mapper's lag a call adds one frame and fuses an earlier one).

The machine these numbers come from is shared (2 cores, several jobs), so timings are noisy:
compare ratios within one run. Results: a summary on stdout and ``bench/results/fusion.json``
(written atomically).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _kinect_at(frame, rgb_cam, depth_cam, uv: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z in the depth camera, Kinect depth there or NaN) for points (uv, depth) of the colour camera."""
    lifted = rgb_cam.backproject_pixels(uv, depth)
    p, z = depth_cam.project(lifted)
    kinect = np.full(depth.shape[0], np.nan)
    inside = depth_cam.in_image(p)
    iu = np.rint(p[inside]).astype(np.int64)
    k = frame.depth[iu[:, 1], iu[:, 0]]
    kinect[inside] = np.where(k > 0, k, np.nan)
    return z, kinect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "7scenes")
    parser.add_argument("--model", type=Path, default=REPO.parent / "shared" / "models" / "fast_depth_224.tflite")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--window", type=int, default=None, help="earlier views (default: MapperConfig's)")
    parser.add_argument("--lag", type=int, default=None, help="later views (default: MapperConfig's)")
    parser.add_argument("--fuse-depth", choices=["median", "mean"], default=None, help="default: MapperConfig's")
    parser.add_argument("--detector", choices=["klt", "orb", "sift"], default="klt")
    parser.add_argument(
        "--gp",
        choices=["default", "residual"],
        default="default",
        help="GP model: the Mapper's default (MAPPER_GP) or DepthGPConfig.residual()",
    )
    parser.add_argument(
        "--tri",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a TriangulationConfig field (repeatable), e.g. --tri variance_factor=True",
    )
    parser.add_argument(
        "--gp-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a DepthGPConfig field of the chosen model (repeatable), e.g. --gp-set align='none'",
    )
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "fusion.json")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.datasets.sevenscenes import SevenScenes
    from gpdepth3d.mapping.tsdf.fusion import FusionConfig, TSDFFusion
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.io import atomic_write
    from gpdepth3d.io import to_jsonable
    from gpdepth3d.mapping.frame_inputs import resize_depth
    from gpdepth3d.mapping.mapper import SEVEN_SCENES_RGB_K, Mapper
    from gpdepth3d.mapping.mapper_config import MAPPER_FUSION, MAPPER_GP, MapperConfig
    from gpdepth3d.metrics import mesh_metrics
    from gpdepth3d.measurements import project_points
    from gpdepth3d.mde.tflite import FastDepthTFLite
    from gpdepth3d.mapping.points.triangulation import TriangulationConfig, triangulate_frames

    import ast

    overrides = {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.tri)}
    gp_overrides = {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.gp_set)}
    fusion = replace(MAPPER_FUSION, voxel_size=0.02, truncation=0.08, depth_max=5.0)
    config = MapperConfig(
        fusion=fusion,
        working_scale=0.5,
        gp=(MAPPER_GP if args.gp == "default" else DepthGPConfig.residual()).replace(**gp_overrides),
        triangulation=TriangulationConfig(detector=args.detector, **overrides),
        **{
            k: v
            for k, v in (("window", args.window), ("lag", args.lag), ("fuse_depth", args.fuse_depth))
            if v is not None
        },
    )
    reader = SevenScenes(args.data)
    n = min(len(reader), args.frames)
    first = reader[0]
    rgb_cam = PinholeCamera.from_K(SEVEN_SCENES_RGB_K, first.camera.width, first.camera.height)
    depth_cam = first.camera
    mapper = Mapper(rgb_cam, config, mde=FastDepthTFLite(args.model))
    work = mapper.work_camera
    depth_work = depth_cam.resized(work.width, work.height)
    mde_volume = TSDFFusion(work, FusionConfig(voxel_size=0.02, truncation=0.08, depth_max=5.0, weighting="uniform"))
    gt_volume = TSDFFusion(
        depth_work, FusionConfig(voxel_size=0.02, truncation=0.08, depth_max=5.0, weighting="uniform")
    )

    rows = []
    t_start = time.perf_counter()
    call_timings = []
    frames = {}

    def record(result) -> None:
        i = result.keyframe_id
        frame = frames.pop(i)
        work_rgb = mapper._work_rgb(frame.rgb)
        mde_volume.integrate(result.mde, frame.pose, rgb=work_rgb)
        gt_volume.integrate(resize_depth(frame.depth, depth_work.shape), frame.pose, rgb=work_rgb)
        pts, _ = frame.camera.backproject(frame.depth)
        gt_rgb = project_points(pts, work).to_depth_map()
        ok = gt_rgb > 0
        row = {"frame": i, "points": len(result.sparse)}
        if ok.any() and result.depth.size:
            for name, depth in (("gp", result.depth), ("mde", result.mde)):
                e = depth[ok] - gt_rgb[ok]
                row[f"rmse_{name}"] = float(np.sqrt(np.mean(e**2)))
                row[f"mae_{name}"] = float(np.median(np.abs(e)))
        s = result.sparse
        if len(s):
            sigma = np.asarray(s.sigma)
            z, kinect = _kinect_at(frame, rgb_cam, depth_cam, s.uv, np.asarray(s.depth))
            good = np.isfinite(kinect) & np.isfinite(sigma)
            err = z[good] - kinect[good]
            row["abs_err"] = np.abs(err).tolist()
            row["sigma"] = sigma[good].tolist()
            row["bias"] = float(np.median(err / kinect[good])) if good.any() else float("nan")
        rows.append(row)
        print(
            f"frame {i}: {row['points']} points"
            + (f", rmse gp {row['rmse_gp']:.3f} mde {row['rmse_mde']:.3f}" if "rmse_gp" in row else ""),
            flush=True,
        )

    for i in range(n):
        frames[i] = reader[i]
        result = mapper.add_frame(frames[i].rgb, frames[i].pose, keyframe_id=i)
        call_timings.append(dict(mapper.timings[-1]))
        if result is not None:
            record(result)
    for result in mapper.flush():
        record(result)
    rows.sort(key=lambda r: r["frame"])
    wall = time.perf_counter() - t_start

    meshes = {"mde": mde_volume.extract_mesh(), "gp_variance": mapper.mesh(), "gt": gt_volume.extract_mesh()}
    metrics = {k: mesh_metrics(m, meshes["gt"]) for k, m in meshes.items() if k != "gt"}

    def coverage(select) -> dict:
        e = np.concatenate(
            [np.array(r["abs_err"]) for r in rows if "abs_err" in r and select(r["frame"])] or [np.zeros(0)]
        )
        s = np.concatenate([np.array(r["sigma"]) for r in rows if "sigma" in r and select(r["frame"])] or [np.zeros(0)])
        return {"points": int(e.size), "within_2sigma": float(np.mean(e <= 2 * s)) if e.size else float("nan")}

    def mean_of(key: str) -> float:
        v = [r[key] for r in rows if key in r]
        return float(np.mean(v)) if v else float("nan")

    stages = sorted({k for t in call_timings for k in t})
    timing = {
        k: {
            "mean": float(np.mean([t[k] for t in call_timings if k in t])),
            "median": float(np.median([t[k] for t in call_timings if k in t])),
        }
        for k in stages
    }
    bias = np.array([r["bias"] for r in rows if "bias" in r])
    npts = np.array([r["points"] for r in rows])
    # for comparison, the batch function on the first frame with the 8 frames after it (the
    # Mapper with lag > 0 triangulates the first frame from its later frames too):
    first_frames = [reader[k] for k in range(min(n, 9))]
    sd0 = triangulate_frames([f.rgb for f in first_frames], [f.pose for f in first_frames], rgb_cam, reference=0)
    z0, k0 = _kinect_at(first_frames[0], rgb_cam, depth_cam, sd0.uv, np.asarray(sd0.depth))
    g0 = np.isfinite(k0)
    summary = {
        "data": str(args.data),
        "frames": n,
        "resolution": [work.height, work.width],
        "mesh_vs_ground_truth_mesh": metrics,
        "depth_rmse_m_mean_over_frames": {"gp": mean_of("rmse_gp"), "mde": mean_of("rmse_mde")},
        "depth_rmse_ratio_gp_over_mde": mean_of("rmse_gp") / mean_of("rmse_mde"),
        "depth_median_abs_error_m_mean_over_frames": {"gp": mean_of("mae_gp"), "mde": mean_of("mae_mde")},
        "points_coverage_2sigma": {
            "all": coverage(lambda k: True),
            "first_half": coverage(lambda k: k < n // 2),
            "second_half": coverage(lambda k: k >= n // 2),
            "even_frames": coverage(lambda k: k % 2 == 0),
            "odd_frames": coverage(lambda k: k % 2 == 1),
        },
        "points_per_frame": float(npts.mean()),
        "points_per_frame_list": npts.tolist(),
        "frames_without_points": int(np.sum(npts == 0)),
        "points_abs_median_bias_over_frames": float(np.median(np.abs(bias))) if bias.size else float("nan"),
        "points_frames_with_abs_bias_over_10pct": int(np.sum(np.abs(bias) > 0.1)),
        "points_bias_per_frame": bias.tolist(),
        "frame0_batch_triangulation_with_frames_1_to_8": {
            "points": len(sd0),
            "within_2sigma": float(np.mean(np.abs(z0[g0] - k0[g0]) <= 2 * np.asarray(sd0.sigma)[g0]))
            if g0.any()
            else None,
        },
        "timing_s_per_keyframe": timing,
        "wall_s": wall,
        "torch_threads": args.threads,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "note": "shared 2-core machine, timings noisy",
        },
        "config": to_jsonable(asdict(config)),
        "gp_model": args.gp,
        "front_end": f"FastDepthTFLite({args.model.name})",
        "sparse_source": f"library triangulation ({args.detector}) from the sequence's RGB frames and poses",
    }
    atomic_write(args.out, lambda p: p.write_text(json.dumps(summary, indent=2)))

    print(
        f"\n7-Scenes, {n} frames at {work.width}x{work.height}, {npts.mean():.0f} points/frame ({int(np.sum(npts == 0))} frames without)"
    )
    for name, m in metrics.items():
        print(
            f"{name:<12} F@5cm {m['fscore']:.3f}  precision {m['precision']:.3f}  recall {m['recall']:.3f}  accuracy {m['accuracy']:.3f} m"
        )
    print(
        f"per-frame RMSE: GP {mean_of('rmse_gp'):.3f} m, FastDepth {mean_of('rmse_mde'):.3f} m "
        f"(ratio {mean_of('rmse_gp') / mean_of('rmse_mde'):.3f})"
    )
    print(
        "2-sigma coverage: "
        + ", ".join(f"{k} {v['within_2sigma']:.3f}" for k, v in summary["points_coverage_2sigma"].items())
    )
    print("ms per keyframe (median): " + ", ".join(f"{k} {1e3 * v['median']:.0f}" for k, v in timing.items()))
    print(f"frame 0 (batch, later frames): {len(sd0)} points; written {args.out}")


if __name__ == "__main__":
    main()
