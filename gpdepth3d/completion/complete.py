"""Depth completion: the public entry point `complete()` and `DepthCompleter` for sequences.

Input rules (documented once, here):

* ``mde_depth``: (H, W) float z-depth in metres. 0, NaN and +/-inf mark pixels with no MDE
  depth (they are not observations). Negative depths raise `InvalidDepthError`.
* ``sparse``: `SparseDepth`. Its image may have another resolution than the MDE as long as it
  shows the same image (equal aspect ratio within 1 %): points are moved to the MDE grid keeping
  the closest point per pixel. An empty set is allowed: the result is then the GP given the MDE
  alone (balanced) or the prior (residual: the MDE with the prior's large variance).
* ``output_shape``: (Ho, Wo) of the result; defaults to the MDE shape and may be larger (the
  paper's M > N upsampling) or smaller. Output pixel centres are placed with the pixel-centre
  convention in the MDE grid.
"""

from __future__ import annotations

import contextlib
import json
import zipfile
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..errors import DataFormatError, GPDepthError, InvalidInputError, ProblemTooLargeError, describe
from ..gp import EngineConfig, SolveInfo, make_engine
from ..gp.compile_ahead import on_cold_cache
from ..gp.model import DepthGPConfig
from ..mde.align import AlignmentResult
from ..measurements import SparseDepth
from .diagnostics import PosteriorWarning as PosteriorWarning
from .formulations import formulation_of
from .problem import build_problem as build_problem
from .problem import check_mde_depth as check_mde_depth


@dataclass(frozen=True)
class DepthPosterior:
    """GP posterior of the depth field on the output grid.

    Attributes:
        mean: (Ho, Wo) posterior mean z-depth, metres.
        variance: (Ho, Wo) posterior marginal variance of the depth, m^2.
        mde: (Ho, Wo) the input MDE depth resampled to the output grid (metres, 0 = none), for
            comparison.
        sparse: The measurements as used, on the GP grid (closest point per pixel).
        config: The model configuration.
        depth_scale: The depth scale (metres) that relative units were multiplied by.
        alignment: Scale/shift applied to the MDE (residual formulation), else identity.
        timings: Seconds spent per stage ("fit": hyperparameter fit when config.fit, "setup", "solve").
        rejected: (N,) bool over ``sparse``: points rejected as outliers (log_residual: their
            leave-one-out z-score given their neighbours exceeded ``config.screen.outlier_threshold``).
        warnings: What the posterior could not support, one sentence each (also issued as
            `PosteriorWarning`): an MDE whose scale disagrees with the points by more than a
            factor of 2, almost no points, points covering little of the image, many rejected, an
            MDE whose depth differences the points barely follow (fitted slope < 0.2), an MDE
            error the points show to be > 1.25x the configured s (``screen.raise_outputscale``); for the
            Gaussian formulations (``balanced``, ``residual``) the MDE's scale and pixels whose
            mean is <= 0 m.
        solve: The engine's facts of this call (`gpdepth3d.gp.SolveInfo`: route, seconds per
            stage); None for a posterior read from a file.
        mde_slope: log_residual: the MDE's log-depth coefficient fitted to this frame
            (`gpdepth3d.gp.slope`; 1 when not fitted): below 1 the points say the MDE over-states
            the depth differences of the scene.
        K: (3, 3) intrinsics of the output grid (pixels) when the caller knew them, else None; saved
            with the file so that the viewer can back-project it.
        stages: The default model's seconds per stage inside ``timings["solve"]`` ("lattice", "engine": the
            engine's call, "detail", "assemble", "calibrate"); empty for the other formulations and from a file.
    """

    mean: np.ndarray
    variance: np.ndarray
    mde: np.ndarray
    sparse: SparseDepth
    config: DepthGPConfig
    depth_scale: float
    alignment: AlignmentResult = field(default_factory=lambda: AlignmentResult(1.0, 0.0, 0))
    timings: dict = field(default_factory=dict)
    rejected: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    solve: SolveInfo | None = None
    mde_slope: float = 1.0
    K: np.ndarray | None = None
    stages: dict = field(default_factory=dict)

    @property
    def n_rejected(self) -> int:
        """Number of measurements rejected as outliers."""
        return 0 if self.rejected is None else int(np.count_nonzero(self.rejected))

    @property
    def std(self) -> np.ndarray:
        """(Ho, Wo) posterior standard deviation, metres."""
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def shape(self) -> tuple[int, int]:
        return self.mean.shape  # type: ignore[return-value]

    def save(self, path: str | Path, *, png: bool = False) -> list[Path]:
        """Writes ``mean``, ``variance``, ``std`` and ``mde`` to ``<path>.npz``, as one set with the PNGs.

        With ``png=True`` also writes ``<stem>_mean.png`` and ``<stem>_std.png`` as 16-bit PNG in
        the KITTI convention (value = metres * 256): values beyond the format's 256 m are stored
        as 65535 with a `gpdepth3d.io.PNGRangeWarning` counting them (the npz keeps the true
        values). The files of one call appear together or not at all, as plain files
        (`gpdepth3d.io.atomic_write_set`; inside a `gpdepth3d.io.output_set` they join it), and
        PNGs of an earlier call with ``png=True`` do not survive a later ``png=False`` call.

        Returns:
            The written paths (npz first).

        Raises:
            OutputError: the path is empty, a directory or too long, or a file cannot be written.
        """
        from ..io import atomic_write_set, check_output_path, depth_png_values, npz_writer, png_writer

        path = check_output_path(path)
        path = path.with_suffix(".npz")
        stem = path.stem
        npz_name, png_names = f"{stem}.npz", (f"{stem}_mean.png", f"{stem}_std.png")
        writers = {
            npz_name: npz_writer(
                mean=self.mean.astype(np.float32),
                variance=self.variance.astype(np.float32),
                std=self.std.astype(np.float32),
                mde=self.mde.astype(np.float32),
                sparse_uvd=np.stack([self.sparse.u, self.sparse.v, self.sparse.depth], 1).astype(np.float32),
                sparse_image_size=np.array(self.sparse.image_size),
                depth_scale=np.float64(self.depth_scale),
                alignment=np.array([self.alignment.scale, self.alignment.shift]),
                mde_slope=np.float64(self.mde_slope),
                config_json=np.array(json.dumps(asdict(self.config))),
                rejected=np.zeros(len(self.sparse), bool) if self.rejected is None else np.asarray(self.rejected, bool),
                warnings=np.array(self.warnings, dtype=str),
                **({} if self.K is None else {"K": np.asarray(self.K, np.float64).reshape(3, 3)}),
            )
        }
        if png:
            for name, values, arg in ((png_names[0], self.mean, "mean"), (png_names[1], self.std, "std")):
                values = depth_png_values(values, argument=f"posterior {arg} ({path.parent / name})", saturate=True)
                writers[name] = png_writer(values, path.parent / name)
        return atomic_write_set(path.with_suffix(""), writers, members=(npz_name, *png_names))

    @classmethod
    def load(cls, path: str | Path, config: DepthGPConfig | None = None) -> "DepthPosterior":
        """Reads a posterior written by `save`, with the config that made it.

        ``config`` replaces the stored config (files written before it was stored get
        ``config`` or `DepthGPConfig()`). A save a kill interrupted is finished first
        (`gpdepth3d.io.clean_output_set`), so the files read belong to one call.

        Raises:
            DataFormatError: a missing or corrupt file, a stored config that is not a JSON object,
                a mean with no finite value, or a variance that is negative or not finite.
        """
        from ..io import check_stored_array, clean_output_set

        path = Path(path)
        with contextlib.suppress(GPDepthError, OSError):  # a read-only folder: read what is there
            clean_output_set(path.with_suffix(""))
        if not path.is_file():
            raise DataFormatError(path, "posterior file not found")
        try:
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("an .npz archive expected (this is a single array)")
            with data as d:
                for k in ("mean", "variance", "mde", "sparse_uvd"):  # forged sizes refused before allocating
                    check_stored_array(path, k)
                uvd = d["sparse_uvd"].astype(np.float64)
                size = tuple(int(x) for x in d["sparse_image_size"])
                sparse = SparseDepth(uvd[:, 0], uvd[:, 1], uvd[:, 2], size)
                align = d["alignment"]
                mean, variance, mde = (d[k].astype(np.float64) for k in ("mean", "variance", "mde"))
                if mean.ndim != 2 or variance.shape != mean.shape or mde.shape != mean.shape:
                    raise ValueError(f"mean {mean.shape}, variance {variance.shape}, mde {mde.shape}: not one 2-D grid")
                if not np.any(np.isfinite(mean)):
                    raise ValueError("the mean has no finite value")
                if not np.all(np.isfinite(variance)) or np.any(variance < 0):
                    bad = int(np.count_nonzero(~(np.isfinite(variance) & (variance >= 0))))
                    raise ValueError(f"{bad} variances negative or not finite (a variance is finite and >= 0)")
                if config is None and "config_json" in d.files:
                    stored = json.loads(str(d["config_json"]))
                    if not isinstance(stored, dict):
                        raise ValueError(f"config_json: expected a JSON object, got a JSON {type(stored).__name__}")
                    known = {f.name for f in fields(DepthGPConfig)}
                    config = DepthGPConfig.from_dict({k: v for k, v in stored.items() if k in known})
                rejected = d["rejected"].astype(bool) if "rejected" in d.files else None
                if rejected is not None and rejected.shape != (len(sparse),):
                    raise ValueError(f"rejected {rejected.shape}: not one flag per point ({len(sparse)})")
                return cls(
                    mean=mean,
                    variance=variance,
                    mde=mde,
                    sparse=sparse,
                    config=config or DepthGPConfig(),
                    depth_scale=float(d["depth_scale"]),
                    alignment=AlignmentResult(float(align[0]), float(align[1]), 0),
                    rejected=rejected,
                    warnings=tuple(str(w) for w in d["warnings"]) if "warnings" in d.files else (),
                    mde_slope=float(d["mde_slope"]) if "mde_slope" in d.files else 1.0,
                    K=np.asarray(d["K"], np.float64).reshape(3, 3) if "K" in d.files else None,
                )
        except ProblemTooLargeError:
            raise
        except (
            KeyError,
            ValueError,
            TypeError,
            IndexError,
            OSError,
            EOFError,
            zipfile.BadZipFile,
            GPDepthError,
        ) as exc:
            raise DataFormatError(path, f"not a gpdepth3d posterior file: {exc}") from None


class DepthCompleter:
    """Completes depth frame after frame with one configuration.

    The engine (and the per-resolution set-up it caches: the elimination structure, the prior
    precision and the output read-out of the ``fast`` engine) is kept between calls, so the frames
    of a sequence after the first are cheaper. With ``config.fit`` each frame's hyperparameters
    are fitted by maximum marginal likelihood, warm-started from the previous frame's values
    (`fitted`; set it to None to start again from ``config``). ``engine`` (a
    `gpdepth3d.gp.EngineConfig`) names the engine and sets its options: device, back-end, route, limits,
    the default model's lattice stride.

    Example:
        >>> completer = DepthCompleter(DepthGPConfig(), engine=EngineConfig(name="exact"))
        >>> posterior = completer(mde_depth, sparse)  # doctest: +SKIP
    """

    def __init__(self, config: DepthGPConfig | None = None, *, engine: EngineConfig | None = None):
        if config is not None and not isinstance(config, DepthGPConfig):
            raise InvalidInputError("config", "a DepthGPConfig (or None for the defaults)", describe(config))
        if engine is not None and not isinstance(engine, EngineConfig):
            raise InvalidInputError("engine", "an EngineConfig (or None for the defaults)", describe(engine))
        self.config = config or DepthGPConfig()
        self.engine_config = engine or EngineConfig()
        self.engine = make_engine(self.engine_config)
        self.fitted: DepthGPConfig | None = None
        self._fit_engine = None
        self._point_fit = None

    def complete(
        self,
        mde_depth: np.ndarray,
        sparse: SparseDepth,
        *,
        output_shape: tuple[int, int] | None = None,
        variance: bool = True,
        frame: str | None = None,
    ) -> DepthPosterior:
        """Posterior depth (mean and variance) given an MDE map and sparse measurements.

        Args:
            mde_depth: (H, W) MDE z-depth in metres (0/NaN/inf = none).
            sparse: Range measurements (any resolution of the same image).
            output_shape: (Ho, Wo) of the result; default (H, W).
            variance: Compute the marginal variance (else it is NaN, and faster).
            frame: Name of the frame, used in the posterior's warnings.
        """
        strategy = formulation_of(self.config)  # `gpdepth3d.completion.formulations`
        with on_cold_cache():  # a first run's later kernels compile on another core meanwhile
            return DepthPosterior(**strategy.posterior(self, mde_depth, sparse, output_shape, variance, frame))

    def map(
        self,
        frames: Iterable[tuple[np.ndarray, SparseDepth]],
        *,
        workers: int | None = 1,
        output_shape: tuple[int, int] | None = None,
        variance: bool = True,
    ) -> Iterator[DepthPosterior]:
        """Completes a sequence of frames, yielding their posteriors in order; ``workers`` frames at a time.

        With ``workers`` > 1 (None: one per core) each worker thread completes whole frames with its own
        completer of this configuration (`gpdepth3d.completion.parallel`): the cores are used across frames
        where a frame alone cannot use them. Each posterior is the one `complete` gives. With ``config.fit``
        a frame starts from the previous frame's fit, so the frames run one after another (as ``workers=1``).

        Args:
            frames: (mde_depth, sparse) pairs, read as the workers need them.
            workers: Frames completed at the same time (>= 1; None: the cores this process may use).
            output_shape, variance: As in `complete`, for every frame.

        Raises:
            InvalidInputError: ``workers`` is not an integer >= 1 or None.
        """
        from .parallel import check_workers, map_frames

        workers = check_workers(workers)
        if workers == 1 or self.config.fit:
            return (self.complete(d, s, output_shape=output_shape, variance=variance) for d, s in frames)
        return map_frames(
            lambda: DepthCompleter(self.config, engine=self.engine_config),
            frames,
            workers,
            output_shape=output_shape,
            variance=variance,
        )

    __call__ = complete


def complete(
    mde_depth: np.ndarray,
    sparse: SparseDepth,
    *,
    config: DepthGPConfig | None = None,
    engine: EngineConfig | None = None,
    output_shape: tuple[int, int] | None = None,
    variance: bool = True,
    frame: str | None = None,
) -> DepthPosterior:
    """Completes one frame: dense posterior depth and variance from an MDE map and sparse depth.

    See `DepthCompleter` for ``config`` and ``engine`` and `DepthCompleter.complete` for the other
    arguments; the module docstring states the input rules.
    """
    return DepthCompleter(config, engine=engine).complete(
        mde_depth, sparse, output_shape=output_shape, variance=variance, frame=frame
    )
