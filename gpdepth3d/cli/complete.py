"""``gpdepth3d complete``: one frame, MDE depth + sparse depth -> posterior mean and variance files."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ._options import GPPreset

METRIC_COLUMNS: dict[str, str] = {
    "rmse": "RMSE [mm]",
    "mae": "MAE [mm]",
    "irmse": "iRMSE [1/km]",
    "imae": "iMAE [1/km]",
    "rel": "REL [-]",
    "delta1": "δ1 [-]",
}
"""The metrics table's columns and their headers with units."""


def _print_metrics(rows: dict[str, dict[str, float]]) -> None:
    print(f"{'method':<8}" + "".join(f"{h:>14}" for h in METRIC_COLUMNS.values()))
    for name, m in rows.items():
        print(f"{name:<8}" + "".join(f"{m[k]:>14.3f}" for k in METRIC_COLUMNS))


def complete_command(
    *,
    mde: str,
    output: str,
    sparse: Optional[Path] = None,
    lidar: Optional[Path] = None,
    calib: Optional[Path] = None,
    gp: GPPreset = DepthGPConfig(),
    engine: EngineConfig = EngineConfig(),
    lidar_image_size: Optional[tuple[int, int]] = None,
    depth_scale: Optional[float] = None,
    mde_png_scale: Optional[float] = None,
    sparse_png_scale: Optional[float] = None,
    sparse_points: Literal["uvd", "xyz"] = "uvd",
    intrinsics: Optional[Path] = None,
    gt: Optional[Path] = None,
    gt_png_scale: Optional[float] = None,
    gt_invalid_value: Optional[int] = None,
    output_size: Optional[tuple[int, int]] = None,
    png: bool = True,
    rgb: Optional[Path] = None,
    models_dir: Optional[Path] = None,
    drop_invalid_points: bool = False,
    preview: bool = True,
    mde_scale: Optional[float] = None,
    sparse_scale: Optional[float] = None,
    ply: Optional[Path] = None,
) -> None:
    """Complete one frame: an RGB image through a front-end (or an MDE depth map) + sparse depth -> depth and sigma.

    Writes OUTPUT.npz (mean, variance, std, mde, in metres / m^2), with --png OUTPUT_mean.png and
    OUTPUT_std.png (16-bit, KITTI convention value = metres * 256), and colourised previews with colour bars
    (OUTPUT_depth_preview.png, OUTPUT_sigma_preview.png, with --gt OUTPUT_error_preview.png). Prints metrics
    when --gt is given, then every file it wrote. The GP is a preset, --preset default|paper|residual (default:
    `DepthGPConfig()`), whose fields can be changed with --gp.FIELD VALUE, e.g. --preset residual --gp.fit.

    Args:
        mde: The monocular depth: a front-end run on --rgb, "fastdepth" (FastDepth TFLite, NYU, indoor; needs the
            [tflite] extra), "rtmonodepth" (RT-MonoDepth-S ONNX, KITTI, outdoor), "rtmonodepth-mono" or a
            .onnx/.tflite model file; or a depth map file (.npy/.npz in metres, 16-bit .png with --depth-scale).
        output: Output path (the .npz suffix is added); an existing folder or a name ending in "/" writes inside
            that folder, named after the --rgb (or --mde) file.
        sparse: Sparse depth: a sparse depth map (.npy/.npz/.png) or a point list (.npz with u, v, depth; .txt lines
            "u v depth [sigma]" in MDE pixels and metres, or "X Y Z" camera-frame metres with --sparse-points xyz).
        lidar: Instead of --sparse: a raw KITTI Velodyne scan (.bin), projected with --calib (closest point per pixel).
        calib: KITTI calibration for --lidar: an object-benchmark calib_*.txt or a raw-data folder with
            calib_cam_to_cam.txt and calib_velo_to_cam.txt.
        lidar_image_size: HEIGHT WIDTH of the image the calibration belongs to (default: the MDE size, refused
            when the calibration's principal point does not fit it); the projected points are then moved to the
            MDE grid, closest point per pixel.
        gp: The GP: --preset "default" (log-residual, `DepthGPConfig()`, robust to bad points), "paper" (the
            paper's balanced GP) or "residual" (MDE as prior mean), then --gp.FIELD to change one of its fields.
        engine: How the posterior is computed (the same posterior whichever): --engine.name fast|exact|kissgp,
            --engine.device cuda, --engine.lattice-stride K (`gpdepth3d.gp.EngineConfig`).
        depth_scale: Metres per unit of every 16-bit PNG input (0.001: millimetres) whose own scale is not
            given. Unset, PNGs are read at KITTI's 1/256 m, and one whose depths are 2.5x (or more) those of
            the frame's other inputs is refused (millimetres read as 1/256 m give 3.9x).
        mde_png_scale: Metres per unit of a 16-bit MDE PNG (default: --depth-scale, else 1/256).
        sparse_png_scale: Metres per unit of a 16-bit sparse PNG (default: --depth-scale, else 1/256).
        sparse_points: How a .txt point list is read: "uvd" (pixels + depth) or "xyz" (camera frame, needs --intrinsics).
        intrinsics: K of the MDE image: "fx,fy,cx,cy" (pixels), a 3x3 K text file or a KITTI calibration.
        gt: Ground-truth depth for metrics (same formats).
        gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (0.001 for Kinect millimetres; default:
            --depth-scale, else 1/256).
        gt_invalid_value: Raw PNG value that marks invalid ground truth (65535 for 7-Scenes).
        output_size: Output HEIGHT WIDTH (default: the MDE size; larger upsamples).
        png: Also write 16-bit PNGs of mean and std.
        rgb: RGB image to run the front-end named by --mde on (the MDE map is then the network's output); with an
            MDE depth file, the image drawn in the previews and colouring --ply.
        models_dir: Folder of the named front-ends' models (default: $GPDEPTH3D_MODELS or ../shared/models).
        drop_invalid_points: Drop point-list rows with a NaN/negative depth or outside the image (their count is
            printed as a warning) instead of refusing the file.
        preview: Also write the colourised previews (PNG with colour bars).
        mde_scale: Metres per unit of an MDE depth file (0.001 for millimetres). Unset, the file must hold metres:
            values that look like millimetres or centimetres are refused before any work.
        sparse_scale: Metres per unit of the sparse depths (and sigmas), any format (0.001 for millimetres). Unset,
            they must be metres: values that look like millimetres or centimetres are refused before any work.
        ply: Also write the posterior as a coloured point cloud (binary PLY with per-point sigma, variance and
            confidence; `gpdepth3d.mapping.cloud`), back-projected with --intrinsics or the --calib of --lidar and
            coloured by --rgb (grey without it).
    """
    from ..completion.frame_inputs import PNGScales, read_frame_inputs
    from ..pipelines.complete_run import plan_outputs, run_complete

    scales = PNGScales(depth_scale, mde_png_scale, sparse_png_scale, gt_png_scale)
    can_backproject = intrinsics is not None or (lidar is not None and calib is not None)
    source = Path(rgb) if rgb is not None else Path(mde)
    plan = plan_outputs(
        output, source, png=png, preview=preview, with_gt=gt is not None, ply=ply, can_backproject=can_backproject
    )
    inputs = read_frame_inputs(
        mde,
        sparse=sparse,
        lidar=lidar,
        calib=calib,
        lidar_image_size=lidar_image_size,
        sparse_points=sparse_points,
        intrinsics=intrinsics,
        rgb=rgb,
        gt=gt,
        gt_invalid_value=gt_invalid_value,
        png_scales=scales,
        mde_scale=mde_scale,
        sparse_scale=sparse_scale,
        models_dir=models_dir,
        drop_invalid_points=drop_invalid_points,
    )
    outcome = run_complete(inputs, plan, gp=gp, engine=engine, output_size=output_size)
    post = outcome.posterior
    print(
        f"completed {inputs.mde.shape[1]}x{inputs.mde.shape[0]} with {len(post.sparse)} measurements "
        f"({gp.formulation}, engine {engine.name}) in {sum(post.timings.values()):.2f} s"
        + (f"; {post.n_rejected} rejected as outliers" if post.n_rejected else "")
    )
    for message in outcome.warnings:
        print(f"warning: {message}")
    if outcome.metrics is not None:
        _print_metrics(outcome.metrics)
        _print_calibration(outcome.calibration)
    print(f"wrote {len(outcome.written)} files in {plan.npz.parent.resolve()}:")
    for path in outcome.written:
        print(f"wrote {path}")


def _print_calibration(cal: dict) -> None:
    print(
        f"calibration: +-1 sigma coverage {cal['coverage_1sigma']:.3f} (calibrated 0.683), +-2 sigma "
        f"{cal['coverage_2sigma']:.3f} (0.954), +-3 sigma {cal['coverage_3sigma']:.3f} (0.997), median "
        f"|error| / sigma {cal['median_abs_z']:.3f} (0.674), AUSE {cal['ause']:.3f} (0: sigma ranks the errors "
        f"perfectly), NLL {cal['nll']:.3f} [nats per pixel]"
    )
