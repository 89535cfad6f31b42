"""Pinhole camera model.

Conventions used everywhere in gpdepth3d (stated once, here):

* Camera frame: OpenCV. x right, y down, z forward (into the scene), metres.
* Pixel coordinates: (u, v) = (column, row). The centre of pixel (row i, column j) is at
  (u, v) = (j, i); the image covers u in [-0.5, width - 0.5), v in [-0.5, height - 0.5).
* ``depth`` is z-depth in metres (the z coordinate of the point in the camera frame), not the
  length of the ray. 0 marks "no depth".
* Poses are ``T_world_camera``: 4x4 rigid transforms mapping camera-frame points into the world.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import CalibrationError, InvalidDepthError, ShapeError, describe


def _is_real(value) -> bool:
    """True for a real number (Python or numpy int/float); False for bool, str, None, arrays."""
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, float, np.integer, np.floating))


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics with the image size they belong to.

    Attributes:
        fx: Focal length along u, pixels.
        fy: Focal length along v, pixels.
        cx: Principal point u, pixels (pixel-centre convention, see module docstring).
        cy: Principal point v, pixels.
        width: Image width, pixels.
        height: Image height, pixels.
        check_principal_point: Require the principal point inside the image (catches
            intrinsics of another image size); `cropped` turns it off since an off-centre crop
            legitimately has its principal point outside.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    check_principal_point: bool = field(default=True, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not _is_real(value) or not np.isfinite(value) or value <= 0:
                raise CalibrationError(name, "a finite focal length > 0 (pixels)", describe(value))
            object.__setattr__(self, name, float(value))
        for name in ("cx", "cy"):
            value = getattr(self, name)
            if not _is_real(value) or not np.isfinite(value):
                raise CalibrationError(name, "a finite principal point (pixels)", describe(value))
            object.__setattr__(self, name, float(value))
        for name in ("width", "height"):
            value = getattr(self, name)
            if not _is_real(value) or not np.isfinite(value) or int(value) != value or value <= 0:
                raise CalibrationError(name, "a positive integer image size", describe(value))
            object.__setattr__(self, name, int(value))
        if self.check_principal_point and not (
            -0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5
        ):
            raise CalibrationError(
                "cx, cy", f"a principal point inside the {self.width}x{self.height} image", (self.cx, self.cy)
            )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> "PinholeCamera":
        """Builds a camera from a 3x3 intrinsic matrix and the image size it belongs to."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise CalibrationError("K", "a 3x3 intrinsic matrix", describe(K))
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or abs(K[1, 0]) > 1e-9:
            raise CalibrationError("K", "last row [0, 0, 1] and K[1, 0] == 0", K.tolist())
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as (height, width)."""
        return (self.height, self.width)

    def check_image(self, array: np.ndarray, argument: str) -> None:
        """Raises `ShapeError` unless ``array`` is (height, width, ...) of this camera."""
        if np.ndim(array) < 2 or tuple(np.shape(array)[:2]) != self.shape:
            raise ShapeError(
                argument, f"an image of shape ({self.height}, {self.width}, ...) for this camera", describe(array)
            )

    def resized(self, width: int, height: int) -> "PinholeCamera":
        """The same camera for the image resized to (width, height) (pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            width,
            height,
            self.check_principal_point,
        )

    def cropped(self, left: int, top: int, width: int, height: int) -> "PinholeCamera":
        """The camera of the crop whose top-left pixel is (left, top) in this image."""
        if left < 0 or top < 0 or left + width > self.width or top + height > self.height:
            raise CalibrationError(
                "crop", f"a window inside the {self.width}x{self.height} image", (left, top, width, height)
            )
        return PinholeCamera(self.fx, self.fy, self.cx - left, self.cy - top, width, height, False)

    # ------------------------------------------------------------------ geometry
    def pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre coordinates (u, v), each of shape (height, width).

        Raises:
            ProblemTooLargeError: a grid beyond the memory limit (`gpdepth3d.limits`), before allocating it.
        """
        from .limits import check_array_size

        check_array_size(f"the pixel grid of a {self.width}x{self.height} camera", (4, self.height, self.width))
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        return u.astype(np.float64), v.astype(np.float64)

    def project(self, points_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projects camera-frame points to pixels.

        Args:
            points_camera: (N, 3) points in the camera frame, metres.

        Returns:
            uv: (N, 2) pixel coordinates (u, v); meaningless where z <= 0.
            z: (N,) z-depth in metres.
        """
        p = np.asarray(points_camera, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ShapeError("points_camera", "an (N, 3) array", describe(p))
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * p[:, 0] / z + self.cx
            v = self.fy * p[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Boolean mask of pixel coordinates that fall inside the image."""
        uv = np.asarray(uv)
        return (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= -0.5)
            & (uv[:, 0] < self.width - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] < self.height - 0.5)
        )

    def backproject_pixels(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Lifts pixels with z-depth to (N, 3) camera-frame points (metres)."""
        uv = np.asarray(uv, dtype=np.float64)
        depth = np.asarray(depth, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ShapeError("uv", "an (N, 2) array", describe(uv))
        if depth.shape != (uv.shape[0],):
            raise ShapeError("depth", f"shape ({uv.shape[0]},) matching uv", describe(depth))
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        return np.stack([x, y, depth], axis=1)

    def backproject(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lifts a depth map to camera-frame points.

        Args:
            depth: (height, width) z-depth in metres; 0 marks no depth.

        Returns:
            points: (N, 3) camera-frame points of the valid pixels (finite depth > 0), metres.
            valid: (height, width) boolean mask of those pixels (row-major order of ``points``).
        """
        depth = np.asarray(depth, dtype=np.float64)
        if depth.shape != self.shape:
            raise ShapeError("depth", f"shape {self.shape} of the camera", describe(depth))
        if np.any(depth < 0):
            raise InvalidDepthError("depth", "z-depth >= 0 (0 = no depth)", f"minimum {np.nanmin(depth)}")
        valid = np.isfinite(depth) & (depth > 0)
        u, v = self.pixel_grid()
        uv = np.stack([u[valid], v[valid]], axis=1)
        return self.backproject_pixels(uv, depth[valid]), valid


def check_pose(T: np.ndarray, argument: str = "T_world_camera", atol: float = 1e-3) -> np.ndarray:
    """Validates a 4x4 rigid transform; returns it as float64 with an exactly orthonormal rotation.

    Recorded poses are stored with a few digits (7-Scenes: |det R - 1| up to 2.4e-4), so the
    rotation is accepted within ``atol`` and then snapped to the nearest rotation (SVD).

    Raises:
        CalibrationError: if T is not 4x4, not finite, its rotation is not orthonormal with
            determinant +1 within ``atol``, or its last row is not [0, 0, 0, 1].
    """
    try:
        T = np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(argument, "a 4x4 rigid transform of numbers", describe(T)) from None
    if T.shape != (4, 4):
        raise CalibrationError(argument, "a 4x4 rigid transform", describe(T))
    if not np.all(np.isfinite(T)):
        raise CalibrationError(argument, "finite values", "NaN or inf entries")
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=atol):
        raise CalibrationError(argument, "last row [0, 0, 0, 1]", T[3].tolist())
    if not np.allclose(R @ R.T, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise CalibrationError(argument, "an orthonormal rotation with det +1", f"det {np.linalg.det(R):.4f}")
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Applies a 4x4 transform to (N, 3) points."""
    points = np.asarray(points, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError("T", "a 4x4 transform", describe(T))
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError("points", "an (N, 3) array", describe(points))
    return points @ T[:3, :3].T + T[:3, 3]


_FOUR_NUMBERS = re.compile(r"^\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*$")
KITTI_PROJECTIONS = ("P2:", "P_rect_02:")
"""Lines of a KITTI calibration file holding camera 02's (3, 4) projection (object benchmark, raw data)."""


def read_intrinsics(spec: str | Path) -> np.ndarray:
    """A 3x3 K from ``"fx,fy,cx,cy"`` (pixels), a text file holding K, or a KITTI calibration file.

    KITTI: an object-benchmark ``calib_*.txt`` (line ``P2:``), a raw-data ``calib_cam_to_cam.txt``
    (line ``P_rect_02:``) or the raw-data folder holding it; K is the left 3x3 of camera 02's projection.

    Raises:
        DataFormatError: a missing or unreadable file.
        CalibrationError: focal lengths that are not positive and finite.
    """
    from .errors import DataFormatError

    match = _FOUR_NUMBERS.match(str(spec))
    if match and not Path(str(spec)).exists():
        fx, fy, cx, cy = (float(x) for x in match.groups())
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    else:
        path = Path(spec)
        if path.is_dir() and (path / "calib_cam_to_cam.txt").is_file():
            path = path / "calib_cam_to_cam.txt"
        if not path.is_file():
            raise DataFormatError(path, "intrinsics not found (give a K file, a KITTI calibration or fx,fy,cx,cy)")
        text = path.read_text(encoding="utf-8", errors="replace")
        lines = [ln.split(":", 1)[1] for ln in text.splitlines() if ln.strip().startswith(KITTI_PROJECTIONS)]
        try:
            if lines:
                K = np.array(lines[0].split(), dtype=np.float64).reshape(3, 4)[:, :3]
            else:
                K = np.array(text.split(), dtype=np.float64).reshape(3, 3)
        except ValueError:
            raise DataFormatError(path, "expected a 3x3 K (9 numbers) or a KITTI calibration with a P2 line") from None
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError("intrinsics", "positive, finite focal lengths fx, fy", f"K = {K.tolist()}")
    return K
