"""Monocular depth front-ends and the alignment of relative depth to metric measurements.

Every front-end follows the `MDE` protocol: ``mde(rgb (H, W, 3) uint8) -> depth (H, W) metres``.
Heavy back-ends (TFLite, onnxruntime, torch) are imported only when their front-end is built.
Named presets of the real networks: `load_frontend` ("fastdepth", "rtmonodepth", ...).
"""

from pathlib import Path

from .align import AlignmentResult as AlignmentResult
from .align import align_depth as align_depth
from .align import align_to_sparse as align_to_sparse
from .array import ArrayMDE as ArrayMDE
from .array import FileMDE as FileMDE
from .base import MDE as MDE
from .base import check_rgb as check_rgb
from .base import default_models_dir as default_models_dir
from .onnx import ONNXDepthModel as ONNXDepthModel
from .onnx import RTMonoDepthONNX as RTMonoDepthONNX
from ..errors import DataFormatError, InvalidInputError, did_you_mean

FRONTENDS: dict[str, str] = {
    "fastdepth": "FastDepth (NYU, indoor), int8 TFLite fast_depth_224.tflite: metres",
    "rtmonodepth": "RT-MonoDepth-S mono+stereo (KITTI, outdoor), rtmonodepth_s_ms_640_192.onnx: metres",
    "rtmonodepth-mono": "RT-MonoDepth-S mono-only (KITTI), rtmonodepth_s_m_640_192.onnx: relative depth, no metric scale",
}
"""Names accepted by `load_frontend`, with what each is."""

FRONTEND_FILES: dict[str, str] = {
    "fastdepth": "fast_depth_224.tflite",
    "rtmonodepth": "rtmonodepth_s_ms_640_192.onnx",
    "rtmonodepth-mono": "rtmonodepth_s_m_640_192.onnx",
}
"""File name of each named front-end's model (in `default_models_dir`)."""


def load_frontend(
    name_or_path: "str | Path",
    *,
    models_dir: "str | Path | None" = None,
    num_threads: "int | None" = None,
    argument: str = "name_or_path",
):
    """A monocular front-end by preset name or model file.

    Args:
        name_or_path: A name of `FRONTENDS` ("fastdepth", "rtmonodepth", "rtmonodepth-mono"), or
            the path of a model file: ``.tflite`` -> `FastDepthTFLite`; ``.onnx`` ->
            `RTMonoDepthONNX` when the file is a published RT-MonoDepth-S export (recognised by its
            sha256; metric or not accordingly), else `ONNXDepthModel` with its output read as
            metres (build `ONNXDepthModel` yourself for disparity outputs).
        models_dir: Folder of the named models (default `default_models_dir`).
        num_threads: CPU threads of the runtime (None = its default).
        argument: The name errors give the front-end by (``"--mde"`` on the command line).

    Returns:
        A callable ``rgb (H, W, 3) uint8 -> depth (H, W)`` (metres; relative for "rtmonodepth-mono").

    Raises:
        InvalidInputError: an unknown name (neither a preset nor a .tflite/.onnx path).
        DataFormatError: the model file is missing or not loadable.
    """
    key = str(name_or_path).strip()
    if key.lower() in FRONTEND_FILES:
        key = key.lower()
        folder = Path(models_dir) if models_dir is not None else default_models_dir()
        path = folder / FRONTEND_FILES[key]
        if not path.is_file():
            raise DataFormatError(
                path, f"model of the {key!r} front-end not found (pass models_dir or set GPDEPTH3D_MODELS)"
            )
    else:
        path = Path(key)
        if path.suffix.lower() not in (".tflite", ".onnx"):
            raise InvalidInputError(
                argument,
                f"a front-end name from {sorted(FRONTENDS)} or a .tflite/.onnx file",
                f"{name_or_path}{did_you_mean(key.lower(), sorted(FRONTENDS))}",
            )
        if not path.is_file():
            raise DataFormatError(path, "model file not found")
    if path.suffix.lower() == ".tflite":
        from .tflite import FastDepthTFLite

        return FastDepthTFLite(path, num_threads=num_threads)
    from .onnx import KNOWN_SHA256, file_sha256

    known = KNOWN_SHA256.get(file_sha256(path))
    if key == "rtmonodepth-mono" or (known is not None and not known[1]):
        return RTMonoDepthONNX(path, metric=False, num_threads=num_threads)
    if key == "rtmonodepth" or known is not None:
        return RTMonoDepthONNX(path, metric=True, num_threads=num_threads)
    return ONNXDepthModel(path, output="depth", num_threads=num_threads)


def __getattr__(name: str):
    if name == "FastDepthTFLite":
        from .tflite import FastDepthTFLite

        return FastDepthTFLite
    if name in ("TorchModuleMDE", "resize_preprocess"):
        from . import torch_module

        return getattr(torch_module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
