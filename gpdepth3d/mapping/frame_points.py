"""A frame on its way through the `Mapper`: its sparse measurements, the notes on them, and the ones the GP gets.

`PendingFrame` holds a frame from `Mapper.add_frame` until it is refined and fused (``MapperConfig.lag``
calls later): its MDE, its measurements (given, SLAM map points with the inverted-pose check,
triangulated), what went wrong with them, and its map-scale correction (`scale_to_map`).
`select_measurements` merges them and keeps the most certain for the GP.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..camera import PinholeCamera
from ..errors import GPDepthError
from ..measurements import SparseDepth
from .points.map_points import MapPointStats, merge_sparse, project_map_points
from ..io.poses import InvertedPoseWarning, PoseCheck, check_pose_orientation
from .mde_check import HeldOutCheck

POSE_TRACK_MIN = 50
"""Feature tracks a frame needs before its pose is checked against them (fewer: too little texture to tell)."""
POSE_TRACK_SHARE = 0.1
"""A frame whose tracks (seen in another view) agree with its pose and its neighbours' in fewer than this share
(`gpdepth3d.mapping.multiview.MultiViewPoints.agreeing`: within the reprojection gate after the bundle
adjustment, in front of the cameras) gets a warning that its pose may not belong to its image: an inverted pose
or another frame's leaves almost none, a pose off by a few centimetres and degrees most (the shares on the shared
sequences: tests/mapping/test_mapping.py)."""


@dataclass
class PendingFrame:
    """A frame added to the `Mapper` and not yet refined and fused (waiting for later views).

    Attributes:
        kid: Its keyframe id.
        T: Its 4x4 ``T_world_camera``.
        work_rgb: (h, w, 3) uint8 colour at the working resolution.
        mde: (h, w) MDE depth at the working resolution, metres (None when the front-end failed).
        error: (stage, exception) of a stage that failed, or None.
        parts: Measurements given with it (`SparseDepth`, map points), at the RGB resolution.
        triangulated: Its own triangulated (and re-found) points, or None.
        notes: Problems that did not stop it (`FrameResult.warnings`).
        map_stats: What became of its SLAM map points, or None.
        pose_check: The inverted-pose check on its map points, or None.
        measurements: What the GP gets (`select_measurements`), once chosen.
        scale: The factor its triangulated depths were divided by (`scale_to_map`).
        scale_var: Its log-scale variance left after that correction.
        pose_doubted: Its feature tracks contradict its pose (`check_tracks` warned): the local
            map's points, placed by that pose, are not used.
        held_out: The held-out comparison of its GP with its rescaled MDE (`mde_check`), once run.
        pose_displacement: How far, pixels, its pose and its neighbours' carry its tracks' points across
            their images from where they are seen (`MultiViewPoints.pose_displacement`; 0 when unknown).
    """

    kid: int
    T: np.ndarray
    work_rgb: np.ndarray
    mde: np.ndarray | None = None
    error: tuple[str, BaseException] | None = None
    parts: list = field(default_factory=list)
    triangulated: SparseDepth | None = None
    notes: list = field(default_factory=list)
    map_stats: MapPointStats | None = None
    pose_check: PoseCheck | None = None
    measurements: SparseDepth | None = None
    scale: float = 1.0
    scale_var: float = 0.0
    pose_doubted: bool = False
    held_out: HeldOutCheck | None = None
    pose_displacement: float = 0.0

    @property
    def mde_fallback(self) -> bool:
        """It is fused as its rescaled MDE: its points' GP predicted held-out points no better."""
        return self.held_out is not None and not self.held_out.gp_better

    @property
    def pose_in_doubt(self) -> bool:
        """Its tracks contradict its pose, or its map points look inverted under it."""
        return self.pose_doubted or (self.pose_check is not None and self.pose_check.inverted)

    def describe(self, stage: str, exc: BaseException) -> str:
        """``"frame <id>: <stage>: <error type>: <message>"``."""
        return f"frame {self.kid}: {stage}: {type(exc).__name__}: {exc}"

    def note(self, stage: str, exc: BaseException) -> None:
        """Notes a stage that failed without stopping the frame (`describe`)."""
        self.notes.append(self.describe(stage, exc))

    def add_map_points(self, points_world: np.ndarray, sigma: np.ndarray | None, camera: PinholeCamera) -> None:
        """Its SLAM map points as measurements, with the inverted-pose check (warned) and what was dropped (noted)."""
        kid, T = self.kid, self.T
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", InvertedPoseWarning)
                self.pose_check = check_pose_orientation(points_world, T, camera, frame=kid)
            for w in caught:
                self.notes.append(str(w.message))
                warnings.warn(w.message, w.category, stacklevel=3)
            points, self.map_stats = project_map_points(points_world, T, camera, sigma=sigma)
            st = self.map_stats
            if st.outside or st.behind or st.nonfinite:
                self.notes.append(
                    f"frame {kid}: {st.outside} of {st.given} map points outside the image, "
                    f"{st.behind} behind the camera, {st.nonfinite} not finite"
                )
            self.parts.append(points)
        except GPDepthError as exc:  # e.g. a bad sigma: the frame goes on without the map points
            self.note("map points", exc)

    def check_tracks(self, seen: int, points: int, *, stacklevel: int = 3) -> None:
        """Warns (noted and as `InvertedPoseWarning`) when only ``points`` of ``seen`` tracks agree with its pose.

        ``points``: the tracks its pose and its neighbours' agree with (`MultiViewPoints.agreeing`).
        """
        if seen < POSE_TRACK_MIN or points >= POSE_TRACK_SHARE * seen:
            return
        message = (
            f"frame {self.kid}: only {points} of {seen} feature tracks agree with this pose and its neighbours': "
            f"check that the poses are T_world_camera of these images (not inverted, not another frame's)"
        )
        self.notes.append(message)
        self.pose_doubted = True
        warnings.warn(message, InvertedPoseWarning, stacklevel=stacklevel)


def select_measurements(parts: list[SparseDepth], image_size: tuple[int, int], max_points: int) -> SparseDepth:
    """``parts`` merged (`merge_sparse`), then at most ``max_points`` kept: the smallest sigma / depth, in order."""
    measurements = merge_sparse(*parts, image_size=image_size)
    if len(measurements) > max_points:
        rel = np.nan_to_num(measurements.sigma / measurements.depth, nan=0.0)
        keep = np.sort(np.argsort(rel, kind="stable")[: int(max_points)])
        measurements = measurements.subset(keep)
    return measurements
