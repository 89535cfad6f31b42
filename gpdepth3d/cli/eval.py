"""``gpdepth3d eval``: protocols x densities x methods on a dataset folder; prints the summary table."""

from __future__ import annotations

import re
import time
from pathlib import Path

from ..errors import InvalidInputError
from ..evaluation.evaluation import DEFAULT_METHODS, markdown_table, run_evaluation
from ..io import check_output_folder, write_together


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def eval_command(
    data: Path,
    *,
    mde: str = "fastdepth",
    protocol: str = "uniform",
    points: str = "",
    output: Path = Path("eval_output"),
    frames: int | None = None,
    stride: int = 1,
    resolution: float = 0.5,
    methods: str = ",".join(DEFAULT_METHODS),
    seed: int = 0,
    device: str | None = None,
    qualitative: bool = True,
    progress: bool = True,
) -> list[dict]:
    """Evaluates depth completion on a dataset folder: prints a table, writes CSV/JSON/PNG.

    Args:
        data: Dataset folder (7scenes, kitti_tiny, kitti_object, ibims_sample, vio_sparse;
            the layout is detected).
        mde: Monocular front-end: "fastdepth" (TFLite FastDepth, indoor; the [tflite] extra),
            "rtmonodepth" (ONNX RT-MonoDepth-S, KITTI, metric), "rtmonodepth-mono" (its mono-only
            model: relative depth), a .tflite/.onnx model file, or "gt-degraded" (a blurred,
            mis-scaled ground truth; datasets with dense ground truth only). The named models are
            read from the models folder beside the data folder's parent (shared/models).
        protocol: Comma-separated protocols: uniform (N points), density (the paper's eight
            densities, shares of the available points), hband (lower half rows), vband (left
            half columns), scanlines (every k-th LiDAR beam; KITTI).
        points: Comma-separated levels, e.g. "50,200,500" (points), "0.0156,0.25" (density)
            or "1,2,4" (scan lines: keep every k-th beam); empty = the protocol's defaults.
        output: Output folder for results.csv, summary.csv, results.json, rmse_<protocol>.png,
            qualitative.png.
        frames: Use at most this many frames (after ``stride``).
        stride: Use every stride-th frame.
        resolution: Evaluation resolution relative to the images (0.5 = half).
        methods: Comma-separated methods from: mde, mde_scale, ip_basic, gp_default, gp_default_fit,
            gp_balanced, gp_balanced_fit, gp_residual, gp_residual_fit, gp_relative (default: all but
            gp_default_fit and gp_balanced_fit, which fit per frame and level).
        seed: Seed of the sampling.
        device: Torch device for the fast GP engine ("cuda"); default NumPy on the CPU.
        qualitative: Also draw the qualitative figure of the first frame.
        progress: Show the progress bar.

    Returns:
        The summary rows (one per protocol, level and method).
    """
    try:
        levels = [float(x) for x in _names(points)]
    except ValueError:
        raise InvalidInputError("points", "comma-separated numbers such as '50,200,500'", points) from None
    check_output_folder(Path(output), "--output")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InvalidInputError("--seed", "an integer >= 0", seed)
    if device is not None and not re.fullmatch(r"cpu|cuda(:\d+)?", device):
        raise InvalidInputError("--device", "cpu, cuda or cuda:N (default: NumPy on the CPU)", device)
    model = None
    if Path(mde).suffix.lower() in (".tflite", ".onnx"):  # a model file: its kind from the suffix
        model, mde = Path(mde), "fastdepth" if Path(mde).suffix.lower() == ".tflite" else "rtmonodepth"
    started = time.time()
    with write_together():  # all of eval's files appear together, or none (full disk, a failing plot)
        summary = run_evaluation(
            data,
            mde=mde,
            protocols=_names(protocol),
            levels=levels or None,
            output=output,
            frames=frames,
            stride=stride,
            resolution=resolution,
            methods=_names(methods),
            model=model,
            seed=seed,
            device=device,
            qualitative=qualitative,
            progress=progress,
        )
    print(markdown_table(summary))
    written = sorted(p for p in Path(output).iterdir() if p.is_file() and p.stat().st_mtime >= started - 1.0)
    print(f"wrote {len(written)} files in {Path(output).resolve()}: {', '.join(p.name for p in written)}")
    return summary
