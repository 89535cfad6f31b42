"""The frame record every dataset reader yields, and the reader base class."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera import PinholeCamera
from ..errors import DataFormatError, InvalidInputError, describe
from ..limits import check_memory
from ..measurements import LidarCalibration, SparseDepth

RESIZED_BYTES_PER_PIXEL = 40
"""Peak bytes per pixel of `Frame.resized`: the image, the depth as float32 and float64, temporaries."""


@dataclass(frozen=True)
class Frame:
    """One image with what a dataset knows about it.

    Attributes:
        name: Frame name (file stem), unique within the dataset.
        rgb: (H, W, 3) uint8 RGB image.
        camera: Intrinsics of ``rgb`` (None when the dataset gives none, e.g. iBims sample).
        depth: (H, W) dense ground-truth z-depth in metres (0 = invalid), or None.
        sparse: Measurements the dataset provides (projected LiDAR, SLAM points, given
            samples) on the image grid, or None.
        pose: (4, 4) T_world_camera, or None.
        calibration: LiDAR-to-camera calibration the sparse points were projected with (KITTI),
            used by the scan-line protocol; None elsewhere.
        lidar: (N, 4) raw LiDAR points (x, y, z, reflectance) in the LiDAR frame, or None.
    """

    name: str
    rgb: np.ndarray
    camera: PinholeCamera | None = None
    depth: np.ndarray | None = None
    sparse: SparseDepth | None = None
    pose: np.ndarray | None = None
    calibration: LidarCalibration | None = None
    lidar: np.ndarray | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self.rgb.shape[:2]  # type: ignore[return-value]

    def resized(self, factor: float) -> "Frame":
        """The frame at ``factor`` times its resolution (0.5 = half).

        The image is resized with area averaging, the dense depth with nearest neighbour (no
        mixing of depths across edges, invalid pixels stay 0), sparse points are snapped to the
        new grid keeping the closest per pixel, intrinsics are rescaled. A LiDAR calibration
        (tied to the full-resolution projection) is dropped.
        """
        import cv2

        if (
            isinstance(factor, (bool, np.bool_))
            or not isinstance(factor, (int, float, np.integer, np.floating))
            or not np.isfinite(factor)
            or factor <= 0
        ):
            raise InvalidInputError("factor", "a resolution factor, a finite number > 0", describe(factor))
        if factor == 1:
            return self
        h, w = self.shape
        nh, nw = max(2, int(round(h * factor))), max(2, int(round(w * factor)))
        # the image (3 bytes), the depth (float32 and float64) and the resize's temporaries, per pixel
        check_memory(f"frame {self.name} resized {factor:g}x to shape {(nh, nw)}", RESIZED_BYTES_PER_PIXEL * nh * nw)
        rgb = cv2.resize(self.rgb, (nw, nh), interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
        depth = None
        if self.depth is not None:
            depth = cv2.resize(self.depth.astype(np.float32), (nw, nh), interpolation=cv2.INTER_NEAREST)
            depth = depth.astype(np.float64)
        return replace(
            self,
            rgb=rgb,
            depth=depth,
            camera=self.camera.resized(nw, nh) if self.camera is not None else None,
            sparse=self.sparse.rasterize((nh, nw)) if self.sparse is not None else None,
            calibration=None,
        )


class DatasetReader:
    """Base of the readers: a sized, indexable sequence of `Frame` read lazily from a folder.

    Subclasses set ``self.names`` (sorted frame names) in ``__init__`` and implement `load`.
    """

    root: Path
    names: list[str]

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataFormatError(self.root, "dataset folder not found")

    def load(self, name: str) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> Frame:
        """The frame at position ``index`` (negative from the end); `load` reads a frame by name.

        Raises:
            InvalidInputError: ``index`` is not an integer (a frame name: use `load`).
            IndexError: ``index`` is out of range.
        """
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            hint = f" (a frame name: use .load({index!r}))" if isinstance(index, str) else ""
            raise InvalidInputError("index", f"a frame position, an integer{hint}", describe(index))
        if not -len(self.names) <= index < len(self.names):
            raise IndexError(f"frame index {index} out of range for {len(self.names)} frames")
        return self.load(self.names[index])

    def __iter__(self) -> Iterator[Frame]:
        for name in self.names:
            yield self.load(name)

    def _require(self, path: Path, what: str) -> Path:
        if not path.is_file():
            raise DataFormatError(path, f"{what} not found")
        return path
