"""Classical depth-completion baseline: IP-Basic (sparse measurements only, no image, no MDE).

Written from the paper: J. Ku, A. Harakeh, S. L. Waslander, "In Defense of Classical Image
Processing: Fast Depth Completion on the CPU", CRV 2018 (arXiv:1802.00036). The algorithm is a
fixed sequence of OpenCV morphological operations on the sparse depth image:

1. invert valid depths, d' = D_max - d, so that dilation (a max filter) prefers *near* points
   over far ones (foreground occludes background) and empty pixels (0) lose to any point;
2. dilate with a 5x5 diamond kernel;
3. close small holes with a 5x5 full kernel;
4. fill remaining small holes (empty pixels only) by a 7x7 full-kernel dilation;
5. extend the top-most value of each column up to the top of the image (optional);
6. fill large holes (empty pixels only) by a 31x31 full-kernel dilation;
7. 5x5 median blur then 5x5 Gaussian blur, applied to filled pixels only;
8. invert back, d = D_max - d'.

Two additions for the very sparse case this project evaluates (tens to hundreds of points,
far sparser than KITTI's ~5 %): pixels still empty after step 6 get the depth of the nearest
filled pixel, so that the output is dense; and (``keep_measurements``) the measured depths are
written back at their pixels at the end, so a measurement is never changed by the filters.
"""

from __future__ import annotations

import numpy as np

from ..depthmap import fill_nearest
from ..errors import InvalidDepthError, InvalidInputError, ShapeError, describe
from ..measurements import SparseDepth

DIAMOND_5 = np.array(
    [[0, 0, 1, 0, 0], [0, 1, 1, 1, 0], [1, 1, 1, 1, 1], [0, 1, 1, 1, 0], [0, 0, 1, 0, 0]], dtype=np.uint8
)


def ip_basic(
    sparse: SparseDepth | np.ndarray,
    shape: tuple[int, int] | None = None,
    *,
    max_depth: float = 100.0,
    extend_top: bool = True,
    blur: bool = True,
    keep_measurements: bool = True,
) -> np.ndarray:
    """Dense depth from sparse depth by IP-Basic (see the module docstring).

    Args:
        sparse: Measurements (`SparseDepth`) or a sparse (H, W) depth map (metres, 0 = none).
        shape: (H, W) of the output for a `SparseDepth` (default: its image size; points are
            rasterised closest-first).
        max_depth: D_max of the inversion, metres; raised automatically above the deepest point.
        extend_top: Step 5 (extend column tops to the image top).
        blur: Step 7 (median and Gaussian blur).
        keep_measurements: Write the measured depths back at the end.

    Returns:
        (H, W) float64 dense depth, metres (all pixels > 0 when at least one point exists;
        all 0 when there is none).
    """
    import cv2

    if isinstance(sparse, SparseDepth):
        depth = sparse.to_depth_map(shape)
    else:
        depth = np.asarray(sparse, dtype=np.float64)
        if depth.ndim != 2 or depth.shape[0] < 2 or depth.shape[1] < 2:
            raise ShapeError("sparse", "a SparseDepth or a 2-D sparse depth map", describe(depth))
        if shape is not None and tuple(shape) != depth.shape:
            raise ShapeError("shape", f"None or the map's shape {depth.shape}", shape)
        depth = np.where(np.isfinite(depth), depth, 0.0)
        if np.any(depth < 0):
            raise InvalidDepthError("sparse", "depths >= 0 (0 = no measurement)", "negative values")
    if not np.isfinite(max_depth) or max_depth <= 0:
        raise InvalidInputError("max_depth", "a depth > 0 in metres", max_depth)
    measured = depth > 0
    if not measured.any():
        return np.zeros(depth.shape)
    d_max = max(float(max_depth), float(depth.max()) * 1.01 + 1e-3)

    inv = np.where(measured, d_max - depth, 0.0).astype(np.float32)
    inv = cv2.dilate(inv, DIAMOND_5)  # 2
    inv = cv2.morphologyEx(inv, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))  # 3
    empty = inv < 0.1 * 1e-3
    inv[empty] = cv2.dilate(inv, np.ones((7, 7), np.uint8))[empty]  # 4
    if extend_top:  # 5
        h, w = inv.shape
        has = inv > 0
        top = np.where(has.any(axis=0), has.argmax(axis=0), h)
        rows = np.arange(h)[:, None]
        cols = np.nonzero(top < h)[0]
        above = rows < top[None, :]
        for c in cols:
            inv[above[:, c], c] = inv[top[c], c]
    empty = inv <= 0
    inv[empty] = cv2.dilate(inv, np.ones((31, 31), np.uint8))[empty]  # 6
    empty = inv <= 0
    if empty.any():  # addition: nearest filled pixel
        inv = fill_nearest(inv, ~empty)
    if blur:  # 7
        med = cv2.medianBlur(inv, 5)
        inv = np.where(inv > 0, med, inv)
        gau = cv2.GaussianBlur(inv, (5, 5), 0)
        inv = np.where(inv > 0, gau, inv)
    out = d_max - inv.astype(np.float64)  # 8
    out = np.maximum(out, 1e-3)
    if keep_measurements:
        out[measured] = depth[measured]
    return out
