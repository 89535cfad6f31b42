"""The metric scale of a reconstruction known up to scale (SfM), from a monocular network's depth at its points.

Structure from motion gives poses and points up to one unknown factor. The network's depth is metric
but wrong by a few to tens of percent per frame and per region. Each point an image observes gives one
ratio ``network depth / model depth`` at its pixel; `metric_scale` takes each frame's median ratio and
the median of those over the frames, and its uncertainty from a bootstrap over frames (the network's
error is shared by the points of one frame, so frames, not points, are the independent draws; pooling
the points instead lets the few frames with many points, a textured corner seen close, set the
scale), with the spread of the ratios (MAD) beside it.

`PieceRule` says when a piece's scale is not to be trusted (too few frames, too wide a bootstrap,
ratios that disagree too much): fusing such a piece puts every point at a wrong depth, which is worse
than the network's own depth.

A network learns sizes in its training camera: shown an image whose field of view is narrower, it sees
things larger and puts them nearer. `focal_ratio` is that factor, from the focal lengths over the image
size of both cameras (the front-ends resize the whole image to their input without keeping the aspect
ratio, so each axis counts); the network's depth times it is the depth the training camera would have
been told (the canonical-camera correction of Metric3D, Yin et al. 2023).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...camera import PinholeCamera, transform_points
from ...checks import Int, check_fields, positive
from ...errors import EmptyInputError, InvalidInputError
from ...io.poses import invert_pose


@dataclass(frozen=True)
class MetricScale:
    """Metres per model unit, with its uncertainty.

    Attributes:
        scale: Median over the frames of each frame's median ratio network depth / model depth
            (metres per unit).
        sigma: Standard deviation of that median over bootstrap draws of frames (metres per unit).
        interval: 2.5 and 97.5 percentiles of the bootstrap medians.
        mad: Median absolute deviation of the per-point ratios over their median (a share: the
            spread of the network's error, not the scale's uncertainty).
        points: Ratios used.
        frames: Frames that gave ratios.
    """

    scale: float
    sigma: float
    interval: tuple[float, float]
    mad: float
    points: int
    frames: int

    @property
    def relative_sigma(self) -> float:
        """``sigma / scale``: the share every metric distance of the map is uncertain by."""
        return self.sigma / self.scale


def focal_ratio(camera: PinholeCamera, training: tuple[float, float, int, int]) -> float:
    """How much narrower ``camera``'s view is than the network's training camera: the factor on its depth.

    Args:
        camera: The images' intrinsics.
        training: ``(fx, fy, width, height)`` of the camera the network was trained with (pixels).

    Returns:
        ``sqrt((fx / width) / (fx_t / width_t) * (fy / height) / (fy_t / height_t))``; 1 for the same view.

    Raises:
        InvalidInputError: training intrinsics that are not four positive numbers.
    """
    t = np.asarray(training, dtype=np.float64)
    if t.shape != (4,) or not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InvalidInputError("training", "(fx, fy, width, height) > 0 of the network's training camera", training)
    fx_t, fy_t, w_t, h_t = t
    return float(np.sqrt((camera.fx / camera.width) / (fx_t / w_t) * (camera.fy / camera.height) / (fy_t / h_t)))


def depth_ratios(
    points_world: np.ndarray, T_world_camera: np.ndarray, camera: PinholeCamera, network_depth: np.ndarray
) -> np.ndarray:
    """Ratios network depth / model depth of the points a frame observes, at their pixels.

    Args:
        points_world: (K, 3) points the frame observes, in the model's frame and units.
        T_world_camera: The frame's 4x4 pose in the model.
        camera: Intrinsics of the image (the model's camera, pixels).
        network_depth: (h, w) the network's depth of the image, metres, any resolution of the image's
            aspect; sampled at the nearest pixel.

    Returns:
        (n,) ratios of the points in front of the camera, inside the image, with depth > 0.
    """
    depth = np.asarray(network_depth, dtype=np.float64)
    p_cam = transform_points(invert_pose(np.asarray(T_world_camera, dtype=np.float64)), np.asarray(points_world))
    z = p_cam[:, 2]
    front = z > 1e-9
    uv, _ = camera.project(p_cam[front])
    h, w = depth.shape
    col = np.rint((uv[:, 0] + 0.5) * w / camera.width - 0.5).astype(np.int64)
    row = np.rint((uv[:, 1] + 0.5) * h / camera.height - 0.5).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    d = depth[row[inside], col[inside]]
    ok = np.isfinite(d) & (d > 0)
    return d[ok] / z[front][inside][ok]


def metric_scale(ratios: Sequence[np.ndarray], *, draws: int = 500, seed: int = 0) -> MetricScale:
    """The median over frames of each frame's median depth ratio, with a bootstrap over frames for its uncertainty.

    Every frame counts once, whatever its number of points: the network's error is a per-frame
    factor, so a frame with many points is one draw of it, not many.

    Args:
        ratios: Per frame, its points' ratios network depth / model depth (`depth_ratios`).
        draws: Bootstrap draws (frames drawn with replacement).
        seed: Random seed of the draws.

    Raises:
        EmptyInputError: no frame with a positive, finite ratio.
        InvalidInputError: ``draws`` < 10.
    """
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 10:
        raise InvalidInputError("draws", "an integer >= 10", draws)
    frames = [r[np.isfinite(r) & (r > 0)] for r in (np.asarray(x, dtype=np.float64).ravel() for x in ratios)]
    frames = [r for r in frames if r.size]
    if not frames:
        raise EmptyInputError("ratios", "frames with positive depth ratios", "none")
    pooled = np.concatenate(frames)
    per_frame = np.array([np.median(r) for r in frames])
    scale = float(np.median(per_frame))
    rng = np.random.default_rng(seed)
    medians = np.median(per_frame[rng.integers(0, len(frames), (draws, len(frames)))], axis=1)
    lo, hi = np.percentile(medians, [2.5, 97.5])
    return MetricScale(
        scale=scale,
        sigma=float(np.std(medians)),
        interval=(float(lo), float(hi)),
        mad=float(np.median(np.abs(pooled / scale - 1.0))),
        points=int(pooled.size),
        frames=len(frames),
    )


@dataclass(frozen=True)
class PieceRule:
    """When a piece of a reconstruction known up to scale is not mapped: its metric scale is not to be trusted.

    A piece's map puts every point at ``scale`` times its model depth; a scale off by a tenth puts a wall
    at 3 m 30 cm away, farther than the network's own depth would. The scale is an average of the
    network's per-frame error, so it needs frames; its bootstrap sigma says how well they pin it down;
    the MAD of the ratios says whether the reconstruction's depths and the network's agree at all (a
    piece of a few frames with a short baseline has depths the network contradicts).

    Attributes:
        min_frames: Frames a piece needs (a smaller piece rests on too few network depth maps).
        max_relative_sigma: Largest ``sigma / scale`` of the scale's bootstrap.
        max_mad: Largest MAD of the ratios over the scale (a share).
    """

    min_frames: int = 8
    max_relative_sigma: float = 0.05
    max_mad: float = 0.2

    def __post_init__(self) -> None:
        check_fields(
            self, {"min_frames": Int(1), "max_relative_sigma": positive("a share"), "max_mad": positive("a share")}
        )

    def refusal(self, frames: int, scale: MetricScale) -> str | None:
        """Why a piece of ``frames`` frames with this scale is not to be mapped, or None when it may be.

        Args:
            frames: The piece's registered frames.
            scale: Its `metric_scale`.

        Returns:
            One line naming the first failed test and its numbers, or None.
        """
        if frames < self.min_frames:
            return f"fewer than {self.min_frames} frames: its scale rests on too few network depth maps"
        if scale.relative_sigma > self.max_relative_sigma:
            return f"scale uncertain: sigma {scale.relative_sigma:.1%} of the scale > {self.max_relative_sigma:.1%}"
        if scale.mad > self.max_mad:
            return (
                f"the network's depth and the reconstruction disagree: MAD of the ratios {scale.mad:.2f} > "
                f"{self.max_mad:.2f}"
            )
        return None
