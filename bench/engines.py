"""Benchmark of the GP engines on real frames: the default model's speed targets, and engine against engine.

Two suites, one run each:

``--suite kitti`` (the default): the default model's speed target. kitti_tiny frame 0 with RT-MonoDepth-S,
prepared as the paper's KITTI protocol does (`gpdepth3d.evaluation.kitti_protocol`: the GP grid at 1/3
resolution, 125 x 414; 20 % of the LiDAR held out; uniform inputs from the rest), at the
paper's eight densities (1/64 ... all of the LiDAR) and two outputs: the 1/3 grid and the full
image (375 x 1242, predicted from the 1/3 grid). Per cell, mean + variance through
`DepthCompleter` (validation, screening, set-up and read-out included; best of ``--repeats``
after a warm-up): the default model (`DepthGPConfig()`), the paper preset
(`DepthGPConfig.paper()`), IP-Basic on the same points in the same run (on the 1/3 grid, resized
to full resolution for the full output, as the protocol scores it), and KISS-GP computing the
default model (one call per cell in its own process, ``--kissgp-timeout`` seconds at most;
denser cells of a resolution are skipped after one times out; with ``--kissgp-timeout 0`` the
KISS-GP cells of the previous run in the output file are kept, marked ``from_run``). Targets: <= 50 ms at 1/3 and
<= 200 ms at full resolution, within 10 x IP-Basic. Results: a table on stdout and
``bench/results/engines_kitti.json`` (with the default model's stages and the engine's route
and stage times per cell).

``--suite engines``: every engine on simulated-MDE frames (time, peak memory, error against exact
on a crop), written to ``bench/results/engines.json``:

    python bench/engines.py --suite engines [--engines fast,fast-grid,fast-torch,kissgp,exact] [--repeats 3]

Inputs of that suite (real sensor data, simulated MDE):
* ``kitti_third``: KITTI raw 2011_09_26_0023 frame 0, LiDAR projected into camera 02, cropped to
  the depth-completion frame (bottom 352 x 1216) and reduced 3x keeping the closest point per
  block: 117 x 405 pixels, ~15k points (the paper's set-up; denser than the ~5k of a single 64-beam
  scan because every 3 x 3 block keeps its closest point).
* ``kitti_full``: the same at 352 x 1216 (~18k points).
* ``7scenes_half``: 7-Scenes frame 0 Kinect depth at 240 x 320 with 500 random points (residual
  set-up). ``7scenes_half_balanced``: the same frame and points with the paper's balanced set-up
  (every MDE pixel an observation). ``7scenes_half_nu15`` / ``7scenes_half_nu25``: the residual set-up
  with Matern nu = 1.5 / 2.5 (l = 30 px: the grid route is refused as too ill-conditioned, the fast
  engine takes its dense route over the points).

The MDE input is SIMULATED from the data (no network here;
`gpdepth3d.datasets.synthetic.simulate_mde`): the depth with holes filled by the nearest valid
value, Gaussian-smoothed (sigma 4 px), scaled by 1.05 and with 3 % multiplicative noise. The model is the paper's balanced set-up for KITTI and the residual set-up for 7-Scenes
unless named otherwise. Engines: ``fast`` (its automatic route, the row says which: the sparse
grid precision; with nu = 0.5 Woodbury over few points or the Neumann series of an
observation-dominated precision; with nu > 0.5 and few points dense algebra over them), ``fast-grid`` (the grid route forced), ``fast-torch`` (the grid
route's torch back-end), ``kissgp``, ``exact``.

Each (engine, size) runs in its own subprocess: peak RSS is that process's maximum resident set
(``resource.getrusage``) minus the RSS after imports and data loading. Times: ``first`` is the
first solve of a resolution (set-up included), ``mean`` / ``mean_var`` the best of ``--repeats``
later solves. Cells of an earlier run that a run does not measure are kept in the JSON (each
row has its date and the machine's load average). The error vs exact is measured on a 40 x 48 crop of each size (exact is infeasible on
the full frames): RMS difference of the means in % of the crop's depth range, and the largest
relative difference of the standard deviations. Results: a table on stdout and
``bench/results/engines.json`` (written atomically).

    python bench/engines.py [--data ../shared/data] [--suite kitti] [--repeats 3] [--kissgp-timeout 120]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
SIZES = ("kitti_third", "kitti_full", "7scenes_half", "7scenes_half_balanced", "7scenes_half_nu15", "7scenes_half_nu25")
CROP = (40, 48)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def load_frame(data: Path, size: str):
    """(mde (H, W) metres, SparseDepth, DepthGPConfig) of one benchmark input."""
    from gpdepth3d.datasets.synthetic import MDESimulation, simulate_mde
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.io import load_depth
    from gpdepth3d.measurements import SparseDepth, downsample_depth

    rng = np.random.default_rng(0)
    if size.startswith("kitti"):
        lidar = np.load(data / "kitti_tiny" / "velodyne_02" / "0000000000.npz")["velodyne_depth"].astype(np.float64)
        lidar = lidar[lidar.shape[0] - 352 :, :1216]
        if size == "kitti_third":
            lidar = downsample_depth(lidar, 3)
        truth = lidar
        sparse = SparseDepth.from_depth_map(lidar)
        config = DepthGPConfig.paper()
    else:
        depth = load_depth(data / "7scenes" / "frame-000000.depth.png", png_scale=1e-3, invalid_value=65535)
        truth = downsample_depth(depth, 2)
        r, c = np.nonzero(truth > 0)
        pick = rng.choice(r.size, 500, replace=False)
        sparse = SparseDepth.from_arrays(
            c[pick].astype(float), r[pick].astype(float), truth[r[pick], c[pick]], truth.shape
        )
        config = DepthGPConfig.paper() if size.endswith("balanced") else DepthGPConfig.residual()
        if size.endswith(("_nu15", "_nu25")):
            config = config.replace(nu=1.5 if size.endswith("_nu15") else 2.5)
    # holes filled from the nearest depth, blurred (sigma 4 px), x1.05, 3 % white relative noise
    sim = MDESimulation(scale=1.05, blur_sigma=4.0 / truth.shape[1], field_amplitude=0.0, noise=0.03)
    return simulate_mde(truth, sim, rng), sparse, config


def make(engine: str, config):
    """A completer running ``engine``: exact, kissgp, fast (automatic route), fast-grid or fast-torch."""
    from gpdepth3d.completion.complete import DepthCompleter
    from gpdepth3d.gp import EngineConfig

    options = {"fast-torch": EngineConfig(backend="torch", route="grid"), "fast-grid": EngineConfig(route="grid")}
    options = options.get(engine, EngineConfig()).replace(name=engine.split("-")[0], max_exact_points=100_000)
    return DepthCompleter(config, engine=options)


def worker(engine: str, size: str, data: Path, repeats: int) -> dict:
    """Runs one (engine, size) cell in this process; returns its measurements."""
    import torch  # noqa: F401  (one-time import, not part of the first-frame time)

    from gpdepth3d.completion.complete import DepthCompleter

    mde, sparse, config = load_frame(data, size)
    base_rss = _rss_mb()
    out: dict = {"engine": engine, "size": size, "shape": list(mde.shape), "points": len(sparse)}
    if engine != "exact":
        completer = make(engine, config)
        t0 = time.perf_counter()
        completer(mde, sparse, variance=True)
        out["first_s"] = time.perf_counter() - t0
        tm, tv = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            completer(mde, sparse, variance=False)
            tm.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            completer(mde, sparse, variance=True)
            tv.append(time.perf_counter() - t0)
        out["mean_s"], out["mean_var_s"] = min(tm), min(tv)
        out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base_rss
        if hasattr(completer.engine, "plan") and config.formulation != "log_residual":
            from gpdepth3d.completion.complete import build_problem

            out["route"] = completer.engine.plan(build_problem(mde, sparse, config)[0])
    # error vs exact on a crop around the image centre row band
    h, w = mde.shape
    r0, c0 = (h - CROP[0]) // 2 + h // 6, (w - CROP[1]) // 2
    r0 = min(max(r0, 0), h - CROP[0])
    crop_mde = mde[r0 : r0 + CROP[0], c0 : c0 + CROP[1]]
    su, sv = sparse.u - c0, sparse.v - r0
    keep = (su >= 0) & (su < CROP[1]) & (sv >= 0) & (sv < CROP[0])
    from gpdepth3d.measurements import SparseDepth

    crop_sparse = SparseDepth(su[keep], sv[keep], sparse.depth[keep], CROP)
    from gpdepth3d.gp import EngineConfig

    exact = EngineConfig(name="exact")
    ref = DepthCompleter(config, engine=exact)(crop_mde, crop_sparse)
    if engine == "exact":
        t0 = time.perf_counter()
        DepthCompleter(config, engine=exact)(crop_mde, crop_sparse, variance=False)
        out["crop_mean_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        DepthCompleter(config, engine=exact)(crop_mde, crop_sparse)
        out["crop_mean_var_s"] = time.perf_counter() - t0
        return out
    crop_completer = make(engine, config)
    if out.get("route"):  # the crop is checked on the route the full frame took
        crop_completer = DepthCompleter(config, engine=EngineConfig(route=out["route"]))
    got = crop_completer(crop_mde, crop_sparse)
    rng_depth = float(np.ptp(ref.mean))
    out["crop_mean_rms_pct_range"] = float(100 * np.sqrt(np.mean((got.mean - ref.mean) ** 2)) / rng_depth)
    out["crop_std_max_rel"] = float(np.max(np.abs(got.std - ref.std) / ref.std))
    return out


def engines_main(args) -> None:
    """The ``engines`` suite (see the module docstring)."""
    rows = []
    for size in args.sizes.split(","):
        for engine in args.engines.split(","):
            cmd = [
                sys.executable,
                __file__,
                "--suite",
                "engines",
                "--data",
                str(args.data),
                "--repeats",
                str(args.repeats),
                "--worker",
                engine,
                size,
            ]
            try:
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                if res.returncode != 0:
                    row = {"engine": engine, "size": size, "error": res.stderr.strip().splitlines()[-1][:200]}
                else:
                    row = json.loads(res.stdout.strip().splitlines()[-1])
            except subprocess.TimeoutExpired:
                row = {"engine": engine, "size": size, "error": f"timeout after {args.timeout:.0f} s"}
            row["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
            row["load_average_1min"] = os.getloadavg()[0]
            rows.append(row)
            _say(_fmt(row))
    path = REPO / "bench" / "results" / "engines.json"
    if path.is_file():  # keep the cells of an earlier run that this run did not measure
        try:
            done = {(r["engine"], r["size"]) for r in rows}
            rows += [r for r in json.loads(path.read_text())["rows"] if (r["engine"], r["size"]) not in done]
        except (ValueError, KeyError):
            pass
    speedups = {}
    for size in SIZES:
        f = next((r for r in rows if r["size"] == size and r["engine"] == "fast" and "mean_var_s" in r), None)
        k = next((r for r in rows if r["size"] == size and r["engine"] == "kissgp" and "mean_var_s" in r), None)
        if f and k:
            speedups[size] = {"mean": k["mean_s"] / f["mean_s"], "mean_var": k["mean_var_s"] / f["mean_var_s"]}
            _say(
                f"speed-up fast vs kissgp on {size}: mean x{speedups[size]['mean']:.0f}, mean+var x{speedups[size]['mean_var']:.0f}"
            )
    from gpdepth3d.io import write_json

    result = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "note": "the 2-core machine was shared with other jobs; load_average_1min per row",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "mde": "simulated from the sensor depth by gpdepth3d.datasets.synthetic.simulate_mde (nearest fill, Gaussian sigma 4 px, x1.05, 3 % noise)",
        "rows": rows,
        "speedup_fast_vs_kissgp": speedups,
    }
    write_json(path, result)
    _say(f"wrote {path}")


def _say(line: str) -> None:
    """Prints a line; a closed pipe (``| head``) must not stop the run before the JSON is written."""
    try:
        print(line, flush=True)
    except BrokenPipeError:
        sys.stdout = open(os.devnull, "w")


def _fmt(r: dict) -> str:
    if "error" in r:
        return f"{r['engine']:10s} {r['size']:22s} ERROR {r['error']}"
    shape = "x".join(map(str, r["shape"]))
    if r["engine"] == "exact":
        return (
            f"{r['engine']:10s} {r['size']:22s} {shape:9s} pts {r['points']:6d}  full frame infeasible; "
            f"{CROP[0]}x{CROP[1]} crop: mean {r['crop_mean_s'] * 1e3:8.1f} ms  mean+var {r['crop_mean_var_s'] * 1e3:8.1f} ms"
        )
    engine = r["engine"] + (f" ({r['route']})" if r["engine"] == "fast" and "route" in r else "")
    return (
        f"{engine:16s} {r['size']:22s} {shape:9s} pts {r['points']:6d}  first {r['first_s'] * 1e3:9.1f} ms  "
        f"mean {r['mean_s'] * 1e3:9.1f} ms  mean+var {r['mean_var_s'] * 1e3:9.1f} ms  peak {r['peak_rss_mb']:7.1f} MB  "
        f"crop err: mean {r['crop_mean_rms_pct_range']:.1e} % of range, std {r['crop_std_max_rel']:.1e} rel"
    )


# ----------------------------------------------------------------------------- the kitti suite


def _frontend(models: Path):
    from gpdepth3d.mde import RTMonoDepthONNX

    return RTMonoDepthONNX(models_dir=models, providers=["CPUExecutionProvider"])


def kissgp_cell(data: Path, models: Path, resolution: str, density: float) -> dict:
    """One KISS-GP call on the default model (run in its own process by `kitti_main`)."""
    from _kitti_speed import completer, draw, kitti_setup, time_completer

    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.gp.model import DepthGPConfig

    setup, _ = kitti_setup(data, _frontend(models))
    c = completer(DepthGPConfig(), EngineConfig(name="kissgp", device="cpu"))
    out = time_completer(
        c, setup, draw(setup, density), None if resolution == "1/3" else setup.full_shape, 1, warmup=False
    )
    out.pop("posterior")
    return out


def kitti_main(args) -> None:
    """The ``kitti`` suite (see the module docstring)."""
    from _kitti_speed import completer, draw, ip_basic_seconds, kitti_setup, machine, time_completer

    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.sampling import PAPER_DENSITIES

    models = args.models or args.data.parent / "models"
    densities = [float(x) for x in args.densities.split(",")] if args.densities else list(PAPER_DENSITIES)
    result = {**machine(), "suite": "kitti", "repeats": args.repeats}
    setup, mde_seconds = kitti_setup(args.data, _frontend(models))
    result["frame"] = {
        "dataset": "kitti_tiny",
        "name": setup.name,
        "grid": list(setup.grid_shape),
        "full": list(setup.full_shape),
        "available_points": len(setup.lidar.available),
        "mde": "RT-MonoDepth-S (onnxruntime, CPU)",
        "mde_seconds": mde_seconds,
    }
    rows = []
    # with --kissgp-timeout 0, the KISS-GP cells of the previous run in the output file are kept (with its date)
    earlier = {}
    if args.kissgp_timeout <= 0 and args.output.exists():
        old = json.loads(args.output.read_text())
        earlier = {
            (r["resolution"], r["density"]): {**r["kissgp"], "from_run": r["kissgp"].get("from_run", old.get("date"))}
            for r in old.get("rows", [])
            if "skipped" not in r.get("kissgp", {"skipped": ""})
        }
    _say(
        f"kitti_tiny {setup.name}, GP grid {setup.grid_shape[0]}x{setup.grid_shape[1]}, mean + variance, "
        f"best of {args.repeats} after a warm-up (ms; x = ratio to IP-Basic in this run)"
    )
    _say(
        f"{'output':6s} {'density':>8s} {'points':>6s} {'IP-Basic':>9s} {'default':>9s} {'x':>5s} {'paper':>9s} "
        f"{'x':>5s} {'kissgp':>10s}  default's stages (ms), route"
    )
    for res in ("1/3", "full"):
        out_shape = None if res == "1/3" else setup.full_shape
        default = completer(DepthGPConfig())
        paper = completer(DepthGPConfig.paper())
        kiss_stopped = args.kissgp_timeout <= 0
        for density in densities:
            sparse = draw(setup, density)
            row = {"resolution": res, "density": density, "points": len(sparse)}
            row["ip_basic_seconds"], _ = ip_basic_seconds(setup, sparse, res == "full", args.repeats)
            for name, c in (("default", default), ("paper", paper)):
                r = time_completer(c, setup, sparse, out_shape, args.repeats)
                r.pop("posterior")
                r["ratio_to_ip_basic"] = r["seconds"] / row["ip_basic_seconds"]
                row[name] = r
            if (res, density) in earlier:
                row["kissgp"] = earlier[(res, density)]
            elif kiss_stopped:
                row["kissgp"] = {
                    "skipped": "an earlier cell timed out" if args.kissgp_timeout > 0 else "--kissgp-timeout 0"
                }
            else:
                cmd = [
                    sys.executable,
                    __file__,
                    "--data",
                    str(args.data),
                    "--models",
                    str(models),
                    "--kissgp-cell",
                    res,
                    repr(density),
                ]
                try:
                    done = subprocess.run(cmd, capture_output=True, text=True, timeout=args.kissgp_timeout)
                    if done.returncode != 0:
                        row["kissgp"] = {"error": (done.stderr.strip().splitlines() or ["?"])[-1][:300]}
                    else:
                        row["kissgp"] = json.loads(done.stdout.strip().splitlines()[-1])
                        row["kissgp"]["ratio_to_ip_basic"] = row["kissgp"]["seconds"] / row["ip_basic_seconds"]
                except subprocess.TimeoutExpired:
                    row["kissgp"] = {"timeout_seconds": args.kissgp_timeout}
                    kiss_stopped = True
            row["load_average_1min"] = os.getloadavg()[0]
            rows.append(row)
            _say(_fmt_kitti(row))
            result["rows"] = rows
            _write_json(result, args.output)
    result["targets"] = _targets(rows)
    _write_json(result, args.output)
    for line in result["targets"]["summary"]:
        _say(line)
    _say(f"wrote {args.output}")


def _targets(rows: list[dict]) -> dict:
    """The speed targets against this run: <= 50 ms at 1/3, <= 200 ms at full resolution, <= 10 x IP-Basic."""
    limit = {"1/3": 0.050, "full": 0.200}
    out: dict = {"summary": []}
    for res in ("1/3", "full"):
        cells = [r for r in rows if r["resolution"] == res]
        if not cells:
            continue
        slow = [r for r in cells if r["default"]["seconds"] > limit[res]]
        far = [r for r in cells if r["default"]["ratio_to_ip_basic"] > 10]
        out[res] = {
            "cells": len(cells),
            "over_time_limit": [r["density"] for r in slow],
            "over_10x_ip_basic": [r["density"] for r in far],
            "worst_seconds": max(r["default"]["seconds"] for r in cells),
            "worst_ratio_to_ip_basic": max(r["default"]["ratio_to_ip_basic"] for r in cells),
        }
        out["summary"].append(
            f"default model, output {res}: {len(cells) - len(slow)}/{len(cells)} cells <= {1e3 * limit[res]:.0f} ms, "
            f"{len(cells) - len(far)}/{len(cells)} within 10x IP-Basic (worst {1e3 * out[res]['worst_seconds']:.0f} ms, "
            f"{out[res]['worst_ratio_to_ip_basic']:.1f}x)"
        )
    return out


def _fmt_kitti(r: dict) -> str:
    d, p, k = r["default"], r["paper"], r["kissgp"]
    ks = f"{1e3 * k['seconds']:8.0f}ms" if "seconds" in k else ("timeout" if "timeout_seconds" in k else "-")
    stages = " ".join(f"{name}={1e3 * v:.0f}" for name, v in d["stages"].items())
    return (
        f"{r['resolution']:6s} {r['density']:8.4f} {r['points']:6d} {1e3 * r['ip_basic_seconds']:9.1f} "
        f"{1e3 * d['seconds']:9.1f} {d['ratio_to_ip_basic']:5.1f} {1e3 * p['seconds']:9.1f} {p['ratio_to_ip_basic']:5.1f} "
        f"{ks:>10s}  {stages}, {d['route']}; paper {p['route']}"
    )


def _write_json(result: dict, path: Path) -> None:
    from gpdepth3d.io import write_json

    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, result)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--suite", choices=("kitti", "engines"), default="kitti")
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("GPDEPTH3D_DATA", REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--models", type=Path, default=None, help="kitti: models folder (default: <data>/../models)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--densities", default="", help="kitti: comma-separated shares (default: the paper's eight)")
    parser.add_argument("--kissgp-timeout", type=float, default=120.0, help="kitti: seconds per KISS-GP cell (0: none)")
    parser.add_argument(
        "--output", type=Path, default=REPO / "bench" / "results" / "engines_kitti.json", help="kitti: the result file"
    )
    parser.add_argument("--engines", default="fast,fast-grid,fast-torch,kissgp,exact", help="engines suite")
    parser.add_argument("--sizes", default=",".join(SIZES), help="engines suite")
    parser.add_argument("--timeout", type=float, default=900.0, help="engines suite: seconds per (engine, size) cell")
    parser.add_argument("--worker", nargs=2, metavar=("ENGINE", "SIZE"), help=argparse.SUPPRESS)
    parser.add_argument("--kissgp-cell", nargs=2, metavar=("RESOLUTION", "DENSITY"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.kissgp_cell:
        models = args.models or args.data.parent / "models"
        print(
            json.dumps(kissgp_cell(args.data, models, args.kissgp_cell[0], float(args.kissgp_cell[1])), default=float)
        )
    elif args.worker:
        print(json.dumps(worker(args.worker[0], args.worker[1], args.data, args.repeats)))
    elif args.suite == "engines":
        engines_main(args)
    else:
        kitti_main(args)


if __name__ == "__main__":
    main()
