"""Benchmark of TSDF fusion on 7-Scenes: MDE-only vs GP-refined (uniform / variance weights) vs ground truth.

Usage::

    python bench/fusion.py [--data ../shared/data/7scenes] [--model ../shared/models/fast_depth_224.tflite]
                           [--frames 60] [--threads 1]

Pipeline per frame (all at half resolution, 320 x 240, voxel 2 cm, truncation 8 cm):

* MDE: FastDepth (int8 TFLite, real network) on the RGB image.
* Sparse points: ORB features the library triangulates itself between the frame and up to 4
  earlier frames (>= 5 cm baseline) with the sequence's poses (not the ground-truth depth);
  per-point sigma from 1 px pixel noise propagated through the triangulation.
* Refinement: `DepthCompleter(DepthGPConfig.residual(engine=--engine))`, exact engine by default
  (every engine gives the same posterior), at most 300 points (the most certain).
* Fusion: `TSDFFusion` with uniform weights (MDE, GP) or variance weights (GP,
  ``w = 1 / (1 + var / 0.1^2)``); the reference mesh is fused from the Kinect depth with the
  depth camera's intrinsics (f = 585). The colour camera is taken as f = 525 (the dataset's K
  is the depth camera's; see `gpdepth3d.mapping.SEVEN_SCENES_RGB_K`).

Metrics (`gpdepth3d.mapping.mesh_metrics`, 50k surface samples per mesh): accuracy (mean
distance mesh -> reference), completeness (reference -> mesh), Chamfer (their mean), precision
and recall at 5 cm, F-score. Timing: mean seconds per frame of each stage (the machine is
shared, so compare ratios). torch runs with ``--threads`` threads (1 by default: on this shared
2-core machine more threads are slower). Results: a table on stdout and
``bench/results/fusion.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import asdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "7scenes")
    parser.add_argument("--model", type=Path, default=REPO.parent / "shared" / "models" / "fast_depth_224.tflite")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--engine", choices=["exact", "fast", "kissgp"], default="exact")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "fusion.json")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    from gpdepth3d.fusion import FusionConfig
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.io import atomic_write
    from gpdepth3d.mapping import SEVEN_SCENES_RGB_K, MapperConfig, _jsonable, fuse_sequence
    from gpdepth3d.mde.tflite import FastDepthTFLite

    config = MapperConfig(
        fusion=FusionConfig(voxel_size=0.02, truncation=0.08, depth_max=5.0),
        working_scale=0.5,
        gp=DepthGPConfig.residual(engine=args.engine),
    )
    t0 = time.perf_counter()
    result = fuse_sequence(
        args.data,
        mde=FastDepthTFLite(args.model),
        rgb_K=SEVEN_SCENES_RGB_K,
        config=config,
        max_frames=args.frames,
        progress=True,
    )
    wall = time.perf_counter() - t0
    timing = result["timing"]
    per_frame = {
        "mde_inference": timing["mde"],
        "triangulation": timing["triangulate"],
        "gp_refine": timing["refine"],
        "fuse_variance": timing["fuse"],
        "fuse_uniform": timing["fuse_uniform"],
        "refine_plus_fuse": timing["refine"] + timing["fuse"],
        "triangulate_refine_fuse": timing["triangulate"] + timing["refine"] + timing["fuse"],
    }
    summary = {
        "data": str(args.data),
        "frames": result["frames"],
        "resolution": [240, 320],
        "sparse_points_per_frame": result["sparse_points"],
        "depth_median_abs_error_m": result["depth_median_abs_error"],
        "sparse_bias_per_frame": result["sparse_bias_per_frame"],
        "mesh_vs_ground_truth_mesh": result["metrics"],
        "timing_s_per_frame": per_frame,
        "wall_s": wall,
        "torch_threads": args.threads,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "config": _jsonable(asdict(config)),
        "front_end": f"FastDepthTFLite({args.model.name})",
        "sparse_source": "library triangulation (ORB) from the sequence's RGB frames and poses",
    }
    atomic_write(args.out, lambda p: p.write_text(json.dumps(summary, indent=2)))

    print(f"\n7-Scenes, {result['frames']} frames at 320x240, {result['sparse_points']:.0f} triangulated points/frame")
    print(
        "per-frame median |depth error| (m): MDE {mde:.3f}, GP {gp:.3f}".format(**result["depth_median_abs_error"])
    )
    import numpy as np

    bias = np.abs(np.array(result["sparse_bias_per_frame"]))
    if bias.size:
        print(
            f"triangulated points vs Kinect, per-frame |median relative error|: median {np.median(bias):.3f}, "
            f"frames above 10 %: {int(np.sum(bias > 0.1))} of {bias.size}"
        )
    print(f"{'variant':<14}{'accuracy m':>12}{'complete m':>12}{'chamfer m':>11}{'prec@5cm':>10}{'rec@5cm':>9}{'F':>7}")
    for name, m in result["metrics"].items():
        print(
            f"{name:<14}{m['accuracy']:>12.4f}{m['completeness']:>12.4f}{m['chamfer']:>11.4f}"
            f"{m['precision']:>10.3f}{m['recall']:>9.3f}{m['fscore']:>7.3f}"
        )
    print("seconds per frame: " + ", ".join(f"{k} {v:.3f}" for k, v in per_frame.items()))
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
