"""The points the `Mapper` finds itself for its frames, and the frames waiting for them.

With the KLT detector a frame's features are followed through ``MapperConfig.window`` earlier and
``lag`` later frames (`TrackTriangulator`), so a frame waits ``lag`` calls before it is refined and
fused; descriptor detectors ("orb", "sift") triangulate each frame at once with a window of earlier
frames (`triangulate_frames`). A frame whose tracks gave few points gets descriptor matches
re-found in views chosen by parallax (`gpdepth3d.mapping.points.refinding`).
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from ..camera import PinholeCamera
from ..measurements import SparseDepth
from .points.features import detect_features
from .frame_points import PendingFrame
from .points.map_points import merge_sparse
from .map_scale import fast_median
from .mapper_config import MapperConfig
from .points.refinding import Refinder
from .points.tracks import TrackTriangulator, triangulate_frames


class OwnPoints:
    """The frames waiting for later views (``queue``) and the tracking and triangulation that gives them points.

    Args:
        camera: Intrinsics of the RGB images (features are found at that resolution).
        config: The `Mapper`'s options (``triangulate``, ``triangulation``, ``refind``, ``window``,
            ``lag``, ``min_baseline``).
    """

    def __init__(self, camera: PinholeCamera, config: MapperConfig):
        self.camera = camera
        self.config = config
        self._window: deque[list] = deque(maxlen=int(config.window))
        self._tracker: TrackTriangulator | None = None
        self._refinder = Refinder(camera, config.refind, config.triangulation)
        self.queue: deque[PendingFrame] = deque()
        # the last frame checked needed re-finding: the next frames' descriptors are computed ahead (speed only)
        self._refinding = False

    @property
    def lagged(self) -> bool:
        """Whether frames wait for ``lag`` later views (own KLT tracks with ``lag`` > 0)."""
        cfg = self.config
        return cfg.triangulate and cfg.triangulation.detector == "klt" and cfg.lag > 0

    @property
    def refinds(self) -> bool:
        """Whether frames with few track points get descriptor points re-found (``refind``)."""
        cfg = self.config
        return cfg.triangulate and cfg.triangulation.detector == "klt" and cfg.refind.detector != "none"

    def step(self, entry: PendingFrame, rgb: np.ndarray) -> PendingFrame | None:
        """Queues the frame, runs one tracking step, and returns the frame whose turn it is (None while the lag fills)."""
        kid, T = entry.kid, entry.T
        self.queue.append(entry)
        ready: PendingFrame | None = None
        if self.refinds:
            self._refinder.add(rgb, T, kid, prefetch=self._refinding)
        if self.lagged:
            tracker = self._get_tracker()
            try:
                points = tracker.add(rgb, T, key=kid)
                for p in self.queue:
                    if p.kid == tracker.last_key:
                        p.check_tracks(tracker.tracks_seen.pop(p.kid, 0), tracker.tracks_agreeing.pop(p.kid, 0))
                        p.pose_displacement = tracker.pose_displacement.pop(p.kid, 0.0)
                        p.triangulated = self._with_refound(p, points)
            except Exception as exc:  # noqa: BLE001 - no points from this step; the MDE still counts
                entry.note("triangulation", exc)
                tracker.reset()  # the tracks start again; the frames waiting get no triangulated points
            if len(self.queue) > self.config.lag:
                ready = self.queue.popleft()
            if self._refinding and self.queue:  # the next frame to refine will likely need re-finding too
                depth = _typical_depth(self.queue[0])
                try:
                    if depth is not None:
                        self._refinder.prepare(self.queue[0].kid, depth)
                except Exception:  # noqa: BLE001 - speed only: without it `points` matches them itself
                    pass
        else:
            ready = self.queue.popleft()
            if self.config.triangulate:
                try:
                    ready.triangulated = self._with_refound(ready, self.triangulate(rgb, T, kid))
                except Exception as exc:  # noqa: BLE001 - no points from this frame; the MDE still counts
                    ready.note("triangulation", exc)
        return ready

    def flush(self) -> tuple[dict, float]:
        """Triangulates the waiting frames from the views there are: (id -> points, seconds per waiting frame)."""
        points: dict = {}
        if not (self.lagged and self._tracker is not None):
            return points, 0.0
        t0 = time.perf_counter()
        try:
            points = dict(self._tracker.flush())
        except Exception as exc:  # noqa: BLE001 - the waiting frames get no points
            for p in self.queue:
                p.note("triangulation", exc)
        return points, (time.perf_counter() - t0) / max(1, len(self.queue))

    def take(self, entry: PendingFrame, points: SparseDepth | None) -> None:
        """Gives a frame its points from `flush` (checked against its tracks, re-found ones added)."""
        if points is not None:
            tracker = self._tracker
            entry.check_tracks(
                tracker.tracks_seen.pop(entry.kid, 0), tracker.tracks_agreeing.pop(entry.kid, 0), stacklevel=4
            )
            entry.pose_displacement = tracker.pose_displacement.pop(entry.kid, 0.0)
            entry.triangulated = self._with_refound(entry, points)

    def triangulate(self, rgb: np.ndarray, T: np.ndarray, kid: int) -> SparseDepth:
        """One frame's points: one KLT step, or its descriptor features against the window of earlier frames."""
        cfg = self.config
        if cfg.triangulation.detector == "klt":
            # multi-view tracks followed frame to frame (one KLT step per frame)
            return self._get_tracker().add(rgb, T, key=kid)
        feats = detect_features(rgb, config=cfg.triangulation)
        partners = [item for item in self._window if np.linalg.norm(item[1][:3, 3] - T[:3, 3]) >= cfg.min_baseline]
        self._window.append([rgb, T, feats, kid])
        if not partners:
            return SparseDepth.empty(self.camera.shape)
        return triangulate_frames(
            [p[0] for p in partners] + [rgb],
            [p[1] for p in partners] + [T],
            self.camera,
            reference=-1,
            config=cfg.triangulation,
            features=[p[2] for p in partners] + [feats],
        )

    def move_waiting(self, new: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Gives waiting frames their new poses (they are fused later with them); returns ``new`` without them."""
        waiting = {p.kid: p for p in self.queue}
        for kid in [k for k in new if k in waiting]:  # not in the volume yet: fused later with the new pose
            waiting[kid].T = new.pop(kid)
        if self._tracker is not None:
            self._tracker.update_poses({p.kid: p.T for p in self.queue})
        self._refinder.update_poses({**{k: new[k] for k in new}, **{p.kid: p.T for p in self.queue}})
        return new

    def update_poses(self, new: dict[int, np.ndarray]) -> None:
        """New poses of fused keyframes, for the triangulations still to come."""
        for item in self._window:
            if item[3] in new:
                item[1] = new[item[3]]
        if self._tracker is not None:  # the poses the next triangulations use
            self._tracker.update_poses(new)

    def _with_refound(self, entry: PendingFrame, points: SparseDepth) -> SparseDepth:
        """The frame's track points, plus descriptor points when they are fewer than ``refind.below``."""
        self._refinding = self.refinds and len(points) < self.config.refind.below
        depth = _typical_depth(entry) if self._refinding else None
        if depth is None:
            return points
        try:
            extra = self._refinder.points(entry.kid, depth)
        except Exception as exc:  # noqa: BLE001 - the frame keeps its track points
            entry.note("descriptor re-finding", exc)
            return points
        return merge_sparse(points, extra, image_size=self.camera.shape)

    def _get_tracker(self) -> TrackTriangulator:
        if self._tracker is None:
            lag = int(self.config.lag) if self.lagged else 0
            self._tracker = TrackTriangulator(
                self.camera, self.config.triangulation, window=int(self.config.window), lag=lag
            )
        return self._tracker


def _typical_depth(entry: PendingFrame) -> float | None:
    """The median of a frame's MDE depth where it has one (metres); None without."""
    if entry.mde is None:
        return None
    valid = entry.mde[entry.mde > 0]
    return fast_median(valid) if valid.size else None
