"""The log-residual GP's lattice: every pixel (stride 1) against every 2nd and 4th (strides 2, 4), on real KITTI.

For each of the paper's eight uniform densities, on kitti_tiny prepared as the paper's protocol does
(RT-MonoDepth-S, GP at 1/3 resolution, 20 % of the LiDAR pixels held out as ground truth):

- time: best of ``--repeats`` `DepthCompleter` calls (mean + variance, 1/3 output) on frame 0, every
  stride in the same run, and the ratios to stride 1;
- accuracy: RMSE over the 7 frames' held-out points and +-2 sigma coverage, for strides 1, 2, 4
  and the default (automatic: `gpdepth3d.completion.lattice.lattice_stride`). Strides 2 and 4 krige
  the field's detail below the lattice back (`gpdepth3d.gp.sublattice`, nu = 0.5).

Writes ``bench/results/lattice.json`` (atomically) and prints a table.

    python bench/lattice.py [--data ../shared/data] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _kitti_speed import REPO, completer, draw, machine, time_completer  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("GPDEPTH3D_DATA", REPO.parent / "shared" / "data"))
    )
    parser.add_argument("--models", type=Path, default=None, help="models folder (default: <data>/../models)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "lattice.json")
    args = parser.parse_args(argv)

    from gpdepth3d import DepthGPConfig
    from gpdepth3d.gp import EngineConfig
    from gpdepth3d.completion.complete import DepthCompleter
    from gpdepth3d.completion.lattice import lattice_stride
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.evaluation.kitti_protocol import (
        PAPER_DENSITIES,
        KittiProtocolConfig,
        lidar_frames,
        prepare_kitti_frame,
        draw_input,
    )
    from gpdepth3d.mde import load_frontend

    models = args.models or args.data.parent / "models"
    mde = load_frontend("rtmonodepth", models_dir=models)
    protocol = KittiProtocolConfig()
    setups = []
    for i, (name, rgb, lidar) in enumerate(lidar_frames(open_dataset(args.data / "kitti_tiny"))):
        setups.append(
            prepare_kitti_frame(name, rgb, lidar, mde, factor=protocol.factor, holdout=protocol.holdout, rng=i)
        )
    strides = ("stride 1", "stride 2", "stride 4")
    engines = {label: EngineConfig(lattice_stride=int(label[-1])) for label in strides}
    engines["default"] = EngineConfig()  # the automatic stride
    rows = []
    for density in PAPER_DENSITIES:
        row: dict = {"density": density}
        setup0 = setups[0]
        sparse0 = draw(setup0, density)
        h, w = setup0.grid_shape
        row["points_frame0"] = len(sparse0.depth)
        row["default_stride"] = lattice_stride(DepthGPConfig(), h, w, len(sparse0.depth), DepthGPConfig().lengthscale)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for label in strides:
                timed = time_completer(
                    completer(DepthGPConfig(), engines[label]), setup0, sparse0, setup0.grid_shape, args.repeats
                )
                row[f"{label} ms"] = 1e3 * timed["seconds"]
            for label, engine in engines.items():
                sq, inside, count = 0.0, 0, 0
                for i, setup in enumerate(setups):
                    sparse = draw_input("uniform", density, setup.lidar.available, rng=np.random.default_rng([7, i]))
                    post = DepthCompleter(DepthGPConfig(), engine=engine)(setup.mde_grid, sparse)
                    gt = setup.lidar.gt_grid
                    v = gt > 0
                    e = post.mean[v] - gt[v]
                    sq += float(np.sum(e**2))
                    inside += int(np.sum(np.abs(e) <= 2 * post.std[v]))
                    count += int(v.sum())
                row[f"{label} rmse mm"] = 1e3 * np.sqrt(sq / count)
                row[f"{label} cov2"] = inside / count
        for label in strides[1:]:
            row[f"{label} speed-up"] = row["stride 1 ms"] / row[f"{label} ms"]
            row[f"{label} / stride 1 rmse"] = row[f"{label} rmse mm"] / row["stride 1 rmse mm"]
        rows.append(row)
        print(" | ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
    result = {**machine(), "frames": [s.name for s in setups], "repeats": args.repeats, "rows": rows}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.output.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(args.output)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
