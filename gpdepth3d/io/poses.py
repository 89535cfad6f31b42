"""Poses: every pose format the library reads (one reader each, `POSE_FORMATS`), trajectories and COLMAP models.

Every pose here is ``T_world_camera`` (4x4, maps camera coordinates to world coordinates; the
OpenCV camera frame: x right, y down, z forward), whatever the file stores. Formats
(`POSE_FORMATS`, read by `read_trajectory`, which also recognises them, `detect_pose_format`):

* ``tum``: TUM RGB-D trajectories (``timestamp tx ty tz qx qy qz qw``, the camera's pose in the
  world) and ORB-SLAM3's ``KeyFrameTrajectory.txt`` / ``CameraTrajectory.txt`` (the same format)
  (`read_tum_trajectory`; every quaternion must be of unit length and every timestamp unique;
  written back with evo, `write_tum_trajectory`);
* ``kitti``: KITTI odometry poses, one row-major 3x4 camera-to-world matrix per line
  (`read_kitti_poses`; `load_poses` gives them as a list);
* ``rows``: one flattened row-major 4x4 camera-to-world matrix per line (`read_flat_poses`);
* ``files``: a folder of per-image text files holding a 4x4 camera-to-world matrix each, as
  7-Scenes' ``frame-XXXXXX.pose.txt`` (`read_pose_files`; the poses carry the files' names);
* ``colmap``: COLMAP models (``cameras``, ``images``, ``points3D``, binary or text) read with
  pycolmap (`read_colmap_model`): COLMAP stores ``cam_from_world`` (world to camera); it is
  inverted here.

A single pose in a file of its own (4x4, or 3x4 as 12 numbers) is read by `load_pose`.

`associate_poses` gives each image of a sequence its pose: by name (per-image files, COLMAP),
by timestamp (TUM, image files named by their time) or by order.

Helpers: `pose_from_tq` / `tq_from_pose` (translation + unit quaternion, ``xyzw`` as TUM and
scipy, or ``wxyz``), `invert_pose`, and `check_pose_orientation`, the loud check for the most
common integration mistake: a ``T_camera_world`` passed where ``T_world_camera`` is expected. It
projects the frame's map points with the pose and with its inverse; when clearly more of them
land in front of the camera and inside the image under the inverse, it warns
(`InvertedPoseWarning`) naming the frame and the figures.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ..camera import PinholeCamera, check_pose, transform_points
from ..errors import CalibrationError, DataFormatError, EmptyInputError, InvalidInputError, ShapeError, describe
from .arrays import _as_path
from .durable import atomic_path

QuaternionOrder = Literal["xyzw", "wxyz"]


class InvertedPoseWarning(UserWarning):
    """A pose looks inverted (``T_camera_world`` given where ``T_world_camera`` is expected)."""


# ---------------------------------------------------------------------- pose helpers
def _quat_xyzw(q: np.ndarray, order: QuaternionOrder) -> np.ndarray:
    if order not in ("xyzw", "wxyz"):
        raise InvalidInputError("order", "'xyzw' or 'wxyz'", order)
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ShapeError("q", "quaternions of shape (..., 4)", describe(q))
    if order == "wxyz":
        q = q[..., [1, 2, 3, 0]]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(norm)) or np.any(np.abs(norm - 1.0) > 1e-3):
        raise CalibrationError("q", "unit quaternions (norm 1 +- 1e-3)", f"norms {np.ravel(norm)[:5]}")
    return q / norm


def pose_from_tq(t: np.ndarray, q: np.ndarray, *, order: QuaternionOrder = "xyzw") -> np.ndarray:
    """4x4 pose(s) from translation(s) and unit quaternion(s).

    Args:
        t: (3,) or (N, 3) translations, metres.
        q: (4,) or (N, 4) unit quaternions (rotation of the pose), in ``order``.
        order: "xyzw" (TUM, scipy, ORB-SLAM3) or "wxyz" (COLMAP text files, evo's arrays).

    Returns:
        (4, 4) or (N, 4, 4) float64 rigid transforms ``[R(q) t; 0 1]``.

    Raises:
        ShapeError: on wrong shapes. CalibrationError: on quaternions that are not unit length.
    """
    from scipy.spatial.transform import Rotation

    t = np.asarray(t, dtype=np.float64)
    single = t.ndim == 1
    t2 = np.atleast_2d(t)
    q2 = np.atleast_2d(_quat_xyzw(q, order))
    if t2.shape[1] != 3 or q2.shape[0] != t2.shape[0]:
        raise ShapeError("t", f"translations of shape (3,) or ({q2.shape[0]}, 3) matching q", describe(t))
    T = np.tile(np.eye(4), (t2.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(q2).as_matrix()
    T[:, :3, 3] = t2
    return T[0] if single else T


def tq_from_pose(T: np.ndarray, *, order: QuaternionOrder = "xyzw") -> tuple[np.ndarray, np.ndarray]:
    """Translation (3,) and unit quaternion (4,) of a rigid 4x4 pose (the inverse of `pose_from_tq`).

    The quaternion has a non-negative scalar part.
    """
    from scipy.spatial.transform import Rotation

    T = check_pose(T, "T")
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # xyzw
    if q[3] < 0:
        q = -q
    if order == "wxyz":
        q = q[[3, 0, 1, 2]]
    elif order != "xyzw":
        raise InvalidInputError("order", "'xyzw' or 'wxyz'", order)
    return T[:3, 3].copy(), q


def invert_pose(T: np.ndarray) -> np.ndarray:
    """The inverse of a rigid 4x4 transform, ``[R^T, -R^T t; 0 1]`` (exact, no general inverse)."""
    T = check_pose(T, "T")
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


# ---------------------------------------------------------------------- the inverted-pose check
@dataclass(frozen=True)
class PoseCheck:
    """Result of `check_pose_orientation`.

    Attributes:
        points: Number of finite map points checked.
        visible: Fraction of them in front of the camera and inside the image under the pose.
        visible_inverse: The same fraction under the inverse pose.
        inverted: True when the pose looks inverted (see `check_pose_orientation`).
    """

    points: int
    visible: float
    visible_inverse: float
    inverted: bool


def _visible_fraction(
    points_world: np.ndarray, T_world_camera: np.ndarray, camera: PinholeCamera, min_depth: float
) -> float:
    pc = transform_points(invert_pose(T_world_camera), points_world)
    front = pc[:, 2] > min_depth
    if not front.any():
        return 0.0
    uv, _ = camera.project(pc[front])
    return float(np.count_nonzero(camera.in_image(uv)) / len(points_world))


def check_pose_orientation(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    frame: object = None,
    min_points: int = 10,
    min_depth: float = 1e-3,
    warn: bool = True,
) -> PoseCheck:
    """Checks that map points are seen by a pose better than by its inverse; warns loudly if not.

    The pose counts as inverted when at least ``min_points`` finite points are given, at most
    half as many are visible (in front of the camera and inside the image) under
    ``T_world_camera`` as under its inverse, and at least 30 % are visible under the inverse.

    Args:
        points_world: (N, 3) map points of this frame in the world frame, metres.
        T_world_camera: 4x4 rigid pose to check.
        camera: Intrinsics the points are projected with.
        frame: Name or index of the frame for the warning.
        min_points: Fewer finite points are not judged (``inverted`` False).
        min_depth: Points closer than this (z, metres) count as behind the camera.
        warn: Issue an `InvertedPoseWarning` when the pose looks inverted.

    Returns:
        `PoseCheck` with the two visible fractions.
    """
    T = check_pose(T_world_camera)
    p = np.asarray(points_world, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError("points_world", "an (N, 3) array", describe(p))
    p = p[np.all(np.isfinite(p), axis=1)]
    n = int(p.shape[0])
    if n == 0:
        return PoseCheck(0, 0.0, 0.0, False)
    vis = _visible_fraction(p, T, camera, min_depth)
    vis_inv = _visible_fraction(p, invert_pose(T), camera, min_depth)
    inverted = n >= min_points and vis_inv >= 0.3 and vis <= 0.5 * vis_inv
    if inverted and warn:
        warnings.warn(
            f"frame {frame}: the pose looks inverted (T_camera_world given as T_world_camera?): "
            f"{vis:.0%} of {n} map points are in front of the camera and inside the image under the pose, "
            f"{vis_inv:.0%} under its inverse",
            InvertedPoseWarning,
            stacklevel=2,
        )
    return PoseCheck(n, vis, vis_inv, bool(inverted))


# ---------------------------------------------------------------------- trajectories
@dataclass(frozen=True)
class Trajectory:
    """A sequence of camera poses.

    Attributes:
        poses: (N, 4, 4) float64 ``T_world_camera`` (rotations snapped to exactly orthonormal,
            as `gpdepth3d.camera.check_pose` does).
        timestamps: (N,) float64 seconds (NaN when the format has none, e.g. KITTI); the finite
            ones are unique (a time with two poses has no nearest pose).
        names: N names of the images the poses belong to (per-image files, COLMAP), or empty.
    """

    poses: np.ndarray
    timestamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ShapeError("poses", "an (N, 4, 4) array", describe(poses))
        poses = np.stack([check_pose(T, f"poses[{i}]") for i, T in enumerate(poses)]) if len(poses) else poses
        ts = np.asarray(self.timestamps, dtype=np.float64)
        if ts.size == 0:
            ts = np.full(len(poses), np.nan)
        if ts.shape != (len(poses),):
            raise ShapeError("timestamps", f"shape ({len(poses)},)", describe(ts))
        if np.any(np.isinf(ts)):
            raise InvalidInputError("timestamps", "finite seconds (or NaN for none)", "inf")
        finite = ts[np.isfinite(ts)]
        if np.unique(finite).size != finite.size:
            raise InvalidInputError(
                "timestamps", "unique timestamps", f"{finite.size - np.unique(finite).size} repeated"
            )
        names = tuple(str(n) for n in self.names)
        if names and len(names) != len(poses):
            raise ShapeError("names", f"{len(poses)} names (one per pose) or none", f"{len(names)}")
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "names", names)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def nearest(self, timestamp: float, *, max_difference: float = 0.02) -> int:
        """Index of the pose closest in time to ``timestamp`` (seconds).

        Raises:
            InvalidInputError: if ``timestamp`` is not a finite number, the trajectory has no
                timestamps, or none is within ``max_difference``.
        """
        if isinstance(timestamp, (bool, np.bool_)) or not isinstance(timestamp, (int, float, np.integer, np.floating)):
            raise InvalidInputError("timestamp", "a finite time in seconds", describe(timestamp))
        if not np.isfinite(timestamp):
            raise InvalidInputError("timestamp", "a finite time in seconds", timestamp)
        if not np.isfinite(max_difference) or max_difference < 0:
            raise InvalidInputError("max_difference", "a time difference >= 0 (seconds)", max_difference)
        if len(self) == 0 or np.all(np.isnan(self.timestamps)):
            raise InvalidInputError("timestamp", "a trajectory with timestamps", "none")
        i = int(np.nanargmin(np.abs(self.timestamps - timestamp)))
        if abs(self.timestamps[i] - timestamp) > max_difference:
            raise InvalidInputError(
                "timestamp", f"a pose within {max_difference} s", f"nearest at {self.timestamps[i] - timestamp:+.3f} s"
            )
        return i


def _check_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "trajectory file not found")
    return path


def _numeric_rows(path: Path, columns: tuple[int, ...], what: str) -> tuple[np.ndarray, np.ndarray]:
    """The numeric rows of a text file (``#`` comments, blank lines, commas skipped), each of ``columns`` values."""
    rows, lines = [], []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(path, f"not a readable {what}: {exc}") from None
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        try:
            values = [float(x) for x in line.split()]
        except ValueError:
            raise DataFormatError(path, f"line {number}: not numbers ({what})") from None
        if len(values) not in columns:
            expected = " or ".join(str(c) for c in columns)
            raise DataFormatError(path, f"line {number}: expected {expected} numbers ({what}), got {len(values)}")
        if not np.all(np.isfinite(values)):
            raise DataFormatError(path, f"line {number}: NaN or inf ({what})")
        rows.append(values)
        lines.append(number)
    if not rows:
        raise DataFormatError(path, f"no poses ({what})")
    if len({len(r) for r in rows}) > 1:
        raise DataFormatError(path, f"lines of different lengths ({what})")
    table = np.array(rows, dtype=np.float64)
    return table, np.array(lines)


QUATERNION_TOLERANCE = 1e-3
"""A file's quaternion may differ from unit length by this much (rounding of written digits); it is
then normalised. Farther from 1 (norm 2, 0.5, all zeros) it is refused: such a quaternion is a
wrong column order or a broken writer, not a rounding."""


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """Reads a TUM RGB-D trajectory (also ORB-SLAM3's ``KeyFrameTrajectory.txt``).

    Lines ``timestamp tx ty tz qx qy qz qw`` give each camera's pose in the world (metres,
    seconds); ``#`` comments are skipped. See https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats.

    Raises:
        DataFormatError: if the file is missing, a line is not 8 finite numbers, a quaternion is
            not of unit length within `QUATERNION_TOLERANCE` (naming the line), or a timestamp repeats.
    """
    path = _check_file(path)
    table, lines = _numeric_rows(path, (8,), "TUM trajectory: timestamp tx ty tz qx qy qz qw")
    norms = np.linalg.norm(table[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_TOLERANCE)
    if bad.size:
        raise DataFormatError(
            path,
            f"line {lines[bad[0]]}: quaternion of norm {norms[bad[0]]:.6g}, expected unit length "
            f"(within {QUATERNION_TOLERANCE}); {bad.size} such line(s)",
        )
    ts = table[:, 0]
    _, first, counts = np.unique(ts, return_index=True, return_counts=True)
    if np.any(counts > 1):
        i = int(first[np.argmax(counts > 1)])
        again = int(np.flatnonzero(ts == ts[i])[1])
        raise DataFormatError(path, f"lines {lines[i]} and {lines[again]}: the same timestamp {float(ts[i])!r} twice")
    q = table[:, 4:8] / norms[:, None]
    return Trajectory(pose_from_tq(table[:, 1:4], q), ts)


def write_tum_trajectory(path: str | Path, trajectory: Trajectory) -> Path:
    """Writes a `Trajectory` as a TUM file with evo, atomically (timestamps NaN become 0, 1, 2...)."""
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    if not isinstance(trajectory, Trajectory):
        raise InvalidInputError("trajectory", "a Trajectory", type(trajectory).__name__)
    ts = np.where(np.isnan(trajectory.timestamps), np.arange(len(trajectory), dtype=np.float64), trajectory.timestamps)
    traj = PoseTrajectory3D(poses_se3=list(trajectory.poses), timestamps=ts)
    path = Path(path)
    with atomic_path(path) as tmp:
        file_interface.write_tum_trajectory_file(str(tmp), traj)
    return path


def read_kitti_poses(path: str | Path) -> Trajectory:
    """Reads KITTI odometry poses: one row-major 3x4 camera-to-world matrix (12 numbers) per line.

    Line k (comments and blank lines skipped) is the pose of the k-th image.

    Raises:
        DataFormatError: if the file is missing, a line is not 12 finite numbers or not a rigid
            transform (naming the line).
    """
    path = _check_file(path)
    table, lines = _numeric_rows(path, (12,), "KITTI 3x4 pose per line")
    return Trajectory(_poses_from_rows(path, table, lines))


def _poses_from_rows(path: Path, table: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Row-major 3x4 or 4x4 matrices, one per row, as checked 4x4 poses (a bad one names its line)."""
    n = table.shape[0]
    if table.shape[1] == 12:
        table = np.hstack([table, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))])
    poses = table.reshape(n, 4, 4)
    out = np.empty_like(poses)
    for i, T in enumerate(poses):
        try:
            out[i] = check_pose(T, "pose")
        except CalibrationError as exc:
            raise DataFormatError(path, f"line {lines[i]}: not a rigid transform: {exc}") from None
    return out


def read_flat_poses(path: str | Path) -> Trajectory:
    """Reads one flattened row-major 4x4 camera-to-world matrix (16 numbers) per line.

    Line k (comments and blank lines skipped) is the pose of the k-th image.

    Raises:
        DataFormatError: if the file is missing, a line is not 16 finite numbers or not a rigid
            transform (naming the line).
    """
    path = _check_file(path)
    table, lines = _numeric_rows(path, (16,), "flattened 4x4 pose per line")
    return Trajectory(_poses_from_rows(path, table, lines))


POSE_FILE_PATTERNS = ("*.pose.txt", "*.txt")
"""The per-image pose files of a folder: ``*.pose.txt`` (7-Scenes) when there are any, else every ``*.txt``."""


def pose_file_key(name: str) -> str:
    """The part of a file name that names its image: up to the first dot (``frame-000000.pose.txt`` -> ``frame-000000``)."""
    return Path(name).name.split(".", 1)[0]


def read_pose_files(folder: str | Path) -> Trajectory:
    """Reads a folder of per-image pose files, each a 4x4 camera-to-world matrix (16 numbers).

    The files are `POSE_FILE_PATTERNS` in sorted name order; the trajectory's ``names`` are the
    file names up to the first dot (`pose_file_key`), matched to images by `associate_poses`.

    Raises:
        DataFormatError: if the folder is missing or has no pose file, a file is not 16 finite
            numbers or not a rigid transform (naming the file).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataFormatError(folder, "pose folder not found")
    files: list[Path] = []
    for pattern in POSE_FILE_PATTERNS:
        files = sorted(p for p in folder.glob(pattern) if p.is_file())
        if files:
            break
    if not files:
        raise DataFormatError(folder, f"no pose files ({' or '.join(POSE_FILE_PATTERNS)})")
    poses = np.stack([load_pose(f) for f in files])
    return Trajectory(poses, names=tuple(pose_file_key(f.name) for f in files))


# ---------------------------------------------------------------------- COLMAP
@dataclass(frozen=True)
class ColmapImage:
    """One registered image of a COLMAP model.

    Attributes:
        name: Image file name as stored in the model.
        camera_id: Its camera.
        T_world_camera: 4x4 pose (COLMAP's ``cam_from_world`` inverted).
        uv: (K, 2) pixel positions of its keypoints that observe a 3-D point (pixel centres at
            integer coordinates, as gpdepth3d: COLMAP's 0.5 offset removed).
        point3D_ids: (K,) ids of the 3-D points they observe.
    """

    name: str
    camera_id: int
    T_world_camera: np.ndarray
    uv: np.ndarray
    point3D_ids: np.ndarray


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP reconstruction as gpdepth3d uses it: cameras, posed images and map points.

    Attributes:
        cameras: camera id -> `PinholeCamera` (distortion dropped, see `read_colmap_model`).
        images: image id -> `ColmapImage`.
        point_ids: (M,) ids of the 3-D points.
        points: (M, 3) positions in the world frame (the model's units).
        colors: (M, 3) uint8 RGB.
        errors: (M,) mean reprojection errors, pixels.
        track_lengths: (M,) number of images observing each point.
    """

    cameras: dict
    images: dict
    point_ids: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    track_lengths: np.ndarray

    def image_by_name(self, name: str) -> int:
        """The id of the image called ``name``."""
        for image_id, image in self.images.items():
            if image.name == name:
                return image_id
        raise InvalidInputError("name", "the name of an image of the model", name)

    def map_points(self, image_id: int) -> np.ndarray:
        """(K, 3) world positions of the 3-D points observed by an image (for `Mapper.add_frame`)."""
        if image_id not in self.images:
            raise InvalidInputError("image_id", "the id of an image of the model", image_id)
        index = {int(pid): i for i, pid in enumerate(self.point_ids)}
        rows = [index[int(pid)] for pid in self.images[image_id].point3D_ids if int(pid) in index]
        return self.points[np.asarray(rows, dtype=np.int64)] if rows else np.zeros((0, 3))

    def trajectory(self) -> Trajectory:
        """The registered images' poses in image-id order (timestamps NaN), named by their image names."""
        ids = sorted(self.images)
        return Trajectory(
            np.stack([self.images[i].T_world_camera for i in ids]) if ids else np.zeros((0, 4, 4)),
            names=tuple(self.images[i].name for i in ids),
        )


_PINHOLE_MODELS = {"SIMPLE_PINHOLE", "PINHOLE"}


def _camera_from_colmap(cam, camera_id: int, ignore_distortion: bool) -> PinholeCamera:
    name = str(cam.model_name) if hasattr(cam, "model_name") else str(cam.model).split(".")[-1]
    if name not in _PINHOLE_MODELS and not ignore_distortion:
        raise CalibrationError(
            f"cameras[{camera_id}]",
            f"a pinhole camera model ({', '.join(sorted(_PINHOLE_MODELS))}); undistort the images first "
            "or pass ignore_distortion=True",
            name,
        )
    # COLMAP puts the centre of the top-left pixel at (0.5, 0.5); gpdepth3d at (0, 0).
    return PinholeCamera(
        float(cam.focal_length_x),
        float(cam.focal_length_y),
        float(cam.principal_point_x) - 0.5,
        float(cam.principal_point_y) - 0.5,
        int(cam.width),
        int(cam.height),
    )


def read_colmap_model(path: str | Path, *, ignore_distortion: bool = False) -> ColmapModel:
    """Reads a COLMAP sparse model (a folder with cameras/images/points3D .bin or .txt) with pycolmap.

    Args:
        path: The model folder (e.g. ``sparse/0``).
        ignore_distortion: Accept camera models with distortion and keep only their focal
            lengths and principal point (else a `CalibrationError`).

    Returns:
        `ColmapModel` with ``T_world_camera`` poses and the 3-D points as map points.

    Raises:
        DataFormatError: if the folder is missing or pycolmap cannot read it, or an image's
            quaternion is not of unit length within `QUATERNION_TOLERANCE` (naming the image).
        CalibrationError: for a camera model with distortion (without ``ignore_distortion``).
    """
    import pycolmap

    path = Path(path)
    if not path.is_dir():
        raise DataFormatError(path, "COLMAP model folder not found")
    _check_colmap_quaternions(path)  # pycolmap turns a zero quaternion into the identity rotation
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError/ValueError on bad models
        raise DataFormatError(path, f"not a COLMAP model: {exc}") from None
    cameras = {int(cid): _camera_from_colmap(cam, int(cid), ignore_distortion) for cid, cam in rec.cameras.items()}
    images = {}
    for iid, img in rec.images.items():
        if not img.has_pose:
            continue
        cam_from_world = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        T_cw = np.eye(4)
        T_cw[:3, :] = np.asarray(cam_from_world.matrix(), dtype=np.float64)
        uv, ids = [], []
        for p2d in img.points2D:
            if p2d.has_point3D():
                uv.append(np.asarray(p2d.xy, dtype=np.float64) - 0.5)
                ids.append(int(p2d.point3D_id))
        images[int(iid)] = ColmapImage(
            str(img.name),
            int(img.camera_id),
            invert_pose(T_cw),
            np.array(uv).reshape(-1, 2),
            np.array(ids, dtype=np.int64),
        )
    pids = np.array(sorted(int(i) for i in rec.points3D), dtype=np.int64)
    pts = [rec.points3D[int(i)] for i in pids]
    return ColmapModel(
        cameras=cameras,
        images=images,
        point_ids=pids,
        points=np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3),
        colors=np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3),
        errors=np.array([p.error for p in pts], dtype=np.float64),
        track_lengths=np.array([p.track.length() for p in pts], dtype=np.int64),
    )


def _colmap_quaternions(path: Path) -> list[tuple[str, np.ndarray]]:
    """(image name, its quaternion qw qx qy qz as stored) of a model's ``images.txt`` or ``images.bin``."""
    import struct

    text, binary = path / "images.txt", path / "images.bin"
    found = []
    if text.is_file():
        lines = [ln for ln in text.read_text(errors="replace").splitlines() if ln.strip() and not ln.startswith("#")]
        for line in lines[::2]:  # each image: its pose line, then its points line
            fields = line.split()
            if len(fields) >= 10:
                try:
                    found.append((fields[9], np.array(fields[1:5], dtype=np.float64)))
                except ValueError:
                    pass  # pycolmap names what it cannot parse
        return found
    if binary.is_file():
        data = binary.read_bytes()
        try:
            (n,), at = struct.unpack_from("<Q", data, 0), 8
            for _ in range(n):
                q = np.array(struct.unpack_from("<4d", data, at + 4))
                at += 4 + 56 + 4
                end = data.index(b"\0", at)
                name = data[at:end].decode("utf-8", "replace")
                (points,) = struct.unpack_from("<Q", data, end + 1)
                at = end + 1 + 8 + 24 * points
                found.append((name, q))
        except (struct.error, ValueError):
            pass  # a cut file: pycolmap names it
    return found


def _check_colmap_quaternions(path: Path) -> None:
    """Refuses a model image whose stored quaternion is not of unit length (all zeros: no rotation at all)."""
    for name, q in _colmap_quaternions(path):
        norm = float(np.linalg.norm(q))
        if not np.isfinite(norm) or abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise DataFormatError(
                path,
                f"image {name}: quaternion {' '.join(f'{x:g}' for x in q)} of norm {norm:.6g}, expected unit "
                f"length (within {QUATERNION_TOLERANCE}): its rotation is unknown",
            )


# ---------------------------------------------------------------------- any format, and images
def _colmap_trajectory(path: str | Path) -> Trajectory:
    """A COLMAP model's registered images as a trajectory (distortion ignored: poses only)."""
    return read_colmap_model(path, ignore_distortion=True).trajectory()


_READERS = {
    "tum": read_tum_trajectory,
    "kitti": read_kitti_poses,
    "rows": read_flat_poses,
    "files": read_pose_files,
    "colmap": _colmap_trajectory,
}
"""One reader per pose format (the module docstring lists them)."""

POSE_FORMATS = tuple(_READERS)
"""The pose formats `read_trajectory` reads (see the module docstring)."""

_COLMAP_FILES = ("images.bin", "images.txt")


def detect_pose_format(path: str | Path) -> str:
    """The format of a pose file or folder (one of `POSE_FORMATS`), from its layout and columns.

    A folder holding ``images.bin`` / ``images.txt`` is a COLMAP model, any other folder holds
    per-image pose files; a text file is TUM with 8 numbers a line, KITTI with 12, rows of a
    flattened 4x4 with 16.

    Raises:
        DataFormatError: if the path is missing or its lines fit none of the formats.
    """
    path = Path(path)
    if path.is_dir():
        return "colmap" if any((path / n).is_file() for n in _COLMAP_FILES) else "files"
    path = _check_file(path)
    table, _ = _numeric_rows(path, (8, 12, 16), "TUM (8 numbers a line), KITTI (12) or a flattened 4x4 (16)")
    return {8: "tum", 12: "kitti", 16: "rows"}[table.shape[1]]


def read_trajectory(path: str | Path, format: str = "auto") -> Trajectory:  # noqa: A002 - the user's word
    """Reads poses in any of `POSE_FORMATS` as ``T_world_camera``.

    Args:
        path: A pose file or folder.
        format: One of `POSE_FORMATS`, or "auto" (`detect_pose_format`).

    Raises:
        InvalidInputError: for an unknown format name.
        DataFormatError: if the file or folder is missing or not of the format.
    """
    if format == "auto":
        format = detect_pose_format(path)
    if format not in POSE_FORMATS:
        raise InvalidInputError("format", f"'auto' or one of {', '.join(POSE_FORMATS)}", format)
    return _READERS[format](path)


ASSOCIATIONS = ("auto", "name", "timestamp", "order")
"""How `associate_poses` matches images and poses."""


def image_timestamp(name: str) -> float | None:
    """The time an image file is named by (TUM RGB-D: ``1305031102.175304.png``), seconds, or None."""
    stem = Path(name).name
    for suffix in Path(name).suffixes[::-1]:
        stem = stem[: -len(suffix)] if stem.endswith(suffix) and not suffix[1:].isdigit() else stem
    try:
        value = float(stem)
    except ValueError:
        return None
    return value if np.isfinite(value) else None


def _timed_name(name: str) -> bool:
    """Whether a file name looks like a time stamp with a fraction (``1305031102.175304.png``, not ``00003.png``)."""
    stem = Path(name).name.rsplit(".", 1)[0]
    return image_timestamp(name) is not None and "." in stem


def _name_keys(names: list[str]) -> list[str]:
    return [pose_file_key(n) for n in names]


def associate_poses(
    trajectory: Trajectory, image_names: list[str], *, by: str = "auto", max_difference: float = 0.02
) -> np.ndarray:
    """The pose of each image: (N, 4, 4) ``T_world_camera`` in the order of ``image_names``.

    Args:
        trajectory: The poses read.
        image_names: File names (or relative paths) of the images, in sequence order.
        by: "name": the trajectory's names (COLMAP image names, pose files' names up to the
            first dot) equal the images' (whole relative path, else file name, else file name
            up to the first dot); "timestamp": each image's file name is its time in seconds
            and gets the pose nearest in time (within ``max_difference``); "order": the k-th
            pose is the k-th image's (as many poses as images); "auto": by name when the
            trajectory has names, by timestamp when it has times and every image is named by
            a time with a fraction (``1305031102.175304.png``), else by order.
        max_difference: Largest time difference of a timestamp match, seconds.

    Raises:
        InvalidInputError: an unknown ``by``, or the chosen association is impossible (no
            names / times).
        ShapeError: "order" with a different number of poses and images.
        DataFormatError: an image without a pose (naming it and how many lack one).
    """
    if by not in ASSOCIATIONS:
        raise InvalidInputError("by", f"one of {', '.join(ASSOCIATIONS)}", by)
    names = [str(n) for n in image_names]
    if not names:
        raise EmptyInputError("image_names", "at least one image", "none")
    if by == "auto":
        if trajectory.names:
            by = "name"
        elif np.any(np.isfinite(trajectory.timestamps)) and all(_timed_name(n) for n in names):
            by = "timestamp"
        else:
            by = "order"
    if by == "order":
        if len(trajectory) != len(names):
            raise ShapeError("poses", f"one pose per image in order ({len(names)} images)", f"{len(trajectory)} poses")
        return trajectory.poses.copy()
    if by == "timestamp":
        if not np.any(np.isfinite(trajectory.timestamps)):
            raise InvalidInputError("by", "a trajectory with timestamps for 'timestamp'", "none (use 'order')")
        index = []
        missing = []
        for n in names:
            t = image_timestamp(n)
            if t is None:
                raise InvalidInputError("image_names", "file names that are times in seconds for 'timestamp'", n)
            try:
                index.append(trajectory.nearest(t, max_difference=max_difference))
            except InvalidInputError:
                missing.append(n)
        if missing:
            raise DataFormatError(
                missing[0], f"no pose within {max_difference} s ({len(missing)} of {len(names)} images lack one)"
            )
        return trajectory.poses[np.array(index)]
    if not trajectory.names:
        raise InvalidInputError("by", "a trajectory with names for 'name' (per-image files, COLMAP)", "none")
    lookups = [
        {n: i for i, n in enumerate(trajectory.names)},
        {Path(n).name: i for i, n in enumerate(trajectory.names)},
        {k: i for i, k in enumerate(_name_keys(list(trajectory.names)))},
    ]
    keys = [names, [Path(n).name for n in names], _name_keys(names)]
    for lookup, key in zip(lookups, keys):
        if len(lookup) == len(trajectory) and all(k in lookup for k in key):
            return trajectory.poses[np.array([lookup[k] for k in key])]
    # which images lack a pose: by the unique naming that matches the most images
    usable = [
        (sum(k in lookup for k in key), lookup, key)
        for lookup, key in zip(lookups, keys)
        if len(lookup) == len(trajectory)
    ]
    if not usable:
        raise DataFormatError(names[0], "no pose of that name (and the poses' names are not unique)")
    _, lookup, key = max(usable, key=lambda u: u[0])
    missing = [n for n, k in zip(names, key) if k not in lookup]
    raise DataFormatError(missing[0], f"no pose of that name ({len(missing)} of {len(names)} images lack one)")


def load_pose(path: str | Path) -> np.ndarray:
    """Reads one pose file: a 4x4 ``T_world_camera`` as 4 rows of 4 numbers (7-Scenes) or one row of 16,
    or a 3x4 as 3 rows of 4 or one row of 12 (``#`` comments and blank lines skipped).

    Returns:
        (4, 4) float64, its rotation snapped to exactly orthonormal (`gpdepth3d.camera.check_pose`).

    Raises:
        DataFormatError: if the file is missing, holds another count of numbers, or is not a rigid
            transform (naming the file).
    """
    path = _as_path(path)
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    table, lines = _numeric_rows(path, (4, 12, 16), "4x4 or 3x4 pose")
    values = table.reshape(1, -1)
    if values.shape[1] not in (12, 16):
        raise DataFormatError(path, f"expected 16 (4x4) or 12 (3x4) numbers, got {values.shape[1]}")
    return _poses_from_rows(path, values, lines[:1])[0]


def load_poses(path: str | Path) -> list[np.ndarray]:
    """Reads one pose per line (12 numbers, row-major 3x4, KITTI odometry style) as 4x4 matrices.

    The KITTI reader, `read_kitti_poses`, as a list (the viewer's form).
    """
    return list(read_kitti_poses(path).poses)
