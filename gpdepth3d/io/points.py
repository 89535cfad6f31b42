"""Sparse point lists: ``.npz`` with ``u``, ``v``, ``depth`` (and optional ``sigma``), or a text file
with one ``u v depth [sigma]`` per line (pixels, metres)."""

from __future__ import annotations

import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, GPDepthError, InvalidDepthError, ShapeError
from ..measurements import SparseDepth
from .arrays import _as_path, check_stored_array
from .depth import KITTI_PNG_SCALE, load_depth


def load_sparse(
    path: str | Path,
    image_size: tuple[int, int] | None = None,
    *,
    png_scale: float = KITTI_PNG_SCALE,
    drop_invalid: bool = False,
) -> SparseDepth:
    """Reads sparse measurements from a point list (``.npz`` u/v/depth, ``.txt``) or a sparse depth map.

    Args:
        path: The file.
        image_size: (height, width) the point coordinates refer to; required for point lists,
            taken from the map for depth images.
        png_scale: Metres per PNG unit for 16-bit PNG depth maps.
        drop_invalid: Point lists: drop rows with a NaN/inf/negative/zero depth, a non-finite
            coordinate or a pixel outside the image, with a warning that gives their count. By
            default such rows raise `InvalidDepthError` with the count.

    Raises:
        DataFormatError: missing, unknown or corrupt files.
        InvalidDepthError: invalid rows in a point list (unless ``drop_invalid``).
        ShapeError: a point list without ``image_size``.
    """
    path = _as_path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                if {"u", "v", "depth"} <= set(data.keys()):
                    if image_size is None:
                        raise ShapeError("image_size", "(height, width) for a point list", None)
                    for member in ("u", "v", "depth", "sigma"):
                        if member in data:
                            check_stored_array(path, member)
                    sigma = data["sigma"] if "sigma" in data else None
                    return _points(path, data["u"], data["v"], data["depth"], image_size, sigma, drop_invalid)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            if isinstance(exc, GPDepthError):
                raise
            raise DataFormatError(path, f"corrupt or unreadable point list: {exc}") from None
    if suffix in (".txt", ".csv"):
        if image_size is None:
            raise ShapeError("image_size", "(height, width) for a point list", None)
        try:
            table = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=2)
        except (ValueError, UnicodeDecodeError) as exc:
            raise DataFormatError(path, f"expected lines 'u v depth [sigma]': {exc}") from None
        if table.shape[0] == 0:
            return SparseDepth.empty(image_size)
        if table.shape[1] not in (3, 4):
            raise DataFormatError(path, f"expected 3 or 4 columns (u v depth [sigma]), got {table.shape[1]}")
        sigma = table[:, 3] if table.shape[1] == 4 else None
        return _points(path, table[:, 0], table[:, 1], table[:, 2], image_size, sigma, drop_invalid)
    depth = load_depth(path, png_scale=png_scale)
    sparse = SparseDepth.from_depth_map(depth)
    if image_size is not None and tuple(image_size) != sparse.image_size:
        raise ShapeError("image_size", f"the size of the sparse map {sparse.image_size}", tuple(image_size))
    return sparse


def _points(path: Path, u, v, depth, image_size, sigma, drop_invalid: bool) -> SparseDepth:
    """Point-list rows as `SparseDepth`: invalid rows raise with their count, or are dropped with a warning."""
    arrays = []
    for name, a in (("u", u), ("v", v), ("depth", depth)) + ((("sigma", sigma),) if sigma is not None else ()):
        a = np.asarray(a)
        if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise DataFormatError(path, f"'{name}' must be real numbers, got dtype {a.dtype}")
        arrays.append(a.astype(np.float64).ravel())
    u, v, d = arrays[:3]
    if not (u.shape == v.shape == d.shape):
        raise DataFormatError(path, f"u, v, depth of different lengths {u.shape[0]}, {v.shape[0]}, {d.shape[0]}")
    full = SparseDepth.from_arrays(u, v, d, image_size, arrays[3] if sigma is not None else None)
    dropped = d.shape[0] - len(full)
    if dropped:
        h, w = full.image_size
        with np.errstate(invalid="ignore"):
            bad_depth = int(np.sum(~(np.isfinite(d) & (d > 0))))
        what = f"{dropped} of {d.shape[0]} rows ({bad_depth} with a NaN/inf/<= 0 depth, the others outside the {w}x{h} image)"
        if not drop_invalid:
            raise InvalidDepthError(
                f"{path}", "finite depths > 0 at pixels inside the image (or drop_invalid=True)", what + " invalid"
            )
        warnings.warn(f"{path}: dropped {what}", stacklevel=3)
    return full
