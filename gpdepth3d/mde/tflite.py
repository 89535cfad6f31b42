"""TFLite front-end: FastDepth (Wofk et al., ICRA 2019) or any same-shaped TFLite depth network.

Needs the optional ``ai-edge-litert`` package (``pip install gpdepth3d[tflite]``); it is imported
only when a `FastDepthTFLite` is built.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import DataFormatError, InvalidInputError
from .base import check_rgb, finish_depth

TFLITE_EXTRA_HINT = "the TFLite front-end needs ai-edge-litert: pip install gpdepth3d[tflite]"


@contextlib.contextmanager
def _runtime_info_dropped() -> Iterator[None]:
    """Drops the runtime's "INFO: ..." lines (written by its C++ logger to file descriptor 2); keeps the rest."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded interpreters): nothing to filter
        yield
        return
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            kept = [
                line for line in caught.read().decode(errors="replace").splitlines() if not line.startswith("INFO:")
            ]
            if kept:
                print("\n".join(kept), file=sys.stderr)


def _interpreter_class():
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"{TFLITE_EXTRA_HINT} ({exc})") from exc
    return Interpreter


class FastDepthTFLite:
    """FastDepth (MobileNet + NNConv5, NYU-Depth-V2) run from an int8 TFLite file on the CPU.

    Pre-processing: the RGB image is resized (bilinear, aspect ratio not kept) to the network
    input (224x224) and fed as uint8 0..255. Post-processing: the quantised output is converted
    to metres with the output tensor's quantisation (``(q - zero_point) * scale``; for
    ``fast_depth_224.tflite`` scale = 0.0717 m, about 0..18 m) and resized back to (H, W).
    Trained indoors (NYU): outdoor scenes get indoor-range depths.

    Args:
        model_path: The ``.tflite`` file (for example ``../shared/models/fast_depth_224.tflite``).
        num_threads: CPU threads for the interpreter (None = every core this process may use;
            the runtime's own default is one thread; its timing: docs/results.md).
        output_scale: Metres per output unit; None takes it from the model's quantisation.

    Raises:
        DataFormatError: if the file is missing, not a TFLite model, or its tensors are not one
            uint8/float32 (1, h, w, 3) input and one (1, h, w[, 1]) output.
        ImportError: naming the ``tflite`` extra when ai-edge-litert is not installed.
    """

    training_intrinsics = (518.86, 519.47, 640, 480)
    """``(fx, fy, width, height)`` of the camera FastDepth was trained with (NYU-Depth-V2's Kinect colour camera),
    for `gpdepth3d.mapping.points.sfm_scale.focal_ratio`."""

    def __init__(self, model_path: str | Path, *, num_threads: int | None = None, output_scale: float | None = None):
        self.model_path = Path(model_path)
        if not self.model_path.is_file():
            raise DataFormatError(self.model_path, "TFLite model file not found")
        Interpreter = _interpreter_class()
        try:
            if num_threads is None:
                num_threads = (
                    len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
                )
            self.num_threads = int(num_threads)
            with _runtime_info_dropped():
                self._interp = Interpreter(model_path=str(self.model_path), num_threads=self.num_threads)
                self._interp.allocate_tensors()
        except (ValueError, RuntimeError) as exc:
            raise DataFormatError(self.model_path, f"not a loadable TFLite model: {exc}") from None
        inputs = self._interp.get_input_details()
        outputs = self._interp.get_output_details()
        if len(inputs) != 1 or len(outputs) != 1:
            raise DataFormatError(
                self.model_path, f"expected one input and one output tensor, got {len(inputs)} and {len(outputs)}"
            )
        self._in, self._out = inputs[0], outputs[0]
        ishape = tuple(int(x) for x in self._in["shape"])
        oshape = tuple(int(x) for x in self._out["shape"])
        if len(ishape) != 4 or ishape[0] != 1 or ishape[3] != 3:
            raise DataFormatError(self.model_path, f"expected an input tensor (1, h, w, 3), got {ishape}")
        if len(oshape) not in (3, 4) or oshape[0] != 1 or (len(oshape) == 4 and oshape[3] != 1):
            raise DataFormatError(self.model_path, f"expected an output tensor (1, h, w[, 1]), got {oshape}")
        if self._in["dtype"] not in (np.uint8, np.float32) or self._out["dtype"] not in (np.uint8, np.float32):
            raise DataFormatError(
                self.model_path,
                f"expected uint8 or float32 tensors, got {self._in['dtype'].__name__} -> {self._out['dtype'].__name__}",
            )
        self.input_size = (ishape[1], ishape[2])
        q_scale, q_zero = self._out.get("quantization", (0.0, 0))
        if output_scale is not None:
            if not np.isfinite(output_scale) or output_scale <= 0:
                raise InvalidInputError("output_scale", "metres per unit > 0", output_scale)
            self.output_scale, self.output_zero = float(output_scale), 0.0
        elif self._out["dtype"] == np.uint8:
            if not q_scale or q_scale <= 0:
                raise DataFormatError(self.model_path, "uint8 output without a quantisation scale: pass output_scale")
            self.output_scale, self.output_zero = float(q_scale), float(q_zero)
        else:
            self.output_scale, self.output_zero = 1.0, 0.0

    def predict_raw(self, rgb: np.ndarray) -> np.ndarray:
        """The network's depth at its own resolution (h, w), metres."""
        import cv2

        rgb = check_rgb(rgb)
        h, w = self.input_size
        x = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if rgb.shape[0] > h else cv2.INTER_LINEAR)
        if self._in["dtype"] == np.float32:
            x = x.astype(np.float32) / 255.0
        self._interp.set_tensor(self._in["index"], x[None])
        self._interp.invoke()
        out = self._interp.get_tensor(self._out["index"]).reshape(h, w).astype(np.float64)
        return (out - self.output_zero) * self.output_scale

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) depth in metres for an (H, W, 3) uint8 RGB image."""
        rgb = check_rgb(rgb)
        return finish_depth(self.predict_raw(rgb), rgb.shape[:2])
