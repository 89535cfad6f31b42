"""Colourised previews of a posterior (`gpdepth3d.pipelines.previews`): files, colour bars, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError, OutputError, ShapeError
from gpdepth3d.pipelines.previews import PREVIEW_SUFFIXES, preview_paths, write_previews


def _maps(h=30, w=40):
    u = np.broadcast_to(np.arange(w, dtype=np.float64), (h, w))
    mean = 2.0 + 3.0 * u / (w - 1)  # 2 m left .. 5 m right
    std = 0.01 + 0.2 * u / (w - 1)
    gt = mean + 0.1
    gt[:5] = 0.0  # no ground truth in the top rows
    return mean, std, mean * 1.1, gt


def _read(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img


class TestWritePreviews:
    def test_files_beside_the_base_name(self, tmp_path):
        mean, std, mde, gt = _maps()
        written = write_previews(tmp_path / "f0", mean, std, mde=mde)
        assert (
            written
            == preview_paths(tmp_path / "f0")
            == [tmp_path / "f0_depth_preview.png", tmp_path / "f0_sigma_preview.png"]
        )
        written = write_previews(tmp_path / "f1", mean, std, depth_gt=gt)
        assert [p.name for p in written] == ["f1" + PREVIEW_SUFFIXES[k] for k in ("depth", "sigma", "error")]
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            p.name for p in preview_paths(tmp_path / "f0") + written
        )

    def test_the_map_is_coloured_by_value(self, tmp_path):
        """A left-to-right depth ramp: the picture changes colour from left to right (not a black 16-bit PNG)."""
        mean, std, _, _ = _maps(60, 80)
        depth = _read(write_previews(tmp_path / "r", mean, std)[0])
        h, w = depth.shape[:2]
        assert h > 100 and w > 200
        saturated = (depth.max(axis=2).astype(int) - depth.min(axis=2)) > 80  # colour, not grey/white/black
        assert saturated.mean() > 0.1
        cols = np.nonzero(saturated.any(axis=0))[0]
        # the map is left of the colour bar: its left and right ends differ in colour
        row = depth[np.nonzero(saturated[:, cols[0]])[0][len(np.nonzero(saturated[:, cols[0]])[0]) // 2]]
        left, right = row[cols[0] + 2].astype(int), row[cols[0] + 40].astype(int)
        assert np.abs(left - right).sum() > 60

    def test_colour_bar_with_units(self, tmp_path, monkeypatch):
        """Every preview has a colour bar labelled with the units (checked on the figure, before rendering)."""
        from matplotlib.figure import Figure

        labels = []
        real = Figure.colorbar

        def spy(self, *args, **kwargs):
            bar = real(self, *args, **kwargs)
            labels.append(bar)
            return bar

        monkeypatch.setattr(Figure, "colorbar", spy)
        mean, std, mde, gt = _maps()
        write_previews(tmp_path / "u", mean, std, mde=mde, depth_gt=gt)
        assert [b.ax.get_ylabel() for b in labels] == ["z-depth [m]", "σ [m]", "|error| [m]"]
        lo, hi = labels[0].mappable.get_clim()
        assert 2.0 <= lo < hi <= 5.5  # the depth scale spans the maps (2nd..98th percentile)

    def test_bad_input(self, tmp_path):
        mean, std, mde, gt = _maps()
        with pytest.raises(ShapeError, match="std"):
            write_previews(tmp_path / "x", mean, std[:, :5])
        with pytest.raises(ShapeError, match="mean"):
            write_previews(tmp_path / "x", mean[0], std)
        with pytest.raises(ShapeError, match="depth_gt"):
            write_previews(tmp_path / "x", mean, std, depth_gt=gt.T)
        with pytest.raises(InvalidInputError, match="base"):
            write_previews("", mean, std)
        (tmp_path / "afile").write_text("x")
        with pytest.raises(OutputError):
            write_previews(tmp_path / "afile" / "x", mean, std)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing half-written

    def test_nan_and_nonpositive_pixels_are_grey_not_errors(self, tmp_path):
        mean, std, _, _ = _maps()
        mean = mean.copy()
        mean[:10] = np.nan
        mean[10:12] = -1.0
        std = std.copy()
        std[0] = np.inf
        paths = write_previews(tmp_path / "n", mean, std)
        assert all(p.stat().st_size > 1000 for p in paths)


class TestPointsOnPreviews:
    def test_image_and_points_drawn_beside_depth_and_sigma(self, tmp_path, monkeypatch):
        from matplotlib.axes import Axes

        from gpdepth3d.measurements import SparseDepth

        mean, std, mde, _ = _maps()
        rgb = np.zeros((60, 80, 3), np.uint8)
        rgb[:, :40] = (255, 0, 0)  # the left half red: the first panel shows the image
        sparse = SparseDepth.from_arrays([10.0, 70.0], [20.0, 40.0], [2.5, 4.5], (60, 80))  # twice the maps' size
        scattered = []
        real = Axes.scatter

        def spy(self, x, y, *args, **kwargs):
            scattered.append((self.get_title(), np.asarray(x), np.asarray(y), kwargs.get("c")))
            return real(self, x, y, *args, **kwargs)

        monkeypatch.setattr(Axes, "scatter", spy)
        written = write_previews(tmp_path / "p", mean, std, mde=mde, rgb=rgb, sparse=sparse)
        assert len(scattered) == 2  # on the image (coloured by depth) and on sigma (white)
        (_, x0, y0, c0), (_, x1, y1, c1) = scattered
        np.testing.assert_array_equal(x0, [5, 35])  # pixel columns on the maps' 30x40 grid
        np.testing.assert_array_equal(y0, [10, 20])
        np.testing.assert_allclose(c0, [2.5, 4.5])
        assert c1 == "white"
        np.testing.assert_array_equal(x1, x0)
        depth = _read(written[0])
        red = (depth[..., 2] > 200) & (depth[..., 1] < 60) & (depth[..., 0] < 60)
        assert red.sum() > 200  # the image panel is drawn

    def test_bad_rgb_and_points(self, tmp_path):
        mean, std, _, _ = _maps()
        with pytest.raises(ShapeError, match="rgb"):
            write_previews(tmp_path / "x", mean, std, rgb=np.zeros((30, 40)))
        with pytest.raises(InvalidInputError, match="sparse"):
            write_previews(tmp_path / "x", mean, std, sparse=np.zeros((3, 3)))
        assert list(tmp_path.iterdir()) == []
