"""The default model's speed on a real KITTI frame, stage by stage, beside IP-Basic in the same run (issue 35's table).

Cells: kitti_tiny frame 0 (KITTI raw), RT-MonoDepth-S (`gpdepth3d.load_frontend("rtmonodepth")`) on the frame,
``frame.resized(1/3)`` with a uniform 1/64, 1/16, 1/4 and all of its LiDAR pixels (`sample_uniform`, seed 0), and
the full-resolution grid with all of its LiDAR. Per cell, a warm `DepthCompleter` (mean + variance), two calls
of warm-up, then ``--repeats`` calls: median and best wall-clock milliseconds of the whole call, the engine's solve
(`DepthPosterior.stages["engine"]`) and each stage's median (`DepthPosterior.stages`, the slope and screen as "fit",
input checks as "setup"); IP-Basic (`gpdepth3d.experiments.baselines.ip_basic`) on the same points and grid, best of
the repeats. When torch sees a GPU, the same cells on CUDA (`EngineConfig(device="cuda", backend="torch")`).

Also: a sequence (the kitti_tiny frames at 1/3, all LiDAR) through `DepthCompleter.map` with one worker and with
one per core, milliseconds per frame; with ``--cold``, ``gpdepth3d demo`` twice in fresh processes with an empty
numba cache (``NUMBA_CACHE_DIR`` a new folder): the first run compiles the kernels, the second loads them.

The machine (CPU model, cores, numba threads) and its load average before and after are recorded: on a shared
machine compare the ratios within one run. Writes bench/results/speed.json (``--output``); `bench/report.py`
renders it into docs/results.md.

    python bench/speed.py [--data ../shared/data] [--models ../shared/models] [--repeats 5] [--cold]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DENSITIES = (("1/64", 1 / 64), ("1/16", 1 / 16), ("1/4", 1 / 4), ("all", 1.0))


def machine() -> dict:
    """CPU model, cores, numba's threads and layer, the platform."""
    import numba

    model = platform.processor() or platform.machine()
    with_cpuinfo = Path("/proc/cpuinfo")
    if with_cpuinfo.is_file():
        names = [
            ln.split(":", 1)[1].strip() for ln in with_cpuinfo.read_text().splitlines() if ln.startswith("model name")
        ]
        model = names[0] if names else model
    return {
        "cpu": model,
        "cpus": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def cells(data: Path, models: Path) -> list[tuple[str, str, np.ndarray, object]]:
    """(grid, density, MDE depth, points) of each cell."""
    import gpdepth3d
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.sampling import sample_uniform

    front = gpdepth3d.load_frontend("rtmonodepth", models_dir=models)
    frame = open_dataset(data / "kitti_tiny")[0]
    third = frame.resized(1 / 3)
    mde = np.asarray(front(third.rgb), np.float64)
    out = []
    for label, density in DENSITIES:
        points = third.sparse if density == 1.0 else sample_uniform(third.sparse, density=density, rng=0)
        out.append(("1/3", label, mde, points))
    out.append(("full", "all", np.asarray(front(frame.rgb), np.float64), frame.sparse))
    return out


def time_cell(completer, mde: np.ndarray, points, repeats: int, sync=None) -> dict:
    """Median and best ms of the call and of the engine, and each stage's median ms (after two warm-up calls)."""
    calls, stages = [], []
    for i in range(repeats + 2):
        t = time.perf_counter()
        post = completer(mde, points)
        if sync is not None:
            sync()
        dt = time.perf_counter() - t
        if i >= 2:
            calls.append(dt)
            stages.append({"setup": post.timings["setup"], "fit": post.timings["fit"], **post.stages})
    engine = [s["engine"] for s in stages]
    return {
        "median_ms": 1e3 * float(np.median(calls)),
        "best_ms": 1e3 * float(np.min(calls)),
        "engine_median_ms": 1e3 * float(np.median(engine)),
        "stages_median_ms": {k: 1e3 * float(np.median([s[k] for s in stages])) for k in stages[0]},
        "route": post.solve.route,
    }


def ip_basic_ms(points, shape: tuple[int, int], repeats: int) -> float:
    """Best ms of IP-Basic on the points over the grid."""
    from gpdepth3d.evaluation.baselines import ip_basic

    best = np.inf
    for _ in range(repeats + 1):
        t = time.perf_counter()
        ip_basic(points, shape)
        best = min(best, time.perf_counter() - t)
    return 1e3 * best


def sequence(data: Path, models: Path) -> dict:
    """ms per frame of the kitti_tiny frames at 1/3 (all LiDAR) through `DepthCompleter.map`, serial and parallel."""
    import gpdepth3d
    from gpdepth3d.completion import DepthCompleter
    from gpdepth3d.datasets import open_dataset

    front = gpdepth3d.load_frontend("rtmonodepth", models_dir=models)
    frames = []
    for frame in open_dataset(data / "kitti_tiny"):
        third = frame.resized(1 / 3)
        frames.append((np.asarray(front(third.rgb), np.float64), third.sparse))
    workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    completer = DepthCompleter()
    list(completer.map(frames[:2], workers=workers))  # warm-up of both paths
    out = {"frames": len(frames), "workers": workers}
    for label, w in (("serial", 1), ("parallel", workers), ("serial_again", 1), ("parallel_again", workers)):
        t = time.perf_counter()
        posteriors = list(completer.map(frames, workers=w))
        out[f"{label}_ms_per_frame"] = 1e3 * (time.perf_counter() - t) / len(frames)
        if label == "serial":
            reference = posteriors
        elif label == "parallel":
            out["max_abs_difference"] = max(
                float(max(np.max(np.abs(a.mean - b.mean)), np.max(np.abs(a.variance - b.variance))))
                for a, b in zip(posteriors, reference)
            )
    return out


def cold_start() -> dict:
    """Seconds of ``gpdepth3d demo`` in a fresh process with an empty numba cache, then again with it filled."""
    out = {}
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as work:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(REPO))
        for label in ("first_run", "second_run"):
            t, c = time.perf_counter(), os.times()
            subprocess.run(
                [sys.executable, "-m", "gpdepth3d.cli", "demo", "--output", str(Path(work) / label)],
                env=env,
                check=True,
                stdout=subprocess.DEVNULL,
            )
            c2 = os.times()
            out[f"{label}_s"] = time.perf_counter() - t
            out[f"{label}_cpu_s"] = (c2.children_user - c.children_user) + (c2.children_system - c.children_system)
            out[f"{label}_load_average_1min"] = os.getloadavg()[0]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("GPDEPTH3D_DATA", REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cold", action="store_true", help="also time a cold and a warm `gpdepth3d demo`")
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "speed.json")
    args = parser.parse_args()
    sys.path.insert(0, str(REPO))
    from gpdepth3d.completion import DepthCompleter
    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.io import write_json

    warnings.simplefilter("ignore")
    models = args.models or args.data.parent / "models"
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine(),
        "load_average_before": list(os.getloadavg()),
        "repeats": args.repeats,
    }
    cuda = False
    try:
        import torch

        cuda = torch.cuda.is_available()
        result["gpu"] = torch.cuda.get_device_name(0) if cuda else None
    except ImportError:
        result["gpu"] = None
    rows = []
    for grid, density, mde, points in cells(args.data, models):
        row = {"grid": grid, "density": density, "points": len(points), "shape": list(mde.shape)}
        row["cpu"] = time_cell(DepthCompleter(), mde, points, args.repeats)
        row["ip_basic_ms"] = ip_basic_ms(points, mde.shape, args.repeats)
        if cuda:
            gpu = DepthCompleter(engine=EngineConfig(device="cuda", backend="torch"))
            row["cuda"] = time_cell(gpu, mde, points, args.repeats, sync=torch.cuda.synchronize)
        rows.append(row)
        print(f"{grid:5s} {density:5s} {len(points):6d} pts: {row['cpu']['median_ms']:8.1f} ms "
              f"(engine {row['cpu']['engine_median_ms']:.1f}), IP-Basic {row['ip_basic_ms']:.1f} ms", flush=True)  # fmt: skip
    result["rows"] = rows
    result["sequence"] = sequence(args.data, models)
    print("sequence:", {k: round(v, 3) if isinstance(v, float) else v for k, v in result["sequence"].items()})
    if args.cold:
        result["cold_start"] = cold_start()
        print("cold start:", {k: round(v, 2) for k, v in result["cold_start"].items()})
    result["load_average_after"] = list(os.getloadavg())
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.output, result)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
