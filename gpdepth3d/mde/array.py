"""Front-ends for precomputed depth: an in-memory map or a folder of depth files."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DataFormatError, InvalidInputError, describe
from .base import check_rgb, finish_depth


class ArrayMDE:
    """Returns a fixed, precomputed depth map (resized to the image) for any image.

    Useful to evaluate a depth map computed elsewhere or to feed a degraded ground truth.

    Args:
        depth: (h, w) depth in metres (0/NaN = none).
    """

    def __init__(self, depth: np.ndarray):
        d = np.asarray(depth, dtype=np.float64)
        if d.ndim != 2 or d.shape[0] < 2 or d.shape[1] < 2:
            raise InvalidInputError("depth", "a 2-D (h, w) depth map", describe(d))
        self.depth = d

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) depth in metres for an (H, W, 3) uint8 image."""
        rgb = check_rgb(rgb)
        return finish_depth(self.depth, rgb.shape[:2])


class FileMDE:
    """Reads precomputed depth maps from files, one per frame.

    Use `predict` with a frame name, or set ``current`` before calling the object (the
    protocol call takes only the image).

    Args:
        folder: Folder holding the depth files.
        pattern: File name pattern with ``{name}`` (for example ``"{name}.npy"``).
        loader: Function path -> (h, w) depth in metres; default `gpdepth3d.io.load_depth`.
    """

    def __init__(
        self, folder: str | Path, *, pattern: str = "{name}.npy", loader: Callable[[Path], np.ndarray] | None = None
    ):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DataFormatError(self.folder, "depth folder not found")
        if "{name}" not in pattern:
            raise InvalidInputError("pattern", "a file name pattern containing '{name}'", pattern)
        self.pattern = pattern
        if loader is None:
            from ..io import load_depth

            loader = load_depth
        self.loader = loader
        self.current: str | None = None

    def predict(self, rgb: np.ndarray, name: str) -> np.ndarray:
        """(H, W) depth (metres) stored for frame ``name``, resized to the image."""
        rgb = check_rgb(rgb)
        return finish_depth(self.loader(self.folder / self.pattern.format(name=name)), rgb.shape[:2])

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        if self.current is None:
            raise InvalidInputError("FileMDE.current", "the name of the frame to read (set it first)", None)
        return self.predict(rgb, self.current)
