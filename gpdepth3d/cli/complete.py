"""``gpdepth3d complete``: one frame, MDE depth + sparse depth -> posterior mean and variance files."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
import tyro

from ..errors import OutputError
from ..gp.model import DepthGPConfig
from ..io import check_output_path

# The GP model as a CLI choice: `gpdepth3d complete ... model:residual --model.lengthscale 30`.
ModelChoice = Union[
    Annotated[DepthGPConfig, tyro.conf.subcommand("default", default=DepthGPConfig(), prefix_name=False)],
    Annotated[DepthGPConfig, tyro.conf.subcommand("paper", default=DepthGPConfig.paper(), prefix_name=False)],
    Annotated[DepthGPConfig, tyro.conf.subcommand("residual", default=DepthGPConfig.residual(), prefix_name=False)],
]


def _print_metrics(rows: dict[str, dict[str, float]]) -> None:
    keys = ("rmse", "mae", "irmse", "imae", "rel", "delta1")
    print(f"{'method':<12}" + "".join(f"{k:>10}" for k in keys))
    for name, m in rows.items():
        print(f"{name:<12}" + "".join(f"{m[k]:>10.3f}" for k in keys))
    print("(rmse, mae in mm; irmse, imae in 1/km; rel fraction; delta1 share)")


def complete_command(
    *,
    mde: Path,
    output: Path,
    sparse: Optional[Path] = None,
    lidar: Optional[Path] = None,
    calib: Optional[Path] = None,
    model: ModelChoice = DepthGPConfig(),
    lidar_image_size: Optional[tuple[int, int]] = None,
    mde_png_scale: float = 1.0 / 256.0,
    sparse_png_scale: float = 1.0 / 256.0,
    sparse_points: Literal["uvd", "xyz"] = "uvd",
    intrinsics: Optional[Path] = None,
    gt: Optional[Path] = None,
    gt_png_scale: float = 1.0 / 256.0,
    gt_invalid_value: Optional[int] = None,
    output_size: Optional[tuple[int, int]] = None,
    png: bool = True,
    rgb: Optional[Path] = None,
    models_dir: Optional[Path] = None,
    drop_invalid_points: bool = False,
) -> None:
    """Complete one frame: MDE depth + sparse depth -> posterior mean and variance.

    Writes OUTPUT.npz (mean, variance, std, mde, in metres / m^2) and, with --png, OUTPUT_mean.png and
    OUTPUT_std.png (16-bit, KITTI convention value = metres * 256). Prints metrics when --gt is given.

    Args:
        mde: MDE depth map (.npy/.npz in metres, or 16-bit .png with --mde-png-scale); with --rgb instead a
            front-end that is run on the image: "rtmonodepth" (KITTI, outdoor), "rtmonodepth-mono", "fastdepth"
            (NYU, indoor) or a .onnx/.tflite model file.
        output: Output path (the .npz suffix is added).
        sparse: Sparse depth: a sparse depth map (.npy/.npz/.png) or a point list (.npz with u, v, depth; .txt lines
            "u v depth [sigma]" in MDE pixels and metres, or "X Y Z" camera-frame metres with --sparse-points xyz).
        lidar: Instead of --sparse: a raw KITTI Velodyne scan (.bin), projected with --calib (closest point per pixel).
        calib: KITTI calibration for --lidar: an object-benchmark calib_*.txt or a raw-data folder with
            calib_cam_to_cam.txt and calib_velo_to_cam.txt.
        lidar_image_size: HEIGHT WIDTH of the image the calibration belongs to (default: the MDE size, refused
            when the calibration's principal point does not fit it); the projected points are then moved to the
            MDE grid, closest point per pixel.
        model: GP model preset ("default": the log-residual GP fitted per frame, robust to bad points;
            "paper": balanced KISS-GP of the paper; "residual": MDE as prior mean).
        mde_png_scale: Metres per unit of a 16-bit MDE PNG.
        sparse_png_scale: Metres per unit of a 16-bit sparse PNG.
        sparse_points: How a .txt point list is read: "uvd" (pixels + depth) or "xyz" (camera frame, needs --intrinsics).
        intrinsics: 3x3 K as text (fx 0 cx / 0 fy cy / 0 0 1) for the MDE image; checked against the image size.
        gt: Ground-truth depth for metrics (same formats).
        gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (1/1000 for Kinect millimetres).
        gt_invalid_value: Raw PNG value that marks invalid ground truth (65535 for 7-Scenes).
        output_size: Output HEIGHT WIDTH (default: the MDE size; larger upsamples).
        png: Also write 16-bit PNGs of mean and std.
        rgb: RGB image to run the front-end named by --mde on (the MDE map is then the network's output).
        models_dir: Folder of the named front-ends' models (default: $GPDEPTH3D_MODELS or ../shared/models).
        drop_invalid_points: Drop point-list rows with a NaN/negative depth or outside the image (their count is
            printed as a warning) instead of refusing the file.
    """
    from ..camera import PinholeCamera
    from ..completion.complete import DepthCompleter, PosteriorWarning
    from ..completion.problem import check_output_shape
    from ..errors import InvalidInputError
    from ..io import check_png_scale, load_depth, load_sparse, read_matrix
    from ..measurements import LidarCalibration, load_velodyne, project_points
    from ..metrics import calibration_metrics, depth_metrics

    # Everything is checked and read before anything is computed or written.
    for name, value in (("--mde-png-scale", mde_png_scale), ("--sparse-png-scale", sparse_png_scale),
                        ("--gt-png-scale", gt_png_scale)):
        check_png_scale(value, name)
    if gt_invalid_value is not None and not 0 <= gt_invalid_value <= 65535:
        raise InvalidInputError("--gt-invalid-value", "a 16-bit PNG value 0..65535", gt_invalid_value)
    if lidar_image_size is not None:
        from ..measurements import _as_shape

        _as_shape(lidar_image_size, "--lidar-image-size")
    out_npz = check_output_path(output, "--output").with_suffix(".npz")
    check_output_targets([out_npz] + ([out_npz.with_name(out_npz.stem + s) for s in ("_mean.png", "_std.png")] if png else []))
    if (sparse is None) == (lidar is None):
        raise InvalidInputError("--sparse / --lidar", "exactly one source of measurements", "both or neither")
    if rgb is not None:
        from ..io import load_rgb
        from ..mde import load_frontend

        mde_depth = load_frontend(str(mde), models_dir=models_dir)(load_rgb(rgb))
    else:
        mde_depth = load_depth(mde, png_scale=mde_png_scale)
    out_shape = check_output_shape(output_size, mde_depth.shape)
    gt_depth = None
    if gt is not None:
        gt_depth = load_depth(gt, png_scale=gt_png_scale, invalid_value=gt_invalid_value)
        if abs((gt_depth.shape[1] / gt_depth.shape[0]) / (out_shape[1] / out_shape[0]) - 1.0) > 0.01:
            raise InvalidInputError(
                "--gt", f"a depth map of the image with the MDE's aspect ratio ({out_shape[1]}x{out_shape[0]})",
                f"{gt_depth.shape[1]}x{gt_depth.shape[0]}",
            )
    camera = None
    if intrinsics is not None:
        camera = PinholeCamera.from_K(read_matrix(intrinsics, (3, 3), "intrinsics"), mde_depth.shape[1], mde_depth.shape[0])
    if lidar is not None:
        if calib is None:
            raise InvalidInputError("--calib", "a KITTI calibration for --lidar", None)
        calibration = LidarCalibration.from_kitti(calib)
        if lidar_image_size is None:
            calibration.check_image_size(mde_depth.shape, "--lidar-image-size (default: the MDE size)")
        measurements = calibration.project(load_velodyne(lidar), lidar_image_size or mde_depth.shape)
    elif sparse_points == "xyz":
        if camera is None:
            raise InvalidInputError("--intrinsics", "intrinsics for --sparse-points xyz", None)
        xyz = _load_table(sparse, 3)
        measurements = project_points(xyz, camera)
    else:
        measurements = load_sparse(sparse, mde_depth.shape, png_scale=sparse_png_scale, drop_invalid=drop_invalid_points)
    completer = DepthCompleter(model)
    with warnings.catch_warnings():  # the posterior's warnings are printed below, one line each
        warnings.simplefilter("ignore", PosteriorWarning)
        posterior = completer.complete(mde_depth, measurements, output_shape=output_size, frame=out_npz.stem)
    written = posterior.save(out_npz, png=png)
    print(
        f"completed {mde_depth.shape[1]}x{mde_depth.shape[0]} with {len(posterior.sparse)} measurements "
        f"({model.formulation}, engine {model.engine}) in {sum(posterior.timings.values()):.2f} s"
        + (f"; {posterior.n_rejected} rejected as outliers" if posterior.n_rejected else "")
    )
    for message in posterior.warnings:
        print(f"warning: {message}")
    if gt_depth is not None:
        if gt_depth.shape != posterior.shape:
            import cv2

            gt_depth = cv2.resize(gt_depth, posterior.shape[::-1], interpolation=cv2.INTER_NEAREST)
        rows = {"mde": depth_metrics(posterior.mde, gt_depth), "gp": depth_metrics(posterior.mean, gt_depth)}
        _print_metrics(rows)
        cal = calibration_metrics(posterior.mean, posterior.variance, gt_depth)
        print(f"calibration: +-1 sigma {cal['coverage_1sigma']:.3f}, +-2 sigma {cal['coverage_2sigma']:.3f}, "
              f"NLL {cal['nll']:.3f}")
    for path in written:
        print(f"wrote {path}")


def check_output_targets(paths: list[Path]) -> None:
    """Checks before any work that each output can be created: no directory in its place, a writable folder.

    Raises:
        OutputError: naming the first path that cannot be written.
    """
    for path in paths:
        check_output_path(path)
        folder = next((p for p in Path(path).absolute().parents if p.exists()), None)
        if folder is not None and not os.access(folder, os.W_OK | os.X_OK):
            raise OutputError(path, f"the folder {folder} is not writable")


def _load_table(path: Path, columns: int) -> np.ndarray:
    from ..errors import DataFormatError

    try:
        table = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DataFormatError(path, f"expected a numeric table: {exc}") from None
    if table.shape[1] < columns:
        raise DataFormatError(path, f"expected at least {columns} columns, got {table.shape[1]}")
    return table[:, -columns:]
