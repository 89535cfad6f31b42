"""``gpdepth3d batch``: complete or evaluate every frame of a dataset folder on Dask (resumable)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from ..pipelines.batch import (
    REPORT_NAME,
    SETTINGS_NAME,
    FramesFailedError,
    HoldoutInputs,
    check_address,
    dataset_frames,
    run_batch,
)
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..io import check_output_folder
from ._options import GPPreset


def batch_command(
    *,
    data: Path,
    output: Path,
    dataset: Optional[Literal["kitti_tiny", "kitti_object", "7scenes", "ibims_sample", "vio_sparse"]] = None,
    task: Literal["complete", "eval"] = "complete",
    workers: Optional[int] = None,
    address: Optional[str] = None,
    frames: Optional[int] = None,
    repeat: int = 1,
    gp: GPPreset = DepthGPConfig(),
    engine: EngineConfig = EngineConfig(),
    factor: int = 3,
    n_input: int = 500,
    mde: Literal["none", "standin", "rtmonodepth", "fastdepth"] = "none",
    models_dir: Optional[Path] = None,
    seed: int = 0,
    png: bool = False,
    preview: bool = True,
    progress: bool = True,
    connect_timeout: float = 10.0,
) -> None:
    """Complete or evaluate every frame of a dataset folder on Dask (resumable; re-run to finish).

    Writes OUTPUT/<frame>.npz (posterior mean, variance, std in metres / m^2) and previews to look at
    (OUTPUT/<frame>_depth_preview.png, OUTPUT/<frame>_sigma_preview.png), with --task eval also
    OUTPUT/<frame>.metrics.json, and OUTPUT/batch_report.json (counts, failures, mean metrics).
    Frames already done are skipped, so a killed run resumes where it stopped. Inputs: --n-input
    measurements sampled from the frame's LiDAR (20 % held out as ground truth for eval) or from its dense
    depth; with --mde rtmonodepth (outdoor) or fastdepth (indoor) the network's depth of each frame's image
    is the MDE, with --mde standin a STAND-IN MDE (densified input points with a smooth scale error).
    Exits with an error if any frame failed. The GP is --preset default|paper|residual (default
    `DepthGPConfig()`), its fields --gp.FIELD; the engine --engine.name, e.g. --engine.name exact.

    Args:
        data: Dataset folder (kitti_tiny, 7scenes, ibims_sample, vio_sparse, kitti_object layouts).
        output: Output folder (created).
        dataset: Dataset kind; default: detected from the folder.
        task: "complete" (posteriors) or "eval" (posteriors + per-frame metrics + aggregate).
        workers: Local Dask worker processes (default: the number of CPUs, as `run_batch`; 0 = no Dask, in this
            process); ignored with --address.
        address: Scheduler address of a running Dask cluster, e.g. tcp://10.0.0.5:8786 (the data and output
            folders must be visible to its workers at the same paths).
        frames: Process at most this many frames (after --repeat).
        repeat: Repeat the dataset's frames this many times under new ids (benchmarks).
        gp: The GP: --preset default|paper|residual, then --gp.FIELD.
        engine: How each posterior is computed: --engine.name "fast" (the default), "exact" (up to a few
            thousand points) or "kissgp", and the other `gpdepth3d.gp.EngineConfig` options.
        factor: Downsample the dataset resolution by this integer factor (3 = the paper's 1/3).
        n_input: Measurements given as input per frame.
        mde: "rtmonodepth" (RT-MonoDepth-S, outdoor) or "fastdepth" (indoor) run on each frame's image, "none"
            (no MDE) or "standin" (clearly a stand-in, see above).
        models_dir: Folder of the networks (default: $GPDEPTH3D_MODELS or ../shared/models).
        seed: Seed of the per-frame sampling.
        png: Also write 16-bit PNGs of mean and std.
        preview: Also write colourised previews per frame (OUTPUT/<frame>_depth_preview.png, _sigma_preview.png;
            colour bars in metres); --no-preview skips them.
        progress: Show the progress bar.
        connect_timeout: Seconds to wait for the scheduler at --address before giving up.
    """
    if address is not None:
        check_address(address)  # before reading the dataset
    check_output_folder(output, "--output")
    specs = dataset_frames(data, dataset, repeat=repeat, limit=frames)
    report = run_batch(
        specs,
        output,
        config=gp,
        engine=engine,
        loader=HoldoutInputs(
            factor=factor,
            n_input=n_input,
            mde=mde,
            seed=seed,
            models_dir=None if models_dir is None else str(models_dir),
        ),
        task=task,
        workers=workers,
        address=address,
        png=png,
        previews=preview,
        progress=progress,
        connect_timeout=connect_timeout,
    )
    print(report.summary())
    if report.aggregate:
        print("  (units: rmse, mae mm; irmse, imae 1/km; rel, delta1, coverage_2sigma fractions; nll nats per pixel)")
    each = "<frame>.npz and its previews" if preview else "<frame>.npz"
    settings = Path(output) / SETTINGS_NAME
    also = f", {settings}" if settings.is_file() else ""
    print(
        f"wrote {report.n_computed} frame(s) ({each}){also} and {Path(output) / REPORT_NAME} "
        f"(in {Path(output).resolve()})"
    )
    if report.failures:
        raise FramesFailedError(
            f"{len(report.failures)} of {report.n_frames} frames failed (first: {report.failures[0].frame_id}: "
            f"{report.failures[0].error}); see {Path(output) / REPORT_NAME}; re-run to retry them"
        )
