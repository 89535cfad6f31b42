"""Benchmark of `Mapper.add_frame` per stage on 7-Scenes (keyframes at frame rate?), plus map extraction and loop closure.

Usage::

    python bench/mapper.py [--data ../shared/data/7scenes] [--model ../shared/models/fast_depth_224.tflite]
                           [--frames 60] [--threads 1] [--out bench/results/mapper.json]

Per `Mapper.add_frame` call, with the library's defaults (`MapperConfig()`: its GP `MAPPER_GP`, the
default model with the stationary GP's variance, on the fast engine, KLT tracks with 8 earlier and 4 later views (the fixed lag:
a call adds one frame and refines and fuses the frame added 4 calls earlier), variance-weighted
TSDF of the posterior median with 2 cm voxels) at ``working_scale=0.5`` (320 x 240 from the
640 x 480 RGB): the stages "mde" (FastDepth int8 TFLite on the RGB image added), "points" (one
KLT step, new corners, the fused frame's triangulation), "gp" (posterior mean and variance),
"fusion" (TSDF integration with per-pixel weights and the keyframe store), and "total"; the
calls that only add a frame (the first 4) count with their MDE and points. `Mapper.flush`
(the last 4 frames) is timed once.

After every frame `Mapper.mesh` (incremental extraction) is timed; after the sequence a full
extraction and `Mapper.point_cloud` once, then one loop closure: the pose
of the middle keyframe is perturbed (2 degrees, 5 cm), `Mapper.update_poses` re-integrates what
moved, and the volume is compared voxel by voxel with fusing all keyframes from scratch with the
new poses.

The process CPU time of each ``add_frame`` is recorded too (with one torch thread it is close to
the wall time an otherwise idle machine would show). Timings are wall-clock seconds on whatever machine runs it (the 2-core development machine is
shared by several jobs: compare ratios within one run; the 1-minute load average before and
after the timed calls is recorded). Results: a table on stdout and
``bench/results/mapper.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _perturbed(T: np.ndarray, degrees: float, metres: float) -> np.ndarray:
    import cv2

    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(degrees), 0.0]))[0] @ T[:3, :3]
    out[:3, 3] += [metres, 0.0, 0.0]
    return out


def _sorted_voxels(fusion) -> dict:
    vox = fusion.voxels()
    order = np.lexsort(vox["coords"].T)
    return {k: v[order] for k, v in vox.items()}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "7scenes")
    parser.add_argument("--model", type=Path, default=REPO.parent / "shared" / "models" / "fast_depth_224.tflite")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "mapper.json")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.datasets.sevenscenes import SevenScenes
    from gpdepth3d.mapping.tsdf.fusion import TSDFFusion
    from gpdepth3d.io import atomic_write
    from gpdepth3d.mapping.frame_result import STAGES
    from gpdepth3d.mapping.mapper import SEVEN_SCENES_RGB_K, Mapper
    from gpdepth3d.mapping.mapper_config import MapperConfig
    from gpdepth3d.mde.tflite import FastDepthTFLite

    reader = SevenScenes(args.data)
    n = min(len(reader), args.frames)
    frames = [reader[i] for i in range(n)]
    camera = PinholeCamera.from_K(SEVEN_SCENES_RGB_K, frames[0].camera.width, frames[0].camera.height)
    config = MapperConfig(working_scale=0.5)
    warm = Mapper(camera, config, mde=FastDepthTFLite(args.model))
    for k in range(min(n, config.lag + 2)):  # warm-up (JIT, caches, every stage once): not timed, not kept
        warm.add_frame(frames[k].rgb, frames[k].pose, keyframe_id=-1 - k)
    mapper = Mapper(camera, config, mde=warm.mde, completer=warm.completer)
    load_before = os.getloadavg()
    results, calls, cpu, mesh_incremental = [], [], [], []
    for i, f in enumerate(frames):
        c0 = time.process_time()
        r = mapper.add_frame(f.rgb, f.pose, keyframe_id=i)  # with the lag: fuses frame i - lag
        cpu.append(time.process_time() - c0)
        calls.append(dict(mapper.timings[-1]))
        if mapper.frames:
            t0 = time.perf_counter()
            mapper.mesh()  # incremental: only the chunks this frame changed
            mesh_incremental.append(time.perf_counter() - t0)
        if r is not None:
            results.append(r)
        print(
            f"call {i:2d}: "
            + (f"frame {r.keyframe_id:2d} fused, {len(r.sparse):4d} points, " if r is not None else "(frame waits), ")
            + ", ".join(f"{k} {1000 * v:6.1f}" for k, v in calls[-1].items())
            + f" ms (process CPU {1000 * cpu[-1]:.0f} ms)"
            + (f", mesh() {1000 * mesh_incremental[-1]:.0f} ms" if r is not None else "")
            + ("" if r is None or r.fused else f"  NOT FUSED: {r.error}")
        )
    load_after = os.getloadavg()
    t0 = time.perf_counter()
    results += mapper.flush()
    t_flush = time.perf_counter() - t0
    mapper.mesh()  # the flushed frames' chunks
    fusing = [t for t in calls if t["gp"] > 0 or t["fusion"] > 0]  # the calls that fused a frame
    keys = list(STAGES) + ["total"]
    per_stage = {
        k: {
            "median_ms": 1000 * float(np.median([t[k] for t in calls])),
            "mean_ms": 1000 * float(np.mean([t[k] for t in calls])),
            "p90_ms": 1000 * float(np.percentile([t[k] for t in calls], 90)),
        }
        for k in keys
    }

    t0 = time.perf_counter()
    full = mapper.fusion.extract_mesh()
    t_mesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = mapper.mesh()
    t_mesh_cached = time.perf_counter() - t0
    t0 = time.perf_counter()
    cloud = mapper.point_cloud()
    t_cloud = time.perf_counter() - t0

    middle = n // 2
    new_pose = _perturbed(mapper.keyframes[middle].T_world_camera, 2.0, 0.05)
    mesh_before = len(mesh.faces)
    update = mapper.update_poses({middle: new_pose})
    scratch = TSDFFusion(mapper.work_camera, mapper.fusion.config)
    t0 = time.perf_counter()
    for kf in mapper.keyframes.values():
        scratch.integrate(
            kf.depth,
            kf.T_world_camera,
            rgb=kf.rgb,
            weights=scratch.weights_for(kf.variance, kf.depth, points=kf.points),
            variance=kf.variance,
        )
    t_scratch = time.perf_counter() - t0
    a, b = _sorted_voxels(mapper.fusion), _sorted_voxels(scratch)
    same_voxels = a["coords"].shape == b["coords"].shape and bool(np.array_equal(a["coords"], b["coords"]))
    max_diff = {k: float(np.max(np.abs(a[k] - b[k]))) for k in a} if same_voxels else None

    summary = {
        "data": str(args.data),
        "frames": n,
        "frames_fused": int(sum(r.fused for r in results)),
        "frame_errors": [r.error for r in results if r.error],
        "resolution": list(mapper.work_camera.shape),
        "points_per_frame_median": float(np.median([len(r.sparse) for r in results])),
        "masked_pixels": int(sum(r.masked_pixels for r in results)),
        "lag": config.lag,
        "window": config.window,
        "add_frame_ms": per_stage,
        "flush_s": t_flush,
        "add_frame_total_ms_calls_that_fused": {
            "calls": len(fusing),
            "median": 1000 * float(np.median([t["total"] for t in fusing])) if fusing else None,
        },
        "add_frame_process_cpu_ms": {"median": 1000 * float(np.median(cpu)), "mean": 1000 * float(np.mean(cpu))},
        "mesh_incremental_after_each_frame_ms": {
            "median": 1000 * float(np.median(mesh_incremental)),
            "last_10_median": 1000 * float(np.median(mesh_incremental[-10:])),
        },
        "mesh_full_extraction_s": t_mesh,
        "mesh_no_change_s": t_mesh_cached,
        "mesh_faces": mesh_before,
        "mesh_faces_full_extraction": len(full.faces),
        "point_cloud_s": t_cloud,
        "point_cloud_points": len(cloud),
        "point_cloud_variance_finite": float(np.mean(np.isfinite(cloud.variance))),
        "loop_closure": {
            "keyframe": middle,
            "perturbation": "2 deg about y, 5 cm along x",
            "reintegrated_keyframes": len(update.reintegrated),
            "blocks_rebuilt": update.blocks,
            "update_poses_s": update.seconds,
            "from_scratch_s": t_scratch,
            "same_voxels_as_from_scratch": same_voxels,
            "max_abs_difference": max_diff,
        },
        "torch_threads": args.threads,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "note": "shared 2-core machine",
        },
        "load_average_1min": {"before": load_before[0], "after": load_after[0]},  # other jobs on the machine
        "config": asdict(config),
        "front_end": f"FastDepthTFLite({args.model.name})",
    }
    atomic_write(args.out, lambda p: p.write_text(json.dumps(summary, indent=2)))

    print(f"\nload average (1 min) {load_before[0]:.2f} before the timed calls, {load_after[0]:.2f} after")
    print(
        f"7-Scenes, {n} frames at {mapper.work_camera.width}x{mapper.work_camera.height}, "
        f"{summary['frames_fused']} fused, median {summary['points_per_frame_median']:.0f} points a frame"
    )
    print(f"{'stage':<8}{'median ms':>11}{'mean ms':>10}{'p90 ms':>9}")
    for k in keys:
        s = per_stage[k]
        print(f"{k:<8}{s['median_ms']:>11.1f}{s['mean_ms']:>10.1f}{s['p90_ms']:>9.1f}")
    print(f"add_frame process CPU time: median {summary['add_frame_process_cpu_ms']['median']:.0f} ms")
    print(
        f"mesh(): incremental after each frame median {1000 * np.median(mesh_incremental):.0f} ms "
        f"(last 10 frames {1000 * np.median(mesh_incremental[-10:]):.0f} ms), full extraction at 60 frames {t_mesh:.3f} s "
        f"({mesh_before} faces, full {len(full.faces)}), unchanged map {t_mesh_cached * 1000:.1f} ms; point_cloud() {t_cloud:.3f} s"
    )
    lc = summary["loop_closure"]
    print(
        f"update_poses (1 keyframe moved): {lc['update_poses_s']:.3f} s, {lc['reintegrated_keyframes']} keyframes re-integrated, "
        f"{lc['blocks_rebuilt']} blocks; from scratch {lc['from_scratch_s']:.3f} s; identical voxels: {same_voxels}, max diff {max_diff}"
    )
    print(f"written {args.out}")
    return summary


if __name__ == "__main__":
    main()
