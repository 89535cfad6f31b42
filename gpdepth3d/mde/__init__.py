"""Monocular depth front-ends and the alignment of relative depth to metric measurements.

Every front-end follows the `MDE` protocol: ``mde(rgb (H, W, 3) uint8) -> depth (H, W) metres``.
Heavy back-ends (TFLite, torch) are imported only when their front-end is built.
"""

from .align import AlignmentResult as AlignmentResult
from .align import align_depth as align_depth
from .align import align_to_sparse as align_to_sparse
from .array import ArrayMDE as ArrayMDE
from .array import FileMDE as FileMDE
from .base import MDE as MDE
from .base import check_rgb as check_rgb


def __getattr__(name: str):
    if name == "FastDepthTFLite":
        from .tflite import FastDepthTFLite

        return FastDepthTFLite
    if name in ("TorchModuleMDE", "resize_preprocess"):
        from . import torch_module

        return getattr(torch_module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
