"""Colour maps of the viewer: a colouring mode's values as RGB, the colour bar, the legend's numbers."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np


if TYPE_CHECKING:  # pragma: no cover
    pass


COLORMAPS = {"depth": "turbo", "sigma": "viridis", "error": "magma"}
"""Matplotlib colormap of each colouring mode."""


MISSING_COLOR = np.array([150, 150, 150], dtype=np.uint8)


def _colorize(values: np.ndarray, vmin: float, vmax: float, cmap: str) -> np.ndarray:
    """Maps values to uint8 RGB with a matplotlib colormap; NaN -> `MISSING_COLOR`."""
    import matplotlib

    span = max(vmax - vmin, 1e-12)
    t = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / span, 0.0, 1.0)
    rgb = (matplotlib.colormaps[cmap](t)[:, :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(values)] = MISSING_COLOR
    return rgb


def colorbar_image(cmap: str, *, width: int = 256, height: int = 20) -> np.ndarray:
    """A horizontal (height, width, 3) uint8 colour bar of a matplotlib colormap, low values left."""
    row = _colorize(np.linspace(0.0, 1.0, width), 0.0, 1.0, cmap)
    return np.ascontiguousarray(np.repeat(row[None], height, axis=0))


def _percentile(values: np.ndarray, q: float, default: float) -> float:
    v = values[np.isfinite(values)]
    return float(np.percentile(v, q)) if v.size else default


def _fmt_m(x: float) -> str:
    return f"{x:.3g} m" if abs(x) >= 0.01 or x == 0 else f"{x * 1000:.3g} mm"
