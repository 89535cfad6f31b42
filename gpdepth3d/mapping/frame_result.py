"""What `Mapper.add_frame` returns for one frame: `FrameResult`, and the stages it times (`STAGES`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..completion.complete import DepthPosterior
from ..measurements import SparseDepth
from .points.map_points import MapPointStats
from ..io.poses import PoseCheck
from .mde_check import HeldOutCheck

STAGES = ("mde", "points", "gp", "fusion")
"""The timed stages of `Mapper.add_frame` (keys of `FrameResult.timings`, plus "total")."""


@dataclass(frozen=True, kw_only=True)
class FrameResult:
    """What `Mapper.add_frame` did with one frame (built by keyword only).

    Attributes:
        depth: (h, w) depth that was fused (posterior mean, or the MDE when not refining),
            metres; masked pixels are 0. Empty (0, 0) when the frame failed before.
        variance: (h, w) its variance, m^2 (NaN when not refining): the posterior's, plus the
            frame's remaining scale uncertainty with ``MapperConfig.scale_variance``.
        mde: (h, w) MDE depth at the working resolution, metres.
        sparse: The measurements used (at the RGB resolution).
        posterior: The GP posterior, or None when not refining (or the GP failed).
        timings: Seconds per stage of the call that returned it: "mde" (of the frame added
            in that call: with ``lag`` > 0 a later one), "points" (map points, one tracking step
            and this frame's triangulation), "gp", "fusion" (this frame) and "total".
        keyframe_id: The frame's id in the keyframe store.
        fused: Whether the frame reached the volume.
        error: Why the frame was not fused (stage, error type and message; names the frame),
            or None.
        warnings: Problems that did not stop the frame (a failed triangulation, an inverted
            pose, points outside the image...).
        masked_pixels: Pixels of the depth masked before fusion because the depth was <= 0
            or not finite (e.g. a GP mean pulled below zero by an outlier point).
        map_points: What became of the given SLAM map points, or None when none were given.
        pose_check: The inverted-pose check on the map points, or None.
        map_scale: The factor the frame's triangulated depths (and sigmas) were divided by to
            agree with the map (``MapperConfig.map_scale_weight``; 1 when not applied).
        fallback_weight: Fusion weight of its pixels no point informs (the MDE alone;
            `FusionConfig.fallback_for`): the configured fallback for a frame without points, near 0
            for one with many; 1 without refinement (uniform weights).
        pose_in_doubt: Its pose failed the pose check: its feature tracks do not triangulate with
            it, or its map points look inverted under it (`PendingFrame.pose_in_doubt`).
        mde_fallback: The frame was fused as its MDE rescaled by one median, with that MDE's
            variance, because its points' GP predicted held-out points no better
            (`gpdepth3d.mapping.mde_check`; ``MapperConfig.held_out``); a warning says so.
        held_out: That held-out comparison, or None when it did not run.
    """

    depth: np.ndarray
    variance: np.ndarray
    mde: np.ndarray
    sparse: SparseDepth
    posterior: DepthPosterior | None
    timings: dict
    keyframe_id: int = -1
    fused: bool = True
    error: str | None = None
    warnings: tuple[str, ...] = ()
    masked_pixels: int = 0
    map_points: MapPointStats | None = None
    pose_check: PoseCheck | None = None
    map_scale: float = 1.0
    fallback_weight: float = 0.0
    pose_in_doubt: bool = False
    mde_fallback: bool = False
    held_out: HeldOutCheck | None = None
