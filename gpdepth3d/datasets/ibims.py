"""A single iBims-1 sample scene: image, dense laser-scan ground truth and given sparse samples."""

from __future__ import annotations

from pathlib import Path

from ..errors import DataFormatError
from ..io import load_depth, load_npz_arrays, load_rgb
from ..measurements import SparseDepth
from .base import DatasetReader, Frame


class IbimsSample(DatasetReader):
    """Reads ``image.png``, ``gt.npz`` (key ``depth``, metres, 0 = invalid) and ``sparse_<n>.npz``.

    The sparse files hold integer ``v``, ``u`` and ``depth``. No intrinsics are given (the
    frame's ``camera`` is None). One frame, named ``"image"``.

    Args:
        root: The folder.
        sparse_count: Which ``sparse_<n>.npz`` becomes ``Frame.sparse`` (None: none).
    """

    def __init__(self, root: str | Path, *, sparse_count: int | None = 100):
        super().__init__(root)
        self._require(self.root / "image.png", "image.png")
        self.names = ["image"]
        self.sparse_counts = sorted(
            int(p.stem.split("_")[1]) for p in self.root.glob("sparse_*.npz") if p.stem.split("_")[1].isdigit()
        )
        if sparse_count is not None and sparse_count not in self.sparse_counts:
            raise DataFormatError(self.root / f"sparse_{sparse_count}.npz", f"not found (have {self.sparse_counts})")
        self.sparse_count = sparse_count

    def load_sparse(self, count: int, image_size: tuple[int, int]) -> SparseDepth:
        """The given sparse samples ``sparse_<count>.npz`` as `SparseDepth`."""
        path = self._require(self.root / f"sparse_{count}.npz", "sparse samples")
        d = load_npz_arrays(path, ["u", "v", "depth"], "sparse samples (u, v, depth)")
        u, v, z = d["u"], d["v"], d["depth"]
        return SparseDepth.from_arrays(u, v, z, image_size)

    def load(self, name: str) -> Frame:
        """The scene (``name`` must be ``"image"``)."""
        if name != "image":
            raise DataFormatError(self.root / f"{name}.png", "the iBims sample has one frame, 'image'")
        rgb = load_rgb(self.root / "image.png")
        depth = load_depth(self._require(self.root / "gt.npz", "ground truth gt.npz"), key="depth")
        if depth.shape != rgb.shape[:2]:
            raise DataFormatError(self.root / "gt.npz", f"depth {depth.shape} != image {rgb.shape[:2]}")
        sparse = self.load_sparse(self.sparse_count, depth.shape) if self.sparse_count is not None else None
        return Frame(name=name, rgb=rgb, depth=depth, sparse=sparse)
