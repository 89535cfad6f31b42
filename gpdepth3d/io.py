"""Reading and writing depth maps, sparse points and images; every write is atomic.

File conventions:

* ``.npy``: a (H, W) float array in metres.
* ``.npz``: the array under ``key`` (default: the only array, or ``depth``/``mean``).
* ``.png``: 16-bit depth; metres = value * ``png_scale``. KITTI stores value = metres * 256
  (``png_scale = 1/256``), 7-Scenes/TUM-style Kinect PNGs store millimetres (``1/1000``). Value 0
  (and 65535 for Kinect, see ``invalid_value``) means no depth.
* Sparse point lists: ``.npz`` with ``u``, ``v``, ``depth`` (and optional ``sigma``), or a text
  file with one ``u v depth [sigma]`` per line (pixels, metres).

Writes go to a temporary file in the destination folder and are renamed into place, so an
interrupted or failed write never leaves a partial file under the final name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .errors import DataFormatError, GPDepthError, InvalidDepthError, ShapeError, describe
from .camera import check_pose
from .measurements import SparseDepth

KITTI_PNG_SCALE = 1.0 / 256.0
_UMASK = os.umask(0o022)  # read the process umask once (at import, before any threads) and restore it
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yields a temporary path beside ``path``; renames it onto ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Calls ``write(tmp_path)`` and moves the result onto ``path`` atomically."""
    with atomic_path(path) as tmp:
        write(tmp)
    return Path(path)


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Writes arrays to a compressed ``.npz`` atomically."""

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return atomic_write(path, write)


def save_depth_png(path: str | Path, depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE) -> Path:
    """Writes a depth map (metres) as a 16-bit PNG, value = round(metres / png_scale); 0 = no depth."""
    import cv2

    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError("depth", "a 2-D depth map", describe(d))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    values = np.zeros(d.shape, dtype=np.float64)
    values[valid] = np.rint(d[valid] / png_scale)
    if np.any(values > 65535):
        raise InvalidDepthError(
            "depth", f"depths up to {65535 * png_scale:.1f} m for png_scale {png_scale}", f"max {d[valid].max():.1f} m"
        )
    img = values.astype(np.uint16)

    def write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), img):
            raise DataFormatError(path, "OpenCV could not write the PNG")

    return atomic_write(Path(path).with_suffix(".png"), write)


def load_depth(
    path: str | Path,
    *,
    png_scale: float = KITTI_PNG_SCALE,
    key: str | None = None,
    invalid_value: int | None = None,
) -> np.ndarray:
    """Reads a (H, W) depth map in metres from ``.npy``, ``.npz`` or 16-bit ``.png``.

    Invalid pixels come back as 0. Raises `DataFormatError` for missing, unknown or corrupt files.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                depth = data[_pick_key(path, list(data.keys()), key)]
        elif suffix == ".png":
            import cv2

            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise DataFormatError(path, "not a readable PNG")
            if raw.ndim != 2 or raw.dtype != np.uint16:
                raise DataFormatError(path, f"expected a single-channel 16-bit depth PNG, got {raw.dtype} {raw.shape}")
            depth = raw.astype(np.float64) * png_scale
            depth[raw == 0] = 0.0
            if invalid_value is not None:
                depth[raw == invalid_value] = 0.0
        else:
            raise DataFormatError(path, f"unknown depth format '{suffix}' (use .npy, .npz or .png)")
    except DataFormatError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"corrupt or unreadable: {exc}") from None
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise DataFormatError(path, f"expected a 2-D depth map, got shape {depth.shape}")
    depth = np.where(np.isfinite(depth), depth, 0.0)
    return depth


def _pick_key(path: Path, keys: list[str], key: str | None) -> str:
    if key is not None:
        if key not in keys:
            raise DataFormatError(path, f"no array '{key}' (has {keys})")
        return key
    if len(keys) == 1:
        return keys[0]
    for k in ("depth", "mean", "velodyne_depth"):
        if k in keys:
            return k
    raise DataFormatError(path, f"several arrays {keys}: say which with key=")


def load_sparse(
    path: str | Path,
    image_size: tuple[int, int] | None = None,
    *,
    png_scale: float = KITTI_PNG_SCALE,
) -> SparseDepth:
    """Reads sparse measurements from a point list (``.npz`` u/v/depth, ``.txt``) or a sparse depth map.

    Args:
        path: The file.
        image_size: (height, width) the point coordinates refer to; required for point lists,
            taken from the map for depth images.
        png_scale: Metres per PNG unit for 16-bit PNG depth maps.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                if {"u", "v", "depth"} <= set(data.keys()):
                    if image_size is None:
                        raise ShapeError("image_size", "(height, width) for a point list", None)
                    sigma = data["sigma"] if "sigma" in data else None
                    return SparseDepth.from_arrays(data["u"], data["v"], data["depth"], image_size, sigma)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            if isinstance(exc, GPDepthError):
                raise
            raise DataFormatError(path, f"corrupt or unreadable point list: {exc}") from None
    if suffix in (".txt", ".csv"):
        if image_size is None:
            raise ShapeError("image_size", "(height, width) for a point list", None)
        try:
            table = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=2)
        except ValueError as exc:
            raise DataFormatError(path, f"expected lines 'u v depth [sigma]': {exc}") from None
        if table.shape[0] == 0:
            return SparseDepth.empty(image_size)
        if table.shape[1] not in (3, 4):
            raise DataFormatError(path, f"expected 3 or 4 columns (u v depth [sigma]), got {table.shape[1]}")
        sigma = table[:, 3] if table.shape[1] == 4 else None
        return SparseDepth.from_arrays(table[:, 0], table[:, 1], table[:, 2], image_size, sigma)
    depth = load_depth(path, png_scale=png_scale)
    sparse = SparseDepth.from_depth_map(depth)
    if image_size is not None and tuple(image_size) != sparse.image_size:
        raise ShapeError("image_size", f"the size of the sparse map {sparse.image_size}", tuple(image_size))
    return sparse


def load_rgb(path: str | Path) -> np.ndarray:
    """Reads an image as (H, W, 3) uint8 RGB."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "image not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DataFormatError(path, "not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_matrix(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray:
    """Reads a whitespace-separated text matrix and checks its shape; DataFormatError otherwise."""
    if not path.is_file():
        raise DataFormatError(path, f"{what} not found")
    try:
        m = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataFormatError(path, f"{what}: not a numeric matrix ({exc})") from None
    if m.size != int(np.prod(shape)):
        raise DataFormatError(path, f"{what}: expected {shape} values, got shape {m.shape}")
    m = m.reshape(shape)
    if not np.all(np.isfinite(m)):
        raise DataFormatError(path, f"{what}: non-finite values")
    return m


def load_pose(path: str | Path) -> np.ndarray:
    """Reads a 4x4 ``T_world_camera`` from text: 4 rows of 4 numbers (7-Scenes/TUM) or 12 numbers (3x4)."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    try:
        values = np.loadtxt(path, ndmin=1).ravel()
    except ValueError as exc:
        raise DataFormatError(path, f"expected numbers of a 4x4 or 3x4 pose: {exc}") from None
    if values.size == 12:
        values = np.concatenate([values, [0.0, 0.0, 0.0, 1.0]])
    if values.size != 16:
        raise DataFormatError(path, f"expected 16 (4x4) or 12 (3x4) numbers, got {values.size}")
    return check_pose(values.reshape(4, 4), str(path))


def load_poses(path: str | Path) -> list[np.ndarray]:
    """Reads one pose per line (12 numbers, row-major 3x4, KITTI odometry style) as 4x4 matrices."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    try:
        table = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataFormatError(path, f"expected lines of 12 numbers: {exc}") from None
    if table.shape[1] != 12:
        raise DataFormatError(path, f"expected 12 numbers per line (3x4 pose), got {table.shape[1]}")
    bottom = np.tile([0.0, 0.0, 0.0, 1.0], (table.shape[0], 1))
    return [check_pose(T.reshape(4, 4), f"{path} line {i + 1}") for i, T in enumerate(np.hstack([table, bottom]))]
