"""Measures the README's results table on the 7-Scenes frames in ../shared/data.

FastDepth front-end, half resolution (320x240), uniform samples of 50/200/500 points plus the
biased field-of-view bands; writes the tables, plots and bench/results/eval_7scenes.json.

    python bench/eval_7scenes.py [--stride 12] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

from gpdepth3d.evaluation.evaluation import markdown_table, run_evaluation
from gpdepth3d.io import write_json

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--stride", type=int, default=12, help="use every stride-th frame (60 frames in all)")
    parser.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "eval_7scenes")
    args = parser.parse_args()
    data = args.data / "7scenes"
    results = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "load_average_1min": os.getloadavg()[0],
    }
    results["uniform"] = run_evaluation(
        data, protocols=["uniform"], levels=[50, 200, 500], output=args.output / "uniform", stride=args.stride
    )
    print(markdown_table(results["uniform"]))
    results["bands"] = run_evaluation(
        data,
        protocols=["hband", "vband"],
        levels=[200],
        output=args.output / "bands",
        stride=args.stride,
        methods=["mde", "mde_scale", "ip_basic", "gp_default", "gp_residual", "gp_residual_fit"],
        qualitative=False,
    )
    print(markdown_table(results["bands"]))
    write_json(ROOT / "bench" / "results" / "eval_7scenes.json", results)


if __name__ == "__main__":
    main()
