"""Project a raw KITTI Velodyne scan into the image, run RT-MonoDepth-S and complete at 1/3 resolution.

    python examples/02_kitti_lidar_projection.py --data ../shared/data/kitti_object

Steps: the scan and the calibration give the LiDAR depth of each pixel (closest point per pixel);
RT-MonoDepth-S (KITTI-trained, ONNX) gives the monocular depth of the whole image; both go to
1/3 resolution (closest point per 3x3 block, the paper's set-up); 20 % of the LiDAR pixels are
held out (seeded) as ground truth, the rest go to the default GP, whose posterior is read out at
full resolution. Printed: RMSE of the network alone and of the GP on the held-out pixels, and the
share of them inside +-2 sigma; written: the posterior (npz + 16-bit PNGs of mean and std).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import gpdepth3d as g


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="the kitti_object folder")
    parser.add_argument("--frame", default="000000")
    parser.add_argument(
        "--models",
        type=Path,
        default=None,
        help="folder of rtmonodepth_s_ms_640_192.onnx (default: ../models beside --data's parent)",
    )
    parser.add_argument("--output", type=Path, default=Path("outputs/example02"))
    args = parser.parse_args(argv)

    from gpdepth3d.depthmap import resize_map
    from gpdepth3d.io import load_rgb
    from gpdepth3d.mde import load_frontend
    from gpdepth3d.sampling import holdout_mask

    rgb = load_rgb(args.data / f"{args.frame}.png")
    calib = g.LidarCalibration.from_kitti(args.data / f"calib_{args.frame}.txt")
    scan = g.load_velodyne(args.data / f"{args.frame}.bin")
    lidar = calib.project(scan, rgb.shape[:2])
    print(f"{scan.shape[0]} LiDAR points -> {len(lidar)} pixels with depth in the {rgb.shape[1]}x{rgb.shape[0]} image")

    network = load_frontend("rtmonodepth", models_dir=args.models or args.data.parent.parent / "models")
    mde_full = np.asarray(network(rgb), dtype=np.float64)  # metres, the image's size
    small = g.downsample_depth(lidar.to_depth_map(), 3)  # closest point per 3x3 block
    mde = resize_map(mde_full, small.shape)

    points = g.SparseDepth.from_depth_map(small)
    held = holdout_mask(len(points), holdout=0.2, rng=0)
    train, test = points.subset(~held), points.subset(held)
    posterior = g.complete(mde, train, output_shape=rgb.shape[:2])
    # held-out pixels (1/3 grid) -> the full-resolution pixel at their block's centre
    rr = np.minimum((test.v.astype(int) * 3 + 1), rgb.shape[0] - 1)
    cc = np.minimum((test.u.astype(int) * 3 + 1), rgb.shape[1] - 1)
    err_gp = posterior.mean[rr, cc] - test.depth
    err_mde = mde_full[rr, cc] - test.depth
    rmse_gp, rmse_mde = float(np.sqrt(np.mean(err_gp**2))), float(np.sqrt(np.mean(err_mde**2)))
    inside = float(np.mean(np.abs(err_gp) <= 2 * posterior.std[rr, cc]))
    print(
        f"{len(train)} LiDAR pixels in, {len(test)} held out: RT-MonoDepth-S alone {rmse_mde:.2f} m RMSE, "
        f"GP {rmse_gp:.2f} m, +-2 sigma covers {inside:.1%}; MDE slope {posterior.mde_slope:.2f}"
    )
    print(
        f"posterior {posterior.shape}, median std {np.median(posterior.std):.3f} m, "
        f"solve {posterior.timings['solve']:.2f} s"
    )
    for path in posterior.save(args.output / f"{args.frame}_posterior", png=True):
        print(f"wrote {path}")
    return {
        "n_lidar": len(lidar),
        "shape": posterior.shape,
        "image_shape": rgb.shape[:2],
        "rmse_gp": rmse_gp,
        "rmse_mde": rmse_mde,
        "coverage_2sigma": inside,
    }


if __name__ == "__main__":
    main()
