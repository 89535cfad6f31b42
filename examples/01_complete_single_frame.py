"""Complete one frame and look at the posterior: synthetic by default, or a 7-Scenes frame.

    python examples/01_complete_single_frame.py                      # built-in synthetic street
    python examples/01_complete_single_frame.py --data ../shared/data/7scenes --points 200

With --data, the ground-truth Kinect depth of a 7-Scenes frame is degraded into a stand-in MDE
(blur, 20 % scale error, noise: stated, not a network) and 200 points are sampled from the
ground truth as the sparse measurements.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import gpdepth3d as g
from gpdepth3d.io import load_depth


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="a 7-Scenes folder (default: synthetic scene)")
    parser.add_argument("--points", type=int, default=200, help="number of sparse points")
    parser.add_argument("--output", type=Path, default=Path("outputs/example01"), help="output folder")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)

    if args.data is None:
        from gpdepth3d.datasets.synthetic import make_scene

        frame = make_scene(0, kind="room")
        gt, mde = frame.depth_gt, frame.mde
        print(frame.notes.splitlines()[0])
    else:
        gt = load_depth(args.data / "frame-000000.depth.png", png_scale=1e-3, invalid_value=65535)
        gt = g.downsample_depth(gt, 4)  # 160 x 120, closest depth per block
        from gpdepth3d.datasets.synthetic import MDESimulation, simulate_mde

        # holes at the median depth, blurred (sigma 3 px), x1.2, 3 % white relative noise
        sim = MDESimulation(scale=1.2, blur_sigma=3.0 / gt.shape[1], field_amplitude=0.0, noise=0.03)
        mde = simulate_mde(gt, sim, rng, fill_depth=float(np.median(gt[gt > 0])))
        print("stand-in MDE: Kinect depth blurred, scaled by 1.2 and noised (not a network)")

    v, u = np.nonzero(gt > 0)
    pick = rng.choice(v.size, min(args.points, v.size), replace=False)
    sparse = g.SparseDepth(u[pick].astype(float), v[pick].astype(float), gt[v[pick], u[pick]], gt.shape)

    posterior = g.complete(mde, sparse)  # the default model (log-residual GP, fitted to the frame)
    before = g.depth_metrics(mde, gt)["rmse"]
    after = g.depth_metrics(posterior.mean, gt)["rmse"]
    cover = g.calibration_metrics(posterior.mean, posterior.variance, gt)["coverage_2sigma"]
    print(f"RMSE MDE {before:.0f} mm -> GP {after:.0f} mm; ±2σ coverage {cover:.2f}")
    for path in posterior.save(args.output / "posterior", png=True):
        print(f"wrote {path}")
    return {"rmse_mde": before, "rmse_gp": after, "coverage_2sigma": cover}


if __name__ == "__main__":
    main()
