"""One frame's inputs read from a user's files: image, MDE, measurements (points or LiDAR), intrinsics, units.

`read_frame_inputs` is what ``gpdepth3d complete`` reads before any work: every file is opened,
checked and converted to metres here, so a bad file or a unit slip stops the call on one line
naming the option that fixes it (``--sparse-png-scale 0.001`` for a millimetre PNG) instead of a
depth map that is wrong by a factor. Errors name the command-line options (``--sparse``, ``--mde``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..camera import PinholeCamera
from ..errors import EmptyInputError, InvalidDepthError, InvalidInputError, ShapeError
from ..io import KITTI_PNG_SCALE, check_png_scale
from ..measurements import SparseDepth

DEPTH_FILE_SUFFIXES = (".npy", ".npz", ".png")
"""`--mde` values with these suffixes are depth maps to read; anything else names a front-end."""

PNG_UNIT_RATIO = 2.5
"""A 16-bit PNG read at the default 1/256 m whose depths are this many times (or more) those of the
frame's other inputs is refused: millimetres read as 1/256 m come out 1000/256 = 3.9 times too far,
while a monocular network's scale is off by well under this factor on the scenes it was trained for."""


@dataclass(frozen=True)
class PNGScales:
    """Metres per unit of each 16-bit PNG input; None where the user gave none (the default 1/256 m).

    Attributes:
        depth: ``--depth-scale``: every PNG input whose own scale is not given.
        mde: ``--mde-png-scale``.
        sparse: ``--sparse-png-scale``.
        gt: ``--gt-png-scale``.
    """

    depth: Optional[float] = None
    mde: Optional[float] = None
    sparse: Optional[float] = None
    gt: Optional[float] = None

    def of(self, name: str) -> tuple[float, bool]:
        """(metres per unit, whether the user gave it) of input ``name`` ("mde", "sparse", "gt")."""
        own = getattr(self, name)
        for value, option in ((own, f"--{name}-png-scale"), (self.depth, "--depth-scale")):
            if value is not None:
                return check_png_scale(value, option), True
        return KITTI_PNG_SCALE, False


@dataclass(frozen=True)
class FrameInputs:
    """A frame's inputs in metres, checked against each other.

    Attributes:
        mde: (H, W) monocular depth, metres (0 where invalid).
        measurements: The sparse depths on the MDE's pixel grid, metres.
        image: (H', W', 3) uint8 RGB image, or None.
        gt: Ground-truth depth (any size of the MDE's aspect ratio), metres (0 invalid), or None.
        camera: Intrinsics of the MDE image (--intrinsics, else the --calib of --lidar), or None.
        source: The file the outputs are named after (the --rgb image, else the --mde file).
    """

    mde: np.ndarray
    measurements: SparseDepth
    image: Optional[np.ndarray]
    gt: Optional[np.ndarray]
    camera: Optional[PinholeCamera]
    source: Path


def is_depth_file(mde: str | Path) -> bool:
    """Whether ``--mde`` names a depth map file (.npy/.npz/.png) rather than a front-end."""
    return Path(str(mde)).suffix.lower() in DEPTH_FILE_SUFFIXES


def check_scale(value: Optional[float], option: str) -> Optional[float]:
    """A unit scale (metres per unit) as given: None or a finite number > 0."""
    if value is not None and not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
        raise InvalidInputError(option, "metres per unit of the file, a finite number > 0", value)
    return value


def read_frame_inputs(
    mde: str,
    *,
    sparse: Optional[Path] = None,
    lidar: Optional[Path] = None,
    calib: Optional[Path] = None,
    lidar_image_size: Optional[tuple[int, int]] = None,
    sparse_points: str = "uvd",
    intrinsics: Optional[str | Path] = None,
    rgb: Optional[Path] = None,
    gt: Optional[Path] = None,
    gt_invalid_value: Optional[int] = None,
    png_scales: PNGScales = PNGScales(),
    mde_scale: Optional[float] = None,
    sparse_scale: Optional[float] = None,
    models_dir: Optional[Path] = None,
    drop_invalid_points: bool = False,
) -> FrameInputs:
    """Reads and checks one frame's inputs (the arguments of ``gpdepth3d complete``, docs/cli.md).

    Args:
        mde: A front-end name or model file run on ``rgb``, or an MDE depth file (.npy/.npz metres, 16-bit .png).
        sparse: Sparse depth map (.npy/.npz/.png) or point list (.npz u/v/depth, .txt "u v depth [sigma]").
        lidar: Instead of ``sparse``: a KITTI Velodyne scan (.bin), projected with ``calib``.
        calib: KITTI calibration of ``lidar``.
        lidar_image_size: (H, W) of the image the calibration belongs to (default: the MDE's).
        sparse_points: "uvd" (pixels + depth) or "xyz" (camera-frame metres, needs ``intrinsics``).
        intrinsics: K of the MDE image ("fx,fy,cx,cy", a K file or a KITTI calibration).
        rgb: The image (the front-end's input; the previews' and the cloud's colours).
        gt: Ground-truth depth for metrics.
        gt_invalid_value: Raw PNG value of invalid ground truth.
        png_scales: Metres per unit of the 16-bit PNG inputs (`PNGScales`).
        mde_scale: Metres per unit of an MDE depth file (unset: it must hold metres).
        sparse_scale: Metres per unit of the sparse depths and sigmas (unset: metres).
        models_dir: Folder of the named front-ends' models.
        drop_invalid_points: Drop invalid point-list rows (counted in a warning) instead of refusing the file.

    Raises:
        InvalidInputError: a bad option or option pair, named. InvalidDepthError: depths that look
        like millimetres or centimetres (a PNG checked against the frame's other inputs), naming
        the option that converts them. DataFormatError: a missing or unreadable file.
    """
    check_scale(mde_scale, "--mde-scale")
    check_scale(sparse_scale, "--sparse-scale")
    for name in ("depth", "mde", "sparse", "gt"):
        value = getattr(png_scales, name)
        if value is not None:
            check_png_scale(value, "--depth-scale" if name == "depth" else f"--{name}-png-scale")
    if gt_invalid_value is not None and not 0 <= gt_invalid_value <= 65535:
        raise InvalidInputError("--gt-invalid-value", "a 16-bit PNG value 0..65535", gt_invalid_value)
    _check_sources(sparse, lidar, calib, lidar_image_size, sparse_points, intrinsics)
    image, mde_depth, mde_png = _read_mde(mde, rgb, png_scales, mde_scale, models_dir)
    gt_depth, gt_png = _read_gt(gt, png_scales, gt_invalid_value, mde_depth.shape) if gt is not None else (None, False)
    camera = None
    if intrinsics is not None:
        from ..camera import read_intrinsics

        camera = PinholeCamera.from_K(read_intrinsics(intrinsics), mde_depth.shape[1], mde_depth.shape[0])
    if lidar is not None:
        measurements, camera_of_lidar = _read_lidar(lidar, calib, lidar_image_size, mde_depth.shape)
        camera = camera or camera_of_lidar
        sparse_png = False
    else:
        measurements, sparse_png = _read_sparse(
            sparse, sparse_points, camera, mde_depth.shape, png_scales, sparse_scale, drop_invalid_points
        )
    _check_png_units(mde_depth, mde_png, measurements, sparse_png, gt_depth, gt_png, mde, sparse, gt)
    source = Path(rgb) if rgb is not None else Path(str(mde))
    return FrameInputs(mde_depth, measurements, image, gt_depth, camera, source)


def _check_sources(sparse, lidar, calib, lidar_image_size, sparse_points, intrinsics) -> None:
    """The option pairs: one source of measurements, --calib/--lidar-image-size only with --lidar."""
    if (sparse is None) == (lidar is None):
        raise InvalidInputError("--sparse / --lidar", "exactly one source of measurements", "both or neither")
    for name, value in (("--calib", calib), ("--lidar-image-size", lidar_image_size)):
        if value is not None and lidar is None:
            raise InvalidInputError(name, "--lidar (it belongs to a LiDAR scan)", f"{name} without --lidar")
    if lidar is not None and calib is None:
        raise InvalidInputError("--calib", "a KITTI calibration for --lidar", None)
    if lidar_image_size is not None:
        from ..measurements import _as_shape

        _as_shape(lidar_image_size, "--lidar-image-size")
    if sparse is not None and sparse_points == "xyz" and intrinsics is None:
        raise InvalidInputError("--intrinsics", "intrinsics for --sparse-points xyz", None)


def _read_mde(mde, rgb, png_scales: PNGScales, mde_scale, models_dir):
    """(image or None, MDE depth in metres, whether it came from a PNG at the default scale)."""
    from ..io import load_depth, load_rgb
    from ..measurements import check_metres

    if not is_depth_file(mde):
        if rgb is None:
            raise InvalidInputError(
                "--rgb", f"an RGB image for the front-end --mde {mde} (or --mde a depth map .npy/.npz/.png)", None
            )
        from ..mde import load_frontend

        network = load_frontend(mde, models_dir=models_dir, argument="--mde")
        image = load_rgb(rgb)
        return image, network(image), False
    scale, given = png_scales.of("mde")
    depth = load_depth(Path(mde), png_scale=scale)
    image = load_rgb(rgb) if rgb is not None else None
    if mde_scale is None:
        check_metres(depth, f"--mde {mde}", "--mde-scale")
    else:
        depth = depth * mde_scale
    default_png = Path(str(mde)).suffix.lower() == ".png" and not given and mde_scale is None
    return image, depth, default_png


def _read_gt(gt, png_scales: PNGScales, invalid_value, mde_shape) -> tuple[np.ndarray, bool]:
    """(ground truth in metres, whether it came from a PNG at the default scale); refused when empty or mis-shaped."""
    from ..io import load_depth

    scale, given = png_scales.of("gt")
    depth = load_depth(gt, png_scale=scale, invalid_value=invalid_value)
    if not np.any(depth > 0):
        raise EmptyInputError("--gt", "a ground-truth map with at least one valid depth (> 0)", "none valid")
    h, w = mde_shape
    if abs((depth.shape[1] / depth.shape[0]) / (w / h) - 1.0) > 0.01:
        raise InvalidInputError(
            "--gt",
            f"a depth map of the image with the MDE's aspect ratio ({w}x{h})",
            f"{depth.shape[1]}x{depth.shape[0]}",
        )
    return depth, Path(gt).suffix.lower() == ".png" and not given


def _read_lidar(lidar, calib, lidar_image_size, mde_shape) -> tuple[SparseDepth, PinholeCamera]:
    """A Velodyne scan projected with its calibration: (measurements, the calibration's camera)."""
    from ..measurements import LidarCalibration, load_velodyne

    calibration = LidarCalibration.from_kitti(calib)
    if lidar_image_size is None:
        calibration.check_image_size(mde_shape, "--lidar-image-size (default: the MDE size)")
    shape = tuple(lidar_image_size or mde_shape)
    measurements = calibration.project(load_velodyne(lidar), shape)
    K = calibration.P[:, :3] / calibration.P[2, 2]
    return measurements, PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], shape[1], shape[0])


def _read_sparse(sparse, sparse_points, camera, mde_shape, png_scales, sparse_scale, drop_invalid):
    """(measurements in metres, whether they came from a PNG at the default scale)."""
    from ..io import load_depth, load_sparse
    from ..measurements import check_metres, project_points

    path = Path(sparse)
    scale, given = png_scales.of("sparse")
    if sparse_points == "xyz":
        measurements = project_points(_load_table(path, 3), camera)
    elif path.suffix.lower() in DEPTH_FILE_SUFFIXES and not _is_point_list(path):
        depth = load_depth(path, png_scale=scale)
        if depth.shape != tuple(mde_shape):
            h, w = mde_shape
            raise ShapeError(
                f"--sparse {path}",
                f"a sparse depth map of the MDE's size {w}x{h} (its pixels are the MDE's)",
                f"{depth.shape[1]}x{depth.shape[0]}",
            )
        measurements = SparseDepth.from_depth_map(depth)
    else:
        measurements = load_sparse(path, mde_shape, png_scale=scale, drop_invalid=drop_invalid)
    if sparse_scale is None:
        check_metres(measurements.depth, f"--sparse {sparse}", "--sparse-scale")
    else:
        m = measurements
        measurements = SparseDepth(m.u, m.v, m.depth * sparse_scale, m.image_size, m.sigma * sparse_scale)
    return measurements, path.suffix.lower() == ".png" and not given and sparse_scale is None


def _is_point_list(path: Path) -> bool:
    """An .npz with u, v, depth (or one that does not open: `load_sparse` names what is wrong with it)."""
    if path.suffix.lower() != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as data:
            return {"u", "v", "depth"} <= set(data.keys())
    except Exception:  # noqa: BLE001 - any unreadable file: the point-list reader reports it
        return True


def _check_png_units(mde, mde_png, measurements, sparse_png, gt, gt_png, mde_name, sparse_name, gt_name) -> None:
    """Refuses a 16-bit PNG read at the default 1/256 m whose depths are `PNG_UNIT_RATIO` x the frame's others.

    Millimetre PNGs (Kinect, HoloLens, 7-Scenes) read at KITTI's 1/256 m are 3.9 times too far; the
    MDE (a network's, or a file in metres), the sparse depths at their pixels and the ground truth
    are compared pairwise, each PNG at the default scale against an input whose unit is known.
    """
    h, w = mde.shape
    u = np.clip(np.round(measurements.u).astype(int), 0, w - 1) if len(measurements) else np.zeros(0, int)
    v = np.clip(np.round(measurements.v).astype(int), 0, h - 1) if len(measurements) else np.zeros(0, int)
    mde_at_points = mde[v, u]
    ratios = []  # (ratio PNG / other, PNG option, what it is compared to)
    if len(measurements):
        r = _median_ratio(measurements.depth, mde_at_points)
        if sparse_png and not mde_png:
            ratios.append((r, "--sparse", sparse_name, "the MDE at its pixels"))
        elif mde_png and not sparse_png:
            ratios.append((r and 1.0 / r, "--mde", mde_name, "the sparse depths"))
    if gt is not None:
        import cv2

        g = cv2.resize(gt, (w, h), interpolation=cv2.INTER_NEAREST) if gt.shape != mde.shape else gt
        r = _median_ratio(g, mde)
        if gt_png and not mde_png:
            ratios.append((r, "--gt", gt_name, "the MDE"))
        elif mde_png and not gt_png:
            ratios.append((r and 1.0 / r, "--mde", mde_name, "the ground truth"))
    for ratio, option, name, other in ratios:
        if ratio is not None and ratio >= PNG_UNIT_RATIO:
            raise InvalidDepthError(
                f"{option} {name}",
                "a 16-bit PNG in KITTI's 1/256 m (the default scale) or its scale given",
                f"depths {ratio:.2f} x {other} (millimetres read as 1/256 m give 3.91 x): say its unit with "
                f"{option}-png-scale 0.001 (or --depth-scale 0.001 for every PNG input)",
            )


def _median_ratio(a: np.ndarray, b: np.ndarray) -> float | None:
    """Median of a / b over pixels where both are finite and > 0; None without such a pixel."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    if not ok.any():
        return None
    return float(np.median(a[ok] / b[ok]))


def _load_table(path: Path, columns: int) -> np.ndarray:
    """The last ``columns`` columns of a numeric text table (an "X Y Z" point list)."""
    from ..errors import DataFormatError

    try:
        table = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise DataFormatError(path, f"expected a numeric table: {exc}") from None
    if table.shape[1] < columns:
        raise DataFormatError(path, f"expected at least {columns} columns, got {table.shape[1]}")
    return table[:, -columns:]
