"""Wall time and F-score of ``gpdepth3d map`` on the shared sequences, run as the README and docs write it.

Usage::

    python bench/map_recipes.py [--out bench/results/map_recipes.json]

Every ``gpdepth3d map ... ../shared/data/...`` line of the README (posed, from images alone, with
``--points``), then docs/mapping.md's posed ones (the 7-Scenes frames, 60), is started as a user starts it: a fresh ``python -m gpdepth3d.cli`` process from the
repository root, with the library's defaults (FastDepth TFLite, the Mapper's own triangulated points,
320-px working width). Recorded per sequence: the process's wall time, the run's own mapping time
(``wall_s`` of its metrics.json), frames fused, frames without points, and the F-score at 5 cm of the map
and of the MDE alone against the mesh fused from the sensor depth; the load average before and after.

Wall-clock seconds on a shared machine (the development machine: 2 cores, several jobs): compare rows of
one run. Results: a table on stdout and ``bench/results/map_recipes.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def recipes() -> dict[str, str]:
    """Every README ``gpdepth3d map`` line, in order (a later line may read an earlier one's output), then
    docs/mapping.md's posed lines on the shared data, by the name of their output folder."""
    lines = re.findall(r"^gpdepth3d map [^\n]*", (REPO / "README.md").read_text(encoding="utf-8"), flags=re.M)
    docs = re.findall(r"^gpdepth3d map [^\n]*", (REPO / "docs" / "mapping.md").read_text(encoding="utf-8"), flags=re.M)
    lines += [line for line in docs if "--poses" in line]
    found: dict[str, str] = {}
    for line in (line.strip() for line in lines if "../shared/data" in line):
        found.setdefault(Path(shlex.split(line)[shlex.split(line).index("--output") + 1]).name, line)
    return found


SEQUENCES = {"7scenes": "7-Scenes", "hololens": "HoloLens walk"}


def label(line: str) -> str:
    """What a ``map`` line maps, for the table: the sequence and where its poses come from."""
    sequence = re.search(r"\.\./shared/data/(\w+)", line).group(1)
    if "--poses" in line:
        poses = "poses given"
    else:
        poses = "the SfM model's poses and points" if "--points" in line else "pycolmap SfM"
    return f"{SEQUENCES.get(sequence, sequence)}, {poses}"


def run_command(line: str) -> tuple[dict, dict]:
    """Runs one ``gpdepth3d`` command line as a user starts it: a fresh process from the repository root.

    Returns:
        (the ``metrics.json`` of its ``--output`` folder, the process: ``output``, ``process_wall_s``,
        ``process_cpu_s``, ``loadavg_before``, ``loadavg_after``).
    """
    argv = shlex.split(line)[1:]
    out = REPO / argv[argv.index("--output") + 1]
    load_before = os.getloadavg()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "gpdepth3d.cli", *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    wall = time.monotonic() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{line}\n{proc.stderr[-3000:]}")
    summary = json.loads((out / "metrics.json").read_text())
    process = {
        "output": str(out),
        "process_wall_s": wall,
        "process_cpu_s": (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
    }
    return summary, process


def run(line: str) -> dict:
    """One ``map`` line's record: its process and what its ``metrics.json`` says."""
    summary, process = run_command(line)
    metrics = summary["metrics"] or {}
    return {
        "command": line,
        "label": label(line),
        "process_wall_s": process["process_wall_s"],
        "mapping_wall_s": summary["wall_s"],
        "frames": summary["frames"],
        "frames_fused": summary["frames_fused"],
        "frames_without_points": len(summary["frames_without_points"]),
        "sparse_points_per_frame_median": summary["sparse_points_per_frame_median"],
        "fscore_map": (metrics.get("map") or {}).get("fscore"),
        "fscore_mde_only": (metrics.get("mde") or {}).get("fscore"),
        "precision_map": (metrics.get("map") or {}).get("precision"),
        "recall_map": (metrics.get("map") or {}).get("recall"),
        "add_frame_median_s": summary["timing_median_s_per_frame"].get("total"),
        "loadavg_before": process["loadavg_before"],
        "loadavg_after": process["loadavg_after"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "map_recipes.json")
    args = parser.parse_args()
    sys.path.insert(0, str(REPO))
    from gpdepth3d.io import write_json

    rows = {}
    for name, line in recipes().items():
        rows[name] = run(line)
        r = rows[name]
        scores = "no sensor depth" if r["fscore_map"] is None else f"F map {r['fscore_map']:.3f}"
        if r["fscore_mde_only"] is not None:
            scores += f", MDE alone {r['fscore_mde_only']:.3f}"
        print(
            f"{name:9s} {r['frames_fused']:3d}/{r['frames']:3d} fused, {scores}, {r['process_wall_s']:.0f} s "
            f"(load {r['loadavg_before'][0]:.1f})",
            flush=True,
        )
    import gpdepth3d

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    write_json(
        args.out,
        {
            "version": gpdepth3d.__version__,
            "commit": commit.stdout.strip() or None,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load_average_1min": {
                "before": min(r["loadavg_before"][0] for r in rows.values()),
                "after": max(r["loadavg_after"][0] for r in rows.values()),
            },
            "sequences": rows,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
