"""Shared pieces of the speed benchmarks on a real KITTI frame (bench/engines.py, bench/cuda.py).

The frame is kitti_tiny frame 0 prepared as the paper's KITTI protocol does
(`gpdepth3d.evaluation.kitti_protocol.prepare_kitti_frame`: RT-MonoDepth-S on the full image, the GP grid at
1/3 resolution, 20 % of the grid's LiDAR pixels held out, inputs drawn from the rest). Output
"1/3" is the GP grid itself (125 x 414), "full" the full image (375 x 1242) predicted from the
same 1/3 grid (the protocol's full-resolution output).
"""

from __future__ import annotations

import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def machine() -> dict:
    """The machine and its load, for the result files."""
    return {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "python": platform.python_version(),
        "load_average_1min": os.getloadavg()[0],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def kitti_setup(data: Path, mde, *, index: int = 0):
    """(KittiFrameSetup, seconds of the MDE) of kitti_tiny frame ``index`` with front-end ``mde``."""
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.evaluation.kitti_protocol import lidar_frames, prepare_kitti_frame

    frames = list(lidar_frames(open_dataset(data / "kitti_tiny")))
    name, rgb, lidar = frames[index]
    t = time.perf_counter()
    setup = prepare_kitti_frame(name, rgb, lidar, mde, factor=3, holdout=0.2, rng=0)
    return setup, time.perf_counter() - t


def draw(setup, density: float):
    """The uniform input of one density (seeded by the density, as every method gets the same points)."""
    from gpdepth3d.evaluation.kitti_protocol import draw_input

    return draw_input("uniform", density, setup.lidar.available, rng=int(round(1e6 * density)))


class Recorder:
    """Wraps an engine and keeps the `SolveInfo` of each call (the benchmark's view of routes and stages)."""

    def __init__(self, engine):
        self.engine = engine
        self.infos: list = []

    def solve(self, problem, **kwargs):
        solution = self.engine.solve(problem, **kwargs)
        self.infos.append(solution.info)
        return solution

    def __getattr__(self, name):
        return getattr(self.engine, name)


def completer(config, engine=None):
    """A `DepthCompleter` whose engine calls are recorded (``completer.engine.infos``)."""
    from gpdepth3d.completion.complete import DepthCompleter

    c = DepthCompleter(config, engine=engine)
    c.engine = Recorder(c.engine)
    return c


def time_completer(c, setup, sparse, out_shape, repeats: int, *, warmup: bool = True, sync=None) -> dict:
    """Best wall-clock seconds of ``repeats`` calls (after one warm-up call) with stages and route.

    Returns:
        {"seconds", "cpu_seconds" (least process CPU time of the calls, every thread counted: less
        sensitive than wall-clock time to other jobs on the machine), "first_seconds" (the warm-up
        call, set-up included), "stages" (the best call's
        `DepthPosterior.timings`), "route", "engine_seconds" (the engine's own stages),
        "posterior" (the last posterior)}.
    """
    out: dict = {}
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        n = repeats + (1 if warmup else 0)
        for i in range(n):
            c.engine.infos.clear()
            t, tc = time.perf_counter(), time.process_time()
            post = c(setup.mde_grid, sparse, output_shape=out_shape)
            if sync is not None:
                sync()
            dt, dc = time.perf_counter() - t, time.process_time() - tc
            if warmup and i == 0:
                out["first_seconds"] = dt
                continue
            runs.append((dt, post.timings, list(c.engine.infos), dc))
    best = min(runs, key=lambda r: r[0])
    out["seconds"] = best[0]
    out["cpu_seconds"] = min(r[3] for r in runs)  # the process's CPU time (all its threads), least of the calls
    out["stages"] = {k: float(v) for k, v in best[1].items()}
    infos = best[2]
    out["route"] = "+".join(i.route for i in infos) if infos else None
    out["engine_seconds"] = [{k: float(v) for k, v in i.seconds.items()} for i in infos]
    out["posterior"] = post
    return out


def ip_basic_seconds(setup, sparse, full: bool, repeats: int) -> tuple[float, np.ndarray]:
    """Best seconds of IP-Basic on the 1/3 grid (resized to full resolution when ``full``, as the protocol does)."""
    import cv2

    from gpdepth3d.evaluation.baselines import ip_basic

    best, out = np.inf, None
    for _ in range(repeats + 1):
        t = time.perf_counter()
        out = ip_basic(sparse, setup.grid_shape)
        if full:
            H, W = setup.full_shape
            out = cv2.resize(out, (W, H), interpolation=cv2.INTER_LINEAR)
        best = min(best, time.perf_counter() - t)
    return best, out


def max_rel(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |a - b| / |b| (b the reference)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))
