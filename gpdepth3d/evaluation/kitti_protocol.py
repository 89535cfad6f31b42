"""The paper's KITTI experiment (Yoon & Kim 2020, Sec. V and Fig. 7) on LiDAR-only data, as functions.

Protocol (one frame, `prepare_kitti_frame`):

1. The frame is cropped to a multiple of ``factor`` (nothing is cropped from KITTI's 375x1242
   at factor 3). The MDE runs on the full-resolution image; its depth is shrunk to the GP grid
   (1/``factor``, the paper's 1/3) by area averaging.
2. The projected LiDAR is shrunk to the same grid keeping the closest point of each
   ``factor`` x ``factor`` block (`gpdepth3d.measurements.downsample_depth`: the paper's
   occlusion-aware downsampling).
3. **Ground truth by hold-out** (the data has no dense ground truth): a seeded share
   ``holdout`` of the grid's LiDAR pixels is held out *before* any input is drawn
   (`gpdepth3d.sampling.holdout_split`). Ground truth at 1/``factor`` = those pixels; at full
   resolution = every full-resolution LiDAR point inside a held-out block. No input point ever
   lies in a held-out block, so neither resolution's ground truth is seen by any method.
4. Inputs (`draw_input`), from the remaining points only: ``uniform``: a share ``density`` of
   them drawn uniformly (`gpdepth3d.sampling.sample_uniform`, the paper's eight levels
   `PAPER_DENSITIES`); ``hband`` / ``vband``: the same number of points drawn only inside a band
   of rows / columns (`gpdepth3d.sampling.sample_band`; all of the band's points when it holds
   fewer), the paper's biased measurements.

Methods (`METHODS`): the MDE alone, IP-Basic (`gpdepth3d.evaluation.baselines.ip_basic`, from the points
only), the paper's balanced GP (`DepthGPConfig.paper()`) and the library's default
(`DepthGPConfig()`). Each is scored at the grid resolution and at full resolution: the GPs
predict the full-resolution grid themselves (``output_shape``); IP-Basic's grid output is resized
bilinearly; the MDE alone at full resolution is the network's own full-resolution output.

Metrics: RMSE, MAE (mm), iRMSE, iMAE (1/km) (`gpdepth3d.metrics.depth_metrics`, the paper's
KITTI metrics), and for the GPs the calibration of the variance (NLL, +-1 sigma / +-2 sigma
coverage; `gpdepth3d.metrics.calibration_metrics`). Per-frame values are averaged over frames.
The paper's own numbers (`PAPER_KITTI_RMSE_MM`) were measured on KITTI depth completion against
its semi-dense ground truth with monodepth2: they are a reference, not the same test.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from .baselines import ip_basic
from ..pipelines.frames import HoldoutLidar as HoldoutLidar
from ..pipelines.frames import holdout_lidar as holdout_lidar
from ..pipelines.frames import mde_to_grid
from ..pipelines.scoring import metric_row
from ..depthmap import resize_map
from ..checks import Bool, Int, Real, Reals, check_fields
from ..errors import EmptyInputError, InvalidInputError, ShapeError, describe
from ..gp.engine import EngineConfig
from ..gp.model import DepthGPConfig
from ..measurements import SparseDepth
from ..sampling import PAPER_DENSITIES, SeedLike, make_rng, sample_band, sample_uniform

KITTI_PROTOCOLS: tuple[str, ...] = ("uniform", "hband", "vband")
"""Input protocols: uniform densities, a horizontal band of rows, a vertical band of columns."""

METHODS: tuple[str, ...] = ("mde", "ip_basic", "gp_paper", "gp_default")
"""MDE alone, IP-Basic, the paper's balanced GP (`DepthGPConfig.paper()`), the default (`DepthGPConfig()`)."""

RESOLUTIONS: tuple[str, ...] = ("grid", "full")
"""Where a method is scored: on the GP grid (1/factor) and at the full image resolution."""

PAPER_KITTI_RMSE_MM: dict[str, float] = {"mde": 3951.0, "1/64": 3701.0, "1/16": 3200.0, "1/4": 2252.0, "1x": 1593.0}
"""The paper's KITTI depth-completion RMSE (mm, Fig. 7 table, monodepth2 front-end, full-resolution
output, uniform densities): MDE alone and the balanced GP with 1/64, 1/16, 1/4 and all of the LiDAR."""

METRICS: tuple[str, ...] = ("rmse", "mae", "irmse", "imae")
CALIBRATION: tuple[str, ...] = ("nll", "coverage_1sigma", "coverage_2sigma")


@dataclass(frozen=True)
class KittiProtocolConfig:
    """Options of the KITTI protocol (see the module docstring).

    Attributes:
        factor: Integer downsampling of the image and LiDAR (3 = the paper's 1/3 resolution).
        holdout: Share of the grid's LiDAR pixels held out as ground truth, in (0, 1).
        densities: Input densities, shares of the points that are not held out, in (0, 1].
        protocols: Names from `KITTI_PROTOCOLS`.
        hband: (start, stop) of the horizontal band, fractions of the image height (rows).
        vband: (start, stop) of the vertical band, fractions of the image width (columns).
        methods: Names from `METHODS`.
        full_resolution: Also score every method at full resolution.
        seed: Seed; frame i draws from ``numpy.random.default_rng([seed, i])``.
    """

    factor: int = 3
    holdout: float = 0.2
    densities: tuple[float, ...] = PAPER_DENSITIES
    protocols: tuple[str, ...] = KITTI_PROTOCOLS
    hband: tuple[float, float] = (0.5, 1.0)
    vband: tuple[float, float] = (0.0, 0.5)
    methods: tuple[str, ...] = METHODS
    full_resolution: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        rules = {"factor": Int(1), "holdout": Real(0.0, 1.0, low_open=True, high_open=True, unit="a share")}
        rules.update(densities=Reals(Real(0.0, 1.0, low_open=True, unit="a share")), full_resolution=Bool(), seed=Int())
        check_fields(self, rules)
        for name, allowed in (("protocols", KITTI_PROTOCOLS), ("methods", METHODS)):
            values = getattr(self, name)
            if not values or any(v not in allowed for v in values):
                raise InvalidInputError(name, f"names from {allowed}", values)
        for name in ("hband", "vband"):
            start, stop = getattr(self, name)
            if not (0.0 <= start < stop <= 1.0):
                raise InvalidInputError(name, "(start, stop) fractions with 0 <= start < stop <= 1", (start, stop))

    def gt_description(self) -> str:
        """How the ground truth was made, for every output."""
        return (
            f"no dense ground truth: {self.holdout:.0%} of the LiDAR pixels at 1/{self.factor} resolution held out "
            f"(seeded) before the inputs are drawn; full-resolution ground truth = the LiDAR points in held-out blocks"
        )


def density_label(density: float) -> str:
    """ "1/64", "3/4", "1x" for the paper's levels, else the number."""
    if density >= 1:
        return "1x"
    for den in (2, 4, 8, 16, 32, 64, 128):
        num = density * den
        if abs(num - round(num)) < 1e-9 and round(num) >= 1:
            return f"{int(round(num))}/{den}"
    return f"{density:.4g}"


# ----------------------------------------------------------------------------- sampling
def draw_input(
    protocol: str,
    density: float,
    available: SparseDepth,
    *,
    rng: SeedLike = 0,
    hband: tuple[float, float] = (0.5, 1.0),
    vband: tuple[float, float] = (0.0, 0.5),
) -> SparseDepth:
    """The input points of one protocol and density, drawn from the available points.

    ``uniform``: round(density x n) of the n available points (at least 1), uniformly. ``hband``
    / ``vband``: as many points, drawn only among those inside the band of rows ``hband`` /
    columns ``vband`` (fractions of the image size; all of them when the band holds fewer).

    Args:
        protocol: A name of `KITTI_PROTOCOLS`.
        density: Share of the available points in (0, 1].
        available: The pool (not held-out points).
        rng: Seed or Generator.
        hband: (start, stop) rows of the horizontal band, fractions.
        vband: (start, stop) columns of the vertical band, fractions.
    """
    if protocol == "uniform":
        return sample_uniform(available, density=density, rng=rng)
    if protocol == "hband":
        return sample_band(available, axis="horizontal", start=hband[0], stop=hband[1], density=density, rng=rng)
    if protocol == "vband":
        return sample_band(available, axis="vertical", start=vband[0], stop=vband[1], density=density, rng=rng)
    raise InvalidInputError("protocol", f"one of {KITTI_PROTOCOLS}", protocol)


# ----------------------------------------------------------------------------- one frame
@dataclass(frozen=True)
class KittiFrameSetup:
    """One frame prepared for the protocol.

    Attributes:
        name: Frame name.
        mde_grid: (h, w) MDE depth on the GP grid, metres.
        mde_full: (h * factor, w * factor) the network's full-resolution depth, metres.
        lidar: The hold-out split (`HoldoutLidar`).
    """

    name: str
    mde_grid: np.ndarray
    mde_full: np.ndarray
    lidar: HoldoutLidar

    @property
    def grid_shape(self) -> tuple[int, int]:
        return self.mde_grid.shape  # type: ignore[return-value]

    @property
    def full_shape(self) -> tuple[int, int]:
        return self.mde_full.shape  # type: ignore[return-value]


def prepare_kitti_frame(
    name: str,
    rgb: np.ndarray,
    lidar_depth: np.ndarray,
    mde: Callable[[np.ndarray], np.ndarray],
    *,
    factor: int = 3,
    holdout: float = 0.2,
    rng: SeedLike = 0,
) -> KittiFrameSetup:
    """Runs the MDE on the full image and splits the LiDAR (steps 1-3 of the module docstring).

    Args:
        name: Frame name (for the rows).
        rgb: (H, W, 3) uint8 RGB image.
        lidar_depth: (H, W) projected LiDAR z-depth in metres (0 = no point).
        mde: Front-end ``rgb -> (H, W) depth`` in metres.
        factor: Grid = 1/factor of the image.
        holdout: Share of grid LiDAR pixels held out.
        rng: Seed or Generator of the hold-out split.
    """
    rgb = np.asarray(rgb)
    d = np.asarray(lidar_depth)
    if rgb.ndim != 3 or rgb.shape[:2] != d.shape:
        raise ShapeError("lidar_depth", f"a map of the image size {rgb.shape[:2]}", describe(d))
    split = holdout_lidar(d, factor=factor, holdout=holdout, rng=rng)
    h, w = split.gt_grid.shape
    depth = np.asarray(mde(rgb), dtype=np.float64)
    if depth.shape != rgb.shape[:2]:
        raise ShapeError("mde", f"a front-end returning the image size {rgb.shape[:2]}", describe(depth))
    mde_full = np.ascontiguousarray(depth[: h * factor, : w * factor])
    mde_grid = mde_to_grid(depth, factor)
    return KittiFrameSetup(name, mde_grid, mde_full, split)


@dataclass
class KittiMethods:
    """Runs the protocol's methods on one input; the GP completers are kept between calls.

    Args:
        paper: Config of ``gp_paper`` (default `DepthGPConfig.paper()`).
        default: Config of ``gp_default`` (default `DepthGPConfig()`, read when built).
        engine: The engine of both (`gpdepth3d.gp.EngineConfig`; None: the ``fast`` engine).
    """

    paper: DepthGPConfig | None = None
    default: DepthGPConfig | None = None
    engine: EngineConfig | None = None
    _completers: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.paper = self.paper or DepthGPConfig.paper()
        self.default = self.default or DepthGPConfig()

    def _completer(self, config):
        from ..completion.complete import DepthCompleter

        if config not in self._completers:
            self._completers[config] = DepthCompleter(config, engine=self.engine)
        return self._completers[config]

    def run(
        self, method: str, setup: KittiFrameSetup, sparse: SparseDepth, resolution: str
    ) -> tuple[np.ndarray, np.ndarray | None, float]:
        """(mean, variance or None, seconds) of ``method`` at ``resolution`` ("grid" or "full")."""
        if resolution not in RESOLUTIONS:
            raise InvalidInputError("resolution", f"one of {RESOLUTIONS}", resolution)
        full = resolution == "full"
        t0 = time.perf_counter()
        if method == "mde":
            return (setup.mde_full if full else setup.mde_grid).copy(), None, 0.0
        if method == "ip_basic":
            out = ip_basic(sparse, setup.grid_shape)
            if full:
                out = resize_map(out, setup.full_shape)
            return out, None, time.perf_counter() - t0
        if method in ("gp_paper", "gp_default"):
            config = self.paper if method == "gp_paper" else self.default
            completer = self._completer(config)
            completer.fitted = None  # with config.fit: every call fits from the config, as complete() would
            post = completer.complete(setup.mde_grid, sparse, output_shape=setup.full_shape if full else None)
            return post.mean, post.variance, time.perf_counter() - t0
        raise InvalidInputError("method", f"one of {METHODS}", method)


def evaluate_kitti_frame(
    setup: KittiFrameSetup, config: KittiProtocolConfig, *, methods: KittiMethods | None = None, rng: SeedLike = 0
) -> list[dict]:
    """Every protocol, density, method and resolution on one prepared frame: one row each.

    Rows hold frame, dataset-independent keys protocol, density, label, method, resolution,
    n_points (input points), n_gt (ground-truth pixels), the `METRICS` (NaN-free), the
    `CALIBRATION` keys (NaN for methods without variance), seconds and gt (how it was made).
    """
    methods = methods or KittiMethods()
    rng = make_rng(rng)
    resolutions = RESOLUTIONS if config.full_resolution else ("grid",)
    rows: list[dict] = []
    for protocol in config.protocols:
        for density in config.densities:
            sparse = draw_input(
                protocol, density, setup.lidar.available, rng=rng, hband=config.hband, vband=config.vband
            )
            for method in config.methods:
                for res in resolutions:
                    gt = setup.lidar.gt_full if res == "full" else setup.lidar.gt_grid
                    row = {
                        "frame": setup.name,
                        "protocol": protocol,
                        "density": float(density),
                        "label": density_label(density),
                        "method": method,
                        "resolution": res,
                        "n_points": len(sparse),
                        "n_gt": int(np.count_nonzero(gt)),
                    }
                    mean, var, seconds = methods.run(method, setup, sparse, res)
                    row.update(metric_row(mean, var, gt, depth_keys=METRICS, calibration_keys=CALIBRATION))
                    row["min_mean"] = float(np.min(mean))
                    row["seconds"] = seconds
                    row["gt"] = config.gt_description()
                    rows.append(row)
    return rows


def lidar_frames(dataset) -> Iterable[tuple[str, np.ndarray, np.ndarray]]:
    """(name, rgb, projected LiDAR depth map) of every frame of a KITTI reader (kitti_tiny, kitti_object)."""
    for i in range(len(dataset)):
        frame = dataset[i]
        if frame.sparse is None:
            raise InvalidInputError("dataset", "frames with projected LiDAR points", frame.name)
        yield frame.name, frame.rgb, frame.sparse.to_depth_map(frame.shape)


def run_kitti_protocol(
    frames: Iterable[tuple[str, np.ndarray, np.ndarray]],
    mde: Callable[[np.ndarray], np.ndarray],
    config: KittiProtocolConfig | None = None,
    *,
    methods: KittiMethods | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """The KITTI protocol over frames; returns one row per (frame, protocol, density, method, resolution).

    Args:
        frames: (name, rgb (H, W, 3) uint8, LiDAR depth (H, W) metres) per frame (see `lidar_frames`).
        mde: Front-end ``rgb -> depth`` (metres), e.g. `gpdepth3d.mde.RTMonoDepthONNX`.
        config: Protocol options (default `KittiProtocolConfig()`).
        methods: Method runner (default `KittiMethods()`: the paper preset and `DepthGPConfig()`).
        progress: Called with each frame's name when it is done.
    """
    config = config or KittiProtocolConfig()
    methods = methods or KittiMethods()
    rows: list[dict] = []
    for index, (name, rgb, lidar) in enumerate(frames):
        rows.extend(run_kitti_frame(name, rgb, lidar, mde, config, index=index, methods=methods))
        if progress is not None:
            progress(name)
    if not rows:
        raise EmptyInputError("frames", "at least one frame", 0)
    return rows


def run_kitti_frame(
    name: str,
    rgb: np.ndarray,
    lidar_depth: np.ndarray,
    mde: Callable[[np.ndarray], np.ndarray],
    config: KittiProtocolConfig | None = None,
    *,
    index: int = 0,
    methods: KittiMethods | None = None,
) -> list[dict]:
    """The protocol on one frame, seeded by ``numpy.random.default_rng([config.seed, index])``
    (``index`` = the frame's position in its dataset, so a frame's draws do not depend on which
    other frames are run); rows as `evaluate_kitti_frame`."""
    config = config or KittiProtocolConfig()
    if isinstance(index, bool) or int(index) != index or index < 0:
        raise InvalidInputError("index", "an integer >= 0", index)
    rng = np.random.default_rng([config.seed, int(index)])
    setup = prepare_kitti_frame(name, rgb, lidar_depth, mde, factor=config.factor, holdout=config.holdout, rng=rng)
    return evaluate_kitti_frame(setup, config, methods=methods, rng=rng)


def summarize_kitti(rows: Sequence[dict]) -> list[dict]:
    """Mean over frames per (resolution, protocol, density, method), in first-seen order.

    Each summary row has the keys of a row (minus frame, gt) with metrics averaged over frames,
    ``frames`` (how many), ``n_points`` and ``n_gt`` (means) and ``min_mean`` (the minimum).
    """
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["resolution"], r["protocol"], r["density"], r["method"]), []).append(r)
    out = []
    for (res, protocol, density, method), rs in groups.items():
        s = {"resolution": res, "protocol": protocol, "density": density, "label": rs[0]["label"], "method": method}
        s["frames"] = len(rs)
        s["n_points"] = float(np.mean([r["n_points"] for r in rs]))
        s["n_gt"] = float(np.mean([r["n_gt"] for r in rs]))
        for k in METRICS + CALIBRATION + ("seconds",):
            vals = [r[k] for r in rs if np.isfinite(r[k])]
            s[k] = float(np.mean(vals)) if vals else math.nan
        s["min_mean"] = float(min(r["min_mean"] for r in rs))
        out.append(s)
    return out


# ----------------------------------------------------------------------------- reports
def _get(summary: Sequence[dict], res: str, protocol: str, label: str, method: str) -> dict | None:
    for s in summary:
        if (s["resolution"], s["protocol"], s["label"], s["method"]) == (res, protocol, label, method):
            return s
    return None


def paper_table(summary: Sequence[dict], *, resolution: str = "full", protocol: str = "uniform") -> str:
    """Markdown: RMSE (mm) per density, one column per method, beside the paper's published numbers.

    The paper's column (`PAPER_KITTI_RMSE_MM`) is its balanced GP with monodepth2 on KITTI depth
    completion (its MDE-alone figure in the header row); '-' where it gives no number.
    """
    methods = list(dict.fromkeys(s["method"] for s in summary))
    labels = list(dict.fromkeys(s["label"] for s in summary if s["protocol"] == protocol))
    paper_col = "paper (KITTI, monodepth2)" if protocol == "uniform" else "paper (no band numbers)"
    head = ["density", "points", paper_col] + [f"{m} RMSE" for m in methods]
    head += [f"{m} ±2σ" for m in methods if m.startswith("gp")]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    mde_cells = ["MDE alone", "0", f"{PAPER_KITTI_RMSE_MM['mde']:.0f}" if protocol == "uniform" else "-"]
    for m in methods:
        s = _get(summary, resolution, protocol, labels[0], "mde") if labels else None
        mde_cells.append(f"{s['rmse']:.0f}" if (m == "mde" and s) else "")
    mde_cells += ["" for m in methods if m.startswith("gp")]
    lines.append("| " + " | ".join(mde_cells) + " |")
    for label in labels:
        first = next((s for s in summary if s["protocol"] == protocol and s["label"] == label), None)
        cells = [label, f"{first['n_points']:.0f}" if first else "-"]
        paper = PAPER_KITTI_RMSE_MM.get(label) if protocol == "uniform" else None
        cells.append(f"{paper:.0f}" if paper is not None else "-")
        for m in methods:
            s = _get(summary, resolution, protocol, label, m)
            cells.append(f"{s['rmse']:.0f}" if s and np.isfinite(s["rmse"]) else "-")
        for m in methods:
            if m.startswith("gp"):
                s = _get(summary, resolution, protocol, label, m)
                ok = s is not None and np.isfinite(s["coverage_2sigma"])
                cells.append(f"{100 * s['coverage_2sigma']:.1f}%" if ok else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def full_table(summary: Sequence[dict]) -> str:
    """Markdown: every summary row with RMSE, MAE, iRMSE, iMAE, calibration, the smallest mean and the
    seconds per frame (wall time of the method; noisy on a shared machine)."""
    head = [
        "resolution",
        "protocol",
        "density",
        "method",
        "points",
        "RMSE mm",
        "MAE mm",
        "iRMSE 1/km",
        "iMAE 1/km",
        "NLL",
        "±1σ",
        "±2σ",
        "min mean m",
        "s / frame",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for s in summary:
        cells = [s["resolution"], s["protocol"], s["label"], s["method"], f"{s['n_points']:.0f}"]
        cells += [f"{s[k]:.0f}" if k in ("rmse", "mae") else f"{s[k]:.2f}" for k in METRICS]
        cells.append(f"{s['nll']:.2f}" if np.isfinite(s["nll"]) else "-")
        for k in ("coverage_1sigma", "coverage_2sigma"):
            cells.append(f"{100 * s[k]:.1f}%" if np.isfinite(s[k]) else "-")
        cells.append(f"{s['min_mean']:.2f}")
        cells.append(f"{s['seconds']:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_kitti(summary: Sequence[dict], path: str | Path, *, title: str = "") -> Path:
    """RMSE (mm) against input density: one panel per protocol (a row of panels per ``dataset`` key
    when the summary rows carry one), one line per method and resolution; PNG written atomically.

    The paper's published RMSE (uniform, full resolution) is drawn as black crosses.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    protocols = list(dict.fromkeys(s["protocol"] for s in summary))
    if not protocols:
        raise EmptyInputError("summary", "at least one summary row", 0)
    datasets = list(dict.fromkeys(s.get("dataset", "") for s in summary))
    fig, axes = plt.subplots(
        len(datasets), len(protocols), figsize=(5.2 * len(protocols), 4.2 * len(datasets)), dpi=100, squeeze=False
    )
    colours = {"mde": "tab:gray", "ip_basic": "tab:green", "gp_paper": "tab:blue", "gp_default": "tab:red"}
    for axrow, dataset in zip(axes, datasets):
        for ax, protocol in zip(axrow, protocols):
            rows = [s for s in summary if s["protocol"] == protocol and s.get("dataset", "") == dataset]
            for method in dict.fromkeys(s["method"] for s in rows):
                for res, style in (("full", "-"), ("grid", ":")):
                    rs = sorted(
                        (s for s in rows if s["method"] == method and s["resolution"] == res),
                        key=lambda s: s["density"],
                    )
                    if rs:
                        ax.plot(
                            [s["density"] for s in rs],
                            [s["rmse"] for s in rs],
                            style,
                            marker="o",
                            ms=3,
                            lw=3.0 if method == "gp_paper" else 1.5,  # visible under an identical default
                            color=colours.get(method),
                            label=f"{method} ({res})",
                        )
            if protocol == "uniform":
                paper = [
                    (d, PAPER_KITTI_RMSE_MM[density_label(d)])
                    for d in PAPER_DENSITIES
                    if density_label(d) in PAPER_KITTI_RMSE_MM
                ]
                ax.plot(*zip(*paper), "kx", ms=8, label="paper (KITTI, monodepth2)")
                ax.axhline(PAPER_KITTI_RMSE_MM["mde"], color="k", lw=0.8, ls="--", label="paper: MDE alone")
            ax.set_xscale("log", base=2)
            ax.set_xlabel("input density (share of the non-held-out LiDAR)")
            ax.set_ylabel("RMSE [mm]")
            ax.set_title(f"{dataset + ': ' if dataset else ''}{protocol}")
            ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path).with_suffix(".png")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
