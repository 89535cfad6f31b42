"""The metric scale of an SfM reconstruction from a network's depth: per-point ratios, median, bootstrap over frames."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import EmptyInputError, InvalidInputError
from gpdepth3d.mapping.points.sfm_scale import MetricScale, PieceRule, depth_ratios, metric_scale


def test_depth_ratios_at_the_points_pixels():
    camera = PinholeCamera(50.0, 50.0, 31.5, 23.5, 64, 48)
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]  # the camera one unit along x
    points = np.array([[1.0, 0.0, 2.0], [1.2, 0.1, 4.0], [1.0, 0.0, -1.0], [50.0, 0.0, 1.0]])
    depth = np.full((24, 32), 6.0)  # half resolution: 6 m everywhere
    r = depth_ratios(points, T, camera, depth)
    np.testing.assert_allclose(r, [3.0, 1.5])  # behind and outside are dropped


def test_depth_ratios_skip_holes():
    camera = PinholeCamera(50.0, 50.0, 31.5, 23.5, 64, 48)
    assert depth_ratios(np.array([[0.0, 0.0, 2.0]]), np.eye(4), camera, np.zeros((48, 64))).size == 0


def test_metric_scale_median_and_bootstrap():
    rng = np.random.default_rng(0)
    true = 2.5
    frames = [true * (1 + rng.normal(0, 0.05)) * (1 + rng.normal(0, 0.02, 200)) for _ in range(40)]
    s = metric_scale(frames)
    assert s.scale == pytest.approx(true, rel=0.03)
    assert s.interval[0] < s.scale < s.interval[1]
    # per-frame error 5 % over 40 frames: the median's spread is about 5 % / sqrt(40) times ~1.25
    assert 0.004 < s.relative_sigma < 0.02
    assert s.frames == 40 and s.points == 8000 and 0.01 < s.mad < 0.08


def test_metric_scale_is_robust_to_outliers():
    frames = [np.r_[np.full(90, 1.5), np.full(10, 40.0)] for _ in range(10)]
    assert metric_scale(frames).scale == pytest.approx(1.5)


def test_metric_scale_counts_every_frame_once():
    """One frame with many points does not outvote nine frames with few: the network's error is per frame."""
    frames = [np.full(1000, 2.0)] + [np.full(50, 1.0) for _ in range(9)]
    s = metric_scale(frames)
    assert s.scale == pytest.approx(1.0)  # pooling the points would give 2.0
    assert s.frames == 10 and s.points == 1450


def test_metric_scale_errors():
    with pytest.raises(EmptyInputError):
        metric_scale([np.zeros(3), np.array([np.nan])])
    with pytest.raises(InvalidInputError):
        metric_scale([np.ones(3)], draws=2)


def test_focal_ratio_of_a_narrower_view():
    from gpdepth3d.mapping.points.sfm_scale import focal_ratio

    training = (500.0, 500.0, 640, 480)
    assert focal_ratio(PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480), training) == pytest.approx(1.0)
    # the same view at half the size, then a view zoomed 1.2x on both axes
    assert focal_ratio(PinholeCamera(250.0, 250.0, 159.5, 119.5, 320, 240), training) == pytest.approx(1.0)
    assert focal_ratio(PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480), training) == pytest.approx(1.2)
    # one axis only: the geometric mean
    assert focal_ratio(PinholeCamera(720.0, 500.0, 319.5, 239.5, 640, 480), training) == pytest.approx(np.sqrt(1.44))
    with pytest.raises(InvalidInputError):
        focal_ratio(PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480), (500.0, 0.0, 640, 480))


def _scale(scale=1.0, sigma=0.02, mad=0.1, frames=20):
    return MetricScale(scale, sigma, (scale - 2 * sigma, scale + 2 * sigma), mad, 1000, frames)


def test_piece_rule_maps_a_trusted_piece():
    assert PieceRule().refusal(20, _scale()) is None
    assert PieceRule().refusal(8, _scale(frames=8)) is None  # the minimum itself is enough


@pytest.mark.parametrize(
    "frames, scale, says",
    [
        (7, _scale(frames=7), "fewer than 8 frames"),
        (3, _scale(sigma=0.2, mad=0.3, frames=3), "fewer than 8 frames"),  # the first failed test is named
        (20, _scale(scale=0.5, sigma=0.03), "sigma 6.0% of the scale > 5.0%"),  # relative, not absolute
        (20, _scale(mad=0.25), "MAD of the ratios 0.25 > 0.20"),
    ],
)
def test_piece_rule_refuses_an_untrusted_piece(frames, scale, says):
    why = PieceRule().refusal(frames, scale)
    assert why is not None and says in why


def test_piece_rule_thresholds_are_its_own():
    rule = PieceRule(min_frames=3, max_relative_sigma=0.5, max_mad=0.5)
    assert rule.refusal(3, _scale(sigma=0.2, mad=0.3, frames=3)) is None
    # an absolute sigma under the bound is still refused when it is large for a small scale
    assert PieceRule().refusal(20, _scale(scale=0.2, sigma=0.04)) is not None
    assert PieceRule().refusal(20, _scale(scale=2.0, sigma=0.04)) is None


@pytest.mark.parametrize(
    "field, value", [("min_frames", 0), ("min_frames", True), ("max_mad", 0.0), ("max_relative_sigma", np.nan)]
)
def test_piece_rule_refuses_bad_settings(field, value):
    with pytest.raises(InvalidInputError, match=field):
        PieceRule(**{field: value})
