"""Evaluation of depth-completion methods on real data: protocols x densities x methods.

Every method sees the same frames, the same MDE map and the same sparse input; metrics are
computed against the same ground truth. Methods (`METHODS`):

* ``mde``: the MDE alone.
* ``mde_scale``: the MDE times one robust global scale fitted to the sparse points.
* ``ip_basic``: IP-Basic (Ku et al. 2018) from the sparse points only (`gpdepth3d.evaluation.baselines`).
* ``gp_default_fit``: the default model with ``fit=True``: its length scale, output scale,
  nugget and global scale fitted per frame by marginal likelihood on the points
  (`gpdepth3d.gp.fit.fit_log_residual`), warm-started along the sequence.
* ``gp_balanced``: the paper's balanced GP (`DepthGPConfig.paper`), MDE pixels and points both
  observations; solved on a GP grid of ``balanced_factor`` times the evaluation resolution (the
  paper worked at 1/3 KITTI resolution) with the output at full evaluation resolution.
* ``gp_balanced_fit``: the same with ``config.fit``: length scale, output scale and sigma_DL
  fitted per frame by maximising the exact marginal likelihood of all its observations
  (`gpdepth3d.completion.marginal_fit.fit_hyperparameters`, starting from the paper's values).
* ``gp_residual``: the residual GP (`DepthGPConfig.residual`): scale-aligned MDE as prior mean,
  the GP models its additive error.
* ``gp_residual_fit``: the residual GP with its length scale, output scale and measurement
  noise (which absorbs the MDE's white error) fitted per frame by maximising the exact marginal
  likelihood (`gpdepth3d.completion.marginal_fit.fit_hyperparameters`, the library's one fitter).
* ``gp_relative``: beyond both: the residual GP on the *ratio* depth / MDE (a multiplicative
  MDE error, whose size grows with depth as a monocular network's does), plus a white-noise
  MDE component (pixel-level error the smooth field cannot explain). See `relative_residual`.

Ground truth: the dense depth of the frame where the dataset has one (7-Scenes, iBims); else a
held-out share of the dataset's own sparse points (KITTI, SLAM features), see
`gpdepth3d.sampling.holdout_split`: the protocols then draw only from the remaining points.

Results: one row per (frame, protocol, level, method) with every `depth_metrics` and
`calibration_metrics` value, aggregated per (protocol, level, method) as the mean over frames;
written as CSV and JSON (atomically), a markdown table, an RMSE-vs-density PNG per protocol and
a qualitative figure. A whole run: `run_evaluation` (the command line: ``gpdepth3d eval``).
"""

from __future__ import annotations

import csv
import io as _io
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Literal, Sequence

import numpy as np

from .baselines import ip_basic
from ..pipelines.scoring import CALIBRATION_NAMES as CALIBRATION_NAMES
from ..pipelines.previews import plot_qualitative
from ..pipelines.scoring import metric_row
from ..datasets.synthetic import MDESimulation, simulate_mde
from ..completion.complete import DepthCompleter
from ..completion.marginal_fit import fit_hyperparameters
from ..datasets import Frame, open_dataset
from ..depthmap import fill_nearest, resize_map
from ..errors import EmptyInputError, InvalidInputError, ProblemTooLargeError
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..io import atomic_path, atomic_write, write_json
from ..mde.align import align_depth
from ..measurements import SparseDepth
from ..metrics import METRIC_NAMES
from ..sampling import (
    PAPER_DENSITIES,
    sample_band,
    sample_scanlines,
    sample_uniform,
    beam_ids,
    holdout_mask,
    lidar_elevation,
)

METHODS: tuple[str, ...] = (
    "mde",
    "mde_scale",
    "ip_basic",
    "gp_default",
    "gp_default_fit",
    "gp_balanced",
    "gp_balanced_fit",
    "gp_residual",
    "gp_residual_fit",
    "gp_relative",
)
PROTOCOLS: tuple[str, ...] = ("uniform", "density", "hband", "vband", "scanlines")
ProtocolName = Literal["uniform", "density", "hband", "vband", "scanlines"]


# ----------------------------------------------------------------------------- methods
@dataclass(frozen=True)
class MethodOutput:
    """A method's dense prediction: mean (H, W) metres, variance (H, W) m^2 or None, seconds."""

    mean: np.ndarray
    variance: np.ndarray | None
    seconds: float
    note: str = ""


def relative_residual(
    mde: np.ndarray, sparse: SparseDepth, completer: DepthCompleter, *, white: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Residual GP on the depth ratio rho = depth / MDE, with an optional white MDE error.

    Model: depth(x) = MDE(x) * rho(x), rho = s * (1 + g(x)) + w(x), where g is the GP of
    ``completer.config`` (residual formulation, relative units so its scales are fractions),
    s the robust global scale (``config.align``) and w white noise of standard deviation
    ``white`` (a fraction): the MDE's pixel-level error, which the smooth g cannot explain.
    Each measured point gives rho_j = z_j / MDE(x_j) with noise sd sqrt((sigma_j / MDE)^2 +
    white^2); the posterior of rho is computed by the completer on a constant unit prior map,
    then mapped back: mean = MDE * E[rho], variance = MDE^2 * (Var[rho] + white^2).

    Args:
        mde: (H, W) MDE depth, metres (0 = none; filled from the nearest valid pixel).
        sparse: Measurements of the same image.
        completer: A `DepthCompleter` whose config has formulation "residual".
        white: White-noise share of the MDE error (e.g. 0.05 = 5 % of the depth).

    Returns:
        (mean (H, W) metres, variance (H, W) m^2).
    """
    cfg = completer.config
    if cfg.formulation != "residual":
        raise InvalidInputError("completer", "a completer with the residual formulation", cfg.formulation)
    if not np.isfinite(white) or white < 0:
        raise InvalidInputError("white", "a share >= 0", white)
    m = np.asarray(mde, dtype=np.float64)
    valid = np.isfinite(m) & (m > 0)
    if not valid.any():
        raise EmptyInputError("mde", "at least one valid MDE pixel", "none")
    if not valid.all():
        m = fill_nearest(np.where(valid, m, 0.0), valid)
    g = sparse.rasterize(m.shape)
    r, c = g.v.astype(np.int64), g.u.astype(np.int64)
    md = m[r, c]
    sig = np.where(np.isfinite(g.sigma), g.sigma, cfg.sigma_meas * (1.0 if cfg.units == "metres" else md))
    ratio_sigma = np.sqrt((sig / md) ** 2 + white**2)
    ratio = SparseDepth(g.u, g.v, g.depth / md, m.shape, ratio_sigma)
    unit_cfg = cfg if cfg.units == "relative" else cfg.replace(units="relative")
    if unit_cfg is not cfg:
        completer = DepthCompleter(unit_cfg)
    post = completer.complete(np.ones_like(m), ratio)
    return m * post.mean, m**2 * (post.variance + white**2)


@dataclass
class MethodSuite:
    """Runs the methods of `METHODS` on one frame with shared engines (caches survive frames).

    With ``engine.name`` "exact" a problem is solved by the exact engine while it fits it
    (``engine.max_exact_points`` observed pixels, 6e7 cross-covariance entries) and by the ``fast``
    engine beyond; "fast" and "kissgp" are used as given.

    Args:
        residual: Config of ``gp_residual`` (default `DepthGPConfig.residual`).
        balanced: Config of ``gp_balanced`` (default `DepthGPConfig.paper`).
        relative: Config of the GP of ``gp_relative`` (residual formulation, relative units).
        relative_white: White MDE error share of ``gp_relative``.
        balanced_factor: GP grid of ``gp_balanced`` relative to the evaluation resolution.
        device: Torch device for the fast engine (None = NumPy on the CPU).
        engine: The engine of the ``gp_residual``, ``gp_relative`` and ``gp_balanced`` methods
            (`gpdepth3d.gp.EngineConfig`; None: the ``fast`` engine).
    """

    residual: DepthGPConfig | None = None
    balanced: DepthGPConfig | None = None
    relative: DepthGPConfig | None = None
    relative_white: float = 0.05
    balanced_factor: float = 0.5
    device: str | None = None
    engine: EngineConfig | None = None
    _completers: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.residual is None:
            self.residual = DepthGPConfig.residual()
        if self.balanced is None:
            self.balanced = DepthGPConfig.paper()
        if self.relative is None:
            self.relative = DepthGPConfig.residual(lengthscale=40.0, outputscale=0.2, sigma_meas=0.01)
        if not 0 < self.balanced_factor <= 1:
            raise InvalidInputError("balanced_factor", "a resolution factor in (0, 1]", self.balanced_factor)

    def _completer(self, config: DepthGPConfig, n_observed: int, n_output: int) -> DepthCompleter:
        """A cached completer; the "exact" engine falls back to "fast" when the problem is too large for it."""
        options = self.engine or EngineConfig()
        if options.name == "exact" and (n_observed > options.max_exact_points or n_observed * n_output > 60_000_000):
            options = options.replace(name="fast")
        if options.name == "fast" and self.device is not None:
            options = options.replace(device=self.device)
        if (config, options) not in self._completers:
            self._completers[config, options] = DepthCompleter(config, engine=options)
        return self._completers[config, options]

    def run(self, name: str, mde: np.ndarray, sparse: SparseDepth) -> MethodOutput:
        """Runs method ``name`` on an (H, W) MDE map and the sparse input; output at (H, W)."""
        t0 = time.perf_counter()
        shape = mde.shape
        if name == "mde":
            return MethodOutput(mde.copy(), None, 0.0)
        if name == "mde_scale":
            g = sparse.rasterize(shape)
            fit = align_depth(mde[g.v.astype(int), g.u.astype(int)], g.depth, "scale")
            return MethodOutput(fit.apply(mde), None, time.perf_counter() - t0)
        if name == "ip_basic":
            return MethodOutput(ip_basic(sparse, shape), None, time.perf_counter() - t0)
        if name in ("gp_default", "gp_default_fit"):  # the library's default model, warm-started along the sequence
            if name not in self._completers:  # the device (--device cuda) reaches the default model too
                engine = EngineConfig() if self.device is None else EngineConfig(device=self.device)
                self._completers[name] = DepthCompleter(DepthGPConfig(fit=name == "gp_default_fit"), engine=engine)
            completer = self._completers[name]
            post = completer.complete(mde, sparse)
            return MethodOutput(post.mean, post.variance, time.perf_counter() - t0, f"{post.n_rejected} rejected")
        if name == "gp_residual":
            post = self._completer(self.residual, len(sparse), mde.size).complete(mde, sparse)
            return MethodOutput(post.mean, post.variance, time.perf_counter() - t0)
        if name == "gp_residual_fit":
            # the library's one fitter (exact marginal likelihood; sigma_meas absorbs the MDE's white error)
            fitted = fit_hyperparameters(
                mde, sparse, self.residual, params=("lengthscale", "outputscale", "sigma_meas")
            )
            # the fitted config differs per frame: no caching of completers for it
            engine = self._completer(self.residual, len(sparse), mde.size).engine_config
            post = DepthCompleter(fitted, engine=engine).complete(mde, sparse)
            note = ""
            return MethodOutput(post.mean, post.variance, time.perf_counter() - t0, note)
        if name == "gp_relative":
            mean, var = relative_residual(
                mde, sparse, self._completer(self.relative, len(sparse), mde.size), white=self.relative_white
            )
            return MethodOutput(mean, var, time.perf_counter() - t0)
        if name in ("gp_balanced", "gp_balanced_fit"):
            h, w = shape
            gh, gw = max(2, round(h * self.balanced_factor)), max(2, round(w * self.balanced_factor))
            small = resize_map(mde, (gh, gw), shrink="area", grow="area")
            n_obs = int(np.sum(np.isfinite(small) & (small > 0)))
            completer = self._completer(self.balanced, n_obs, h * w)
            if name == "gp_balanced_fit":  # a fresh fit per frame (no warm start across frames)
                completer = DepthCompleter(completer.config.replace(fit=True), engine=completer.engine_config)
            post = completer.complete(small, sparse, output_shape=shape)
            note = "" if (gh, gw) == shape else f"GP grid {gw}x{gh}"
            return MethodOutput(post.mean, post.variance, time.perf_counter() - t0, note)
        raise InvalidInputError("method", f"one of {METHODS}", name)


# ----------------------------------------------------------------------------- protocols
def protocol_levels(protocol: str, points: Sequence[float] | None) -> list[float]:
    """Default levels of a protocol: numbers of points (uniform, bands), densities, or k (scan lines)."""
    if points:
        return [float(p) for p in points]
    if protocol == "density":
        return list(PAPER_DENSITIES)
    if protocol == "scanlines":
        return [1.0, 2.0, 4.0, 8.0]
    return [50.0, 200.0, 500.0]


def level_label(protocol: str, level: float) -> str:
    """Human-readable label of a level ("200 pts", "1/16", "every 4th beam")."""
    if protocol == "density":
        if level >= 1:
            return "1x"
        inv = 1.0 / level
        return f"1/{inv:.0f}" if abs(inv - round(inv)) < 1e-6 else f"{level:.3g}"
    if protocol == "scanlines":
        return f"1/{int(level)} beams"
    return f"{int(level)} pts"


def draw_sparse(
    protocol: str, level: float, available: SparseDepth, *, rng: np.random.Generator, beams: np.ndarray | None = None
) -> SparseDepth:
    """The sparse input of one protocol level, drawn from the available points.

    * uniform: ``level`` points uniformly at random.
    * density: a share ``level`` of the available points.
    * hband / vband: ``level`` points inside the lower half rows / the left half columns.
    * scanlines: every ``level``-th LiDAR beam (``beams`` = beam id per available point).
    """
    if protocol == "uniform":
        return sample_uniform(available, n=int(level), rng=rng)
    if protocol == "density":
        return sample_uniform(available, density=float(level), rng=rng)
    if protocol == "hband":
        return sample_band(available, axis="horizontal", start=0.5, stop=1.0, n=int(level), rng=rng)
    if protocol == "vband":
        return sample_band(available, axis="vertical", start=0.0, stop=0.5, n=int(level), rng=rng)
    if protocol == "scanlines":
        if beams is None:
            raise InvalidInputError("beams", "beam ids of the available points (LiDAR data only)", None)
        return sample_scanlines(available, keep_every=int(level), beams=beams)
    raise InvalidInputError("protocol", f"one of {PROTOCOLS}", protocol)


# ----------------------------------------------------------------------------- running
@dataclass(frozen=True)
class EvalSetup:
    """Ground truth and available points of one frame at the evaluation resolution."""

    frame: Frame
    mde: np.ndarray
    gt: np.ndarray
    available: SparseDepth
    beams: np.ndarray | None
    gt_kind: str


def prepare_frame(
    frame: Frame,
    mde: Callable[[np.ndarray], np.ndarray],
    *,
    resolution: float = 0.5,
    holdout: float = 0.2,
    rng: np.random.Generator,
    need_beams: bool = False,
) -> EvalSetup:
    """Resizes a frame, runs the MDE and splits off ground truth (dense, or held-out points).

    Beam ids for the scan-line protocol are recovered at full resolution (with the frame's
    LiDAR calibration when it has one) and carried to the evaluation grid.
    """
    beams_full = None
    if need_beams:
        if frame.sparse is None:
            raise InvalidInputError("protocol", "a dataset with LiDAR points for 'scanlines'", frame.name)
        if frame.calibration is None and frame.camera is None:
            raise InvalidInputError("protocol", "a dataset with a camera or LiDAR calibration", frame.name)
        beams_full = beam_ids(lidar_elevation(frame.sparse, frame.calibration, frame.camera))
    small = frame.resized(resolution)
    depth_map = np.asarray(mde(small.rgb), dtype=np.float64)
    beams = None
    if small.depth is not None:
        gt = small.depth
        available = SparseDepth.from_depth_map(gt)
        kind = "dense"
        if need_beams:
            raise InvalidInputError("protocol", "'scanlines' only for LiDAR datasets", frame.name)
    else:
        if frame.sparse is None or len(frame.sparse) < 2:
            raise InvalidInputError("data", "dense ground truth or sparse points to hold out", frame.name)
        full = frame.sparse
        if beams_full is not None:
            # keep beam ids through the closest-per-pixel rasterisation by rasterising (depth, beam) pairs
            g = full.rasterize(small.shape)
            row, col = full.pixel_indices(small.shape)
            lookup = {}
            order = np.lexsort((full.depth, row * small.shape[1] + col))
            for i in order[::-1]:
                lookup[(row[i], col[i])] = beams_full[i]
            grid_beams = np.array([lookup[(int(v), int(u))] for v, u in zip(g.v, g.u)], dtype=np.int64)
        else:
            g = full.rasterize(small.shape)
            grid_beams = None
        test = holdout_mask(len(g), holdout=holdout, rng=rng)
        available = g.subset(~test)
        gt = g.subset(test).to_depth_map()
        beams = grid_beams[~test] if grid_beams is not None else None
        kind = f"held-out {holdout:.0%} of points"
    return EvalSetup(small, depth_map, gt, available, beams, kind)


def evaluate(
    frames: Iterable[Frame],
    mde: Callable[[np.ndarray], np.ndarray],
    *,
    protocols: Sequence[str] = ("uniform",),
    levels: dict[str, Sequence[float]] | None = None,
    methods: Sequence[str] = METHODS,
    suite: MethodSuite | None = None,
    resolution: float = 0.5,
    seed: int = 0,
    progress: bool = True,
    on_frame: Callable[[EvalSetup, dict], None] | None = None,
) -> list[dict]:
    """Runs every method on every frame, protocol and level; returns one row per run.

    Args:
        frames: The frames (e.g. a dataset reader, or a list).
        mde: The MDE front-end, rgb (H, W, 3) uint8 -> depth (H, W) metres.
        protocols: Names from `PROTOCOLS`.
        levels: Per protocol the levels (see `protocol_levels`); default per protocol.
        methods: Names from `METHODS`.
        suite: The method runner (default `MethodSuite()`).
        resolution: Evaluation resolution relative to the dataset's images (0.5 = half).
        seed: Seed of all random draws (each frame gets its own stream).
        progress: Show a tqdm bar over frames.
        on_frame: Called after each frame with its setup and {(protocol, level, method): output}.

    Returns:
        Rows with keys frame, protocol, level, label, method, n_points, every metric of
        `METRIC_NAMES` and of calibration (NaN where a method gives no variance), seconds, note.
    """
    from tqdm import tqdm

    for p in protocols:
        if p not in PROTOCOLS:
            raise InvalidInputError("protocols", f"names from {PROTOCOLS}", p)
    for m in methods:
        if m not in METHODS:
            raise InvalidInputError("methods", f"names from {METHODS}", m)
    if not np.isfinite(resolution) or not 0 < resolution <= 4:
        raise InvalidInputError("resolution", "a factor in (0, 4]", resolution)
    suite = suite or MethodSuite()
    levels = dict(levels or {})
    frames = list(frames) if not hasattr(frames, "__len__") else frames
    rows: list[dict] = []
    bar = tqdm(frames, desc="eval", unit="frame", disable=not progress, total=len(frames))
    for index, frame in enumerate(bar):
        rng = np.random.default_rng([seed, index])
        setup = prepare_frame(frame, mde, resolution=resolution, rng=rng, need_beams="scanlines" in protocols)
        outputs: dict = {}
        for protocol in protocols:
            for level in protocol_levels(protocol, levels.get(protocol)):
                sparse = draw_sparse(protocol, level, setup.available, rng=rng, beams=setup.beams)
                for method in methods:
                    row = {
                        "frame": frame.name,
                        "protocol": protocol,
                        "level": float(level),
                        "label": level_label(protocol, level),
                        "method": method,
                        "n_points": len(sparse),
                        "gt": setup.gt_kind,
                    }
                    try:
                        if len(sparse) == 0 and method not in ("mde",):
                            raise EmptyInputError("sparse", "at least one measurement", 0)
                        out = suite.run(method, setup.mde, sparse)
                    except (ProblemTooLargeError, EmptyInputError, ImportError) as exc:
                        row.update({k: math.nan for k in METRIC_NAMES + CALIBRATION_NAMES})
                        row.update(seconds=math.nan, note=f"skipped: {exc}")
                        rows.append(row)
                        continue
                    row.update(metric_row(out.mean, out.variance, setup.gt))
                    row.update(seconds=out.seconds, note=out.note)
                    rows.append(row)
                    outputs[(protocol, float(level), method)] = (out, sparse)
        if on_frame is not None:
            on_frame(setup, outputs)
    return rows


def summarize(rows: Sequence[dict]) -> list[dict]:
    """Mean over frames of every metric per (protocol, level, method), in first-seen order.

    A run that was skipped (NaN) is left out of the mean; ``frames`` counts the runs averaged.
    """
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["protocol"], r["level"], r["method"]), []).append(r)
    out = []
    for (protocol, level, method), rs in groups.items():
        s = {"protocol": protocol, "level": level, "label": rs[0]["label"], "method": method}
        ok = [r for r in rs if np.isfinite(r["rmse"])]
        s["frames"] = len(ok)
        s["n_points"] = float(np.mean([r["n_points"] for r in rs]))
        for k in METRIC_NAMES + CALIBRATION_NAMES + ("seconds",):
            vals = [r[k] for r in ok if np.isfinite(r[k])]
            s[k] = float(np.mean(vals)) if vals else math.nan
        notes = sorted({r["note"] for r in rs if r["note"]})
        s["note"] = "; ".join(notes)[:300]
        out.append(s)
    return out


# ----------------------------------------------------------------------------- output
def write_csv(rows: Sequence[dict], path: str | Path) -> Path:
    """Writes rows (dicts with one key set) as CSV, atomically."""
    if not rows:
        raise EmptyInputError("rows", "at least one row", 0)
    keys = list(rows[0].keys())
    buf = _io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    for r in rows:
        writer.writerow({k: r.get(k) for k in keys})
    return atomic_write(path, lambda tmp: tmp.write_text(buf.getvalue()))


TABLE_UNITS: dict[str, str] = {
    "rmse": "mm",
    "mae": "mm",
    "irmse": "1/km",
    "imae": "1/km",
    "rel": "-",
    "delta1": "%",
    "delta2": "%",
    "delta3": "%",
    "nll": "nats/px",
    "coverage_1sigma": "%",
    "coverage_2sigma": "%",
}
"""Units of the columns of `markdown_table` (shown in its header)."""


def markdown_table(summary: Sequence[dict], *, metrics: Sequence[str] | None = None) -> str:
    """A markdown table of the summary: one row per (protocol, level, method)."""
    metrics = list(
        metrics or ("rmse", "mae", "irmse", "imae", "rel", "delta1", "nll", "coverage_1sigma", "coverage_2sigma")
    )
    head = ["protocol", "level", "method", "points"] + [
        f"{k} [{TABLE_UNITS[k]}]" if k in TABLE_UNITS else k for k in metrics
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for s in summary:
        cells = [s["protocol"], s["label"], s["method"], f"{s['n_points']:.0f}"]
        for k in metrics:
            v = s[k]
            if not np.isfinite(v):
                cells.append("-")
            elif k in ("rmse", "mae", "irmse", "imae"):
                cells.append(f"{v:.0f}")
            elif k.startswith("coverage") or k.startswith("delta"):
                cells.append(f"{100 * v:.1f}%")
            else:
                cells.append(f"{v:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_rmse_vs_level(summary: Sequence[dict], protocol: str, path: str | Path) -> Path:
    """Paper-style plot: RMSE (mm) against the level (points/density) per method, PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [s for s in summary if s["protocol"] == protocol and np.isfinite(s["rmse"])]
    if not rows:
        raise EmptyInputError("summary", f"rows of protocol {protocol!r}", 0)
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for method in dict.fromkeys(s["method"] for s in rows):
        rs = sorted((s for s in rows if s["method"] == method), key=lambda s: s["n_points"])
        ax.plot([s["n_points"] for s in rs], [s["rmse"] for s in rs], marker="o", label=method)
    ax.set_xscale("log")
    ax.set_xlabel("number of sparse points (mean)")
    ax.set_ylabel("RMSE [mm]")
    ax.set_title(f"RMSE vs density ({protocol})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(Path(path).with_suffix(".png")) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path).with_suffix(".png")


def qualitative_choice(outputs: dict) -> tuple | None:
    """The (protocol, level, method) the qualitative figure shows: the default model at its highest level.

    Falls back to the first method with a variance when ``gp_default`` was not run; None without any.

    Args:
        outputs: {(protocol, level, method): (output with ``.variance``, sparse)} of one frame.
    """
    for key in sorted(outputs, key=lambda k: (k[2] != "gp_default", -k[1])):
        if outputs[key][0].variance is not None:
            return key
    return None


# ----------------------------------------------------------------------------- stand-in MDE
class DegradedGroundTruthMDE:
    """A stand-in MDE built from the ground truth (for tests and ablations, not a real network).

    The current frame's dense ground truth (set ``frame``; holes filled from the nearest valid
    pixel) through `gpdepth3d.datasets.synthetic.simulate_mde`: blurred (``blur`` = Gaussian
    sigma as a fraction of the image width), multiplied by ``scale`` and by a smooth random
    log-depth error of standard deviation ``noise`` (correlation length a quarter of the width);
    the same error field for every frame of a run (``seed``).
    """

    def __init__(self, *, scale: float = 1.15, noise: float = 0.1, blur: float = 0.03, seed: int = 0):
        self.scale, self.noise, self.blur, self.seed = scale, noise, blur, seed
        self.frame: Frame | None = None

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        if self.frame is None or self.frame.depth is None:
            raise InvalidInputError("mde", "'gt-degraded' only with a dataset with dense ground truth", None)
        gt = resize_map(self.frame.depth.astype(np.float32), rgb.shape[:2], shrink="nearest", grow="nearest")
        if not (gt > 0).any():
            raise EmptyInputError("ground truth", "valid pixels", 0)
        sim = MDESimulation(
            scale=self.scale, blur_sigma=self.blur, field_amplitude=self.noise, field_lengthscale=0.25, noise=0.0
        )
        return simulate_mde(gt, sim, np.random.default_rng(self.seed))


# ----------------------------------------------------------------------------- a whole run
DEFAULT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m not in ("gp_balanced_fit", "gp_default_fit"))
"""The methods of `run_evaluation` by default: all but the fitted gp_balanced_fit and gp_default_fit (they fit per
frame and level)."""

FRONTEND_NAMES: tuple[str, ...] = ("fastdepth", "rtmonodepth", "rtmonodepth-mono", "gt-degraded")
"""The MDE choices of `run_evaluation`: the named networks and the ground-truth stand-in."""


def run_evaluation(
    data: str | Path,
    *,
    mde: str = "fastdepth",
    protocols: Sequence[str] = ("uniform",),
    levels: Sequence[float] | None = None,
    output: str | Path = "eval_output",
    frames: int | None = None,
    stride: int = 1,
    resolution: float = 0.5,
    methods: Sequence[str] = DEFAULT_METHODS,
    model: str | Path | None = None,
    seed: int = 0,
    device: str | None = None,
    qualitative: bool = True,
    progress: bool = True,
) -> list[dict]:
    """Evaluates depth completion on a dataset folder and writes CSV/JSON/markdown/PNG results.

    Writes into ``output``: results.csv (one row per frame, protocol, level and method),
    summary.csv, results.json, summary.md (`markdown_table` of the summary), rmse_<protocol>.png
    and, with ``qualitative``, qualitative.png (the first frame).

    Args:
        data: Dataset folder (7scenes, kitti_tiny, kitti_object, ibims_sample, vio_sparse;
            the layout is detected).
        mde: Monocular front-end (`FRONTEND_NAMES`): "fastdepth" (TFLite FastDepth, indoor),
            "rtmonodepth" (ONNX RT-MonoDepth-S, KITTI, metric), "rtmonodepth-mono" (its
            mono-only model: relative depth) or "gt-degraded" (a blurred, mis-scaled ground
            truth; datasets with dense ground truth only).
        protocols: Names from `PROTOCOLS`: uniform (N points), density (the paper's eight
            densities, shares of the available points), hband (lower half rows), vband (left
            half columns), scanlines (every k-th LiDAR beam; KITTI).
        levels: The levels of every protocol, e.g. (50, 200, 500) points, (0.0156, 0.25)
            densities or (1, 2, 4) scan-line strides; None = each protocol's defaults.
        output: Output folder.
        frames: Use at most this many frames (after ``stride``).
        stride: Use every stride-th frame.
        resolution: Evaluation resolution relative to the images (0.5 = half).
        methods: Names from `METHODS` (default `DEFAULT_METHODS`).
        model: The front-end's model file (default: its file in the folder of
            `gpdepth3d.mde.default_models_dir` near ``data``, i.e. shared/models).
        seed: Seed of the sampling.
        device: Torch device for the fast GP engine ("cuda"); default NumPy on the CPU.
        qualitative: Also draw the qualitative figure of the first frame (the default model's posterior at the
            highest level, else the first method with a variance).
        progress: Show the progress bar.

    Returns:
        The summary rows (one per protocol, level and method).
    """
    data = Path(data)
    protocols, method_list, level_values = _check_eval_args(protocols, methods, levels, stride, frames, mde)
    dataset = open_dataset(data)
    indices = list(range(0, len(dataset), stride))[: frames if frames is not None else None]
    front, degraded = _front_end(mde, data, model, seed)
    first: dict = {}

    def keep_first(setup: EvalSetup, outputs: dict) -> None:
        if first or not qualitative:
            return
        key = qualitative_choice(outputs)
        if key is not None:
            out, sparse = outputs[key]
            first.update(setup=setup, out=out, sparse=sparse, key=key)

    levels = {p: level_values for p in protocols} if level_values else None
    rows = evaluate(
        _EvalFrames(dataset, indices, degraded),
        front,
        protocols=protocols,
        levels=levels,
        methods=method_list,
        suite=MethodSuite(device=device),
        resolution=resolution,
        seed=seed,
        progress=progress,
        on_frame=keep_first,
    )
    summary = summarize(rows)
    output = Path(output)
    info = {
        "data": str(data),
        "dataset": type(dataset).__name__,
        "mde": mde,
        "resolution": resolution,
        "frames": [dataset.names[i] for i in indices],
        "seed": seed,
    }
    _write_results(rows, summary, output, info, protocols)
    if first:
        _plot_first(first, output)
    return summary


def _check_eval_args(
    protocols: Sequence[str] | str,
    methods: Sequence[str] | str,
    levels: Sequence[float] | None,
    stride: int,
    frames: int | None,
    mde: str,
) -> tuple[list[str], list[str], list[float]]:
    """Checks `run_evaluation`'s choices: (protocols, methods, levels) as lists."""
    protocols = list(protocols) if not isinstance(protocols, str) else [protocols]
    for p in protocols:
        if p not in PROTOCOLS:
            raise InvalidInputError("protocols", f"names from {PROTOCOLS}", protocols)
    method_list = list(methods) if not isinstance(methods, str) else [methods]
    for m in method_list:
        if m not in METHODS:
            raise InvalidInputError("methods", f"names from {METHODS}", methods)
    level_values = list(levels) if levels is not None else []
    if not all(isinstance(x, (int, float, np.integer, np.floating)) and math.isfinite(x) for x in level_values):
        raise InvalidInputError("levels", "finite numbers such as (50, 200, 500)", levels)
    if int(stride) != stride or stride < 1:
        raise InvalidInputError("stride", "an integer >= 1", stride)
    if frames is not None and (int(frames) != frames or frames < 1):
        raise InvalidInputError("frames", "a number of frames >= 1", frames)
    if mde not in FRONTEND_NAMES:
        raise InvalidInputError("mde", " or ".join(repr(n) for n in FRONTEND_NAMES), mde)
    return protocols, method_list, level_values


def _front_end(mde: str, data: Path, model: str | Path | None, seed: int) -> tuple[Any, Any]:
    """The monocular front-end named ``mde`` and, for "gt-degraded", the same object (else None)."""
    degraded = None
    if mde in ("fastdepth", "rtmonodepth", "rtmonodepth-mono"):
        from ..mde import default_models_dir, load_frontend

        front = load_frontend(mde, models_dir=default_models_dir(near=data)) if model is None else load_frontend(model)
    else:
        degraded = DegradedGroundTruthMDE(seed=seed)
        front = degraded
    return front, degraded


class _EvalFrames:
    """The chosen frames of a dataset, read one at a time (each shown to the degraded front-end first)."""

    def __init__(self, dataset: Any, indices: list[int], degraded: Any) -> None:
        self.dataset, self.indices, self.degraded = dataset, indices, degraded

    def __len__(self):
        return len(self.indices)

    def __iter__(self):
        for i in self.indices:
            f = self.dataset[i]
            if self.degraded is not None:
                self.degraded.frame = f
            yield f


def _write_results(rows: list[dict], summary: list[dict], output: Path, info: dict, protocols: list[str]) -> None:
    """Writes results.csv, summary.csv, results.json, summary.md and the RMSE plots."""
    write_csv(rows, output / "results.csv")
    write_csv(summary, output / "summary.csv")
    write_json(output / "results.json", {**info, "summary": summary, "rows": rows})
    table = markdown_table(summary)
    atomic_write(output / "summary.md", lambda tmp: tmp.write_text(table + "\n"))
    for p in protocols:
        if any(s["protocol"] == p and np.isfinite(s["rmse"]) for s in summary):
            plot_rmse_vs_level(summary, p, output / f"rmse_{p}.png")


def _plot_first(first: dict, output: Path) -> None:
    """Draws qualitative.png of the kept first frame."""
    s, out = first["setup"], first["out"]
    protocol_name, level, method = first["key"]
    plot_qualitative(
        s.frame.rgb,
        s.mde,
        first["sparse"],
        out.mean,
        np.sqrt(np.maximum(out.variance, 0)),
        s.gt,
        output / "qualitative.png",
        title=f"{s.frame.name}: {method}, {protocol_name} {level_label(protocol_name, level)}",
    )
