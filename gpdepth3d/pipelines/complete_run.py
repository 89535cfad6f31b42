"""Complete one frame from files to files: what ``gpdepth3d complete`` runs between parsing and printing.

`plan_outputs` names and checks every output before any work; `run_complete` completes the frame
read by `gpdepth3d.completion.frame_inputs.read_frame_inputs`, scores it against its ground truth
and writes the posterior, its PNGs, its previews and its cloud as one set (`gpdepth3d.io.output_set`).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np

from ..completion.complete import DepthCompleter, DepthPosterior, PosteriorWarning
from ..completion.frame_inputs import FrameInputs
from ..errors import InvalidInputError, OutputError
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..io import PNGRangeWarning, check_output_path, output_set
from .previews import preview_paths, write_previews


@dataclass(frozen=True)
class OutputPlan:
    """The files of one completion: the posterior ``npz`` and what goes with it.

    Attributes:
        npz: The posterior file.
        png: Also its 16-bit mean and std PNGs.
        preview: Also its colourised previews.
        ply: The coloured cloud, or None.
    """

    npz: Path
    png: bool = True
    preview: bool = True
    ply: Optional[Path] = None

    @property
    def base(self) -> Path:
        """The npz without its suffix: the stem every other output is named after."""
        return self.npz.with_suffix("")

    def members(self) -> list[str]:
        """Every name the set may hold (those not written this time are removed in the same commit)."""
        names = [self.npz.name] + [self.npz.stem + s for s in ("_mean.png", "_std.png")]
        names += [p.name for p in preview_paths(self.base, with_error=True)]
        return names + ([self.ply.name] if self.ply is not None else [])


@dataclass
class CompleteOutcome:
    """What `run_complete` did: the posterior, its scores against the ground truth, the files written.

    Attributes:
        posterior: The depth posterior (``K`` set when intrinsics were known).
        metrics: "mde" and "gp" -> `gpdepth3d.metrics.depth_metrics`, or None without ground truth.
        calibration: `gpdepth3d.metrics.calibration_metrics` of the posterior, or None.
        written: The files written.
        warnings: One line each: the posterior's warnings and the PNG range warnings.
    """

    posterior: DepthPosterior
    metrics: Optional[dict] = None
    calibration: Optional[dict] = None
    written: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def output_npz(output: str | Path, source: Path) -> Path:
    """The posterior file of ``--output``: ``OUTPUT.npz``, or ``OUTPUT/<source stem>.npz`` for a folder.

    A folder is an existing one or a name ending in a path separator (``out/``).

    Raises:
        OutputError: an empty name or one that cannot be written.
    """
    text = os.fspath(output)
    if text.endswith(("/", os.sep)) or (text and Path(text).is_dir()):
        return check_output_path(Path(text) / f"{source.stem or 'completion'}.npz", "--output")
    return check_output_path(text, "--output").with_suffix(".npz")


def check_output_targets(paths: list[Path]) -> None:
    """Checks before any work that each output can be created: no directory in its place, a writable folder.

    Raises:
        OutputError: naming the first path that cannot be written.
    """
    for path in paths:
        check_output_path(path)
        folder = next((p for p in Path(path).absolute().parents if p.exists()), None)
        if folder is not None and not os.access(folder, os.W_OK | os.X_OK):
            raise OutputError(path, f"the folder {folder} is not writable")


def plan_outputs(
    output: str | Path,
    source: Path,
    *,
    png: bool = True,
    preview: bool = True,
    with_gt: bool = False,
    ply: Optional[Path] = None,
    can_backproject: bool = False,
) -> OutputPlan:
    """Names every output of a completion and checks that each can be written, before any work.

    Args:
        output: ``--output``: a file name (``.npz`` added) or a folder.
        source: The input the outputs are named after inside a folder (the image, else the MDE file).
        png: With the 16-bit PNGs. preview: With the previews. with_gt: With the error preview.
        ply: The cloud's file (``.ply``), or None.
        can_backproject: Intrinsics are known (--intrinsics, or --lidar with --calib): needed for ``ply``.

    Raises:
        OutputError: an output that cannot be written. InvalidInputError: a bad ``ply``.
    """
    npz = output_npz(output, Path(source))
    plan = OutputPlan(npz, png, preview, None)
    targets = [npz] + ([npz.with_name(npz.stem + s) for s in ("_mean.png", "_std.png")] if png else [])
    check_output_targets(targets + (preview_paths(plan.base, with_error=with_gt) if preview else []))
    if ply is None:
        return plan
    ply = check_output_path(ply, "--ply")
    if ply.suffix.lower() != ".ply":
        raise InvalidInputError("--ply", "a file name ending in .ply", str(ply))
    if not can_backproject:
        raise InvalidInputError(
            "--ply", "intrinsics to back-project with: --intrinsics K.txt, or --lidar with --calib", "neither"
        )
    check_output_targets([ply])
    return replace(plan, ply=ply)


def run_complete(
    inputs: FrameInputs,
    plan: OutputPlan,
    *,
    gp: DepthGPConfig = DepthGPConfig(),
    engine: EngineConfig = EngineConfig(),
    output_size: Optional[tuple[int, int]] = None,
) -> CompleteOutcome:
    """Completes a frame, scores it against its ground truth and writes its files as one set.

    Args:
        inputs: The frame (`read_frame_inputs`).
        plan: Its outputs (`plan_outputs`).
        gp: The GP. engine: How the posterior is computed.
        output_size: (H, W) of the output (default: the MDE's).

    Returns:
        The posterior, its metrics and the files written.
    """
    from ..completion.problem import check_output_shape

    check_output_shape(output_size, inputs.mde.shape)
    with warnings.catch_warnings():  # the posterior's warnings are returned, one line each
        warnings.simplefilter("ignore", PosteriorWarning)
        posterior = DepthCompleter(gp, engine=engine).complete(
            inputs.mde, inputs.measurements, output_shape=output_size, frame=plan.npz.stem
        )
    if inputs.camera is not None:  # saved with the file, so that `view` back-projects it without being told
        posterior = replace(posterior, K=inputs.camera.resized(posterior.shape[1], posterior.shape[0]).K)
    outcome = CompleteOutcome(posterior, warnings=list(posterior.warnings))
    gt = _gt_on(inputs.gt, posterior.shape)
    if gt is not None:
        from ..metrics import calibration_metrics, depth_metrics

        outcome.metrics = {"mde": depth_metrics(posterior.mde, gt), "gp": depth_metrics(posterior.mean, gt)}
        outcome.calibration = calibration_metrics(posterior.mean, posterior.variance, gt)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PNGRangeWarning)
        outcome.written = _write(posterior, plan, inputs, gt)
    for w in caught:
        if issubclass(w.category, PNGRangeWarning):
            outcome.warnings.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return outcome


def _gt_on(gt: Optional[np.ndarray], shape: tuple[int, int]) -> Optional[np.ndarray]:
    """The ground truth on the output grid (nearest neighbour: no depth is blended across an edge)."""
    if gt is None or gt.shape == tuple(shape):
        return gt
    import cv2

    return cv2.resize(gt, shape[::-1], interpolation=cv2.INTER_NEAREST)


def _write(posterior: DepthPosterior, plan: OutputPlan, inputs: FrameInputs, gt) -> list[Path]:
    """One set: the npz, its PNGs, the previews and the cloud appear together or not at all."""
    with output_set(plan.base, members=plan.members()):
        written = list(posterior.save(plan.npz, png=plan.png))
        if plan.preview:
            written += write_previews(
                plan.base,
                posterior.mean,
                posterior.std,
                mde=posterior.mde,
                depth_gt=gt,
                rgb=inputs.image,
                sparse=posterior.sparse,
            )
        if plan.ply is not None:
            written.append(_write_cloud(plan.ply, posterior, inputs.image, inputs.camera))
    return written


def _write_cloud(path: Path, posterior: DepthPosterior, image: Optional[np.ndarray], camera) -> Path:
    """Back-projects the posterior on its output grid (camera resized to it), coloured by the image (grey without)."""
    import cv2

    from ..mapping.cloud import backproject_posterior

    h, w = posterior.shape
    if image is None:
        colours = np.full((h, w, 3), 128, np.uint8)
    else:
        shrink = image.shape[0] > h
        colours = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    cloud = backproject_posterior(posterior, colours, camera.resized(w, h))
    return cloud.save_ply(path)
