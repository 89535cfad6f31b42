"""``gpdepth3d complete``: one frame, MDE depth + sparse depth -> posterior mean and variance files."""

from __future__ import annotations

import os
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from ..errors import OutputError
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..io import PNGRangeWarning, check_output_path, output_set
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

DEPTH_FILE_SUFFIXES = (".npy", ".npz", ".png")
"""`--mde` values with these suffixes are depth maps to read; anything else names a front-end."""


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
            .onnx/.tflite model file; or a depth map file (.npy/.npz in metres, 16-bit .png with --mde-png-scale).
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
        mde_png_scale: Metres per unit of a 16-bit MDE PNG.
        sparse_png_scale: Metres per unit of a 16-bit sparse PNG.
        sparse_points: How a .txt point list is read: "uvd" (pixels + depth) or "xyz" (camera frame, needs --intrinsics).
        intrinsics: K of the MDE image: "fx,fy,cx,cy" (pixels), a 3x3 K text file or a KITTI calibration.
        gt: Ground-truth depth for metrics (same formats).
        gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (1/1000 for Kinect millimetres).
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
    from ..camera import PinholeCamera, read_intrinsics
    from ..completion.complete import DepthCompleter, PosteriorWarning
    from ..completion.problem import check_output_shape
    from ..errors import InvalidInputError
    from ..io import check_png_scale, load_depth, load_sparse
    from ..measurements import LidarCalibration, SparseDepth, check_metres, load_velodyne, project_points
    from ..metrics import calibration_metrics, depth_metrics

    # Everything is checked and read before anything is computed or written.
    for name, value in (
        ("--mde-png-scale", mde_png_scale),
        ("--sparse-png-scale", sparse_png_scale),
        ("--gt-png-scale", gt_png_scale),
    ):
        check_png_scale(value, name)
    for name, value in (("--mde-scale", mde_scale), ("--sparse-scale", sparse_scale)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InvalidInputError(name, "metres per unit of the file, a finite number > 0", value)
    if gt_invalid_value is not None and not 0 <= gt_invalid_value <= 65535:
        raise InvalidInputError("--gt-invalid-value", "a 16-bit PNG value 0..65535", gt_invalid_value)
    if lidar_image_size is not None:
        from ..measurements import _as_shape

        _as_shape(lidar_image_size, "--lidar-image-size")
    from ..pipelines.previews import preview_paths, write_previews

    out_npz = output_npz(output, Path(rgb) if rgb is not None else Path(mde))
    base = out_npz.with_suffix("")
    png_names = [out_npz.stem + s for s in ("_mean.png", "_std.png")]
    preview_names = [p.name for p in preview_paths(base, with_error=True)]
    check_output_targets(
        [out_npz]
        + ([out_npz.with_name(n) for n in png_names] if png else [])
        + (preview_paths(base, with_error=gt is not None) if preview else [])
    )
    if ply is not None:
        ply = check_output_path(ply, "--ply")
        if ply.suffix.lower() != ".ply":
            raise InvalidInputError("--ply", "a file name ending in .ply", str(ply))
        if intrinsics is None and (lidar is None or calib is None):
            raise InvalidInputError(
                "--ply", "intrinsics to back-project with: --intrinsics K.txt, or --lidar with --calib", "neither"
            )
        check_output_targets([ply])
    if (sparse is None) == (lidar is None):
        raise InvalidInputError("--sparse / --lidar", "exactly one source of measurements", "both or neither")
    for name, value in (("--calib", calib), ("--lidar-image-size", lidar_image_size)):
        if value is not None and lidar is None:
            raise InvalidInputError(name, "--lidar (it belongs to a LiDAR scan)", f"{name} without --lidar")
    is_file = Path(mde).suffix.lower() in DEPTH_FILE_SUFFIXES
    image = None
    if not is_file:
        if rgb is None:
            raise InvalidInputError(
                "--rgb", f"an RGB image for the front-end --mde {mde} (or --mde a depth map .npy/.npz/.png)", None
            )
        from ..io import load_rgb
        from ..mde import load_frontend

        network = load_frontend(mde, models_dir=models_dir)
        image = load_rgb(rgb)
        mde_depth = network(image)
    else:
        mde_depth = load_depth(Path(mde), png_scale=mde_png_scale)
        if rgb is not None:
            from ..io import load_rgb

            image = load_rgb(rgb)
        if mde_scale is None:
            check_metres(mde_depth, f"--mde {mde}", "--mde-scale")
        else:
            mde_depth = mde_depth * mde_scale
    out_shape = check_output_shape(output_size, mde_depth.shape)
    gt_depth = None
    if gt is not None:
        gt_depth = load_depth(gt, png_scale=gt_png_scale, invalid_value=gt_invalid_value)
        if not np.any(gt_depth > 0):
            from ..errors import EmptyInputError

            raise EmptyInputError("--gt", "a ground-truth map with at least one valid depth (> 0)", "none valid")
        if abs((gt_depth.shape[1] / gt_depth.shape[0]) / (out_shape[1] / out_shape[0]) - 1.0) > 0.01:
            raise InvalidInputError(
                "--gt",
                f"a depth map of the image with the MDE's aspect ratio ({out_shape[1]}x{out_shape[0]})",
                f"{gt_depth.shape[1]}x{gt_depth.shape[0]}",
            )
    camera = calibration_camera = None
    if intrinsics is not None:
        camera = PinholeCamera.from_K(read_intrinsics(intrinsics), mde_depth.shape[1], mde_depth.shape[0])
    if lidar is not None:
        if calib is None:
            raise InvalidInputError("--calib", "a KITTI calibration for --lidar", None)
        calibration = LidarCalibration.from_kitti(calib)
        if lidar_image_size is None:
            calibration.check_image_size(mde_depth.shape, "--lidar-image-size (default: the MDE size)")
        lidar_shape = lidar_image_size or mde_depth.shape
        measurements = calibration.project(load_velodyne(lidar), lidar_shape)
        K = calibration.P[:, :3] / calibration.P[2, 2]
        calibration_camera = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], lidar_shape[1], lidar_shape[0])
    elif sparse_points == "xyz":
        if camera is None:
            raise InvalidInputError("--intrinsics", "intrinsics for --sparse-points xyz", None)
        xyz = _load_table(sparse, 3)
        measurements = project_points(xyz, camera)
    else:
        measurements = load_sparse(
            sparse, mde_depth.shape, png_scale=sparse_png_scale, drop_invalid=drop_invalid_points
        )
    if sparse is not None:
        if sparse_scale is None:
            check_metres(measurements.depth, f"--sparse {sparse}", "--sparse-scale")
        else:
            m = measurements
            measurements = SparseDepth(m.u, m.v, m.depth * sparse_scale, m.image_size, m.sigma * sparse_scale)
    completer = DepthCompleter(gp, engine=engine)
    with warnings.catch_warnings():  # the posterior's warnings are printed below, one line each
        warnings.simplefilter("ignore", PosteriorWarning)
        posterior = completer.complete(mde_depth, measurements, output_shape=output_size, frame=out_npz.stem)
    known = camera or calibration_camera
    if known is not None:  # saved with the file, so that `view` back-projects it without being told
        posterior = replace(posterior, K=known.resized(posterior.shape[1], posterior.shape[0]).K)
    print(
        f"completed {mde_depth.shape[1]}x{mde_depth.shape[0]} with {len(posterior.sparse)} measurements "
        f"({gp.formulation}, engine {engine.name}) in {sum(posterior.timings.values()):.2f} s"
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
        print(
            f"calibration: +-1 sigma coverage {cal['coverage_1sigma']:.3f} (calibrated 0.683), +-2 sigma "
            f"{cal['coverage_2sigma']:.3f} (0.954), +-3 sigma {cal['coverage_3sigma']:.3f} (0.997), median "
            f"|error| / sigma {cal['median_abs_z']:.3f} (0.674), AUSE {cal['ause']:.3f} (0: sigma ranks the errors "
            f"perfectly), NLL {cal['nll']:.3f} [nats per pixel]"
        )
    # One set: the npz, its PNGs and the previews appear together or not at all; names of an
    # earlier call not written now (its error preview, its PNGs) go in the same commit.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PNGRangeWarning)
        with output_set(base, members=[out_npz.name, *png_names, *preview_names] + ([ply.name] if ply else [])):
            written = list(posterior.save(out_npz, png=png))
            if preview:
                written += write_previews(
                    base,
                    posterior.mean,
                    posterior.std,
                    mde=posterior.mde,
                    depth_gt=gt_depth,
                    rgb=image,
                    sparse=posterior.sparse,
                )
            if ply is not None:
                written.append(_write_cloud(ply, posterior, image, known))
    for w in caught:
        if issubclass(w.category, PNGRangeWarning):
            print(f"warning: {w.message}")
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    print(f"wrote {len(written)} files in {out_npz.parent.resolve()}:")
    for path in written:
        print(f"wrote {path}")


def _write_cloud(path: Path, posterior, image: Optional[np.ndarray], camera) -> Path:
    """Back-projects the posterior on its output grid (camera resized to it), coloured by the image (grey without)."""
    import cv2

    from ..mapping.cloud import backproject_posterior

    h, w = posterior.shape
    if image is None:
        colours = np.full((h, w, 3), 128, np.uint8)
    else:
        shrink = image.shape[0] > h
        colours = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    cloud = backproject_posterior(posterior, colours, camera.resized(w, h))
    return cloud.save_ply(path)


def output_npz(output: str | Path, source: Path) -> Path:
    """The posterior file of ``--output``: ``OUTPUT.npz``, or ``OUTPUT/<source stem>.npz`` for a folder.

    A folder is an existing one or a name ending in a path separator (``out/``).

    Raises:
        OutputError: an empty name or one that cannot be written.
    """
    text = os.fspath(output)
    if text.endswith(("/", os.sep)) or (text and Path(text).is_dir()):
        return check_output_path(Path(text) / f"{source.stem or 'completion'}.npz", "--output")
    return check_output_path(text, "--output").with_suffix(".npz")


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
