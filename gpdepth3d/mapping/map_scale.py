"""The depth scale of a frame's points against the map (`map_scale`), and the depth a posterior fuses (`fused_depth`).

A frame's triangulated points share their views' pose errors: a common scale error that the
keyframes already fused measure independently. `map_scale` measures it, `scale_to_map` pulls the
points part of the way (``MapperConfig.map_scale_weight``); `fused_depth` is the posterior's median
(or mean) depth that goes into the TSDF. See docs/mapping.md.
"""

from __future__ import annotations

from typing import Collection, Iterable, Literal

import numpy as np

from ..camera import PinholeCamera, check_pose, transform_points
from ..completion.complete import DepthPosterior
from ..errors import InvalidInputError
from ..measurements import SparseDepth
from .map_store import Keyframe


def fused_depth(posterior: DepthPosterior, estimate: Literal["median", "mean"] = "median") -> np.ndarray:
    """The depth map to fuse from a posterior: its pixel-wise median (default) or mean, metres.

    The default model's posterior is log-normal per pixel (`gpdepth3d.gp.model`, "log_residual"):
    its median is ``mean / sqrt(1 + variance / mean^2)``, nearer than the mean by the factor
    ``exp(v / 2)`` of the log variance v. For the Gaussian formulations ("balanced",
    "residual") the median is the mean. Pixels with a mean <= 0 or not finite are returned as
    they are (the fusion masks them).

    Args:
        posterior: A `DepthPosterior` (or any object with ``mean``, ``variance`` and ``config``).
        estimate: "median" or "mean".

    Returns:
        (H, W) float64 depth, metres.
    """
    if estimate not in ("median", "mean"):
        raise InvalidInputError("estimate", "'median' or 'mean'", estimate)
    mean = np.asarray(posterior.mean, dtype=np.float64)
    config = getattr(posterior, "config", None)
    if estimate == "mean" or getattr(config, "formulation", None) != "log_residual":
        return mean
    var = np.asarray(posterior.variance, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(mean) & (mean > 0) & np.isfinite(var) & (var >= 0)
        return np.where(ok, mean / np.sqrt(1.0 + np.where(ok, var, 0.0) / np.where(ok, mean, 1.0) ** 2), mean)


def map_scale(
    sparse: SparseDepth,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    stored: Iterable[Keyframe],
    work_camera: PinholeCamera,
    *,
    recent: int = 20,
    max_relative_sigma: float = 0.1,
    min_points: int = 20,
    min_keyframes: int = 3,
) -> tuple[float, int]:
    """The log depth scale of a frame's measurements relative to keyframes already fused.

    Every measurement is lifted with ``camera`` and the frame's pose, projected into each of
    the ``recent`` last stored keyframes (`Keyframe`: fused depth, variance and pose at the
    working resolution of ``work_camera``) and compared with that keyframe's depth where the
    keyframe is confident (standard deviation <= ``max_relative_sigma`` x depth): the
    keyframe's median of log(the measurement's depth in it / its depth there). The result is
    the median over the keyframes with at least ``min_points`` comparisons, and counts only
    when there are ``min_keyframes`` of them.

    Args:
        sparse: The frame's measurements (of ``camera``'s image).
        T_world_camera: The frame's 4x4 pose.
        camera: Intrinsics of the frame's image.
        stored: The stored keyframes, oldest first (e.g. ``Mapper.keyframes.values()``).
        work_camera: Intrinsics of the keyframes' depth maps.
        recent: How many of the most recent keyframes to compare with.
        max_relative_sigma: Keyframe pixels less certain than this are not compared.
        min_points: Comparisons a keyframe needs to count.
        min_keyframes: Keyframes needed for a result.

    Returns:
        (log scale, > 0 when the measurements lie farther than the map; the number of keyframes
        used: 0 when there were too few, and the log scale is then 0).
    """
    T = check_pose(T_world_camera)
    if len(sparse) < min_points:
        return 0.0, 0
    kfs = list(stored)[-int(recent) :]
    if len(kfs) < min_keyframes:
        return 0.0, 0
    pts = transform_points(T, camera.backproject_pixels(sparse.uv, np.asarray(sparse.depth, dtype=np.float64)))
    # the points in every keyframe's camera at once (stored poses are rigid: checked when added)
    poses = np.stack([kf.T_world_camera for kf in kfs])
    pc = np.matmul(pts[None] - poses[:, None, :3, 3], poses[:, :3, :3])  # (K, N, 3)
    z = pc[..., 2]
    h, w = work_camera.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(work_camera.fx * pc[..., 0] / z + work_camera.cx)
        v = np.rint(work_camera.fy * pc[..., 1] / z + work_camera.cy)
        inside = (z > 1e-3) & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    logs = []
    for k in np.nonzero(np.count_nonzero(inside, axis=1) >= min_points)[0]:
        kf, ins = kfs[k], inside[k]
        iu, iv = u[k, ins].astype(np.int64), v[k, ins].astype(np.int64)
        d = kf.depth[iv, iu].astype(np.float64)
        var = kf.variance[iv, iu].astype(np.float64)
        with np.errstate(invalid="ignore"):
            ok = (d > 0) & np.isfinite(var) & (var <= (max_relative_sigma * d) ** 2)
        if np.count_nonzero(ok) >= min_points:
            logs.append(fast_median(np.log(z[k, ins][ok] / d[ok])))
    if len(logs) < min_keyframes:
        return 0.0, 0
    return float(np.median(logs)), len(logs)


def fast_median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array without NaN (the same value, a tenth of the overhead)."""
    m = x.size // 2
    if x.size % 2:
        return float(np.partition(x, m)[m])
    p = np.partition(x, (m - 1, m))
    return float((p[m - 1] + p[m]) / 2)


def scale_to_map(
    points: SparseDepth,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    stored: Collection[Keyframe],
    work_camera: PinholeCamera,
    *,
    weight: float,
    recent: int = 20,
    max_relative_sigma: float = 0.1,
) -> tuple[SparseDepth, float, float]:
    """A frame's points with a share ``weight`` of their log scale against the map (`map_scale`) taken out.

    Depths and sigmas are divided by ``s = exp(weight * log_scale)``; ``weight`` 0, no stored
    keyframe or too few comparisons leave the points as they are (s = 1).

    Returns:
        (the scaled points, s, the log-scale variance left: ``weight (1 - weight) log_scale^2``).
    """
    if not (weight > 0 and stored):
        return points, 1.0, 0.0
    log_s, used = map_scale(
        points, T_world_camera, camera, stored, work_camera, recent=recent, max_relative_sigma=max_relative_sigma
    )
    if not used:
        return points, 1.0, 0.0
    scale = float(np.exp(weight * log_s))
    scaled = SparseDepth(points.u, points.v, points.depth / scale, points.image_size, points.sigma / scale)
    return scaled, scale, weight * (1.0 - weight) * log_s**2
