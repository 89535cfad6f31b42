"""The Mapper's own points of the last frames, kept in the world frame, to fill the gaps of a frame's points.

A frame's own triangulation finds points where its tracks and matches survive, which leaves parts of
the image without any (fast motion, blur, a view that left the textured part of the scene). The same
surfaces were often triangulated in the frames just before. `LocalMap` keeps the points of the last
``frames`` frames in the world frame and projects them into a new frame, where they fill the cells
of a coarse grid that hold none of the frame's own points: the frame's points stay first (they are
measured in its own image and scaled to the map), the others add what it could not see. This is the
local map of keyframe SLAM (e.g. ORB-SLAM's local map tracking, https://arxiv.org/abs/1502.00956),
used as measurements rather than for tracking.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ...camera import PinholeCamera, transform_points
from ...errors import InvalidInputError
from ...measurements import SparseDepth
from .map_points import project_map_points


def cell_ids(sparse: SparseDepth, cell: float) -> np.ndarray:
    """Cell index (row-major, on a grid of ``cell``-pixel squares) of each measurement."""
    width = int(np.ceil(sparse.image_size[1] / cell))
    return (np.floor(sparse.v / cell) * width + np.floor(sparse.u / cell)).astype(np.int64)


def fill_cells(own: SparseDepth, others: SparseDepth, cell: float) -> SparseDepth:
    """The measurements of ``others`` in the ``cell``-pixel cells that hold none of ``own``, one per cell.

    In each empty cell the measurement of smallest sigma / depth is kept (the same surface seen from
    several earlier frames gives one measurement, not several that the GP would count as independent).

    Args:
        own: The frame's own measurements.
        others: Candidate measurements of the same image.
        cell: Cell size, pixels (> 0).

    Returns:
        The kept measurements of ``others`` (a `SparseDepth` of the same image).
    """
    if not np.isfinite(cell) or cell <= 0:
        raise InvalidInputError("cell", "a cell size > 0 (pixels)", cell)
    if not len(others):
        return others
    taken = np.unique(cell_ids(own, cell)) if len(own) else np.zeros(0, np.int64)
    ids = cell_ids(others, cell)
    free = ~np.isin(ids, taken)
    order = np.lexsort((others.sigma / others.depth, ids))  # per cell, the most certain first
    order = order[free[order]]
    first = np.ones(order.size, bool)
    first[1:] = ids[order][1:] != ids[order][:-1]
    return others.subset(np.sort(order[first]))


class LocalMap:
    """The triangulated points of the last ``frames`` frames, in the world frame.

    Args:
        frames: Frames remembered (oldest dropped first).
        cell: Cell size of `fill` as a fraction of the image width.
    """

    def __init__(self, frames: int, cell: float):
        if isinstance(frames, bool) or int(frames) != frames or frames < 1:
            raise InvalidInputError("frames", "an integer >= 1", frames)
        if not np.isfinite(cell) or not 0 < cell <= 1:
            raise InvalidInputError("cell", "a fraction of the image width in (0, 1]", cell)
        self.frames, self.cell = int(frames), float(cell)
        self._points: OrderedDict = OrderedDict()  # key -> (points in its camera frame, sigma, T_world_camera)

    def __len__(self) -> int:
        return sum(len(s) for _, s, _ in self._points.values())

    def add(self, key: object, points: SparseDepth, T_world_camera: np.ndarray, camera: PinholeCamera) -> None:
        """Remembers a frame's points (pixels and depth of ``camera``'s image, its pose)."""
        if len(points):
            xyz = camera.backproject_pixels(np.column_stack([points.u, points.v]), points.depth)
            self._points[key] = (xyz, points.sigma.copy(), np.asarray(T_world_camera, np.float64))
            self._points.move_to_end(key)
        while len(self._points) > self.frames:
            self._points.popitem(last=False)

    def update_poses(self, poses: dict) -> None:
        """New poses of remembered frames (after a loop closure): their points move with them."""
        for key, T in poses.items():
            if key in self._points:
                xyz, sigma, _ = self._points[key]
                self._points[key] = (xyz, sigma, np.asarray(T, np.float64))

    def seen(self, T_world_camera: np.ndarray, camera: PinholeCamera) -> SparseDepth:
        """Every remembered point a camera sees, as its sparse depth (the sigma they were triangulated with)."""
        if not self._points:
            return SparseDepth.empty(camera.shape)
        world = np.concatenate([transform_points(T, xyz) for xyz, _, T in self._points.values()])
        sigma = np.concatenate([s for _, s, _ in self._points.values()])
        return project_map_points(world, T_world_camera, camera, sigma=sigma)[0]

    def fill(
        self, own: SparseDepth, T_world_camera: np.ndarray, camera: PinholeCamera, seen: SparseDepth | None = None
    ) -> SparseDepth:
        """The remembered points seen by a camera, in the grid cells that ``own`` leaves empty (`fill_cells`).

        ``seen``: `seen`'s result for this camera when the caller has it."""
        seen = self.seen(T_world_camera, camera) if seen is None else seen
        return fill_cells(own, seen, self.cell * camera.width)
