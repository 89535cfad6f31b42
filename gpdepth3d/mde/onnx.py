"""ONNX front-ends: any single-image depth network exported to ONNX, and RT-MonoDepth-S.

`ONNXDepthModel` runs a network with one float32 NCHW RGB input and one depth-like output on
onnxruntime (the CUDA execution provider first when onnxruntime reports it, else the CPU).
What the output means is an option (``output``):

* ``"depth"``: the output is depth; metres = output x ``depth_factor``.
* ``"disparity"``: the output is inverse depth; metres = ``depth_factor`` / output.
* ``"sigmoid_disparity"``: monodepth2's convention. The output d in [0, 1] is mapped to
  s = ``min_disp`` + (``max_disp`` - ``min_disp``) d, s is resized bilinearly to the image
  size and metres = ``depth_factor`` / s.

`RTMonoDepthONNX` is the preset for RT-MonoDepth-S (Feng et al., ICIP 2024; monodepth2 family),
trained self-supervised on KITTI raw at 640x192: ``min_disp = 0.01``, ``max_disp = 10``
(monodepth2's ``disp_to_depth`` with depths 0.1 ... 100) and ``depth_factor = 5.4`` (monodepth2's
stereo scale factor) for the mono+stereo model ``rtmonodepth_s_ms_640_192.onnx``, which is metric.
The mono-only model ``rtmonodepth_s_m_640_192.onnx`` has no metric scale: ``metric=False`` returns
1 / s, relative depth to be scaled per frame (`gpdepth3d.mde.align_depth`, or the residual GP's
``align``; on kitti_tiny the factor is about 15.6).

onnxruntime is imported only when a front-end is built.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from ..errors import DataFormatError, InvalidInputError
from .base import check_rgb, finish_depth

OutputKind = Literal["depth", "disparity", "sigmoid_disparity"]

RTMONODEPTH_FILES: dict[bool, str] = {True: "rtmonodepth_s_ms_640_192.onnx", False: "rtmonodepth_s_m_640_192.onnx"}
"""File names of RT-MonoDepth-S by ``metric``: mono+stereo (metric) and mono-only (relative)."""

KNOWN_SHA256: dict[str, tuple[str, bool]] = {
    "b50dda5598fcaceed39ae7f80a1ecf62ea94b2c6a62081d31157be7571d0aed0": ("rtmonodepth_s_ms_640_192", True),
    "9bb865f6af08d72a22457f613e6cc9d750b6349f5fca370c2ed3ec1e86d80610": ("rtmonodepth_s_m_640_192", False),
}
"""sha256 of the published RT-MonoDepth-S exports -> (name, has metric scale)."""

MONODEPTH2_STEREO_SCALE = 5.4
"""Metres per unit of monodepth2-family depth trained with stereo pairs (KITTI baseline 0.54 m x 10)."""


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def default_providers() -> list[str]:
    """onnxruntime execution providers to use: CUDA first when available, always the CPU last."""
    import onnxruntime

    available = onnxruntime.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]


class ONNXDepthModel:
    """A single-image depth network run from an ONNX file with onnxruntime.

    Pre-processing: the whole RGB image is resized to the network input (h, w) (area averaging
    when shrinking, bilinear when enlarging; aspect ratio not kept, no crop), scaled to [0, 1]
    (``input_divisor``) and fed as float32 (1, 3, h, w). Any mean/std normalisation must be inside
    the graph. Post-processing: see the module docstring (``output``); the map is resized to the
    image size (H, W) bilinearly and non-finite or negative values become 0.

    Args:
        model_path: The ``.onnx`` file.
        output: What the network outputs: "depth", "disparity" or "sigmoid_disparity".
        depth_factor: Metres per output unit ("depth"), or the numerator of the inversion
            ("disparity", "sigmoid_disparity").
        min_disp: "sigmoid_disparity": the disparity of output 0.
        max_disp: "sigmoid_disparity": the disparity of output 1.
        input_size: (h, w) of the network input; required only when the graph's input size is
            dynamic, else it must match the graph.
        input_divisor: The uint8 values are divided by this (255 gives [0, 1]).
        providers: onnxruntime execution providers (default `default_providers`: CUDA first
            when onnxruntime has it, then the CPU).
        num_threads: CPU threads of the session (None = onnxruntime's default).

    Raises:
        DataFormatError: if the file is missing, not a loadable ONNX model, or its graph does not
            have one float (1, 3, h, w) input and one (1, h, w) / (1, 1, h, w) output.
        InvalidInputError: on a bad option (named in the message).
    """

    def __init__(
        self,
        model_path: str | Path,
        *,
        output: OutputKind = "depth",
        depth_factor: float = 1.0,
        min_disp: float = 0.01,
        max_disp: float = 10.0,
        input_size: tuple[int, int] | None = None,
        input_divisor: float = 255.0,
        providers: Sequence[str] | None = None,
        num_threads: int | None = None,
    ):
        import onnxruntime

        self.model_path = Path(model_path)
        if output not in ("depth", "disparity", "sigmoid_disparity"):
            raise InvalidInputError("output", "'depth', 'disparity' or 'sigmoid_disparity'", output)
        for name, value in (("depth_factor", depth_factor), ("input_divisor", input_divisor)):
            if not np.isfinite(value) or value <= 0:
                raise InvalidInputError(name, "a finite value > 0", value)
        if output == "sigmoid_disparity" and not (
            np.isfinite(min_disp) and np.isfinite(max_disp) and 0 < min_disp < max_disp
        ):
            raise InvalidInputError("min_disp, max_disp", "0 < min_disp < max_disp", (min_disp, max_disp))
        if num_threads is not None and (int(num_threads) != num_threads or num_threads < 1):
            raise InvalidInputError("num_threads", "None or an integer >= 1", num_threads)
        if not self.model_path.is_file():
            raise DataFormatError(self.model_path, "ONNX model file not found")
        self.output, self.depth_factor = output, float(depth_factor)
        self.min_disp, self.max_disp, self.input_divisor = float(min_disp), float(max_disp), float(input_divisor)
        options = onnxruntime.SessionOptions()
        if num_threads is not None:
            options.intra_op_num_threads = int(num_threads)
        self.providers = list(providers) if providers is not None else default_providers()
        try:
            self.session = onnxruntime.InferenceSession(str(self.model_path), options, providers=self.providers)
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/InvalidProtobuf types
            raise DataFormatError(self.model_path, f"not a loadable ONNX model: {exc}") from None
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(outputs) != 1:
            raise DataFormatError(
                self.model_path, f"expected one input and one output, got {len(inputs)} and {len(outputs)}"
            )
        inp, out = inputs[0], outputs[0]
        if inp.type != "tensor(float)":
            raise DataFormatError(self.model_path, f"expected a float32 input tensor, got {inp.type}")
        shape = list(inp.shape)
        if len(shape) != 4 or shape[1] != 3 or (isinstance(shape[0], int) and shape[0] != 1):
            raise DataFormatError(self.model_path, f"expected an input (1, 3, h, w), got {tuple(shape)}")
        graph_hw = tuple(int(s) if isinstance(s, int) else None for s in shape[2:])
        if input_size is not None:
            size = tuple(int(s) for s in input_size)
            if len(size) != 2 or min(size) < 2 or any(g is not None and g != s for g, s in zip(graph_hw, size)):
                raise InvalidInputError("input_size", f"(h, w) matching the graph's input {graph_hw}", input_size)
            self.input_size: tuple[int, int] = size  # type: ignore[assignment]
        elif None in graph_hw:
            raise InvalidInputError("input_size", f"(h, w): the graph's input size is dynamic {graph_hw}", None)
        else:
            self.input_size = graph_hw  # type: ignore[assignment]
        oshape = list(out.shape)
        if len(oshape) not in (3, 4) or (len(oshape) == 4 and isinstance(oshape[1], int) and oshape[1] != 1):
            raise DataFormatError(self.model_path, f"expected an output (1, h, w) or (1, 1, h, w), got {tuple(oshape)}")
        self.input_name, self.output_name = inp.name, out.name

    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """The network input of an (H, W, 3) uint8 RGB image: float32 (1, 3, h, w)."""
        import cv2

        rgb = check_rgb(rgb)
        h, w = self.input_size
        shrink = rgb.shape[0] > h or rgb.shape[1] > w
        x = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        return np.ascontiguousarray((x.astype(np.float32) / np.float32(self.input_divisor)).transpose(2, 0, 1)[None])

    def predict_raw(self, rgb: np.ndarray) -> np.ndarray:
        """The network's output map at its own resolution, (h, w) float32, no conversion."""
        (out,) = self.session.run([self.output_name], {self.input_name: self.preprocess(rgb)})
        out = np.asarray(out, dtype=np.float32)
        return out.reshape(out.shape[-2], out.shape[-1])

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) float64 depth for an (H, W, 3) uint8 RGB image (metres, or relative; 0 = invalid)."""
        import cv2

        rgb = check_rgb(rgb)
        shape = rgb.shape[:2]
        raw = self.predict_raw(rgb)
        if self.output == "depth":
            return finish_depth(raw.astype(np.float64) * self.depth_factor, shape)
        if self.output == "sigmoid_disparity":
            s = self.min_disp + (self.max_disp - self.min_disp) * raw.astype(np.float64)
        else:
            s = raw.astype(np.float64)
        if s.shape != shape:
            s = cv2.resize(s, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(s > 0, self.depth_factor / s, 0.0)
        depth[~np.isfinite(depth)] = 0.0  # float64 throughout (finish_depth would round to float32)
        return depth


class RTMonoDepthONNX(ONNXDepthModel):
    """RT-MonoDepth-S (KITTI, 640x192) with monodepth2's conversion to depth.

    depth = f / (0.01 + 9.99 d) with the network's sigmoid disparity d resized to the image size
    (as s, before the inversion); f = 5.4 m for the mono+stereo model (metric depth, the default),
    f = 1 with ``metric=False`` (relative depth without metric scale: the mono-only model; align
    it to measurements before use). Trained on KITTI street scenes: indoor images get street-range
    depths.

    Args:
        model_path: The ``.onnx`` file; default: ``RTMONODEPTH_FILES[metric]`` in ``models_dir``.
        metric: True: the mono+stereo model, metres. False: relative depth (mono-only model).
        models_dir: Folder of the default file (default: `gpdepth3d.mde.default_models_dir`).
        providers: onnxruntime execution providers (default: CUDA when available, then CPU).
        num_threads: CPU threads of the session.

    Raises:
        InvalidInputError: ``metric=True`` with the published mono-only model (recognised by its
            sha256), which has no metric scale.
        DataFormatError: see `ONNXDepthModel`.
    """

    def __init__(
        self,
        model_path: str | Path | None = None,
        *,
        metric: bool = True,
        models_dir: str | Path | None = None,
        providers: Sequence[str] | None = None,
        num_threads: int | None = None,
    ):
        if model_path is None:
            from .base import default_models_dir

            model_path = Path(models_dir) if models_dir is not None else default_models_dir()
            model_path = model_path / RTMONODEPTH_FILES[bool(metric)]
        path = Path(model_path)
        if metric and path.is_file():
            known = KNOWN_SHA256.get(file_sha256(path))
            if known is not None and not known[1]:
                raise InvalidInputError(
                    "metric", f"False for {known[0]} (trained on monocular video only: no metric scale)", metric
                )
        self.metric = bool(metric)
        super().__init__(
            path,
            output="sigmoid_disparity",
            depth_factor=MONODEPTH2_STEREO_SCALE if metric else 1.0,
            min_disp=0.01,
            max_disp=10.0,
            providers=providers,
            num_threads=num_threads,
        )
