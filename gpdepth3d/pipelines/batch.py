"""Dataset-scale completion and evaluation on a Dask cluster, resumable frame by frame.

`run_batch` maps one frame's work (load, complete, write; with ``task="eval"`` also score)
over a list of `FrameSpec` on Dask: a `distributed.LocalCluster` of ``workers`` processes by
default (no set-up), or the cluster whose scheduler listens at ``address``
(``"tcp://host:8786"``). ``workers=0`` runs the same work in this process without Dask.

Guarantees:

* Light tasks: a frame spec is a few strings; each worker reads its frame from the dataset
  folder itself (no image crosses the scheduler), so the folder and ``output_dir`` must be
  visible to every worker at the same path (one machine, or a shared file system).
* Resumable: each frame's outputs are named by its frame id and written atomically
  (`gpdepth3d.io.atomic_path`); a frame counts as done only when its *final* file exists
  (``<id>.npz`` for ``complete``, ``<id>.metrics.json`` for ``eval``, written last). A
  re-run skips done frames; a killed run leaves only temporary files, which the next run
  deletes before it starts. One run at a time per ``output_dir`` (a lock file enforces it),
  and one set of settings: ``batch_settings.json`` records the model config and the loader,
  and a run with other settings is refused rather than mixing results.
* Failures stay local: an exception in one frame (or the loss of the worker computing it) is
  recorded with the frame id and the error in the `BatchReport` and in
  ``batch_report.json``; the other frames go on. Failed frames have no final file, so the
  next run retries them.

Inputs of a frame (`HoldoutInputs`): the default builds the input by *holdout*: ``n_input``
measurements sampled from the frame's points (projected LiDAR, or the dense ground truth where
the dataset has one), a disjoint ``holdout`` share of the LiDAR held out as ground truth for
``eval``. The MDE input is a real network run on the frame's image (``mde="rtmonodepth"``,
outdoor, or ``"fastdepth"``, indoor; see `gpdepth3d.mde.load_frontend`), absent
(``mde="none"``: the residual GP's prior mean is then the median measured depth) or a clearly
labelled stand-in (``mde="standin"``: the *input* points densified by nearest neighbour and
perturbed by a smooth random scale error; never the held-out points). Any picklable
``loader(spec) -> FrameInputs`` can replace it.

A script that calls `run_batch` with a local cluster must guard its entry point with
``if __name__ == "__main__":`` (Dask starts its worker processes with ``spawn``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import re
import threading
import time
import traceback
import uuid
import zlib
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, Optional, Sequence

import numpy as np

from ..errors import ConnectionFailedError, GPDepthError, InvalidInputError, OutputError, describe
from ..limits import check_memory
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..io import clean_output_folder, to_jsonable, write_json, write_problem
from ..measurements import SparseDepth, downsample_depth
from .frames import holdout_lidar, mde_to_grid
from .scoring import CALIBRATION_NAMES, metric_row
from .previews import preview_paths, write_previews

Task = Literal["complete", "eval"]
TASKS = ("complete", "eval")
REPORT_NAME = "batch_report.json"
SETTINGS_NAME = "batch_settings.json"
LOCK_NAME = ".gpdepth3d_batch.lock"
_FRAME_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,199}$")
# Temporary files of gpdepth3d.io.atomic_path: ".<stem>.<random>.tmp<suffix>".
_TEMP_FILE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")


class FramesFailedError(GPDepthError):
    """Some frames of a batch failed (raised by ``gpdepth3d batch``, `gpdepth3d.cli.batch`, after the others were written)."""


# ---------------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class FrameSpec:
    """What a worker needs to find one frame: a few strings, never the data.

    Attributes:
        frame_id: Unique name of the frame's outputs (letters, digits, ``_ . + -``; not
            starting with ``.`` or ``-``).
        root: Dataset folder (must be readable by the workers at this path).
        name: Frame name within the dataset (`gpdepth3d.datasets` reader's ``names``).
        kind: Dataset kind (a key of `gpdepth3d.datasets.READERS`); None = detect from files.
    """

    frame_id: str
    root: str
    name: str
    kind: Optional[str] = None


def check_frame_id(frame_id: str) -> str:
    """Returns ``frame_id`` if it is a safe, non-hidden file name stem, else raises `InvalidInputError`."""
    if not isinstance(frame_id, str) or not _FRAME_ID.match(frame_id):
        raise InvalidInputError(
            "frame_id",
            "1-200 characters of letters, digits, '_', '.', '+', '-' (not starting with '.' or '-')",
            frame_id,
        )
    return frame_id


SPEC_BYTES = 2048
"""Memory one frame of a batch holds while the batch runs (its spec, its id, its row of the report), bytes:
a ``repeat`` beyond the memory limit is refused before any frame is made."""


def dataset_frames(
    root: str | Path, kind: str | None = None, *, repeat: int = 1, limit: int | None = None
) -> list[FrameSpec]:
    """Frame specs of every frame of a dataset folder, optionally repeated and truncated.

    Args:
        root: Dataset folder (any layout `gpdepth3d.datasets.open_dataset` reads).
        kind: Dataset kind; None = detect.
        repeat: Each frame appears this many times; copies get the ids ``<name>-r0001`` ...
            (the first keeps ``<name>``). For load tests and benchmarks: the copies read the
            same files but are separate frames with their own outputs.
        limit: Keep at most this many specs (after repeating).

    Returns:
        The specs, in dataset order (repeats of the whole dataset one after the other).

    Raises:
        InvalidInputError: a bad ``repeat`` or ``limit``. ProblemTooLargeError: more frames than the
            memory limit holds (`SPEC_BYTES` each), before any is made.
    """
    from ..datasets import detect_format, open_dataset

    for name, value, low in (("repeat", repeat, 1), ("limit", limit, 0)):
        number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
        ok = number and math.isfinite(value) and int(value) == value and value >= low
        if not (ok or (name == "limit" and value is None)):
            raise InvalidInputError(name, f"an integer >= {low}" + (" (or None)" if name == "limit" else ""), value)
    kind = kind or detect_format(root)
    reader = open_dataset(root, kind)
    root_s = str(Path(root).resolve())
    total = int(repeat) * len(reader.names) if limit is None else min(int(limit), int(repeat) * len(reader.names))
    check_memory(f"a batch of {total} frames (--repeat {repeat})", total * SPEC_BYTES)
    specs = []
    for r in range(int(repeat)):
        for name in reader.names:
            if len(specs) == total:  # a limit stops the repeats: only the frames kept are made
                return specs
            frame_id = name if r == 0 else f"{name}-r{r:04d}"
            specs.append(FrameSpec(check_frame_id(frame_id), root_s, name, kind))
    return specs


def _check_frames(frames: Sequence[FrameSpec]) -> list[FrameSpec]:
    if isinstance(frames, (str, bytes, Path)) or not hasattr(frames, "__iter__"):
        raise InvalidInputError("frames", "a sequence of FrameSpec", type(frames).__name__)
    frames = list(frames)
    seen: set[str] = set()
    for i, spec in enumerate(frames):
        if not hasattr(spec, "frame_id"):
            raise InvalidInputError(f"frames[{i}]", "a FrameSpec (or an object with a frame_id)", type(spec).__name__)
        check_frame_id(spec.frame_id)
        if spec.frame_id in seen:
            raise InvalidInputError("frames", "unique frame ids", f"{spec.frame_id!r} twice")
        seen.add(spec.frame_id)
    return frames


# ---------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class FrameInputs:
    """The inputs of one frame on the GP grid.

    Attributes:
        mde: (H, W) MDE z-depth in metres (0 = none; all 0 = no MDE).
        sparse: Input measurements, image size (H, W).
        gt: (H, W) ground-truth z-depth for ``eval`` (metres, 0 = none), or None.
        info: Small JSON-able description (counts, what the MDE is).
    """

    mde: np.ndarray
    sparse: SparseDepth
    gt: Optional[np.ndarray] = None
    info: dict = field(default_factory=dict)


@lru_cache(maxsize=8)
def _reader(root: str, kind: str | None):
    from ..datasets import open_dataset

    return open_dataset(root, kind)


@lru_cache(maxsize=4)
def _frontend(name: str, models_dir: str | None):
    """One network front-end per name and worker process."""
    from ..mde import load_frontend

    return load_frontend(name, models_dir=models_dir)


def frame_seed(seed: int, frame_id: str) -> int:
    """A per-frame seed that depends only on ``seed`` and the frame id (stable across runs and machines)."""
    return (int(seed) * 1_000_003 + zlib.crc32(frame_id.encode())) % (2**32)


@dataclass(frozen=True)
class HoldoutInputs:
    """Builds a frame's inputs from a dataset frame by holdout (the default loader).

    Measurement source: the frame's ``sparse`` points (projected LiDAR, SLAM points) if it
    has them, else the valid pixels of its dense ground truth. All maps are shrunk by
    ``factor`` with `downsample_depth` (closest depth per block).

    Ground truth (``eval``): the dense depth where the dataset has one; otherwise a random
    ``holdout`` share of the points, which are then never given as input.

    Input: ``n_input`` points drawn uniformly from the points not held out.

    MDE: a network run on the frame's full-resolution image and shrunk to the grid by area
    averaging (``"rtmonodepth"``, ``"fastdepth"``: `gpdepth3d.mde.load_frontend`, models from
    ``models_dir``), ``"none"`` (no MDE) or ``"standin"``, a STAND-IN for an MDE network: the
    input points densified by nearest neighbour and multiplied by a smooth random scale error of
    about ``standin_error`` (relative, std). It is built from the input points only, so it
    carries no information about the held-out points.

    Attributes:
        factor: Integer downsampling of the dataset resolution (3 = the paper's 1/3).
        n_input: Number of input measurements per frame.
        holdout: Share of the points held out as ground truth (only without dense depth).
        mde: "rtmonodepth", "fastdepth", "none" or "standin" (see above).
        standin_error: Relative std of the stand-in's scale error.
        models_dir: Folder of the networks (default `gpdepth3d.mde.default_models_dir`).
        seed: Base seed; each frame draws from `frame_seed(seed, frame_id)`.
    """

    factor: int = 3
    n_input: int = 500
    holdout: float = 0.2
    mde: Literal["none", "standin", "rtmonodepth", "fastdepth"] = "none"
    standin_error: float = 0.1
    seed: int = 0
    models_dir: Optional[str] = None

    def __post_init__(self) -> None:
        if int(self.factor) != self.factor or self.factor < 1:
            raise InvalidInputError("factor", "an integer >= 1", self.factor)
        if int(self.n_input) != self.n_input or self.n_input < 1:
            raise InvalidInputError("n_input", "an integer >= 1", self.n_input)
        if not (np.isfinite(self.holdout) and 0 < self.holdout < 1):
            raise InvalidInputError("holdout", "a share in (0, 1)", self.holdout)
        if self.mde not in ("none", "standin", "rtmonodepth", "fastdepth"):
            raise InvalidInputError("mde", "'none', 'standin', 'rtmonodepth' or 'fastdepth'", self.mde)
        if not (np.isfinite(self.standin_error) and self.standin_error >= 0):
            raise InvalidInputError("standin_error", "a relative std >= 0", self.standin_error)

    def __call__(self, spec: FrameSpec) -> FrameInputs:
        """Reads ``spec``'s frame from its dataset and builds the inputs (runs on the worker)."""
        frame = _reader(spec.root, spec.kind).load(spec.name)
        network = None
        if self.mde in ("rtmonodepth", "fastdepth"):
            network = _frontend(self.mde, self.models_dir)(frame.rgb)
        return self.from_maps(
            spec.frame_id,
            points=None if frame.sparse is None else frame.sparse.to_depth_map(),
            dense_gt=frame.depth,
            mde_map=network,
        )

    def from_maps(
        self,
        frame_id: str,
        *,
        points: np.ndarray | None,
        dense_gt: np.ndarray | None = None,
        mde_map: np.ndarray | None = None,
    ) -> FrameInputs:
        """Builds the inputs from full-resolution maps.

        Args:
            frame_id: Seeds the random draws.
            points: (H, W) sparse depth map (metres, 0 = none), or None to sample the dense GT.
            dense_gt: (H, W) dense ground truth (metres, 0 = invalid), or None.
            mde_map: (H, W) network MDE (metres) for ``mde="rtmonodepth"/"fastdepth"``.
        """
        from ..sampling import sample_uniform

        if points is None and dense_gt is None:
            raise InvalidInputError("frame", "sparse points or a dense depth map", "neither")
        rng = np.random.default_rng(frame_seed(self.seed, frame_id))
        if dense_gt is not None:
            source = downsample_depth(points if points is not None else dense_gt, self.factor)
            pool = SparseDepth.from_depth_map(source)
            n_available = len(pool)
            gt = downsample_depth(dense_gt, self.factor)
        else:
            split = holdout_lidar(points, factor=self.factor, holdout=self.holdout, rng=rng)
            pool, gt, n_available = split.available, split.gt_grid, split.n_grid
        shape = gt.shape
        sparse = sample_uniform(pool, n=self.n_input, rng=rng)
        if self.mde in ("rtmonodepth", "fastdepth"):
            if mde_map is None:
                raise InvalidInputError("mde_map", f"the network's depth map for mde={self.mde!r}", None)
            mde = mde_to_grid(mde_map, self.factor)
        else:
            mde = self._standin(sparse, rng) if self.mde == "standin" else np.zeros(shape)
        info = {
            "shape": list(shape),
            "n_available": n_available,
            "n_input": len(sparse),
            "n_gt": int(np.count_nonzero(gt)),
            "gt": "dense" if dense_gt is not None else "holdout",
            "mde": "STAND-IN: densified input points x smooth scale error" if self.mde == "standin" else self.mde,
        }
        return FrameInputs(mde=mde, sparse=sparse, gt=gt, info=info)

    def _standin(self, sparse: SparseDepth, rng: np.random.Generator) -> np.ndarray:
        from ..datasets.synthetic import MDESimulation, simulate_mde

        shape = sparse.image_size
        if len(sparse) == 0:
            return np.zeros(shape)
        # an error field of correlation length max(H, W) / 8 * sqrt(2) (Gaussian sigma max(H, W) / 8)
        sim = MDESimulation(
            scale=1.0,
            blur_sigma=0.0,
            field_amplitude=self.standin_error,
            field_lengthscale=max(shape) / 8.0 * np.sqrt(2.0) / shape[1],
            noise=0.0,
        )
        return simulate_mde(sparse.to_depth_map(shape), sim, rng)


# ---------------------------------------------------------------------------------- one frame
@dataclass(frozen=True)
class FrameResult:
    """What a worker returns for one frame (small: the outputs are on disk).

    Attributes:
        frame_id: The frame.
        ok: True when the final file was written.
        seconds: Wall time of the frame on the worker.
        error: ``"<ExceptionType>: <message>"`` when it failed, else None.
        traceback: Formatted traceback of the failure, else None.
        metrics: ``eval``: the frame's metrics, else None.
    """

    frame_id: str
    ok: bool
    seconds: float
    error: Optional[str] = None
    traceback: Optional[str] = None
    metrics: Optional[dict] = None


def output_paths(
    output_dir: str | Path, frame_id: str, task: Task, *, png: bool = False, previews: bool = False
) -> dict[str, Path]:
    """The files a frame writes: ``posterior`` (``<id>.npz``), with ``png`` ``mean_png`` and ``std_png``,
    with ``previews`` ``depth_preview`` and ``sigma_preview``, for eval ``metrics``; ``final`` is the last one
    written.

    A frame is done only when every one of these files exists (`frame_done`).
    """
    output_dir = Path(output_dir)
    paths = {"posterior": output_dir / f"{frame_id}.npz"}
    if png:
        paths["mean_png"] = output_dir / f"{frame_id}_mean.png"
        paths["std_png"] = output_dir / f"{frame_id}_std.png"
    if previews:
        for kind, path in zip(("depth_preview", "sigma_preview"), preview_paths(output_dir / frame_id)):
            paths[kind] = path
    if task == "eval":
        paths["metrics"] = output_dir / f"{frame_id}.metrics.json"
    paths["final"] = paths["metrics" if task == "eval" else "posterior"]
    return paths


def frame_done(output_dir: str | Path, frame_id: str, task: Task, *, png: bool = False, previews: bool = False) -> bool:
    """Whether every output of the frame exists (npz, the PNGs with ``png``, previews, the metrics for eval)."""
    return all(p.is_file() for p in output_paths(output_dir, frame_id, task, png=png, previews=previews).values())


_COMPLETERS: dict = {}
_COMPLETERS_LOCK = threading.Lock()


def _completer(config: DepthGPConfig, engine: EngineConfig | None = None):
    """One `DepthCompleter` per configuration, engine and worker process (engines cache per-resolution set-up)."""
    from ..completion.complete import DepthCompleter

    key = (config, engine or EngineConfig())
    with _COMPLETERS_LOCK:
        if key not in _COMPLETERS:
            _COMPLETERS[key] = DepthCompleter(config, engine=key[1])
        return _COMPLETERS[key]


def process_frame(
    spec: FrameSpec,
    output_dir: str,
    *,
    config: DepthGPConfig,
    loader: Callable[[FrameSpec], FrameInputs],
    task: Task = "complete",
    variance: bool = True,
    png: bool = False,
    previews: bool = False,
    engine: EngineConfig | None = None,
) -> FrameResult:
    """Does one frame: load, complete, write atomically (and score for ``eval``); never raises.

    Returns a failed `FrameResult` (with the error and traceback) instead of raising, so one
    bad frame cannot stop a batch. ``eval`` writes the posterior first and the metrics file
    last: the metrics file marks the frame done.
    """
    t0 = time.perf_counter()
    try:
        paths = output_paths(output_dir, spec.frame_id, task, png=png, previews=previews)
        inputs = loader(spec)
        if not isinstance(inputs, FrameInputs):
            raise InvalidInputError("loader", "a callable returning FrameInputs", type(inputs).__name__)
        posterior = _completer(config, engine).complete(
            inputs.mde, inputs.sparse, variance=variance or task == "eval", frame=spec.frame_id
        )
        written = []
        try:
            if previews:  # before the posterior: the frame's last file marks it done
                written = write_previews(
                    Path(output_dir) / spec.frame_id,
                    posterior.mean,
                    np.sqrt(np.maximum(posterior.variance, 0)),
                    mde=inputs.mde if np.shape(inputs.mde) == posterior.mean.shape else None,
                )
            posterior.save(paths["posterior"], png=png)
        except BaseException:  # a frame without its posterior keeps none of its files (a full disk)
            for path in written:
                with contextlib.suppress(OSError):
                    Path(path).unlink()
            raise
        metrics = None
        if task == "eval":
            metrics = evaluate_posterior(posterior.mean, posterior.variance, inputs.gt)
            record = {
                "frame_id": spec.frame_id,
                "name": getattr(spec, "name", None),
                "metrics": metrics,
                "inputs": inputs.info,
                "timings": posterior.timings,
            }
            write_json(paths["metrics"], record)
        return FrameResult(spec.frame_id, True, time.perf_counter() - t0, metrics=metrics)
    except Exception as exc:  # noqa: BLE001 - a batch reports every frame's failure and goes on
        return FrameResult(
            getattr(spec, "frame_id", "?"),
            False,
            time.perf_counter() - t0,
            error=f"{type(exc).__name__}: {exc}",
            traceback=traceback.format_exc(),
        )


def evaluate_posterior(mean: np.ndarray, variance: np.ndarray, gt: np.ndarray | None) -> dict[str, float]:
    """Depth metrics (`depth_metrics`) and variance calibration (`calibration_metrics`) against ``gt``.

    The `gpdepth3d.pipelines.scoring.metric_row` of the frame with every depth metric, ``n``
    (the number of ground-truth pixels) and every calibration key.
    """
    from ..errors import EmptyInputError
    from ..metrics import METRIC_NAMES

    if gt is None:
        raise EmptyInputError("gt", "ground truth for task='eval' (a loader that returns FrameInputs.gt)", None)
    return metric_row(mean, variance, gt, depth_keys=METRIC_NAMES + ("n",), calibration_keys=CALIBRATION_NAMES)


# ---------------------------------------------------------------------------------- report
@dataclass(frozen=True)
class FrameFailure:
    """A frame that failed: its id and the error (``"<Type>: <message>"``), with the traceback."""

    frame_id: str
    error: str
    traceback: str = ""


@dataclass(frozen=True)
class BatchReport:
    """Outcome of `run_batch`.

    Attributes:
        task: "complete" or "eval".
        output_dir: Where the outputs are.
        n_frames: Frames asked for.
        n_computed: Frames computed and written by this run.
        n_skipped: Frames already done before this run (final file present).
        failures: Frames that failed in this run (no final file; a re-run retries them).
        seconds: Wall time of the whole run (including cluster start-up), s.
        startup_seconds: Cluster start-up / connection time, s.
        compute_seconds: Time from the first submission to the last result, s.
        frames_per_second: ``n_computed / compute_seconds``.
        temp_files_removed: Stale temporary files of killed runs deleted at the start.
        workers: Worker processes (Dask) that ran the frames; 0 = in-process.
        aggregate: ``eval``: mean of each metric over all done frames (this and earlier runs),
            with ``frames``; None for ``complete``.
    """

    task: str
    output_dir: Path
    n_frames: int
    n_computed: int
    n_skipped: int
    failures: tuple[FrameFailure, ...]
    seconds: float
    startup_seconds: float
    compute_seconds: float
    frames_per_second: float
    temp_files_removed: int
    workers: int
    aggregate: Optional[dict] = None

    @property
    def ok(self) -> bool:
        """True when every frame is done."""
        return not self.failures and self.n_computed + self.n_skipped == self.n_frames

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = [
            f"{self.task}: {self.n_frames} frames: {self.n_computed} computed, {self.n_skipped} already done, "
            f"{len(self.failures)} failed; {self.frames_per_second:.2f} frames/s on {self.workers} worker(s) "
            f"(start-up {self.startup_seconds:.1f} s, total {self.seconds:.1f} s)"
        ]
        for f in self.failures:
            lines.append(f"  FAILED {f.frame_id}: {f.error}")
        if self.aggregate:
            keys = [
                k
                for k in ("rmse", "mae", "irmse", "imae", "rel", "delta1", "nll", "coverage_2sigma")
                if k in self.aggregate
            ]
            lines.append(
                f"  mean over {self.aggregate['frames']} frames: "
                + ", ".join(f"{k} {self.aggregate[k]:.4g}" for k in keys)
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["output_dir"] = str(self.output_dir)
        d["ok"] = self.ok
        return d


def aggregate_metrics(output_dir: str | Path, frame_ids: Sequence[str]) -> Optional[dict]:
    """Mean of every metric over the frames whose ``<id>.metrics.json`` exists (per-frame average, KITTI style).

    Returns None when no frame has metrics; else the means plus ``frames`` (count) and
    ``pixels`` (evaluated ground-truth pixels in total).
    """
    rows = []
    for frame_id in frame_ids:
        path = output_paths(output_dir, frame_id, "eval")["metrics"]
        if path.is_file():
            rows.append(json.loads(path.read_text())["metrics"])
    if not rows:
        return None
    keys = [k for k in rows[0] if k != "n"]
    # NaN is written as null (`gpdepth3d.io.write_json`)
    agg = {k: float(np.mean([math.nan if r[k] is None else r[k] for r in rows])) for k in keys}
    agg["frames"] = len(rows)
    agg["pixels"] = int(sum(r.get("n", 0) for r in rows))
    return agg


# ---------------------------------------------------------------------------------- driver
@contextlib.contextmanager
def _exclusive(output_dir: Path) -> Iterator[None]:
    """Holds an exclusive lock on ``output_dir`` for one run (fcntl.flock; no-op where unavailable)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    try:
        fh = open(output_dir / LOCK_NAME, "a")
    except OSError as exc:
        raise OutputError(output_dir / LOCK_NAME, write_problem(exc)) from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if os.fstat(fh.fileno()).st_ino != os.stat(output_dir / LOCK_NAME).st_ino:
                raise OSError("the lock file was removed by the run that held it")  # that run was just ending
        except OSError:
            raise InvalidInputError(
                "output_dir", "a folder no other batch run is writing to", f"{output_dir} is locked by another run"
            ) from None
        try:
            yield
        finally:  # no lock file stays behind: it is removed while still held
            with contextlib.suppress(OSError):
                os.unlink(output_dir / LOCK_NAME)
            fcntl.flock(fh, fcntl.LOCK_UN)


@contextlib.contextmanager
def _settings_kept_with_outputs(output_dir: Path, frames, task: str, png: bool, previews: bool) -> Iterator[None]:
    """Removes a ``batch_settings.json`` this run wrote when it ends (or fails) without one frame's outputs."""
    fresh = not (output_dir / SETTINGS_NAME).exists()
    try:
        yield
    finally:
        if fresh and not any(frame_done(output_dir, f.frame_id, task, png=png, previews=previews) for f in frames):
            with contextlib.suppress(OSError):
                (output_dir / SETTINGS_NAME).unlink()


def fingerprint(obj: Any) -> str:
    """A stable text identity of a config or loader: the repr of a dataclass, else the qualified name."""
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return repr(obj)
    target = obj if hasattr(obj, "__qualname__") else type(obj)
    return f"{getattr(target, '__module__', '?')}.{target.__qualname__}"


def check_settings(
    output_dir: str | Path, config: DepthGPConfig, loader: Any, engine: EngineConfig | None = None
) -> None:
    """Refuses to mix outputs of different settings in one folder; records them on first use.

    ``output_dir/batch_settings.json`` holds the model config, the lattice stride (it sets the
    approximation) and the `fingerprint` of the loader the existing outputs were made with. A run with
    other settings raises `InvalidInputError` (skipped frames would otherwise keep results of the old
    settings). The engine is not part of the settings: every engine computes the same posterior, so a
    run may be resumed with another one.
    """
    import dataclasses

    path = Path(output_dir) / SETTINGS_NAME
    stride = (engine or EngineConfig()).lattice_stride
    settings = {"config": dataclasses.asdict(config), "lattice_stride": stride, "loader": fingerprint(loader)}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except (ValueError, GPDepthError):
            old = None
        if old != to_jsonable(settings):
            raise InvalidInputError(
                "config, loader",
                f"the settings the outputs in {output_dir} were made with ({old}); use a new output_dir",
                settings,
            )
        return
    write_json(path, settings)


def remove_stale_temp_files(output_dir: str | Path) -> int:
    """Deletes temporary files left by killed writers (``.<stem>.<random>.tmp<suffix>``); returns how many."""
    n = clean_output_folder(output_dir)  # finishes interrupted commits of output sets, deletes their temporaries
    for path in Path(output_dir).iterdir():
        if path.is_file() and _TEMP_FILE.match(path.name):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                n += 1
    return n


def _import_dask():
    try:
        import distributed
    except ImportError:
        raise ImportError(
            "gpdepth3d batch runs on Dask: install it with `pip install 'gpdepth3d[batch]'` "
            "(or `pip install distributed`), or run it in this process: workers=0 (on the command line: --workers 0)"
        ) from None
    return distributed


def warm_up() -> None:
    """Imports what a frame needs, on each worker of a local cluster at start-up (not during the first frame). The
    workers share the cores between them, so none starts a process compiling kernels ahead on a cold cache
    (`gpdepth3d.gp.compile_ahead`), unless the user's environment asks for it."""
    from ..gp.compile_ahead import ENV_SWITCH

    os.environ.setdefault(ENV_SWITCH, "0")
    import scipy.linalg  # noqa: F401
    import scipy.ndimage  # noqa: F401

    from .. import datasets, metrics, sampling  # noqa: F401
    from ..completion import complete  # noqa: F401


_ADDRESS = re.compile(r"(?:(tcp|tls|ws|wss|ucx)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})/?")


def check_address(address: str) -> str:
    """Validates a Dask scheduler address: ``[tcp|tls|ws|wss|ucx://]host:port``; returns it.

    Raises:
        InvalidInputError: for anything else (no port, a port outside 1..65535, not a string).
    """
    expected = "a Dask scheduler address such as 'tcp://host:8786'"
    if not isinstance(address, str):
        raise InvalidInputError("address", expected, describe(address))
    m = _ADDRESS.fullmatch(address.strip())
    if m is None or not 1 <= int(m.group(3)) <= 65535:
        raise InvalidInputError("address", expected, repr(address))
    return address.strip()


def make_output_dir(output_dir: str | Path) -> Path:
    """Creates ``output_dir`` (and its parents) or raises `OutputError` (a file in the way, read-only)."""
    output_dir = Path(output_dir)
    if str(output_dir) == "":
        raise OutputError("''", "output_dir needs a folder name")
    if output_dir.exists() and not output_dir.is_dir():
        raise OutputError(output_dir, "a file is in the way (expected a folder)")
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(output_dir, f"cannot create the folder: {write_problem(exc)}") from None
    if not os.access(output_dir, os.W_OK | os.X_OK):
        raise OutputError(output_dir, "the folder is not writable")
    return output_dir


@contextlib.contextmanager
def _client(workers: int, address: str | None, connect_timeout: float = 10.0) -> Iterator[tuple[Any, int]]:
    """A Dask client (and the number of worker threads) on a new LocalCluster or at ``address``."""
    distributed = _import_dask()
    if address is None:
        cluster = distributed.LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.ERROR
        )
        try:
            with distributed.Client(cluster) as client:
                client.run(warm_up)
                yield client, workers
        finally:
            cluster.close()
    else:
        try:
            client = distributed.Client(address, timeout=f"{connect_timeout}s")
        except (OSError, TimeoutError, asyncio.TimeoutError) as exc:
            raise ConnectionFailedError(
                address, f"no Dask scheduler answered within {connect_timeout:g} s ({type(exc).__name__})"
            ) from None
        with client:
            threads = sum(client.nthreads().values())
            if threads == 0:
                try:
                    client.wait_for_workers(1, timeout=connect_timeout)
                except (OSError, TimeoutError, asyncio.TimeoutError):
                    raise ConnectionFailedError(
                        address, f"the scheduler has no worker after {connect_timeout:g} s"
                    ) from None
                threads = sum(client.nthreads().values())
            client.run(warm_up)
            yield client, threads


def run_batch(
    frames: Sequence[FrameSpec],
    output_dir: str | Path,
    *,
    config: DepthGPConfig | None = None,
    engine: EngineConfig | None = None,
    loader: Callable[[FrameSpec], FrameInputs] | None = None,
    task: Task = "complete",
    workers: int | None = None,
    address: str | None = None,
    variance: bool = True,
    png: bool = False,
    previews: bool = False,
    max_in_flight: int | None = None,
    progress: bool = True,
    connect_timeout: float = 10.0,
) -> BatchReport:
    """Completes (or evaluates) many frames on Dask, skipping done frames and isolating failures.

    Args:
        frames: Frame specs with unique ids (see `dataset_frames`).
        output_dir: Folder of the outputs (created); one run at a time per folder.
        config: GP model; default ``DepthGPConfig()`` (the library's default model).
        engine: The engine and its options (`gpdepth3d.gp.EngineConfig`; default the ``fast`` engine; "exact"
            for a few thousand points).
        loader: Picklable ``loader(spec) -> FrameInputs`` run on the workers; default
            `HoldoutInputs()`.
        task: "complete" (write ``<id>.npz`` posteriors) or "eval" (also write
            ``<id>.metrics.json`` and aggregate them).
        workers: Local worker processes (one thread each); default the number of CPUs;
            0 = run in this process without Dask. Ignored with ``address``.
        address: Scheduler address of a running Dask cluster (e.g. ``"tcp://10.0.0.5:8786"``);
            None = start a LocalCluster.
        variance: Compute the posterior variance (always on for ``eval``).
        png: Also write 16-bit PNGs of mean and std per frame.
        previews: Also write colourised previews per frame (``<id>_depth_preview.png``, ``<id>_sigma_preview.png``,
            colour bars in metres; needs the variance).
        max_in_flight: Frames submitted but not finished at any time (default twice the
            worker threads): bounds the scheduler's memory on huge datasets and the work in
            flight when a run is killed. A frame that kills its worker process (segfault,
            out of memory) is retried on other workers and then reported as ``KilledWorker``
            (Dask's ``distributed.scheduler.allowed-failures``, default 3); frames waiting on
            that worker are rescheduled.
        progress: Show a tqdm progress bar (frames/s).
        connect_timeout: Seconds to wait for the scheduler at ``address`` (and for its first
            worker) before `ConnectionFailedError`.

    Returns:
        The `BatchReport`; it is also written to ``output_dir/batch_report.json``.
    """
    t_start = time.perf_counter()
    frames, workers, address, config, engine, loader = _check_batch_args(
        frames, task, workers, address, connect_timeout, max_in_flight, config, engine, loader
    )
    output_dir = make_output_dir(output_dir)

    with _exclusive(output_dir), _settings_kept_with_outputs(output_dir, frames, task, png, previews):
        check_settings(output_dir, config, loader, engine)
        removed = remove_stale_temp_files(output_dir)
        previews = bool(previews) and (variance or task == "eval")
        todo = [f for f in frames if not frame_done(output_dir, f.frame_id, task, png=png, previews=previews)]
        n_skipped = len(frames) - len(todo)
        kwargs = dict(
            config=config, engine=engine, loader=loader, task=task, variance=variance, png=png, previews=previews
        )
        results, startup, compute, n_workers = _compute_frames(
            todo, output_dir, kwargs, workers, address, connect_timeout, max_in_flight, progress
        )

        failures = tuple(
            FrameFailure(r.frame_id, r.error or "unknown error", r.traceback or "") for r in results if not r.ok
        )
        n_computed = sum(r.ok for r in results)
        aggregate = aggregate_metrics(output_dir, [f.frame_id for f in frames]) if task == "eval" else None
        report = BatchReport(
            task=task,
            output_dir=output_dir,
            n_frames=len(frames),
            n_computed=n_computed,
            n_skipped=n_skipped,
            failures=failures,
            seconds=time.perf_counter() - t_start,
            startup_seconds=startup,
            compute_seconds=compute,
            frames_per_second=n_computed / compute if compute > 0 else 0.0,
            temp_files_removed=removed,
            workers=n_workers,
            aggregate=aggregate,
        )
        write_json(output_dir / REPORT_NAME, report.to_dict())
    return report


def _check_batch_args(
    frames: Sequence[FrameSpec],
    task: Any,
    workers: Any,
    address: Any,
    connect_timeout: Any,
    max_in_flight: Any,
    config: Any,
    engine: Any,
    loader: Any,
) -> tuple:
    """Checks `run_batch`'s arguments and fills in the defaults (frames, workers, address, config, engine, loader)."""
    frames = _check_frames(frames)
    if task not in TASKS:
        raise InvalidInputError("task", "'complete' or 'eval'", task)
    if workers is None:
        workers = os.cpu_count() or 1
    if int(workers) != workers or workers < 0:
        raise InvalidInputError("workers", "an integer >= 0 (0 = in this process)", workers)
    workers = int(workers)
    if address is not None:
        address = check_address(address)
    if (
        isinstance(connect_timeout, bool)
        or not isinstance(connect_timeout, (int, float))
        or not np.isfinite(connect_timeout)
        or connect_timeout <= 0
    ):
        raise InvalidInputError("connect_timeout", "seconds > 0", connect_timeout)
    if max_in_flight is not None and (int(max_in_flight) != max_in_flight or max_in_flight < 1):
        raise InvalidInputError("max_in_flight", "an integer >= 1", max_in_flight)
    config = config or DepthGPConfig()
    if not isinstance(config, DepthGPConfig):
        raise InvalidInputError("config", "a DepthGPConfig", type(config).__name__)
    engine = engine or EngineConfig()
    if not isinstance(engine, EngineConfig):
        raise InvalidInputError("engine", "an EngineConfig", type(engine).__name__)
    loader = loader or HoldoutInputs()
    if not callable(loader):
        raise InvalidInputError("loader", "a callable loader(spec) -> FrameInputs", type(loader).__name__)
    return frames, workers, address, config, engine, loader


def _compute_frames(
    todo: list[FrameSpec],
    output_dir: Path,
    kwargs: dict,
    workers: int,
    address: str | None,
    connect_timeout: float,
    max_in_flight: int | None,
    progress: bool,
) -> tuple[list[FrameResult], float, float, int]:
    """Runs the frames to do in this process or on Dask: (results, startup s, compute s, workers)."""
    task = kwargs["task"]
    results: list[FrameResult] = []
    startup = 0.0
    t_compute = time.perf_counter()
    n_workers = 0
    bar = _progress_bar(len(todo), task, progress and bool(todo))
    try:
        if todo and (workers == 0 and address is None):
            for spec in todo:
                results.append(process_frame(spec, str(output_dir), **kwargs))
                _advance(bar, results)
        elif todo:
            t0 = time.perf_counter()
            with _client(workers, address, connect_timeout) as (client, threads):
                startup = time.perf_counter() - t0
                n_workers = len(client.nthreads()) or workers
                t_compute = time.perf_counter()
                window = int(max_in_flight or 2 * max(threads, 1))
                results = _run_dask(client, todo, str(output_dir), kwargs, window, bar)
    finally:
        if bar is not None:
            bar.close()
    compute = time.perf_counter() - t_compute if todo else 0.0
    return results, startup, compute, n_workers


def _progress_bar(total: int, task: str, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    # rate_noinv: always frames/s (tqdm would switch to s/frame below one frame per second).
    fmt = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_noinv_fmt}{postfix}]"
    return tqdm(total=total, unit="frame", desc=task, dynamic_ncols=True, bar_format=fmt)


def _advance(bar, results: list[FrameResult]) -> None:
    if bar is None:
        return
    failed = sum(not r.ok for r in results)
    if failed:
        bar.set_postfix(failed=failed, refresh=False)
    bar.update(1)


def _run_dask(client, todo: list[FrameSpec], output_dir: str, kwargs: dict, window: int, bar) -> list[FrameResult]:
    """Submits frames in a sliding window of ``window`` futures; collects results as they complete."""
    distributed = _import_dask()
    token = uuid.uuid4().hex[:8]
    pending = iter(todo)
    by_key: dict[str, FrameSpec] = {}

    def submit(spec: FrameSpec):
        key = f"gpdepth3d-{kwargs['task']}-{spec.frame_id}-{token}"
        by_key[key] = spec
        return client.submit(process_frame, spec, output_dir, key=key, pure=False, **kwargs)

    first = [submit(s) for _, s in zip(range(window), pending)]
    results: list[FrameResult] = []
    queue = distributed.as_completed(first)
    try:
        for future in queue:
            spec = by_key.pop(future.key)
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - lost worker (KilledWorker), cancelled, ...
                result = FrameResult(
                    spec.frame_id, False, 0.0, error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc()
                )
            future.release()
            results.append(result)
            _advance(bar, results)
            nxt = next(pending, None)
            if nxt is not None:
                queue.add(submit(nxt))
    except BaseException:
        client.cancel(list(queue.futures))
        raise
    return results
