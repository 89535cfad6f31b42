"""Sparse range measurements: `SparseDepth`, LiDAR projection and occlusion-aware resampling.

A measurement is a pixel position (u, v) in an image of known size, a z-depth in metres and a
standard deviation in metres. Whenever several measurements fall into one pixel (projection of a
LiDAR scan, downsampling to a coarser grid), the closest one is kept: the farther points are
hidden behind it (the z-buffer rule of the paper's occlusion handling).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import PinholeCamera
from .errors import CalibrationError, DataFormatError, InvalidDepthError, ShapeError, describe


DEPTH_RANGE = (1e-6, 1e6)
"""Depths and standard deviations a measurement may have (metres): the MDE's bounds."""


LIKELY_UNITS = ((2000.0, "millimetres", 1e-3), (200.0, "centimetres", 1e-2))
"""(median above which, unit, metres per unit): depths whose median exceeds 200 (2000) "metres" are
far more likely centimetres (millimetres) of an indoor or street scene than a scene 200 m away."""


def likely_unit(depths: np.ndarray) -> tuple[str, float] | None:
    """The unit depths (finite, > 0) most likely are in when not metres: (name, metres per unit), or None.

    The median decides (`LIKELY_UNITS`): above 2000 millimetres, above 200 centimetres.
    """
    d = np.asarray(depths, dtype=np.float64).ravel()
    with np.errstate(invalid="ignore"):
        d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        return None
    median = float(np.median(d))
    for above, unit, factor in LIKELY_UNITS:
        if median > above:
            return unit, factor
    return None


def check_metres(depths: np.ndarray, argument: str, option: str) -> None:
    """Refuses depths that look like millimetres or centimetres, naming the option that converts them.

    Called on a user's files before any work, so a unit slip is caught on one line instead of a
    depth map wrong by 1000x (or a 16-bit PNG that cannot hold it).

    Args:
        depths: The depths as read (any shape; 0, NaN and inf are ignored).
        argument: What they are, e.g. ``"--sparse points.txt"``.
        option: The option that scales them to metres, e.g. ``"--sparse-scale"``.

    Raises:
        InvalidDepthError: the median looks like millimetres or centimetres (`likely_unit`).
    """
    guess = likely_unit(depths)
    if guess is not None:
        unit, factor = guess
        d = np.asarray(depths, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            median = float(np.median(d[np.isfinite(d) & (d > 0)]))
        raise InvalidDepthError(
            argument,
            "depths in metres",
            f"median {median:.4g}: these look like {unit}, convert them with {option} {factor:g}",
        )


def _as_shape(image_size: tuple[int, int], argument: str = "image_size") -> tuple[int, int]:
    """Validates (height, width): two integers >= 1 (integral floats accepted); returns ints."""
    expected = "(height, width) with two positive integers"
    if isinstance(image_size, (str, bytes)) or not hasattr(image_size, "__len__") or len(image_size) != 2:
        raise ShapeError(argument, expected, describe(image_size))
    for s in image_size:
        real = not isinstance(s, (bool, np.bool_)) and isinstance(s, (int, float, np.integer, np.floating))
        if not real or not np.isfinite(s) or int(s) != s or s <= 0:
            raise ShapeError(argument, expected, describe(image_size))
    return (int(image_size[0]), int(image_size[1]))


@dataclass(frozen=True)
class SparseDepth:
    """Sparse depth measurements in one image.

    Attributes:
        u: (N,) column coordinates, pixels (pixel centres at integers).
        v: (N,) row coordinates, pixels.
        depth: (N,) z-depth, metres, finite and > 0.
        sigma: (N,) standard deviation of each depth, metres; NaN means "use the model's
            default sigma_meas".
        image_size: (height, width) of the image the coordinates refer to.
    """

    u: np.ndarray
    v: np.ndarray
    depth: np.ndarray
    image_size: tuple[int, int]
    sigma: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        shape = _as_shape(self.image_size)
        object.__setattr__(self, "image_size", shape)
        arrays = {}
        for name in ("u", "v", "depth"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.ndim != 1:
                raise ShapeError(name, "a 1-D array", describe(a))
            arrays[name] = a
        n = arrays["depth"].shape[0]
        sigma = self.sigma
        sigma = np.full(n, np.nan) if sigma is None else np.asarray(sigma, dtype=np.float64)
        if np.ndim(sigma) == 0:
            sigma = np.full(n, float(sigma))
        arrays["sigma"] = sigma
        for name, a in arrays.items():
            if a.shape != (n,):
                raise ShapeError(name, f"shape ({n},) like depth", describe(a))
        if not np.all(np.isfinite(arrays["u"])) or not np.all(np.isfinite(arrays["v"])):
            raise InvalidDepthError("u, v", "finite pixel coordinates", "NaN or inf")
        d = arrays["depth"]
        if not np.all(np.isfinite(d)) or np.any(d <= 0):
            bad = int(np.sum(~np.isfinite(d) | (d <= 0)))
            raise InvalidDepthError(
                "depth", "finite z-depths > 0 (drop invalid points with SparseDepth.from_arrays)", f"{bad} invalid"
            )
        lo, hi = DEPTH_RANGE
        outside = (d < lo) | (d > hi)
        if np.any(outside):  # beyond any camera: the GP's scales would under/overflow
            raise InvalidDepthError(
                "depth",
                f"z-depths in [{lo:g}, {hi:g}] m",
                f"{int(outside.sum())} outside, e.g. {float(d[outside][0]):g}",
            )
        s = arrays["sigma"]
        if np.any(s[np.isfinite(s)] <= 0) or np.any(np.isinf(s)):
            raise InvalidDepthError("sigma", "standard deviations > 0 (or NaN for the default)", "<= 0 or inf")
        with np.errstate(invalid="ignore"):
            outside = np.isfinite(s) & ((s < lo) | (s > hi))
        if np.any(outside):
            raise InvalidDepthError(
                "sigma",
                f"standard deviations in [{lo:g}, {hi:g}] m (or NaN for the default)",
                f"{int(outside.sum())} outside, e.g. {float(s[outside][0]):g}",
            )
        h, w = shape
        inside = (arrays["u"] >= -0.5) & (arrays["u"] < w - 0.5) & (arrays["v"] >= -0.5) & (arrays["v"] < h - 0.5)
        if not np.all(inside):
            raise InvalidDepthError(
                "u, v",
                f"coordinates inside the {w}x{h} image (drop outside points with SparseDepth.from_arrays)",
                f"{int(np.sum(~inside))} points outside",
            )
        for name, a in arrays.items():
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(cls, image_size: tuple[int, int]) -> "SparseDepth":
        """No measurements."""
        z = np.zeros(0)
        return cls(z, z, z, image_size)

    @classmethod
    def from_arrays(
        cls,
        u: np.ndarray,
        v: np.ndarray,
        depth: np.ndarray,
        image_size: tuple[int, int],
        sigma: np.ndarray | float | None = None,
    ) -> "SparseDepth":
        """Builds measurements, silently dropping invalid ones.

        Dropped: non-finite or non-positive depth, non-finite coordinates, points outside the
        image. Use the constructor instead to have such points raise.
        """
        u = np.asarray(u, dtype=np.float64).ravel()
        v = np.asarray(v, dtype=np.float64).ravel()
        depth = np.asarray(depth, dtype=np.float64).ravel()
        if not (u.shape == v.shape == depth.shape):
            raise ShapeError("u, v, depth", "three arrays of one length", (u.shape, v.shape, depth.shape))
        if sigma is None:
            sigma = np.full(depth.shape, np.nan)
        sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), depth.shape)
        h, w = _as_shape(image_size)
        with np.errstate(invalid="ignore"):
            keep = (
                np.isfinite(depth)
                & (depth > 0)
                & np.isfinite(u)
                & np.isfinite(v)
                & (u >= -0.5)
                & (u < w - 0.5)
                & (v >= -0.5)
                & (v < h - 0.5)
            )
        return cls(u[keep], v[keep], depth[keep], (h, w), sigma[keep])

    @classmethod
    def from_depth_map(cls, depth_map: np.ndarray, sigma: float | None = None) -> "SparseDepth":
        """Measurements from a sparse depth image (0, NaN or inf = no measurement; metres)."""
        d = np.asarray(depth_map, dtype=np.float64)
        if d.ndim != 2:
            raise ShapeError("depth_map", "a 2-D (height, width) depth image", describe(d))
        if np.any(d < 0):
            raise InvalidDepthError("depth_map", "depths >= 0 (0 = no measurement)", f"minimum {np.nanmin(d)}")
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0)
        v, u = np.nonzero(valid)
        return cls(u.astype(np.float64), v.astype(np.float64), d[valid], d.shape, sigma)

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return int(self.depth.shape[0])

    @property
    def uv(self) -> np.ndarray:
        """(N, 2) pixel coordinates."""
        return np.stack([self.u, self.v], axis=1)

    def subset(self, index: np.ndarray) -> "SparseDepth":
        """The measurements selected by a boolean mask or an index array."""
        return SparseDepth(self.u[index], self.v[index], self.depth[index], self.image_size, self.sigma[index])

    def with_sigma(self, sigma: float | np.ndarray) -> "SparseDepth":
        """The same points with new standard deviations (metres)."""
        return SparseDepth(self.u, self.v, self.depth, self.image_size, np.broadcast_to(sigma, self.depth.shape))

    def pixel_indices(self, shape: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Integer (row, col) of each point on a grid of ``shape`` covering the same image.

        The grid may have another resolution than ``image_size``: coordinates are rescaled with
        the pixel-centre convention and rounded to the nearest pixel centre.
        """
        h, w = self.image_size if shape is None else _as_shape(shape)
        sh, sw = self.image_size
        col = np.rint((self.u + 0.5) * (w / sw) - 0.5).astype(np.int64)
        row = np.rint((self.v + 0.5) * (h / sh) - 0.5).astype(np.int64)
        return np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)

    def rasterize(self, shape: tuple[int, int] | None = None) -> "SparseDepth":
        """Snaps the points to the pixel centres of a grid of ``shape``, closest point per pixel.

        This is the occlusion-aware resampling of the paper: when several points land in one
        pixel only the nearest survives. The result has ``image_size == shape``.
        """
        shape = self.image_size if shape is None else _as_shape(shape)
        if len(self) == 0:
            return SparseDepth.empty(shape)
        row, col = self.pixel_indices(shape)
        flat = row * shape[1] + col
        keep = None
        if flat.size == 1 or np.all(flat[1:] > flat[:-1]):  # already one point per pixel, by pixel (a rasterisation)
            return SparseDepth(col.astype(np.float64), row.astype(np.float64), self.depth, shape, self.sigma)
        if shape[0] * shape[1] <= 16 * flat.size:  # dense points: a pixel table instead of a sort
            slot = np.full(shape[0] * shape[1], -1, dtype=np.int64)
            slot[flat] = np.arange(flat.size)
            if np.count_nonzero(slot >= 0) == flat.size:  # one point per pixel: ordered by pixel
                keep = slot[slot >= 0]
        if keep is None:
            order = np.lexsort((self.depth, flat))  # by pixel, then nearest first
            first = np.ones(order.shape, dtype=bool)
            first[1:] = flat[order][1:] != flat[order][:-1]
            keep = order[first]
        return SparseDepth(
            col[keep].astype(np.float64), row[keep].astype(np.float64), self.depth[keep], shape, self.sigma[keep]
        )

    def to_depth_map(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Dense (height, width) image with the closest depth per pixel and 0 elsewhere."""
        r = self.rasterize(shape)
        out = np.zeros(r.image_size, dtype=np.float64)
        out[r.v.astype(np.int64), r.u.astype(np.int64)] = r.depth
        return out


# ---------------------------------------------------------------------- projection
def project_points(
    points_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    min_depth: float = 1e-3,
    sigma: float | np.ndarray | None = None,
) -> SparseDepth:
    """Projects camera-frame 3-D points into the image, keeping the closest point per pixel.

    Args:
        points_camera: (N, 3) points in the OpenCV camera frame, metres.
        camera: The camera; points projecting outside its image are dropped.
        min_depth: Points with z below this (behind or at the camera) are dropped.
        sigma: Optional per-point depth standard deviation (metres).

    Returns:
        `SparseDepth` on the camera's pixel grid, one point per pixel at most.
    """
    uv, z = camera.project(points_camera)
    keep = np.isfinite(z) & (z > min_depth)
    uv, z = uv[keep], z[keep]
    if sigma is not None:
        sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), keep.shape)[keep]
    sparse = SparseDepth.from_arrays(uv[:, 0], uv[:, 1], z, camera.shape, sigma)
    return sparse.rasterize()


def downsample_depth(depth: np.ndarray, factor: int) -> np.ndarray:
    """Shrinks a sparse or dense depth map by an integer factor keeping the closest depth per block.

    Invalid pixels (0, NaN, inf) are ignored; a block with no valid pixel becomes 0. The output
    has shape (height // factor, width // factor); trailing rows and columns that do not fill a
    block are dropped (crop first to keep them).
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError("depth", "a 2-D depth map", describe(d))
    if int(factor) != factor or factor < 1:
        raise ShapeError("factor", "an integer >= 1", factor)
    factor = int(factor)
    h, w = d.shape[0] // factor, d.shape[1] // factor
    if h == 0 or w == 0:
        raise ShapeError("factor", f"at most the image size {d.shape}", factor)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    blocks = np.where(valid, d, np.inf)[: h * factor, : w * factor]
    blocks = blocks.reshape(h, factor, w, factor).min(axis=(1, 3))
    blocks[~np.isfinite(blocks)] = 0.0
    return blocks


# ---------------------------------------------------------------------- LiDAR & calibration
@dataclass(frozen=True)
class LidarCalibration:
    """LiDAR-to-image calibration.

    Attributes:
        P: (3, 4) projection matrix of the rectified camera (KITTI ``P2``), pixels.
        T_camera_lidar: (4, 4) transform from LiDAR to the (rectified) camera frame, including
            KITTI's ``R0_rect``.
    """

    P: np.ndarray
    T_camera_lidar: np.ndarray

    def __post_init__(self) -> None:
        P = np.asarray(self.P, dtype=np.float64)
        T = np.asarray(self.T_camera_lidar, dtype=np.float64)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise CalibrationError("P", "a finite 3x4 projection matrix", describe(P))
        if T.shape == (3, 4):
            T = np.vstack([T, [0, 0, 0, 1]])
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise CalibrationError("T_camera_lidar", "a finite 3x4 or 4x4 transform", describe(T))
        check_projection(P, "P")
        check_rotation(T[:3, :3], "T_camera_lidar")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=ROTATION_ATOL):
            raise CalibrationError("T_camera_lidar", "a rigid transform with last row [0, 0, 0, 1]", T[3].tolist())
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "T_camera_lidar", T)

    @classmethod
    def from_kitti(cls, path: str | Path, camera: int = 2) -> "LidarCalibration":
        """Reads a KITTI object-benchmark calibration file (``P2``, ``R0_rect``, ``Tr_velo_to_cam``).

        Also accepts the raw-data pair ``calib_cam_to_cam.txt`` when given its folder: then
        ``calib_velo_to_cam.txt`` (R, T) and ``calib_cam_to_cam.txt`` (P_rect_0N, R_rect_00)
        are read from that folder.
        """
        path = Path(path)
        if path.is_dir():
            return cls._from_kitti_raw(path, camera)
        values = _read_kitti_kv(path)
        try:
            P = values[f"P{camera}"].reshape(3, 4)
            R0 = values.get("R0_rect", values.get("R_rect", np.eye(3).ravel())).reshape(3, 3)
            Tr = values.get("Tr_velo_to_cam", values.get("Tr_velo_cam"))
            if Tr is None:
                raise KeyError("Tr_velo_to_cam")
            Tr = Tr.reshape(3, 4)
        except (KeyError, ValueError) as exc:
            raise DataFormatError(path, f"not a KITTI calibration file (missing or malformed {exc})") from None
        _check_kitti(path, P, R0, Tr, f"P{camera}", "R0_rect", "Tr_velo_to_cam")
        R = np.eye(4)
        R[:3, :3] = R0
        T = R @ np.vstack([Tr, [0, 0, 0, 1]])
        return cls(P, T)

    @classmethod
    def _from_kitti_raw(cls, folder: Path, camera: int) -> "LidarCalibration":
        c2c = _read_kitti_kv(folder / "calib_cam_to_cam.txt")
        v2c = _read_kitti_kv(folder / "calib_velo_to_cam.txt")
        try:
            P = c2c[f"P_rect_0{camera}"].reshape(3, 4)
            R0 = c2c["R_rect_00"].reshape(3, 3)
            Tr = np.hstack([v2c["R"].reshape(3, 3), v2c["T"].reshape(3, 1)])
        except (KeyError, ValueError) as exc:
            raise DataFormatError(folder, f"not a KITTI raw calibration folder (missing {exc})") from None
        _check_kitti(folder, P, R0, Tr, f"P_rect_0{camera}", "R_rect_00", "calib_velo_to_cam R")
        R = np.eye(4)
        R[:3, :3] = R0
        return cls(P, R @ np.vstack([Tr, [0, 0, 0, 1]]))

    def check_image_size(self, image_size: tuple[int, int], argument: str = "image_size") -> None:
        """Refuses an image size the calibration cannot belong to.

        The principal point of ``P`` (pixels of the calibrated image) must lie in the middle
        half of the image in each direction (KITTI's P2: (609.6, 172.9) in a 1242x375 image);
        a smaller image (say a 320x240 MDE) means the points must be projected at the
        calibrated size and moved to the MDE grid.

        Raises:
            CalibrationError: naming ``argument``, with the principal point and the size.
        """
        h, w = _as_shape(image_size, argument)
        K = self.P[:, :3]
        if abs(K[2, 2]) < 1e-12:
            raise CalibrationError("P", "a projection matrix with P[2, 2] != 0", self.P.tolist())
        cx, cy = K[0, 2] / K[2, 2], K[1, 2] / K[2, 2]
        if not (0.25 * w <= cx + 0.5 <= 0.75 * w and 0.25 * h <= cy + 0.5 <= 0.75 * h):
            raise CalibrationError(
                argument,
                f"the size of the image the calibration belongs to (its principal point ({cx:.1f}, {cy:.1f}) should "
                "lie near the image centre)",
                f"{w}x{h}",
            )

    def project(self, points_lidar: np.ndarray, image_size: tuple[int, int], *, min_depth: float = 1e-3) -> SparseDepth:
        """Projects LiDAR points into the image, closest point per pixel.

        Args:
            points_lidar: (N, 3) or (N, 4) LiDAR points (x, y, z[, reflectance]), metres.
            image_size: (height, width) of the image.
            min_depth: Points with camera z below this are dropped.

        Returns:
            `SparseDepth` of z-depths in the rectified camera frame.
        """
        p = np.asarray(points_lidar, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] not in (3, 4):
            raise ShapeError("points_lidar", "an (N, 3) or (N, 4) array", describe(p))
        cam = p[:, :3] @ self.T_camera_lidar[:3, :3].T + self.T_camera_lidar[:3, 3]
        homog = np.hstack([cam, np.ones((cam.shape[0], 1))]) @ self.P.T
        # P = K [I | t]: the image z of a point is cam z + t_z; use the camera z as depth.
        z = homog[:, 2]
        keep = np.isfinite(z) & (cam[:, 2] > min_depth) & (z > min_depth)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = homog[:, 0] / z
            v = homog[:, 1] / z
        sparse = SparseDepth.from_arrays(u[keep], v[keep], z[keep], image_size)
        return sparse.rasterize()


ROTATION_ATOL = 1e-3
"""Tolerance of a calibration's rotation: |R R^T - I| and |det R - 1| (KITTI's files: ~1e-7)."""


def check_rotation(R: np.ndarray, argument: str) -> None:
    """Refuses a 3x3 matrix that is not a rotation (orthonormal, det +1) within `ROTATION_ATOL`.

    A scaled or sheared extrinsic multiplies or bends every projected depth silently.

    Raises:
        CalibrationError: naming ``argument``, with the singular values and the determinant.
    """
    R = np.asarray(R, dtype=np.float64)
    det = float(np.linalg.det(R)) if R.shape == (3, 3) and np.all(np.isfinite(R)) else float("nan")
    if not (R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=ROTATION_ATOL) and abs(det - 1) < ROTATION_ATOL):
        sv = np.linalg.svd(R, compute_uv=False) if R.shape == (3, 3) and np.all(np.isfinite(R)) else []
        raise CalibrationError(
            argument,
            "a rotation (orthonormal, det +1: a rigid transform, no scale)",
            f"singular values {np.round(sv, 4).tolist()}, det {det:.4g}",
        )


def check_projection(P: np.ndarray, argument: str) -> None:
    """Refuses a 3x4 projection whose 3x3 part is not K R with focal lengths > 0 (e.g. all zeros).

    Raises:
        CalibrationError: naming ``argument`` and the matrix.
    """
    M = np.asarray(P, dtype=np.float64)[:, :3]
    scale = M[2, 2]
    if not (abs(scale) > 1e-12 and M[0, 0] / scale > 0 and M[1, 1] / scale > 0 and abs(np.linalg.det(M)) > 1e-12):
        raise CalibrationError(
            argument, "a projection K [R | t] with focal lengths > 0 and P[2, 2] != 0", np.round(P, 4).tolist()
        )


def _check_kitti(path: Path, P, R0, Tr, p_name: str, r0_name: str, tr_name: str) -> None:
    """Checks the three matrices of a KITTI calibration, each error naming the file and the entry."""
    check_projection(P, f"{path}: {p_name}")
    check_rotation(R0, f"{path}: {r0_name}")
    check_rotation(np.asarray(Tr)[:3, :3], f"{path}: {tr_name}")


def _read_kitti_kv(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise DataFormatError(path, "calibration file not found")
    values: dict[str, np.ndarray] = {}
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DataFormatError(path, "not a text calibration file (binary content)") from None
    except OSError as exc:
        raise DataFormatError(path, f"unreadable: {exc.strerror or exc}") from None
    for line in text.splitlines():
        if ":" not in line:
            continue
        key, rest = line.split(":", 1)
        try:
            values[key.strip()] = np.array([float(x) for x in rest.split()])
        except ValueError:
            continue  # e.g. calib_time: 09-Jan-2012 13:57:47
    if not values:
        raise DataFormatError(path, "no 'key: numbers' lines found")
    return values


def load_velodyne(path: str | Path) -> np.ndarray:
    """Reads a KITTI Velodyne ``.bin`` scan as an (N, 4) float32 array (x, y, z, reflectance).

    Raises:
        DataFormatError: missing file, or a size that is not a whole number of 16-byte records
            (a truncated or foreign file).
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "Velodyne scan not found")
    size = path.stat().st_size
    if size == 0 or size % 16:
        raise DataFormatError(
            path, f"expected float32 (x, y, z, r) records of 16 bytes, got {size} bytes (not a multiple of 16)"
        )
    raw = np.fromfile(path, dtype=np.float32)
    return raw.reshape(-1, 4)
