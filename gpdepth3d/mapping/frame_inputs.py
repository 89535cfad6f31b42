"""Checks and resizing of what `Mapper.add_frame` is given: keyframe ids, map point sigmas, MDE depth maps."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..camera import PinholeCamera
from ..errors import InvalidInputError, ShapeError, describe


def resize_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resizes a depth map (nearest for shrinking keeps no mixed depths; linear when growing)."""
    import cv2

    if depth.shape == tuple(shape):
        return depth
    interp = cv2.INTER_NEAREST if shape[0] < depth.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(depth.astype(np.float32), (shape[1], shape[0]), interpolation=interp).astype(np.float64)


def check_keyframe_id(value: Any) -> int:
    """A keyframe id as an int; a bool, a string, NaN or a fraction raise `InvalidInputError`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError("keyframe_id", "an integer", value)
    if isinstance(value, int) and not -(2**63) <= value < 2**63:  # beyond int64 (numpy cannot hold it)
        raise InvalidInputError("keyframe_id", "an integer within int64 (|id| < 2**63)", value)
    if not np.isfinite(value) or int(value) != value or not -(2**63) <= int(value) < 2**63:
        raise InvalidInputError("keyframe_id", "an integer within int64 (|id| < 2**63)", value)
    return int(value)


def check_map_points_sigma(value: Any) -> np.ndarray:
    """Map point sigma(s) as float64 (a number or (N,) numbers, finite, > 0 metres) or `InvalidInputError`."""
    try:
        sigma = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(
            "map_points_sigma", "depth sigma(s) in metres: a number or (N,) numbers", value
        ) from None
    if sigma.ndim > 1 or not np.all(np.isfinite(sigma)) or not np.all(sigma > 0):
        raise InvalidInputError(
            "map_points_sigma", "finite depth sigma(s) > 0 metres, a number or (N,)", describe(sigma)
        )
    return sigma


def check_mde_depth(mde_depth: Any, camera: PinholeCamera) -> np.ndarray:
    """An MDE depth map as float64 (h, w), any resolution with ``camera``'s aspect ratio (1 %), or `ShapeError`."""
    mde_depth = np.asarray(mde_depth, dtype=np.float64)
    if mde_depth.ndim != 2 or min(mde_depth.shape) < 2:
        raise ShapeError("mde_depth", "a 2-D (h, w) depth map", describe(mde_depth))
    h, w = mde_depth.shape
    if abs((w / h) / (camera.width / camera.height) - 1) > 0.01:
        raise ShapeError(
            "mde_depth", f"a depth map with the aspect ratio of the {camera.width}x{camera.height} image", (h, w)
        )
    return mde_depth
