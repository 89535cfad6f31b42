"""Options of the `Mapper`: `MapperConfig` and the GP and TSDF settings it starts from."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


from ..checks import Bool, Choice, Instance, Int, Real, check_fields, non_negative, positive
from ..gp.model import CalibrationConfig, DepthGPConfig
from .tsdf.fusion_config import FusionConfig
from .points.refinding import RefindConfig
from .points.triangulation_config import TriangulationConfig

MAPPER_FUSION = FusionConfig(relative_sigma_ref=0.05)
"""The `Mapper`'s TSDF options: variance weights relative to depth (`FusionConfig.relative_sigma_ref`)."""

MAPPER_GP = DepthGPConfig(lengthscale=64.0, calibration=CalibrationConfig(reach=None))
"""The `Mapper`'s GP: the default model with the variance of the stationary GP and twice its length scale: a
frame's own points are fewer than a LiDAR's and gather on texture, and their correction must reach the
surfaces between them (see `MapperConfig.gp`)."""


@dataclass(frozen=True)
class MapperConfig:
    """Options of the `Mapper` (the measurements behind the defaults: docs/results.md).

    Attributes:
        gp: GP model of the refinement (`MAPPER_GP`: the default model with the stationary GP's
            variance, a length scale of 64 grid pixels, fixed hyperparameters, fast engine): the
            fusion weights need that variance.
        fusion: TSDF options (`MAPPER_FUSION`: weights from the posterior variance relative to
            depth). With ``refine`` the volume also keeps a per-voxel variance (`Mapper.point_cloud`).
        triangulation: Feature tracking and triangulation options.
        refind: Descriptor re-finding for frames whose KLT tracks gave few points (large camera
            motion): views chosen by parallax, SIFT matches under the poses' epipolar geometry
            (`gpdepth3d.mapping.points.refinding`); ``RefindConfig(detector="none")`` turns it off.
        refine: False fuses the (resized) MDE depth itself, with uniform weights (a baseline).
        triangulate: Triangulate the frames' own features.
        window: Earlier frames a frame's KLT tracks are triangulated with.
        lag: Later frames a frame waits for before it is triangulated, refined and fused: views
            on both sides pull its depth less with one view's pose error. `add_frame` then returns
            the frame added ``lag`` calls earlier, `flush` the last ones; 0 fuses each frame at once.
        fuse_depth: "median" (default) or "mean" of the posterior: the TSDF's zero crossing is where
            the surface is as likely in front as behind, the median (log-normal:
            ``mean / sqrt(1 + variance / mean^2)``).
        map_scale_weight: Weight in [0, 1] of the map in the depth scale of a frame's triangulated
            points (`map_scale`; 0 off): the points of one frame share their views' pose errors, a
            common scale error that the keyframes already fused measure independently.
        map_scale_keyframes: The most recent keyframes `map_scale` compares with.
        map_scale_max_sigma: Keyframe pixels less certain than this fraction of their depth are
            not compared by `map_scale`: below ``FusionConfig.max_relative_sigma``, so that the
            scale comes from pixels that points informed, not from keyframes' MDE fallback.
        scale_variance: Add the frame's remaining scale uncertainty ``w (1 - w) (log s)^2 depth^2``
            (w the ``map_scale_weight``, log s the disagreement with the map) to the fused variance:
            the GP treats its points' errors as independent, but they share this scale error.
        min_baseline: Earlier frames closer than this to the camera centre are not used by the
            descriptor detectors ("orb", "sift"), metres.
        working_scale: Resolution of refinement and fusion relative to the RGB images.
        max_points: Most measurements per frame given to the GP, the most certain first (smallest
            sigma / depth): the GP solve grows with them.
        local_map_frames: Earlier frames whose triangulated points fill the gaps of a frame's own
            (`gpdepth3d.mapping.points.local_map`; 0 off): in grid cells without a point of its own, a frame
            gets the most certain of the points those frames triangulated that it sees.
        local_map_cell: Cell size of that fill, a fraction of the image width.
        keep_keyframes: Keep every fused frame's depth, variance, pose and colour at the working
            resolution (about 0.6 MB a frame at 320x240), for `update_poses` and `save`.
        sigma_calibration_frames: Frames whose overlap with the local map calibrates the sigma of the
            Mapper's own points (`gpdepth3d.mapping.point_calibration`; 0 off, and off without the local
            map): where a frame's points and the local map's meet, their differences over their sigmas
            must spread as z-scores do; a wider spread (poses worse than the triangulation's prior)
            widens every own point's sigma by it.
        held_out: Share of a frame's points held out to test its refinement (`gpdepth3d.mapping.mde_check`;
            0 off): the GP on the other points must predict them better than the MDE rescaled by one
            median, else the frame is fused as that rescaled MDE with its variance, weighted as a frame
            without points (``FrameResult.mde_fallback``). The map is then never worse than the MDE's.
            The test costs one more GP solve a frame.
        min_held_out: Fewest held-out points the test needs; a frame with fewer is not tested.
        fuse_inverted_poses: Fuse a frame whose given map points look inverted under its pose
            (`check_pose_orientation`); False (default): the frame is reported (``FrameResult.error``,
            `Mapper.failures`) and not fused, since such a pose puts its depth in the wrong place.
    """

    gp: DepthGPConfig = MAPPER_GP
    fusion: FusionConfig = MAPPER_FUSION
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    refind: RefindConfig = field(default_factory=RefindConfig)
    refine: bool = True
    triangulate: bool = True
    window: int = 8
    lag: int = 4
    fuse_depth: Literal["median", "mean"] = "median"
    map_scale_weight: float = 0.65
    map_scale_keyframes: int = 20
    map_scale_max_sigma: float = 0.15
    scale_variance: bool = True
    min_baseline: float = 0.05
    working_scale: float = 1.0
    max_points: int = 450
    local_map_frames: int = 8
    local_map_cell: float = 0.02
    keep_keyframes: bool = True
    sigma_calibration_frames: int = 10
    held_out: float = 0.2
    min_held_out: int = 10
    fuse_inverted_poses: bool = False

    def __post_init__(self) -> None:
        rules = {"gp": Instance(DepthGPConfig), "fusion": Instance(FusionConfig), "refind": Instance(RefindConfig)}
        rules.update(triangulation=Instance(TriangulationConfig), fuse_depth=Choice(("median", "mean")))
        rules.update(max_points=Int(1), window=Int(1), lag=Int(0), map_scale_keyframes=Int(1), local_map_frames=Int(0))
        rules.update(map_scale_weight=Real(0.0, 1.0, unit="a weight"), map_scale_max_sigma=positive("of the depth"))
        rules.update(
            min_baseline=non_negative("metres"), local_map_cell=Real(0.0, 1.0, low_open=True, unit="of the width")
        )
        rules.update(working_scale=Real(0.0, 1.0, low_open=True, unit="a factor"))
        rules.update(sigma_calibration_frames=Int(0), min_held_out=Int(1))
        rules.update(held_out=Real(0.0, 1.0, high_open=True, unit="a share of the points"))
        flags = ("refine", "triangulate", "scale_variance", "keep_keyframes", "fuse_inverted_poses")
        rules.update({name: Bool() for name in flags})
        check_fields(self, rules)
