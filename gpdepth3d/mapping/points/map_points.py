"""SLAM map points as a frame's sparse depth: projection with a count of what was dropped, merging measurements."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...camera import PinholeCamera, check_pose, transform_points
from ...errors import ShapeError, describe
from ...measurements import SparseDepth, project_points
from ...io.poses import invert_pose


@dataclass(frozen=True)
class MapPointStats:
    """What became of the SLAM map points given for one frame.

    Attributes:
        given: Points given.
        nonfinite: Points with a NaN or inf coordinate (dropped).
        behind: Finite points behind the camera or closer than ``min_depth`` (dropped).
        outside: Points in front of the camera that project outside the image (dropped).
        used: Measurements kept (after keeping the closest point per pixel).
    """

    given: int
    nonfinite: int
    behind: int
    outside: int
    used: int


def project_map_points(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    sigma: float | np.ndarray | None = None,
    min_depth: float = 1e-3,
) -> tuple[SparseDepth, MapPointStats]:
    """SLAM map points (world frame) as sparse depth of one posed camera, with a count of the dropped ones.

    Args:
        points_world: (N, 3) map points in the world frame, metres.
        T_world_camera: 4x4 pose of the camera.
        camera: Intrinsics; points projecting outside the image or behind the camera are dropped
            (and counted).
        sigma: Optional per-point (N,) or shared depth standard deviation, metres.
        min_depth: Points with z below this are dropped.

    Returns:
        (`SparseDepth` on the camera's grid, closest point per pixel; `MapPointStats`).
    """
    T = check_pose(T_world_camera)
    p = np.asarray(points_world, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError("points_world", "an (N, 3) array", describe(p))
    n = p.shape[0]
    if sigma is not None:
        s = np.asarray(sigma, dtype=np.float64)
        if s.ndim > 1 or (s.ndim == 1 and s.shape[0] != n):
            raise ShapeError("sigma", f"a scalar or shape ({n},)", describe(s))
        sigma = np.broadcast_to(s, (n,))
    finite = np.all(np.isfinite(p), axis=1)
    pc = transform_points(invert_pose(T), p[finite])
    uv, z = camera.project(pc)
    front = z > min_depth
    inside = front & camera.in_image(uv)
    keep = np.flatnonzero(finite)[inside]
    sparse = project_points(pc[inside], camera, min_depth=min_depth, sigma=None if sigma is None else sigma[keep])
    stats = MapPointStats(
        given=int(n),
        nonfinite=int(n - finite.sum()),
        behind=int((~front).sum()),
        outside=int((front & ~inside).sum()),
        used=len(sparse),
    )
    return sparse, stats


def sparse_from_map_points(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    sigma: float | np.ndarray | None = None,
    min_depth: float = 1e-3,
) -> SparseDepth:
    """SLAM map points (world frame) as sparse depth of one posed camera.

    Points behind the camera, outside the image or not finite are dropped; `project_map_points`
    returns how many of each (`Mapper.add_frame` reports them on its `FrameResult`).

    Args:
        points_world: (N, 3) map points in the world frame, metres.
        T_world_camera: 4x4 pose of the camera.
        camera: Intrinsics.
        sigma: Optional per-point (N,) or shared depth standard deviation, metres.
        min_depth: Points with z below this are dropped.

    Returns:
        `SparseDepth` on the camera's grid (closest point per pixel).
    """
    return project_map_points(points_world, T_world_camera, camera, sigma=sigma, min_depth=min_depth)[0]


def merge_sparse(*parts: SparseDepth, image_size: tuple[int, int]) -> SparseDepth:
    """Concatenates measurements of one image (all of size ``image_size``), closest per pixel."""
    parts = tuple(p for p in parts if p is not None and len(p))
    if not parts:
        return SparseDepth.empty(image_size)
    for p in parts:
        if p.image_size != tuple(image_size):
            raise ShapeError("sparse", f"measurements of a {image_size} image", p.image_size)
    cat = SparseDepth(
        np.concatenate([p.u for p in parts]),
        np.concatenate([p.v for p in parts]),
        np.concatenate([p.depth for p in parts]),
        image_size,
        np.concatenate([p.sigma for p in parts]),
    )
    return cat.rasterize()
