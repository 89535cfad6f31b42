"""Array helpers on (H, W) maps: fill holes from the nearest valid pixel, resize a map.

The one implementation of each; the layers above (completion, mapping, experiments, viewer)
call these rather than their own copies.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .errors import EmptyInputError, InvalidInputError, ShapeError, describe

Interpolation = Literal["nearest", "linear", "area", "cubic"]
INTERPOLATIONS: tuple[str, ...] = ("nearest", "linear", "area", "cubic")
"""Names accepted by `resize_map` (OpenCV's INTER_NEAREST, INTER_LINEAR, INTER_AREA, INTER_CUBIC)."""


def fill_nearest(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fills every invalid pixel with the value of the nearest valid pixel (Euclidean distance).

    Args:
        values: (H, W) map of any dtype (e.g. depth in metres).
        valid: (H, W) boolean mask of the pixels whose value is kept.

    Returns:
        ``values`` itself when every pixel is valid, else a new (H, W) map equal to ``values``
        at the valid pixels and to the nearest valid pixel's value elsewhere (ties broken as
        `scipy.ndimage.distance_transform_edt` breaks them).

    Raises:
        ShapeError: ``values`` is not 2-D or ``valid`` has another shape.
        EmptyInputError: no pixel is valid.
    """
    values = np.asarray(values)
    valid = np.asarray(valid, dtype=bool)
    if values.ndim != 2:
        raise ShapeError("values", "an (H, W) map", describe(values))
    if valid.shape != values.shape:
        raise ShapeError("valid", f"a mask of the shape of values {values.shape}", describe(valid))
    if valid.all():
        return values
    if not valid.any():
        raise EmptyInputError("valid", "at least one valid pixel to fill from", 0)
    from scipy.ndimage import distance_transform_edt

    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    return values[ri, ci]


def resize_map(
    image: np.ndarray, shape: tuple[int, int], *, shrink: Interpolation = "linear", grow: Interpolation = "linear"
) -> np.ndarray:
    """Resizes an (H, W) or (H, W, C) map to ``shape`` = (rows, cols) with OpenCV.

    ``shrink`` is used when the map loses rows (``shape[0] < H``), ``grow`` otherwise; e.g.
    ``shrink="area", grow="linear"`` for images, ``shrink="nearest"`` for a depth map that must
    not mix depths across edges, ``"nearest"`` for both for masks and label maps.

    Args:
        image: (H, W) or (H, W, C) array (dtype kept: OpenCV's, e.g. uint8, float32, float64).
        shape: (rows, cols) of the result, each >= 1.
        shrink: Interpolation (`INTERPOLATIONS`) when the map gets fewer rows.
        grow: Interpolation when it keeps or gains rows.

    Returns:
        ``image`` itself when it already has ``shape``, else the resized array.

    Raises:
        ShapeError: ``image`` is not 2-D/3-D or ``shape`` is not two integers >= 1.
        InvalidInputError: an unknown interpolation name.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ShapeError("image", "an (H, W) or (H, W, C) map", describe(image))
    if (
        isinstance(shape, (str, bytes))
        or not hasattr(shape, "__len__")
        or len(shape) != 2
        or any(isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) or s < 1 for s in shape)
    ):
        raise ShapeError("shape", "(rows, cols): two integers >= 1", describe(shape))
    for name, value in (("shrink", shrink), ("grow", grow)):
        if value not in INTERPOLATIONS:
            raise InvalidInputError(name, f"one of {INTERPOLATIONS}", value)
    rows, cols = int(shape[0]), int(shape[1])
    if image.shape[:2] == (rows, cols):
        return image
    import cv2

    flags = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "area": cv2.INTER_AREA, "cubic": cv2.INTER_CUBIC}
    interp = flags[shrink if rows < image.shape[0] else grow]
    return cv2.resize(image, (cols, rows), interpolation=interp)
