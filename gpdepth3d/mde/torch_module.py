"""Torch front-end: wraps any ``torch.nn.Module`` depth network loaded from a local checkpoint.

Nothing is downloaded: the caller builds the network and loads its weights. How to plug in two
common models on a machine that has their code and weights:

**monodepth2** (Godard et al. 2019; outputs a sigmoid disparity; relative scale for the mono
models, metric-ish for the stereo ones)::

    import torch, networks                        # from the monodepth2 repository
    enc = networks.ResnetEncoder(18, False); dec = networks.DepthDecoder(enc.num_ch_enc, range(4))
    enc_sd = torch.load("mono_640x192/encoder.pth", map_location="cpu")
    enc.load_state_dict({k: v for k, v in enc_sd.items() if k in enc.state_dict()})
    dec.load_state_dict(torch.load("mono_640x192/depth.pth", map_location="cpu"))

    class Mono2(torch.nn.Module):
        def __init__(self):
            super().__init__(); self.enc, self.dec = enc, dec
        def forward(self, x):                       # x: (1, 3, 192, 640) in 0..1
            disp = self.dec(self.enc(x))[("disp", 0)]
            return 1 / 100 + (1 / 0.1 - 1 / 100) * disp   # monodepth2's disp_to_depth -> 1/depth

    mde = TorchModuleMDE(Mono2(), preprocess=resize_preprocess((192, 640)), output="inverse")

**Depth Anything V2** (relative, affine-invariant disparity; metric variants output metres)::

    from depth_anything_v2.dpt import DepthAnythingV2   # from the Depth-Anything-V2 repository
    net = DepthAnythingV2(encoder="vits", features=64, out_channels=[48, 96, 192, 384])
    net.load_state_dict(torch.load("depth_anything_v2_vits.pth", map_location="cpu"))
    mde = TorchModuleMDE(net, preprocess=resize_preprocess((518, 518), mean=IMAGENET_MEAN,
                         std=IMAGENET_STD, multiple_of=14), output="disparity")
    # a metric checkpoint (depth_anything_v2_metric_hypersim_vits.pth, max_depth=20) uses output="depth"

Relative outputs ("inverse" up to scale, "disparity") must be aligned to metric measurements
before use: `gpdepth3d.mde.align_to_sparse(depth, sparse, mode="scale_shift", space="inverse")`
(or the residual GP's ``align`` option for a scale).
"""

from __future__ import annotations

from typing import Any, Callable, Literal

import numpy as np

from ..errors import InvalidInputError
from .base import check_rgb, finish_depth

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
OutputKind = Literal["depth", "inverse", "disparity"]


def resize_preprocess(
    size: tuple[int, int] | None = None,
    *,
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0),
    std: tuple[float, float, float] = (1.0, 1.0, 1.0),
    multiple_of: int = 1,
) -> Callable[[np.ndarray], Any]:
    """A pre-processing function rgb (H, W, 3) uint8 -> float32 tensor (1, 3, h, w).

    The image is resized (bilinear) to ``size`` = (h, w) (None keeps it), each side rounded to a
    multiple of ``multiple_of`` (ViT patch size), scaled to 0..1 and normalised with mean/std.
    """
    if size is not None and (len(size) != 2 or min(size) < 1):
        raise InvalidInputError("size", "(height, width) with positive sizes, or None", size)
    if int(multiple_of) < 1:
        raise InvalidInputError("multiple_of", "an integer >= 1", multiple_of)
    m = np.asarray(mean, dtype=np.float32).reshape(1, 1, 3)
    s = np.asarray(std, dtype=np.float32).reshape(1, 1, 3)

    def preprocess(rgb: np.ndarray):
        import cv2
        import torch

        h, w = rgb.shape[:2] if size is None else size
        h = max(multiple_of, int(round(h / multiple_of)) * multiple_of)
        w = max(multiple_of, int(round(w / multiple_of)) * multiple_of)
        x = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR) if (h, w) != rgb.shape[:2] else rgb
        x = (x.astype(np.float32) / 255.0 - m) / s
        return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None]

    return preprocess


class TorchModuleMDE:
    """Runs a ``torch.nn.Module`` as an MDE front-end (see the module docstring for examples).

    Args:
        module: The network, weights already loaded; put in eval mode and moved to ``device``.
        preprocess: rgb (H, W, 3) uint8 -> input tensor (1, 3, h, w) (see `resize_preprocess`).
        output: What the network returns: "depth" (metres), "inverse" (1/depth, 1/m: the
            result is 1/output) or "disparity" (affine-invariant disparity, relative: the result
            is 1/output and must be aligned to metric measurements).
        device: Torch device ("cpu", "cuda", ...).
        select: Picks the depth tensor out of the module's output (default: the output itself,
            or the first element of a tuple/list, or the only value of a dict).
        min_value: Outputs <= this are treated as invalid (depth 0) for "inverse"/"disparity".

    Call: (H, W, 3) uint8 RGB -> (H, W) float64 depth (metres, or relative units for
    "disparity"), 0 where the network gave no valid value.
    """

    def __init__(
        self,
        module: Any,
        *,
        preprocess: Callable[[np.ndarray], Any] | None = None,
        output: OutputKind = "depth",
        device: str = "cpu",
        select: Callable[[Any], Any] | None = None,
        min_value: float = 1e-6,
    ):
        import torch

        if not isinstance(module, torch.nn.Module):
            raise InvalidInputError("module", "a torch.nn.Module", type(module).__name__)
        if output not in ("depth", "inverse", "disparity"):
            raise InvalidInputError("output", "'depth', 'inverse' or 'disparity'", output)
        self.device = torch.device(device)
        self.module = module.eval().to(self.device)
        self.preprocess = preprocess or resize_preprocess()
        self.output = output
        self.select = select
        self.min_value = float(min_value)

    def _pick(self, out: Any):
        if self.select is not None:
            return self.select(out)
        if isinstance(out, (tuple, list)):
            return out[0]
        if isinstance(out, dict):
            if len(out) != 1:
                raise InvalidInputError(
                    "select", "a function picking the depth from the module's dict output", list(out)
                )
            return next(iter(out.values()))
        return out

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) depth for an (H, W, 3) uint8 RGB image (see the class docstring)."""
        import torch

        rgb = check_rgb(rgb)
        x = self.preprocess(rgb)
        if not isinstance(x, torch.Tensor):
            raise InvalidInputError("preprocess", "a function returning a torch.Tensor", type(x).__name__)
        with torch.no_grad():
            y = self._pick(self.module(x.to(self.device)))
        y = torch.as_tensor(y).detach().to("cpu", torch.float64).squeeze()
        if y.ndim != 2:
            raise InvalidInputError("module output", "one (h, w) map (after squeezing)", tuple(y.shape))
        pred = y.numpy()
        if self.output != "depth":
            with np.errstate(divide="ignore"):
                pred = np.where(pred > self.min_value, 1.0 / pred, 0.0)
        return finish_depth(pred, rgb.shape[:2])
