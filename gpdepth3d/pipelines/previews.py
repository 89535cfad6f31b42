"""Colourised previews of a depth posterior that a person can look at (PNG, colour bar, units).

The 16-bit PNGs of `DepthPosterior.save` (KITTI convention, metres x 256) look black in an image
viewer; these previews show the same maps with a colour map, a labelled colour bar and the units:

* ``BASE_depth_preview.png``: the image with the measurements drawn on it, the MDE and the GP posterior
  mean side by side on one depth scale (turbo; the points coloured on the same scale);
* ``BASE_sigma_preview.png``: the posterior standard deviation (viridis), the measurements as white
  dots (sigma is smallest at them);
* ``BASE_error_preview.png`` (with ground truth): |GP mean − ground truth| and |MDE − ground truth|
  on one scale (magma), grey where there is no ground truth.

Drawn with matplotlib's Agg canvas (no display, no pyplot state) and written atomically
(`gpdepth3d.io.atomic_write`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InvalidInputError, ShapeError, describe
from ..io import atomic_path, atomic_write
from ..measurements import SparseDepth

PREVIEW_SUFFIXES: dict[str, str] = {
    "depth": "_depth_preview.png",
    "sigma": "_sigma_preview.png",
    "error": "_error_preview.png",
}
"""File name suffix of each preview (appended to the output base name)."""


MAX_DOTS = 1500
"""At most this many measurements are drawn as dots on the sigma preview (a LiDAR scan is thinned)."""


def preview_paths(base: str | Path, *, with_error: bool = False) -> list[Path]:
    """The preview files `write_previews` writes for ``base`` (``dir/name``, no suffix)."""
    base = Path(base)
    kinds = ("depth", "sigma", "error") if with_error else ("depth", "sigma")
    return [base.with_name(base.name + PREVIEW_SUFFIXES[k]) for k in kinds]


def _map(value: np.ndarray, argument: str, shape: Optional[tuple[int, ...]]) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64) if value is not None else None
    if a is None or a.ndim != 2 or min(a.shape) < 1:
        raise ShapeError(argument, "a 2-D (H, W) map in metres", describe(value))
    if shape is not None and a.shape != shape:
        raise ShapeError(argument, f"a map of the mean's shape {shape}", describe(a))
    return a


def _image(rgb: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """An (H, W, 3) uint8 image resized to ``shape`` (area averaging when shrinking)."""
    import cv2

    a = np.asarray(rgb)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.dtype != np.uint8 or min(a.shape[:2]) < 1:
        raise ShapeError("rgb", "an (H, W, 3) uint8 RGB image", describe(rgb))
    a = np.ascontiguousarray(a[..., :3])
    if a.shape[:2] != shape:
        shrink = a.shape[0] > shape[0]
        a = cv2.resize(a, (shape[1], shape[0]), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return a


def _range(values: list[np.ndarray], lo_q: float, hi_q: float) -> tuple[float, float]:
    v = np.concatenate([x[np.isfinite(x)].ravel() for x in values])
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = (float(np.percentile(v, lo_q)), float(np.percentile(v, hi_q)))
    return lo, hi if hi > lo else lo + max(abs(lo), 1.0) * 1e-3


def _figure(
    panels: list[tuple[str, np.ndarray]],
    cmap: str,
    vmin: float,
    vmax: float,
    label: str,
    path: Path,
    points: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]] = None,
    point_panels: tuple[int, ...] = (),
    point_colour: Optional[str] = None,
) -> Path:
    """One row of panels with a shared colour bar; an (H, W, 3) panel is drawn as an image.

    ``points`` (rows, cols, depth) are drawn on the panels ``point_panels``: coloured by depth on
    the colour scale, or in ``point_colour``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import matplotlib

    h, w = panels[0][1].shape[:2]
    aspect = h / w
    n = len(panels)
    width = 6.0 * n if w >= h else 4.0 * n
    fig = Figure(figsize=(width + 1.2, max(2.2, width / n * aspect + 1.0)), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, n, squeeze=False)[0]
    colormap = matplotlib.colormaps[cmap].with_extremes(bad=(0.6, 0.6, 0.6))
    image = None
    size = max(2.0, 60.0 / max(1.0, np.sqrt(len(points[0])))) if points is not None and len(points[0]) else 2.0
    for i, (ax, (title, values)) in enumerate(zip(axes, panels)):
        if values.ndim == 3:
            ax.imshow(values, interpolation="nearest")
        else:
            image = ax.imshow(
                np.ma.masked_invalid(values), cmap=colormap, vmin=vmin, vmax=vmax, interpolation="nearest"
            )
        if points is not None and i in point_panels and len(points[0]):
            rows, cols, depth = points
            if point_colour is None:
                few = len(depth) <= 500  # a few points get an outline; a LiDAR scan would turn black with them
                ax.scatter(
                    cols,
                    rows,
                    c=depth,
                    cmap=colormap,
                    vmin=vmin,
                    vmax=vmax,
                    s=size if few else 0.5,
                    linewidths=0.3 if few else 0,
                    edgecolors="black",
                )
            else:
                step = max(1, len(rows) // MAX_DOTS)  # a dense scan would hide the map: every step-th point
                ax.scatter(
                    cols[::step], rows[::step], c=point_colour, s=size * 0.5 if len(rows) <= 500 else 0.3, linewidths=0
                )
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    bar = fig.colorbar(image, ax=list(axes), fraction=0.046 / n if n > 1 else 0.046, pad=0.02)
    bar.set_label(label)
    atomic_write(path, lambda p: fig.savefig(p, format="png", bbox_inches="tight", pad_inches=0.05))
    return path


def write_previews(
    base: str | Path,
    mean: np.ndarray,
    std: np.ndarray,
    *,
    mde: Optional[np.ndarray] = None,
    depth_gt: Optional[np.ndarray] = None,
    rgb: Optional[np.ndarray] = None,
    sparse: Optional[SparseDepth] = None,
) -> list[Path]:
    """Writes colourised PNG previews of a depth posterior, each with a colour bar and its units.

    Args:
        base: Output base path (``dir/name``); the files are ``name`` + `PREVIEW_SUFFIXES`.
        mean: (H, W) posterior mean z-depth, metres (<= 0 or NaN: no depth, drawn grey).
        std: (H, W) posterior standard deviation, metres.
        mde: Optional (H, W) MDE depth, metres, drawn beside the mean on the same scale.
        depth_gt: Optional (H, W) ground-truth depth, metres (0 or NaN = none): adds the error preview.
        rgb: Optional (h, w, 3) uint8 RGB image of the scene (any size: resized to the mean's), drawn first
            with ``sparse`` on it.
        sparse: Optional measurements (any image size of the mean's aspect ratio): drawn on the image
            (or on the mean) coloured by depth, and on sigma as white dots.

    Returns:
        The paths written (depth, sigma, then error with ground truth).

    Raises:
        ShapeError: a map that is not 2-D or not of the mean's shape.
        OutputError: a file that cannot be written (nothing is left half-written).
    """
    mean = _map(mean, "mean", None)
    std = _map(std, "std", mean.shape)
    if mde is not None:
        mde = _map(mde, "mde", mean.shape)
    if depth_gt is not None:
        depth_gt = _map(depth_gt, "depth_gt", mean.shape)
    if not isinstance(base, (str, Path)) or not str(base):
        raise InvalidInputError("base", "an output path without suffix", describe(base))
    if rgb is not None:
        rgb = _image(rgb, mean.shape)
    points = None
    if sparse is not None:
        if not isinstance(sparse, SparseDepth):
            raise InvalidInputError("sparse", "a SparseDepth", describe(sparse))
        rows, cols = sparse.pixel_indices(mean.shape)
        points = (rows, cols, sparse.depth)
    with np.errstate(invalid="ignore"):
        shown = np.where(mean > 0, mean, np.nan)
        mde_shown = np.where(mde > 0, mde, np.nan) if mde is not None else None
    paths = preview_paths(base, with_error=depth_gt is not None)
    depth_panels = ([("MDE", mde_shown)] if mde_shown is not None else []) + [("GP posterior mean", shown)]
    lo, hi = _range([p[1] for p in depth_panels], 2, 98)
    n_points = 0 if points is None else len(points[0])
    if rgb is not None:
        depth_panels.insert(0, (f"image and {n_points} points" if points is not None else "image", rgb))
    on = (0,) if rgb is not None or points is None else (len(depth_panels) - 1,)
    _figure(depth_panels, "turbo", lo, hi, "z-depth [m]", paths[0], points, on)
    sig = np.where(np.isfinite(std) & (std >= 0), std, np.nan)
    _, top = _range([sig], 0, 98)
    shown_dots = "" if n_points <= MAX_DOTS else f"{len(range(0, n_points, max(1, n_points // MAX_DOTS)))} of "
    title = "GP posterior σ" + (f" ({shown_dots}{n_points} points in white)" if points is not None else "")
    _figure([(title, sig)], "viridis", 0.0, top, "σ [m]", paths[1], points, (0,), "white")
    if depth_gt is not None:
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth_gt) & (depth_gt > 0)
            err = np.where(valid, np.abs(shown - depth_gt), np.nan)
            panels = [("|GP mean − ground truth|", err)]
            if mde_shown is not None:
                panels.insert(0, ("|MDE − ground truth|", np.where(valid, np.abs(mde_shown - depth_gt), np.nan)))
        _, top = _range([p[1] for p in panels], 0, 95)
        _figure(panels, "magma", 0.0, top, "|error| [m]", paths[2])
    return paths


def plot_qualitative(
    rgb: np.ndarray,
    mde: np.ndarray,
    sparse: SparseDepth,
    mean: np.ndarray,
    std: np.ndarray,
    gt: np.ndarray,
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """Six panels: RGB, MDE, sparse input, GP mean, GP std, |error| of the mean (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    valid = np.isfinite(gt) & (gt > 0)
    vmax = float(np.percentile(np.concatenate([gt[valid], mean.ravel()]), 99)) if valid.any() else float(mean.max())
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), dpi=90)
    sp_map = sparse.to_depth_map(mean.shape)
    err = np.where(valid, np.abs(mean - gt), np.nan)
    panels = [
        (rgb, "RGB", None, None),
        (mde, "MDE [m]", "magma_r", (0, vmax)),
        (np.where(sp_map > 0, sp_map, np.nan), f"sparse ({len(sparse)} pts) [m]", "magma_r", (0, vmax)),
        (mean, "GP mean [m]", "magma_r", (0, vmax)),
        (std, "GP std [m]", "viridis", (0, float(np.percentile(std, 99)))),
        (err, "|mean - gt| [m]", "inferno", (0, float(np.nanpercentile(err, 99)) if valid.any() else 1)),
    ]
    for ax, (img, name, cmap, lim) in zip(axes.ravel(), panels):
        if cmap is None:
            ax.imshow(img)
        else:
            if name.startswith("sparse"):
                yy, xx = np.nonzero(np.isfinite(img))
                ax.imshow(np.zeros(mean.shape), cmap="gray", vmin=0, vmax=1)
                im = ax.scatter(xx, yy, c=img[yy, xx], s=6, cmap=cmap, vmin=lim[0], vmax=lim[1])
                ax.set_xlim(-0.5, mean.shape[1] - 0.5)
                ax.set_ylim(mean.shape[0] - 0.5, -0.5)
            else:
                cm = matplotlib.colormaps[cmap].with_extremes(bad="0.75")  # no ground truth: grey
                im = ax.imshow(img, cmap=cm, vmin=lim[0], vmax=max(lim[1], 1e-6))
            fig.colorbar(im, ax=ax, fraction=0.035)
        ax.set_title(name)
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(Path(path).with_suffix(".png")) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path).with_suffix(".png")
