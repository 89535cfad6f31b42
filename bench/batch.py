"""Benchmark of `gpdepth3d.pipelines.batch`: frames/s on Dask with 1 and 2 local workers against the plain loop.

The ``kitti_tiny`` frames (7) are repeated under new frame ids to ``--frames`` frames (200 by
default; the copies read the same files but are separate frames with their own samples and
outputs). Each frame: 1/3 resolution, ``--n-input`` LiDAR points as input (20 % held out),
``DepthGPConfig.residual()`` on ``EngineConfig(name=...)``, posterior mean and variance written to ``.npz``.

Measured:

* plain loop: `gpdepth3d.pipelines.batch.process_frame` called frame after frame in this process with
  one BLAS/torch thread (what each Dask worker gets), writing the same files;
* ``run_batch`` with a LocalCluster of 1 and of 2 worker processes (one thread each);
  ``compute`` is first submission to last result, ``total`` adds the cluster start-up;
* scaling = frames/s with 2 workers / frames/s with 1 worker;
* overhead per frame = (compute time with 1 worker - plain loop time) / frames, and the same
  with the start-up included;
* CPU seconds of each run (this process, which hosts the Dask scheduler, plus its waited-for
  child processes, the workers: ``getrusage`` SELF + CHILDREN) and the CPU overhead per frame
  against the plain loop. Unlike wall time, CPU time hardly depends on what else runs on the
  machine, so it is the robust overhead figure on a busy machine.

Prints a table and writes ``bench/results/batch.json`` (atomically). Timings on a shared
2-core machine are noisy: the load average before and after each run is recorded.

Usage: ``python bench/batch.py [--frames 200] [--n-input 200] [--engine exact]``
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import platform
import shutil
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def default_data() -> Path:
    env = os.environ.get("GPDEPTH3D_DATA")
    return (Path(env) if env else REPO.parent / "shared" / "data") / "kitti_tiny"


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its terminated, waited-for children."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    return total


def plain_loop(frames, out: Path, config, engine, loader) -> float:
    """Seconds for the frames done one after the other in this process with one thread."""
    from threadpoolctl import threadpool_limits

    from gpdepth3d.pipelines.batch import warm_up, process_frame
    from gpdepth3d.gp import make_engine

    # Load every native library first: threadpoolctl limits only the pools loaded when it is
    # entered (scipy.linalg's BLAS would otherwise come in during frame 1 with all cores).
    warm_up()
    make_engine(engine)
    try:
        import torch

        torch_threads = torch.get_num_threads()
        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        torch, torch_threads = None, 0
    try:
        with threadpool_limits(1):
            t0 = time.perf_counter()
            for spec in frames:
                result = process_frame(spec, str(out), config=config, engine=engine, loader=loader)
                if not result.ok:
                    raise RuntimeError(f"frame {result.frame_id} failed: {result.error}")
            return time.perf_counter() - t0
    finally:
        if torch is not None:
            torch.set_num_threads(torch_threads)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=default_data())
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--n-input", type=int, default=200)
    parser.add_argument("--engine", default="exact", choices=["exact", "fast", "kissgp"])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "batch.json")
    args = parser.parse_args()

    import distributed

    from gpdepth3d.pipelines.batch import HoldoutInputs, dataset_frames, run_batch
    from gpdepth3d.io import write_json
    from gpdepth3d.gp.engine import EngineConfig
    from gpdepth3d.gp.model import DepthGPConfig

    if not args.data.is_dir():
        raise SystemExit(f"kitti_tiny not found at {args.data} (set GPDEPTH3D_DATA or pass --data)")
    n_base = len(dataset_frames(args.data))
    frames = dataset_frames(args.data, repeat=math.ceil(args.frames / n_base), limit=args.frames)
    config = DepthGPConfig.residual()
    engine = EngineConfig(name=args.engine)
    loader = HoldoutInputs(factor=3, n_input=args.n_input)
    scratch = Path(tempfile.mkdtemp(prefix="gpdepth3d_bench_batch_"))
    rows = []
    try:
        load0 = os.getloadavg()
        cpu0 = cpu_seconds()
        plain_s = plain_loop(frames, scratch / "plain", config, engine, loader)
        plain_cpu = cpu_seconds() - cpu0
        rows.append(
            {
                "mode": "plain loop",
                "workers": 0,
                "frames": len(frames),
                "startup_s": 0.0,
                "compute_s": plain_s,
                "total_s": plain_s,
                "frames_per_s": len(frames) / plain_s,
                "cpu_s": plain_cpu,
                "load_before": load0[0],
                "load_after": os.getloadavg()[0],
            }
        )
        print(f"plain loop: {len(frames) / plain_s:.3f} frames/s", flush=True)
        for w in args.workers:
            load0 = os.getloadavg()
            cpu0 = cpu_seconds()
            report = run_batch(
                frames, scratch / f"dask{w}", config=config, engine=engine, loader=loader, workers=w, progress=False
            )
            if not report.ok:
                raise RuntimeError(report.summary())
            rows.append(
                {
                    "mode": "dask LocalCluster",
                    "workers": w,
                    "frames": report.n_computed,
                    "startup_s": report.startup_seconds,
                    "compute_s": report.compute_seconds,
                    "total_s": report.seconds,
                    "frames_per_s": report.frames_per_second,
                    "cpu_s": cpu_seconds() - cpu0,
                    "load_before": load0[0],
                    "load_after": os.getloadavg()[0],
                }
            )
            print(f"dask {w} worker(s): {report.frames_per_second:.3f} frames/s", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    by_workers = {r["workers"]: r for r in rows}
    n = len(frames)
    summary = {}
    if 1 in by_workers and 2 in by_workers:
        summary["scaling_2_vs_1"] = by_workers[2]["frames_per_s"] / by_workers[1]["frames_per_s"]
    if 1 in by_workers:
        summary["overhead_per_frame_s"] = (by_workers[1]["compute_s"] - plain_s) / n
        summary["overhead_per_frame_with_startup_s"] = (by_workers[1]["total_s"] - plain_s) / n
        summary["plain_s_per_frame"] = plain_s / n
        summary["plain_cpu_s_per_frame"] = plain_cpu / n
        summary["cpu_overhead_per_frame_s"] = (by_workers[1]["cpu_s"] - plain_cpu) / n
    if 2 in by_workers:
        summary["cpu_overhead_per_frame_2_workers_s"] = (by_workers[2]["cpu_s"] - plain_cpu) / n

    print()
    print(
        f"{'mode':<20}{'workers':>8}{'frames':>8}{'start-up s':>12}{'compute s':>11}{'frames/s':>10}"
        f"{'CPU s':>9}{'load':>12}"
    )
    for r in rows:
        print(
            f"{r['mode']:<20}{r['workers']:>8}{r['frames']:>8}{r['startup_s']:>12.2f}{r['compute_s']:>11.1f}"
            f"{r['frames_per_s']:>10.3f}{r['cpu_s']:>9.1f}{r['load_before']:>6.1f}->{r['load_after']:<5.1f}"
        )
    for key, value in summary.items():
        print(f"{key}: {value:.4f}")
    print(f"(machine: {os.cpu_count()} CPUs, shared; load = 1-min load average before -> after)")

    result = {
        "benchmark": "batch",
        "settings": {
            "data": str(args.data),
            "frames": n,
            "base_frames": n_base,
            "resolution": "1/3 (downsample_depth factor 3)",
            "n_input": args.n_input,
            "holdout": loader.holdout,
            "config": "DepthGPConfig.residual()",
            "engine": "EngineConfig(name=%r)" % args.engine,
            "threads_per_worker": 1,
        },
        "rows": rows,
        "summary": summary,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "dask_distributed": distributed.__version__,
            "note": "2-core machine shared with other jobs while measuring; see load averages",
        },
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    write_json(args.output, result)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
