"""The CUDA paths against the CPU on a real KITTI frame: fast engine (torch back-end), KISS-GP, ONNX front-end.

On one machine with a CUDA GPU (run it there; without one it records that and stops):

* **ONNX front-end**: RT-MonoDepth-S on the kitti_tiny frame with every onnxruntime execution
  provider available (CUDA, CPU): seconds per frame (best of 10 after a warm-up) and the largest
  relative difference of the depth maps.
* **fast engine**: the default model (`DepthGPConfig()`) and the paper preset
  (`DepthGPConfig.paper()`) at KITTI 1/3 (125 x 414) and with full-resolution output
  (375 x 1242 from the 1/3 grid), at the densities 1/64, 1/16, 1/4 and 1 of the LiDAR, mean +
  variance through `DepthCompleter`: the CPU (compiled back-end, automatic route) against CUDA
  (`EngineConfig(device="cuda")`: the torch back-end, grid route), best of ``--repeats`` after
  a warm-up, with the largest relative difference of the CUDA posterior's mean and variance
  from the CPU one.
* **KISS-GP** (GPyTorch) on CUDA for the same cells, one call each in its own process (after a
  warm-up solve at the lowest density), killed after ``--kissgp-timeout`` seconds, the denser
  cells of that (model, output) then skipped; its agreement with the CPU fast engine.

Writes bench/results/cuda.json (``--output``) after every section, so a run cut short leaves
what it measured, and prints a table.

    python bench/cuda.py [--data ../shared/data] [--models ../shared/models] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _kitti_speed import REPO, completer, draw, kitti_setup, machine, max_rel, time_completer  # noqa: E402

DENSITIES = (1 / 64, 1 / 16, 1 / 4, 1.0)
ARGS = None  # the parsed command line (for the KISS-GP cells' processes)


def _write(result: dict, path: Path) -> None:
    from gpdepth3d.io import write_json

    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, result)


def onnx_section(data: Path, models: Path) -> tuple[dict, object]:
    """Times the front-end per provider; returns the rows and the fastest front-end."""
    import onnxruntime

    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.mde import RTMonoDepthONNX

    rgb = open_dataset(data / "kitti_tiny")[0].rgb
    rows, depths, fronts = {}, {}, {}
    for provider in onnxruntime.get_available_providers():
        if provider not in ("CUDAExecutionProvider", "CPUExecutionProvider"):
            continue
        providers = [provider] if provider == "CPUExecutionProvider" else [provider, "CPUExecutionProvider"]
        try:
            mde = RTMonoDepthONNX(models_dir=models, providers=providers)
            depths[provider] = np.asarray(mde(rgb), dtype=np.float64)  # warm-up
            times = []
            for _ in range(10):
                t = time.perf_counter()
                mde(rgb)
                times.append(time.perf_counter() - t)
            rows[provider] = {"seconds": min(times), "session_providers": mde.session.get_providers()}
            fronts[provider] = mde
        except Exception as exc:  # a provider that is listed but fails to run: record it
            rows[provider] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
    if "CUDAExecutionProvider" in depths and "CPUExecutionProvider" in depths:
        rows["cuda_vs_cpu_depth_max_rel"] = max_rel(depths["CUDAExecutionProvider"], depths["CPUExecutionProvider"])
    rows["available_providers"] = onnxruntime.get_available_providers()
    best = fronts.get("CUDAExecutionProvider") or fronts.get("CPUExecutionProvider")
    return rows, best


def engine_rows(setup, device: str, repeats: int, kissgp_cell: float, kissgp_total: float, rows: list, done) -> None:
    """Appends one row per (resolution, model, density) to ``rows``, calling ``done(row)`` after each."""
    import torch

    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.gp.model import DepthGPConfig

    sync = torch.cuda.synchronize if device.startswith("cuda") else None
    models = {"default": DepthGPConfig(), "paper": DepthGPConfig.paper()}
    kiss_spent, kiss_stop = 0.0, set()
    for res in ("1/3", "full"):
        out_shape = None if res == "1/3" else setup.full_shape
        for name, config in models.items():
            cpu = completer(config)
            gpu = completer(config, EngineConfig(device=device, backend="torch"))
            for density in DENSITIES:
                sparse = draw(setup, density)
                row = {"model": name, "resolution": res, "density": density, "points": len(sparse)}
                c = time_completer(cpu, setup, sparse, out_shape, repeats)
                g = time_completer(gpu, setup, sparse, out_shape, repeats, sync=sync)
                pc, pg = c.pop("posterior"), g.pop("posterior")
                row["cpu"], row["cuda"] = c, g
                row["cuda_vs_cpu"] = {
                    "mean_max_rel": max_rel(pg.mean, pc.mean),
                    "variance_max_rel": max_rel(pg.variance, pc.variance),
                }
                key = (name, res)
                if key in kiss_stop or kiss_spent > kissgp_total:
                    row["kissgp_cuda"] = {
                        "skipped": "an earlier cell of this model and resolution timed out"
                        if key in kiss_stop
                        else "total KISS-GP budget spent"
                    }
                else:
                    t = time.perf_counter()
                    row["kissgp_cuda"] = _kissgp_subprocess(name, res, density, device, kissgp_cell)
                    kiss_spent += time.perf_counter() - t
                    if "timeout_seconds" in row["kissgp_cuda"]:
                        kiss_stop.add(key)
                    elif "mean" in row["kissgp_cuda"]:
                        pk = row["kissgp_cuda"]
                        pk["vs_cpu_fast"] = {
                            "mean_max_rel": max_rel(pk.pop("mean"), pc.mean),
                            "variance_max_rel": max_rel(pk.pop("variance"), pc.variance),
                        }
                rows.append(row)
                done(row)


def _kissgp_subprocess(model: str, res: str, density: float, device: str, timeout: float) -> dict:
    """One KISS-GP cell in its own process (a warm-up solve first), killed after ``timeout`` seconds."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cell.npz"
        cmd = [
            sys.executable,
            __file__,
            "--data",
            str(ARGS.data),
            "--models",
            str(ARGS.models_dir),
            "--device",
            device,
            "--kissgp-cell",
            model,
            res,
            repr(density),
            str(out),
        ]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"timeout_seconds": timeout}
        if done.returncode != 0:
            return {"error": (done.stderr.strip().splitlines() or ["?"])[-1][:300]}
        row = json.loads(done.stdout.strip().splitlines()[-1])
        with np.load(out) as z:
            row["mean"], row["variance"] = z["mean"], z["variance"]
        return row


def kissgp_cell(data: Path, models: Path, model: str, res: str, density: float, device: str, out: Path) -> dict:
    """The KISS-GP cell run by `_kissgp_subprocess`: a warm-up solve at the lowest density, then the cell."""
    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.mde import RTMonoDepthONNX

    setup, _ = kitti_setup(data, RTMonoDepthONNX(models_dir=models, providers=["CPUExecutionProvider"]))
    config = DepthGPConfig() if model == "default" else DepthGPConfig.paper()
    c = completer(config, EngineConfig(name="kissgp", device=device))
    time_completer(c, setup, draw(setup, DENSITIES[0]), None, 1, warmup=False)  # CUDA context, kernels
    sync = None
    if device.startswith("cuda"):
        import torch

        sync = torch.cuda.synchronize
    r = time_completer(
        c, setup, draw(setup, density), None if res == "1/3" else setup.full_shape, 1, warmup=False, sync=sync
    )
    post = r.pop("posterior")
    np.savez(out, mean=post.mean, variance=post.variance)
    return r


def _fmt(r: dict) -> str:
    k = r.get("kissgp_cuda", {})
    ks = f"{1e3 * k['seconds']:9.1f} ms" if "seconds" in k else f"{'-':>12s}"
    return (
        f"{r['model']:8s} {r['resolution']:5s} {r['density']:7.4f} {r['points']:6d}  "
        f"cpu {1e3 * r['cpu']['seconds']:8.1f} ms ({r['cpu']['route']})  cuda {1e3 * r['cuda']['seconds']:8.1f} ms  "
        f"kissgp-cuda {ks}  cuda-cpu mean {r['cuda_vs_cpu']['mean_max_rel']:.1e} var {r['cuda_vs_cpu']['variance_max_rel']:.1e}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("GPDEPTH3D_DATA", REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--kissgp-timeout",
        type=float,
        default=40.0,
        help="seconds per KISS-GP cell (own process); denser cells of the model and output are skipped after one times out",
    )
    parser.add_argument(
        "--kissgp-total", type=float, default=180.0, help="no new KISS-GP cell after this many seconds of them"
    )
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "cuda.json")
    parser.add_argument("--device", default="cuda", help="torch device of the GPU columns ('cpu': a dry run)")
    parser.add_argument("--kissgp-cell", nargs=4, metavar=("MODEL", "RES", "DENSITY", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    models = args.models or args.data.parent / "models"
    global ARGS
    ARGS = args
    args.models_dir = models
    if args.kissgp_cell:
        m, res, density, out = args.kissgp_cell
        print(json.dumps(kissgp_cell(args.data, models, m, res, float(density), args.device, Path(out)), default=float))
        return

    def say(line: str) -> None:
        print(line, flush=True)

    import torch

    result: dict = {
        **machine(),
        "torch": torch.__version__,
        "cuda_available": torch.cuda.is_available(),
        "device": args.device,
    }
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        result["note"] = "no CUDA device: nothing measured"
        _write(result, args.output)
        say("no CUDA device: nothing measured")
        return
    import numba

    result["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    result["numba_threads"] = numba.get_num_threads()
    result["note"] = (
        "one machine: CPU = its CPU cores (compiled back-end, automatic route), CUDA = its GPU "
        "(torch back-end, grid route); the leave-one-out screening of the default model runs on the CPU "
        "in both; seconds are wall-clock per frame through DepthCompleter"
    )
    t0 = time.perf_counter()
    result["onnx"], mde = onnx_section(args.data, models)
    say(f"onnx: {json.dumps(result['onnx'], default=str)}")
    setup, mde_seconds = kitti_setup(args.data, mde)
    result["frame"] = {
        "name": setup.name,
        "grid": list(setup.grid_shape),
        "full": list(setup.full_shape),
        "available_points": len(setup.lidar.available),
        "mde_seconds": mde_seconds,
    }
    _write(result, args.output)
    say("model    res   density points  (best of %d after a warm-up; mean + variance)" % args.repeats)
    result["rows"] = []

    def done(row: dict) -> None:
        say(_fmt(row))
        _write(result, args.output)

    engine_rows(setup, args.device, args.repeats, args.kissgp_timeout, args.kissgp_total, result["rows"], done)
    result["seconds_total"] = time.perf_counter() - t0
    _write(result, args.output)
    say(f"wrote {args.output}")


if __name__ == "__main__":
    main()
