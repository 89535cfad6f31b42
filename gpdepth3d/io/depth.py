"""Depth maps: 16-bit PNG values and writers, and the depth reader (``.npy``, ``.npz``, ``.png``).

File conventions:

* ``.npy``: a (H, W) float array in metres.
* ``.npz``: the array under ``key`` (default: the only array, or ``depth``/``mean``).
* ``.png``: 16-bit depth; metres = value * ``png_scale``. KITTI stores value = metres * 256
  (``png_scale = 1/256``), 7-Scenes/TUM-style Kinect PNGs store millimetres (``1/1000``). Value 0
  (and 65535 for Kinect, see ``invalid_value``) means no depth.
"""

from __future__ import annotations

import os
import warnings
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DataFormatError, InvalidDepthError, InvalidInputError, OutputError, ShapeError, describe
from .arrays import _as_path, _pick_key, check_stored_array
from .images import _imread
from .durable import atomic_write


KITTI_PNG_SCALE = 1.0 / 256.0


class PNGRangeWarning(UserWarning):
    """Depths beyond a 16-bit PNG's range were stored at its limit (the float outputs keep them)."""


def depth_png_values(
    depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE, *, argument: str = "depth", saturate: bool = False
) -> np.ndarray:
    """The (H, W) uint16 values of a depth PNG, value = round(metres / png_scale).

    0 = no depth: pixels with depth <= 0, NaN or inf (a PNG holds no negative depths). The
    range is the format's (KITTI's 1/256: 256 m): beyond it a depth saturates at 65535 with
    ``saturate``, else it is refused. Everything is validated before anything is written.

    Raises:
        ShapeError: if ``depth`` is not 2-D.
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
        InvalidDepthError: if a depth does not fit 16 bits at ``png_scale`` and not ``saturate``.

    Warns:
        PNGRangeWarning: with ``saturate``, naming how many pixels were stored at the limit.
    """
    png_scale = check_png_scale(png_scale)
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ShapeError(argument, "a 2-D depth map", describe(d))
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise ShapeError(argument, "a real-valued depth map", describe(d))
    d = d.astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    values = np.zeros(d.shape, dtype=np.float64)
    values[valid] = np.rint(d[valid] / png_scale)
    over = values > 65535
    n_over = int(np.count_nonzero(over))
    if n_over:
        limit = f"{65535 * png_scale:.1f} m for a 16-bit PNG with png_scale {png_scale}"
        if not saturate:
            raise InvalidDepthError(argument, f"depths up to {limit}", f"max {d[valid].max():.4g} m")
        warnings.warn(
            f"{argument}: {n_over} of {d.size} pixels beyond {limit} (max {d[valid].max():.4g} m) stored as "
            f"{65535 * png_scale:.1f} m; the float outputs keep the true values",
            PNGRangeWarning,
            stacklevel=2,
        )
        values[over] = 65535
    return values.astype(np.uint16)


def png_writer(values: np.ndarray, path: str | Path) -> Callable[[Path], None]:
    """A ``write(path)`` function storing uint16 ``values`` as a PNG (errors name ``path``)."""

    def write(tmp: Path) -> None:
        import cv2

        target = tmp if tmp.suffix.lower() == ".png" else tmp.with_suffix(".png")
        if not cv2.imwrite(str(target), values):
            raise OutputError(path, "OpenCV could not write the PNG")
        if target != tmp:
            os.replace(target, tmp)

    return write


def save_depth_png(path: str | Path, depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE) -> Path:
    """Writes a depth map (metres) as a 16-bit PNG, value = round(metres / png_scale); 0 = no depth."""
    values = depth_png_values(depth, png_scale)
    path = Path(path).with_suffix(".png")
    return atomic_write(path, png_writer(values, path))


def check_png_scale(png_scale: float, argument: str = "png_scale") -> float:
    """Validates metres per PNG unit: a finite real number > 0; returns it as float."""
    if isinstance(png_scale, (bool, np.bool_)) or not isinstance(png_scale, (int, float, np.integer, np.floating)):
        raise InvalidInputError(argument, "metres per PNG unit, a finite number > 0", describe(png_scale))
    if not np.isfinite(png_scale) or png_scale <= 0:
        raise InvalidInputError(argument, "metres per PNG unit, a finite number > 0", png_scale)
    return float(png_scale)


def load_depth(
    path: str | Path, *, png_scale: float = KITTI_PNG_SCALE, key: str | None = None, invalid_value: int | None = None
) -> np.ndarray:
    """Reads a (H, W) depth map in metres from ``.npy``, ``.npz`` or 16-bit ``.png``.

    Invalid pixels (0, NaN, inf, ``invalid_value``) come back as 0.

    Raises:
        DataFormatError: for missing, unknown or corrupt files, and arrays that are not a
            real-valued (H, W) map (complex, strings, objects).
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
    """
    path = _as_path(path)
    png_scale = check_png_scale(png_scale)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            check_stored_array(path)
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                member = _pick_key(path, list(data.keys()), key)
                check_stored_array(path, member)
                depth = data[member]
        elif suffix == ".png":
            import cv2

            raw = _imread(path, cv2.IMREAD_UNCHANGED)
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
    depth = np.asarray(depth)
    if depth.dtype == np.bool_ or not (
        np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)
    ):
        raise DataFormatError(path, f"expected a real-valued (float or integer) depth map, got dtype {depth.dtype}")
    depth = depth.astype(np.float64)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise DataFormatError(path, f"expected a 2-D depth map, got shape {depth.shape}")
    depth = np.where(np.isfinite(depth), depth, 0.0)
    return depth
