"""The exact city-block (L1, taxicab) distance transform of an image, compiled.

Every pixel's L1 distance to the nearest of some source pixels: the L1 distance is separable, min over sources of
|di| + |dj| = min over rows of (|di| + the row's 1-D distance), so a 1-D transform of every row (two sweeps) and
then of every column of the result (two sweeps) is exact. The outlier screen's incremental rounds (`gpdepth3d.gp.points`) and the
coverage warning (`gpdepth3d.completion.diagnostics`) use it.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..errors import InvalidInputError, ShapeError, describe


@nb.njit(cache=True, nogil=True)
def _transform(d):  # pragma: no cover - compiled
    """The transform in place over d (0 at the sources, a bound at least every distance elsewhere), one axis after
    the other (the L1 distance is separable): each row from the left and from the right, then each column down and
    up, row by row (those two sweeps run along the rows' contiguous pixels)."""
    height, width = d.shape
    for i in range(height):
        for j in range(1, width):
            d[i, j] = min(d[i, j], d[i, j - 1] + 1)
        for j in range(width - 2, -1, -1):
            d[i, j] = min(d[i, j], d[i, j + 1] + 1)
    for i in range(1, height):
        for j in range(width):
            d[i, j] = min(d[i, j], d[i - 1, j] + 1)
    for i in range(height - 2, -1, -1):
        for j in range(width):
            d[i, j] = min(d[i, j], d[i + 1, j] + 1)


def taxicab_transform(shape: tuple[int, int], rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Each pixel's L1 distance (pixels) to the nearest source pixel (rows[i], cols[i]).

    Args:
        shape: (H, W) of the image, both >= 1.
        rows, cols: (N,) integer pixel coordinates of the sources inside it (repeats allowed).

    Returns:
        (H, W) int64 distances; H + W everywhere when there is no source.

    Raises:
        InvalidInputError: a shape that is not two sizes >= 1.
        ShapeError: rows and cols of different lengths, or sources outside the image.
    """
    if len(shape) != 2 or min(int(s) for s in shape) < 1:
        raise InvalidInputError("shape", "(H, W) with H, W >= 1", describe(shape))
    h, w = int(shape[0]), int(shape[1])
    rows = np.asarray(rows, dtype=np.int64).ravel()
    cols = np.asarray(cols, dtype=np.int64).ravel()
    if rows.shape != cols.shape:
        raise ShapeError("rows, cols", "two (N,) arrays of the same length", f"{rows.shape}, {cols.shape}")
    if rows.size and (rows.min() < 0 or rows.max() >= h or cols.min() < 0 or cols.max() >= w):
        raise ShapeError("rows, cols", f"pixels of the {h} x {w} image", "sources outside it")
    d = np.full((h, w), h + w, dtype=np.int64)
    d[rows, cols] = 0
    _transform(d)
    return d
