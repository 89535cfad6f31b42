"""Do hyperparameters fitted per frame beat the fixed ones on real data? (7-Scenes, FastDepth.)

Runs the evaluation (`gpdepth3d.evaluation.evaluation.run_evaluation`) at 320x240 with 200 points, uniform and
in the lower half-band, for the paper's balanced GP with its fixed values (``gp_balanced``) and
fitted per frame by maximum marginal likelihood (``gp_balanced_fit``: ``DepthGPConfig.paper(fit=True)``),
the residual GP fixed / fitted, and the default model fixed / fitted (``gp_default_fit``:
``DepthGPConfig(fit=True)``). Writes bench/results/fit_7scenes.json.

    python bench/fit.py [--data ../shared/data] [--stride 12]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gpdepth3d.evaluation.evaluation import markdown_table, run_evaluation
from gpdepth3d.io import write_json

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--stride", type=int, default=12, help="use every stride-th frame")
    parser.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "fit_7scenes")
    args = parser.parse_args()
    rows = run_evaluation(
        args.data / "7scenes",
        protocols=["uniform", "hband"],
        levels=[200],
        output=args.output,
        stride=args.stride,
        methods=[
            "mde",
            "gp_default",
            "gp_default_fit",
            "gp_balanced",
            "gp_balanced_fit",
            "gp_residual",
            "gp_residual_fit",
        ],
        qualitative=False,
        progress=False,
    )
    print(markdown_table(rows))
    write_json(
        ROOT / "bench" / "results" / "fit_7scenes.json",
        {
            "dataset": "7scenes",
            "mde": "FastDepth TFLite",
            "resolution": "320x240",
            "command": "python bench/fit.py",
            "rows": rows,
        },
    )


if __name__ == "__main__":
    main()
