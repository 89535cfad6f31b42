"""The monocular-depth front-end protocol and checks shared by every front-end.

A front-end is any callable ``mde(rgb) -> depth``: ``rgb`` is an (H, W, 3) uint8 RGB image and
``depth`` an (H, W) float64 z-depth map in metres (0 = no depth) of the same size. Front-ends
that predict relative depth (inverse depth, disparity, affine-invariant depth) return it in
their own units; align them to metric measurements with `gpdepth3d.mde.align_depth` (the
residual formulation does this itself, see ``DepthGPConfig.align``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..errors import InvalidInputError, ShapeError, describe


@runtime_checkable
class MDE(Protocol):
    """A monocular depth estimator: ``__call__(rgb (H, W, 3) uint8) -> depth (H, W) float metres``."""

    def __call__(self, rgb: np.ndarray) -> np.ndarray: ...


def check_rgb(rgb: np.ndarray, argument: str = "rgb") -> np.ndarray:
    """Validates an (H, W, 3) uint8 RGB image and returns it as a C-contiguous array.

    Raises:
        ShapeError: if ``rgb`` is not (H, W, 3) with H, W >= 2.
        InvalidInputError: if its dtype is not uint8.
    """
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 2 or a.shape[1] < 2:
        raise ShapeError(argument, "an (H, W, 3) RGB image with H, W >= 2", describe(a))
    if a.dtype != np.uint8:
        raise InvalidInputError(argument, "dtype uint8 (0..255 RGB)", describe(a))
    return np.ascontiguousarray(a)


def finish_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resizes a predicted depth map to ``shape`` (bilinear) and marks non-finite/negative as 0.

    Args:
        depth: (h, w) predicted map.
        shape: (H, W) wanted output shape.

    Returns:
        (H, W) float64 depth, 0 where the prediction is invalid.
    """
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ShapeError("depth", "a 2-D predicted map", describe(d))
    if d.shape != tuple(shape):
        d = cv2.resize(d, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
    d = d.astype(np.float64)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def default_models_dir(near: str | Path | None = None) -> Path:
    """The folder of the real networks (the one rule for finding the model files).

    ``$GPDEPTH3D_MODELS`` when set; else the first existing of, with ``near`` (a data folder
    such as ``shared/data/7scenes``), ``<near>/../../models``, ``<near>/../models`` and
    ``<near>/models``, then ``../shared/models`` (from the working directory) and
    ``shared/models`` beside the repository (``<repo>/../shared/models``); the first candidate
    when none exists.

    Args:
        near: A data folder whose neighbourhood is searched first (None = skip).
    """
    env = os.environ.get("GPDEPTH3D_MODELS")
    if env:
        return Path(env)
    candidates = []
    if near is not None:
        near = Path(near)
        candidates += [near.parent.parent / "models", near.parent / "models", near / "models"]
    candidates += [Path.cwd().parent / "shared" / "models", Path(__file__).resolve().parents[3] / "shared" / "models"]
    for c in candidates:
        if c.is_dir():
            return c
    return candidates[0]
