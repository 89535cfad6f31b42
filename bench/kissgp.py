"""Benchmark of the ``kissgp`` engine (GPyTorch KISS-GP, the paper's method) at 1/3 KITTI resolution.

Data: ``kitti_tiny`` frame 0. The projected LiDAR (375x1242, metres) is reduced with
``downsample_depth(lidar, 3)`` (closest point per 3x3 block) to the 125x414 GP grid; those
points are the range measurements. The MDE is *simulated* (there is no network output here):
the 1/3-resolution LiDAR filled to a dense map by nearest neighbour, blurred (Gaussian,
sigma 2 px), scaled by 1.1 and perturbed by a smooth relative error (+-5 %) and 1 % white noise.

Runs, each timed on the whole 125x414 frame with ``torch.set_num_threads(2)``:

* ``balanced`` (the paper's preset, ``DepthGPConfig.paper()``): every MDE pixel + every LiDAR point.
* ``residual`` (``DepthGPConfig.residual()``) with all LiDAR points (mean only: the exact variance
  of all of them costs ~10^13 flops by any method, `gpdepth3d.gp.kissgp.variance_flops`) and
  with 500 of them (mean and variance; Cholesky route).
* ``default`` (``DepthGPConfig()``, the library's model) through ``DepthCompleter`` with
  ``EngineConfig(name="kissgp")``, RT-MonoDepth-S as the MDE (the real network, as bench/cuda.py), at the
  KITTI protocol's densities 1/64 .. 1: seconds of mean + variance (one call after a warm-up at the
  lowest density), the engine's variance method and CG iterations (no agreement columns: the lattice's
  read-out off the grid nodes is KISS-GP's cubic interpolation, the one approximation of the engine).

For the first three: time for mean only, time for mean + variance, CG iterations (mean solve; mean over
the batched variance solves), the variance method, and the agreement with the exact engine on a
40x80 crop of the same frame (the crop's own problem solved by both engines): relative RMS of
the mean difference (rms(mean_k - mean_e) / rms(mean_e - mean(mean_e))) and the median / 95th
percentile / max relative error of the variance.

Prints a table and writes ``bench/results/kissgp.json`` atomically. Timings on a shared
2-core machine are noisy; the load average is recorded.

Usage: ``python bench/kissgp.py [--data PATH] [--device cpu|cuda] [--frame 0] [--threads 2]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DENSITIES = (1 / 64, 1 / 16, 1 / 4, 1.0)  # the KITTI protocol's fractions of the LiDAR (as bench/cuda.py)


def default_data() -> Path:
    env = os.environ.get("GPDEPTH3D_DATA")
    return (Path(env) if env else REPO.parent / "shared" / "data") / "kitti_tiny"


def simulated_frame(folder: Path, frame: int, seed: int = 0):
    """(mde (125, 414), lidar (125, 414)) in metres: LiDAR at 1/3 resolution and a simulated MDE."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    from gpdepth3d import downsample_depth

    path = folder / "velodyne_02" / f"{frame:010d}.npz"
    with np.load(path) as d:
        lidar_full = d["velodyne_depth"].astype(np.float64)
    lidar = downsample_depth(lidar_full, 3)
    valid = lidar > 0
    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    dense = gaussian_filter(lidar[ri, ci], 2.0)
    rng = np.random.default_rng(seed)
    smooth = gaussian_filter(rng.standard_normal(dense.shape), 10)
    smooth *= 0.05 / max(np.abs(smooth).max(), 1e-12)
    mde = dense * 1.1 * (1.0 + smooth) * (1.0 + 0.01 * rng.standard_normal(dense.shape))
    return mde, lidar


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def agreement(mde, sparse, config, crop, device) -> dict:
    """kissgp vs exact on a crop: relative mean RMS and variance relative errors."""
    from gpdepth3d import SparseDepth
    from gpdepth3d.completion.complete import build_problem
    from gpdepth3d.gp.exact import ExactEngine
    from gpdepth3d.gp.kissgp import KissGPEngine

    (r0, r1), (c0, c1) = crop
    keep = (sparse.v >= r0) & (sparse.v < r1) & (sparse.u >= c0) & (sparse.u < c1)
    sub = SparseDepth(sparse.u[keep] - c0, sparse.v[keep] - r0, sparse.depth[keep], (r1 - r0, c1 - c0))
    problem, *_ = build_problem(mde[r0:r1, c0:c1], sub, config)
    me, ve = ExactEngine(max_points=10_000).solve(problem)
    engine = KissGPEngine(device=device)
    mk, vk = solution = engine.solve(problem)
    rel = np.abs(vk - ve) / ve
    return {
        "crop": [[r0, r1], [c0, c1]],
        "observed": solution.info.details["observed"],
        "mean_rel_rms": rms(mk - me) / rms(me - me.mean()),
        "var_rel_median": float(np.median(rel)),
        "var_rel_p95": float(np.percentile(rel, 95)),
        "var_rel_max": float(rel.max()),
        "variance_method": solution.info.details.get("variance_method"),
    }


def run_case(name, mde, sparse, config, device, variance: bool, crop) -> dict:
    from gpdepth3d.completion.complete import build_problem
    from gpdepth3d.gp.kissgp import KissGPEngine

    problem, *_ = build_problem(mde, sparse, config)
    engine = KissGPEngine(device=device)
    t = time.perf_counter()
    stats_mean = engine.solve(problem, variance=False).info.details
    t_mean = time.perf_counter() - t
    row = {
        "case": name,
        "shape": list(problem.shape),
        "observed": stats_mean["observed"],
        "time_mean_s": t_mean,
        "cg_iterations_mean": stats_mean["cg_iterations_mean"],
        "cg_residual_mean": stats_mean["cg_residual_mean"],
        "preconditioner": stats_mean["preconditioner"],
    }
    if variance:
        t = time.perf_counter()
        st = engine.solve(problem, variance=True).info.details
        row["time_mean_variance_s"] = time.perf_counter() - t
        row.update(
            variance_method=st.get("variance_method"),
            cg_iterations_variance=st.get("cg_iterations_variance"),
            probe_vectors=st.get("probe_vectors"),
        )
    print(f"  {name}: {row}", flush=True)
    row["agreement_with_exact"] = agreement(mde, sparse, config, crop, device)
    print(f"  {name}: agreement {row['agreement_with_exact']}", flush=True)
    return row


def default_model_rows(data: Path, models: Path, device: str) -> list[dict]:
    """The default model with the kissgp engine at the KITTI protocol's densities (see the module docstring)."""
    import sys
    import warnings

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _kitti_speed import draw, kitti_setup

    from gpdepth3d import DepthCompleter, DepthGPConfig
    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.mde import RTMonoDepthONNX

    setup, _ = kitti_setup(data, RTMonoDepthONNX(models_dir=models, providers=["CPUExecutionProvider"]))
    completer = DepthCompleter(DepthGPConfig(), engine=EngineConfig(name="kissgp", device=device))
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        completer(setup.mde_grid, draw(setup, DENSITIES[0]))  # warm-up
        for density in DENSITIES:
            sparse = draw(setup, density)
            t = time.perf_counter()
            post = completer(setup.mde_grid, sparse)
            st = post.solve.details
            rows.append(
                {
                    "case": f"default, {density:g} of the LiDAR",
                    "shape": list(setup.grid_shape),
                    "observed": st["observed"],
                    "time_mean_variance_s": time.perf_counter() - t,
                    "cg_iterations_mean": st["cg_iterations_mean"],
                    "cg_residual_mean": st["cg_residual_mean"],
                    "variance_method": st.get("variance_method"),
                    "cg_iterations_variance": st.get("cg_iterations_variance"),
                }
            )
            print(f"  {rows[-1]}", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=default_data(), help="kitti_tiny folder")
    parser.add_argument("--models", type=Path, default=REPO.parent / "shared" / "models", help="networks folder")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--device", default=None, help="torch device (default: cuda if available)")
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "kissgp.json")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = parser.parse_args()

    import torch

    from gpdepth3d import DepthGPConfig, SparseDepth
    from gpdepth3d.gp.kissgp import default_device
    from gpdepth3d.io import atomic_path

    torch.set_num_threads(args.threads)
    device = args.device or default_device()
    mde, lidar = simulated_frame(args.data, args.frame)
    sparse = SparseDepth.from_depth_map(lidar)
    rng = np.random.default_rng(1)
    few = sparse.subset(np.sort(rng.choice(len(sparse), 500, replace=False)))
    crop = ((75, 115), (160, 240))  # 40x80 pixels in the LiDAR-covered lower half
    load_before = os.getloadavg()
    rows = [
        run_case("balanced, all LiDAR", mde, sparse, DepthGPConfig.paper(), device, True, crop),
        run_case("residual, all LiDAR", mde, sparse, DepthGPConfig.residual(), device, False, crop),
        run_case("residual, 500 LiDAR", mde, few, DepthGPConfig.residual(), device, True, crop),
    ]
    rows += default_model_rows(args.data.parent, args.models, device)
    result = {
        "benchmark": "kissgp engine, 1/3 KITTI resolution (kitti_tiny; simulated MDE, the default model's rows "
        "RT-MonoDepth-S)",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "frame": args.frame,
        "device": device,
        "torch_threads": torch.get_num_threads(),
        "lidar_points": len(sparse),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "rows": rows,
    }
    header = (
        f"{'case':30s} {'obs':>6s} {'mean s':>8s} {'CG it':>6s} {'mean+var s':>11s} {'var method':>10s} "
        f"{'var CG it':>9s} {'crop mean rel':>13s} {'crop var med/p95/max':>26s}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        a = r.get("agreement_with_exact")
        mean = f"{r['time_mean_s']:.2f}" if "time_mean_s" in r else "-"
        mv = f"{r['time_mean_variance_s']:.2f}" if "time_mean_variance_s" in r else "-"
        vit = r.get("cg_iterations_variance")
        vit = "-" if vit is None else f"{vit:.0f}"
        crop = (
            f"{a['mean_rel_rms']:13.1e} {a['var_rel_median']:8.1e}/{a['var_rel_p95']:8.1e}/{a['var_rel_max']:8.1e}"
            if a
            else f"{'-':>13s} {'-':>26s}"
        )
        print(
            f"{r['case']:30s} {r['observed']:6d} {mean:>8s} {r['cg_iterations_mean']:6d} {mv:>11s} "
            f"{str(r.get('variance_method', '-')):>10s} {vit:>9s} {crop}"
        )
    print(f"device {device}, {torch.get_num_threads()} threads, load {load_before[0]:.1f} -> {os.getloadavg()[0]:.1f}")
    with atomic_path(args.output) as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
