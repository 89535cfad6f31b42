"""SLAM-facing incremental mapping: refine each frame's MDE depth with sparse points, fuse into a TSDF.

A `Mapper` takes posed frames one by one::

    mapper = Mapper(camera, MapperConfig(), mde=FastDepthTFLite(model_path))
    for rgb, T_world_camera, slam_points in stream:
        mapper.add_frame(rgb, T_world_camera, map_points_world=slam_points)
        mesh = mapper.mesh()          # at any time (the frames fused so far)
    mapper.flush()                    # the last frames, which waited for later views

Per frame: (1) the MDE depth (given, or from the front-end callable ``rgb -> depth``);
(2) sparse measurements from any of: a `SparseDepth`, SLAM map points in world coordinates
(transformed by the pose and projected, `sparse_from_map_points`), and features the library
triangulates itself from KLT tracks through up to ``window`` earlier and ``lag`` later frames
(`gpdepth3d.mapping.triangulation`; with ``lag`` > 0 a frame is refined and fused ``lag`` calls
after it was added, see `MapperConfig.lag`), their depth scale pulled towards the keyframes
already fused (`map_scale`); (3) the GP posterior (`DepthCompleter`, one kept for the whole
sequence); (4) TSDF fusion of the posterior median (`fused_depth`) with per-pixel weights from
its variance (`gpdepth3d.mapping.fusion`).

Resolution: ``camera`` describes the RGB images given to `Mapper.add_frame`; features are
detected at that resolution, while refinement and fusion run at ``working_scale`` times it
(e.g. 0.5 for 320x240 from 640x480).

Robustness: after its arguments are validated, a frame never raises. A posterior mean <= 0 or
not finite is masked and counted before fusion; a stage that fails (the MDE front-end, the GP,
the fusion of a frame with nothing in range) is recorded on the `FrameResult` and in
`Mapper.failures`, naming the frame, and the sequence goes on. Map points outside the image,
behind the camera or not finite are counted (`MapPointStats`), and a pose under which the map
points look inverted warns (`gpdepth3d.mapping.trajectories.InvertedPoseWarning`).

Back-end interface: every fused frame is kept in a keyframe store (depth, variance, pose and
colour at the working resolution, by keyframe id). `Mapper.update_poses` applies a loop
closure by rebuilding only the TSDF blocks the moved keyframes reached before or reach now,
which gives exactly the volume of fusing every keyframe from scratch with the new poses.
`Mapper.save` / `Mapper.load` write and read the map (volume and keyframe store). Poses of a
back-end's trajectory file (TUM, ORB-SLAM3, KITTI, COLMAP) come from `gpdepth3d.mapping.trajectories`.

`gpdepth3d.experiments.mapping_run.fuse_sequence` (and ``gpdepth3d fuse``) runs the whole pipeline on a
7-Scenes-style sequence and compares the meshes from MDE-only, GP-refined and ground-truth depth.
"""

from __future__ import annotations

import json
import time
import warnings
import zipfile
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from ..camera import PinholeCamera, check_pose, transform_points
from ..completion.complete import DepthCompleter, DepthPosterior
from ..datasets.sevenscenes import COLOUR_INTRINSICS
from ..errors import CalibrationError, DataFormatError, GPDepthError, InvalidInputError, ShapeError, describe
from ..gp.model import CalibrationConfig, DepthGPConfig
from ..io import save_npz, write_json
from ..measurements import SparseDepth
from .cloud import ColoredCloud
from .features import detect_features
from .fusion import FusionConfig, IntegrationStats, TSDFFusion, save_mesh
from .map_points import MapPointStats, merge_sparse, project_map_points
from .refinding import RefindConfig, Refinder
from .tracks import TrackTriangulator, triangulate_frames
from .trajectories import InvertedPoseWarning, PoseCheck, check_pose_orientation
from .triangulation_config import TriangulationConfig

MDEFrontEnd = Callable[[np.ndarray], np.ndarray]


def _resize_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resizes a depth map (nearest for shrinking keeps no mixed depths; linear when growing)."""
    import cv2

    if depth.shape == tuple(shape):
        return depth
    interp = cv2.INTER_NEAREST if shape[0] < depth.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(depth.astype(np.float32), (shape[1], shape[0]), interpolation=interp).astype(np.float64)


MAPPER_FUSION = FusionConfig(relative_sigma_ref=0.05)
"""The `Mapper`'s TSDF options: variance weights relative to depth (`FusionConfig.relative_sigma_ref`)."""

MAPPER_GP = DepthGPConfig(calibration=CalibrationConfig(reach=None))
"""The `Mapper`'s GP: the default model with the variance of the stationary GP (see `MapperConfig.gp`)."""


@dataclass(frozen=True)
class MapperConfig:
    """Options of the `Mapper`.

    Numbers behind the defaults (F at 5 cm, chosen on one half of a sequence, confirmed on the
    other): bench/results/mapping_settings.json and bench/results/mapping_sequences.json.

    Attributes:
        gp: GP model of the refinement (`MAPPER_GP`: the default model with the stationary GP's
            variance, fixed hyperparameters, fast engine): the fusion weights need that variance.
        fusion: TSDF options (`MAPPER_FUSION`: weights from the posterior variance relative to
            depth). With ``refine`` the volume also keeps a per-voxel variance (`Mapper.point_cloud`).
        triangulation: Feature tracking and triangulation options.
        refind: Descriptor re-finding for frames whose KLT tracks gave few points (large camera
            motion): views chosen by parallax, ORB matches under the poses' epipolar geometry
            (`gpdepth3d.mapping.refinding`); ``RefindConfig(detector="none")`` turns it off.
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
        keep_keyframes: Keep every fused frame's depth, variance, pose and colour at the working
            resolution (about 0.6 MB a frame at 320x240), for `update_poses` and `save`.
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
    keep_keyframes: bool = True
    fuse_inverted_poses: bool = False

    def __post_init__(self) -> None:
        if int(self.max_points) != self.max_points or self.max_points < 1:
            raise InvalidInputError("max_points", "an integer >= 1", self.max_points)
        if int(self.window) != self.window or self.window < 1:
            raise InvalidInputError("window", "an integer >= 1", self.window)
        if isinstance(self.lag, bool) or int(self.lag) != self.lag or self.lag < 0:
            raise InvalidInputError("lag", "an integer >= 0", self.lag)
        if self.fuse_depth not in ("median", "mean"):
            raise InvalidInputError("fuse_depth", "'median' or 'mean'", self.fuse_depth)
        if not np.isfinite(self.map_scale_weight) or not 0 <= self.map_scale_weight <= 1:
            raise InvalidInputError("map_scale_weight", "a weight in [0, 1]", self.map_scale_weight)
        if not np.isfinite(self.map_scale_max_sigma) or self.map_scale_max_sigma <= 0:
            raise InvalidInputError("map_scale_max_sigma", "a fraction of the depth > 0", self.map_scale_max_sigma)
        if (
            isinstance(self.map_scale_keyframes, bool)
            or int(self.map_scale_keyframes) != self.map_scale_keyframes
            or self.map_scale_keyframes < 1
        ):
            raise InvalidInputError("map_scale_keyframes", "an integer >= 1", self.map_scale_keyframes)
        if not np.isfinite(self.min_baseline) or self.min_baseline < 0:
            raise InvalidInputError("min_baseline", "a distance >= 0 (metres)", self.min_baseline)
        if not np.isfinite(self.working_scale) or not 0 < self.working_scale <= 1:
            raise InvalidInputError("working_scale", "a factor in (0, 1]", self.working_scale)


STAGES = ("mde", "points", "gp", "fusion")

POSE_TRACK_MIN = 50
"""Feature tracks a frame needs before its pose is checked against them (fewer: too little texture to tell)."""
POSE_TRACK_SHARE = 0.1
"""A frame whose own triangulation keeps fewer than this share of its tracks (seen in another view) gets a
warning that its pose may not belong to its image. On the 60 shared 7-Scenes frames (the tracker's defaults,
window 8, lag 4) the share is 0.21-0.98 (below 0.3 only in the blurred frames 24-38); with the pose of frame 12
or 40 inverted, moved by 0.3 m or turned by 0.2 rad, that frame's share is 0.00-0.04 (and 0.02-0.05 in the
frames 36-41 around frame 40, whose windows hold it: they are warned about too)."""
"""The timed stages of `Mapper.add_frame` (keys of `FrameResult.timings`, plus "total")."""


@dataclass(frozen=True)
class FrameResult:
    """What `Mapper.add_frame` did with one frame.

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


@dataclass
class Keyframe:
    """One fused frame as the keyframe store keeps it (everything at the working resolution).

    Attributes:
        keyframe_id: Its id.
        T_world_camera: 4x4 pose it is fused with.
        depth: (h, w) float32 fused depth, metres (0 = none).
        variance: (h, w) float32 depth variance, m^2 (NaN when not refining).
        rgb: (h, w, 3) uint8 colour.
        block_keys: (M,) int64 keys of the TSDF blocks it reached.
        points: Sparse measurements it was refined with (they set its fallback weight,
            `FusionConfig.fallback_for`).
    """

    keyframe_id: int
    T_world_camera: np.ndarray
    depth: np.ndarray
    variance: np.ndarray
    rgb: np.ndarray
    block_keys: np.ndarray
    points: int = 0


@dataclass(frozen=True)
class PoseUpdate:
    """What `Mapper.update_poses` did.

    Attributes:
        moved: Ids of the keyframes whose pose changed.
        reintegrated: Ids of the keyframes integrated again (the moved ones and those sharing
            a block with them), in integration order.
        blocks: Number of TSDF blocks rebuilt.
        seconds: Wall time.
    """

    moved: tuple[int, ...]
    reintegrated: tuple[int, ...]
    blocks: int
    seconds: float


@dataclass
class _Pending:
    """A frame added to the `Mapper` and not yet refined and fused (waiting for later views)."""

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
    stored,
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
            logs.append(_median(np.log(z[k, ins][ok] / d[ok])))
    if len(logs) < min_keyframes:
        return 0.0, 0
    return float(np.median(logs)), len(logs)


def _median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array without NaN (the same value, a tenth of the overhead)."""
    m = x.size // 2
    if x.size % 2:
        return float(np.partition(x, m)[m])
    p = np.partition(x, (m - 1, m))
    return float((p[m - 1] + p[m]) / 2)


def _keyframe_id(value: Any) -> int:
    """A keyframe id as an int; a bool, a string, NaN or a fraction raise `InvalidInputError`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError("keyframe_id", "an integer", value)
    if not np.isfinite(value) or int(value) != value:
        raise InvalidInputError("keyframe_id", "an integer", value)
    return int(value)


def _sigma_array(value: Any) -> np.ndarray:
    """Map point sigma(s) as float64 (a number or (N,) numbers, finite, > 0 metres) or `InvalidInputError`."""
    try:
        sigma = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(
            "map_points_sigma", "depth sigma(s) in metres: a number or (N,) numbers", value
        ) from None
    if sigma.ndim > 1 or not np.all(np.isfinite(sigma)) or not np.all(sigma > 0):
        raise InvalidInputError(
            "map_points_sigma", "finite depth sigma(s) > 0 metres, a number or (N,)", describe(sigma)
        )
    return sigma


def _describe_error(stage: str, exc: BaseException) -> str:
    return f"{stage}: {type(exc).__name__}: {exc}"


class Mapper:
    """Incremental dense mapping from posed RGB frames, MDE depth and sparse SLAM measurements.

    Every fused frame is kept in a keyframe store (depth, variance, pose and colour at the
    working resolution; ``config.keep_keyframes``), so that a loop closure can move poses
    afterwards (`update_poses`) and the map can be saved and loaded (`save`, `load`).

    Args:
        camera: Intrinsics of the RGB images passed to `add_frame`.
        config: Options.
        mde: Optional front-end ``rgb -> depth`` (metres) used when a frame comes without MDE depth.
        completer: Optional `DepthCompleter` to reuse (default: one built from ``config.gp``).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        config: MapperConfig | None = None,
        *,
        mde: MDEFrontEnd | None = None,
        completer: DepthCompleter | None = None,
    ):
        if not isinstance(camera, PinholeCamera):
            raise InvalidInputError("camera", "a PinholeCamera", type(camera).__name__)
        self.camera = camera
        self.config = config or MapperConfig()
        if mde is not None and not callable(mde):
            raise InvalidInputError("mde", "a callable rgb -> depth", type(mde).__name__)
        self.mde = mde
        s = self.config.working_scale
        self.work_camera = (
            camera if s == 1 else camera.resized(max(2, round(camera.width * s)), max(2, round(camera.height * s)))
        )
        self.completer = completer or (DepthCompleter(self.config.gp) if self.config.refine else None)
        if self.config.refine:
            fusion_cfg = replace(self.config.fusion, integrate_variance=True)
        else:
            fusion_cfg = replace(self.config.fusion, weighting="uniform", integrate_variance=False)
        self.fusion = TSDFFusion(self.work_camera, fusion_cfg)
        self._window: deque[list] = deque(maxlen=int(self.config.window))
        self._tracker: TrackTriangulator | None = None
        self._refinder = Refinder(camera, self.config.refind, self.config.triangulation)
        self._queue: deque[_Pending] = deque()
        self.keyframes: dict[int, Keyframe] = {}
        self.frames = 0
        self._next_id = 0
        self.timings: list[dict] = []
        self.failures: list[str] = []

    # ------------------------------------------------------------------ per frame
    def add_frame(
        self,
        rgb: np.ndarray,
        T_world_camera: np.ndarray,
        *,
        mde_depth: np.ndarray | None = None,
        sparse: SparseDepth | None = None,
        map_points_world: np.ndarray | None = None,
        map_points_sigma: float | np.ndarray | None = None,
        keyframe_id: int | None = None,
    ) -> FrameResult | None:
        """Adds one posed frame; refines and fuses the frame whose turn it is; never stops on bad data.

        With ``config.lag = 0`` (or without the Mapper's own triangulation) the frame given is
        refined and fused in this call and its `FrameResult` returned. With ``lag = L > 0`` a
        frame waits until its features have been followed into L later frames: this call adds
        the frame (its MDE, its measurements and one tracking step) and refines and fuses the
        frame added L calls earlier, whose `FrameResult` it returns (``keyframe_id`` names it;
        None while the first L frames come in). `flush` finishes the frames still waiting.

        Arguments are validated first (wrong types, shapes, a non-rigid pose raise). After that,
        whatever the data does (an MDE front-end that fails, a failed triangulation, a GP mean
        <= 0 or NaN, a frame with nothing to fuse) is recorded on the `FrameResult` of that
        frame (``fused``, ``error``, ``warnings``, ``masked_pixels``) and in `failures`,
        naming the frame, and the sequence goes on.

        Args:
            rgb: (H, W, 3) uint8 RGB image of ``camera``'s size.
            T_world_camera: 4x4 rigid pose.
            mde_depth: (h, w) MDE depth, metres, any resolution of the same image; default: the
                front-end's output for ``rgb``.
            sparse: Extra measurements (any resolution of the same image).
            map_points_world: (N, 3) SLAM map points in the world frame, metres; points behind
                the camera or outside the image are counted (``map_points``) and a pose under
                which they look inverted warns (`InvertedPoseWarning`). They are projected with
                the pose given here.
            map_points_sigma: Their depth sigma(s), metres (default: the model's sigma_meas).
            keyframe_id: Id in the keyframe store (default: the next integer); the back-end's
                keyframe id, used by `update_poses`.

        Returns:
            `FrameResult` of the frame refined and fused in this call (depth fused, variance,
            measurements, timings of this call, what went wrong), or None when no frame's turn
            has come yet.

        Raises:
            ShapeError: on image / depth size mismatches.
            CalibrationError: on a non-rigid pose.
            InvalidInputError: when neither mde_depth nor a front-end is given, the keyframe id
                is taken or not an integer, or map_points_sigma is not finite and > 0.
        """
        t_start = time.perf_counter()
        timings = dict.fromkeys(STAGES, 0.0)
        T = check_pose(T_world_camera)
        rgb = np.asarray(rgb)
        kid = self._check_frame_args(rgb, mde_depth, sparse, keyframe_id)
        if map_points_sigma is not None:
            map_points_sigma = _sigma_array(map_points_sigma)
        if mde_depth is not None:
            mde_depth = self._check_mde(mde_depth)
        self._next_id = max(self._next_id, kid + 1)
        entry = _Pending(kid=kid, T=T, work_rgb=self._work_rgb(rgb))

        # 1. MDE of the frame given
        t0 = time.perf_counter()
        try:
            if mde_depth is None:
                mde_depth = self._check_mde(self.mde(rgb))
            entry.mde = _resize_depth(np.where(np.isfinite(mde_depth), mde_depth, 0.0), self.work_camera.shape)
        except Exception as exc:  # noqa: BLE001 - a front-end failing on one frame must not end the run
            entry.error = ("mde", exc)
        timings["mde"] = time.perf_counter() - t0

        # 2. points: the frame's own measurements now, one tracking step (triangulates the frame whose turn it is)
        t0 = time.perf_counter()
        if sparse is not None:
            entry.parts.append(sparse.rasterize(self.camera.shape))
        if map_points_world is not None:
            self._add_map_points(entry, map_points_world, map_points_sigma)
        ready = self._track_step(entry, rgb)
        timings["points"] = time.perf_counter() - t0
        if ready is None:
            timings["total"] = time.perf_counter() - t_start
            self.timings.append(timings)
            return None
        return self._finish(ready, timings, t_start)

    def _track_step(self, entry: _Pending, rgb: np.ndarray) -> _Pending | None:
        """Queues the frame, runs one tracking step, and returns the frame whose turn it is (None while the lag fills)."""
        kid, T = entry.kid, entry.T
        self._queue.append(entry)
        ready: _Pending | None = None
        if self._refinds:
            self._refinder.add(rgb, T, kid)
        if self._lagged:
            tracker = self._get_tracker()
            try:
                points = tracker.add(rgb, T, key=kid)
                for p in self._queue:
                    if p.kid == tracker.last_key:
                        self._check_tracks(p, tracker.tracks_seen.pop(p.kid, 0), len(points))
                        p.triangulated = self._with_refound(p, points)
            except Exception as exc:  # noqa: BLE001 - no points from this step; the MDE still counts
                entry.notes.append(f"frame {kid}: " + _describe_error("triangulation", exc))
                tracker.reset()  # the tracks start again; the frames waiting get no triangulated points
            if len(self._queue) > self.config.lag:
                ready = self._queue.popleft()
        else:
            ready = self._queue.popleft()
            if self.config.triangulate:
                try:
                    ready.triangulated = self._with_refound(ready, self._triangulate(rgb, T, kid))
                except Exception as exc:  # noqa: BLE001 - no points from this frame; the MDE still counts
                    ready.notes.append(f"frame {kid}: " + _describe_error("triangulation", exc))
        return ready

    def _add_map_points(self, entry: _Pending, points_world: np.ndarray, sigma: np.ndarray | None) -> None:
        """The frame's SLAM map points as measurements, with the inverted-pose check and what was dropped."""
        kid, T = entry.kid, entry.T
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", InvertedPoseWarning)
                entry.pose_check = check_pose_orientation(points_world, T, self.camera, frame=kid)
            for w in caught:
                entry.notes.append(str(w.message))
                warnings.warn(w.message, w.category, stacklevel=3)
            points, entry.map_stats = project_map_points(points_world, T, self.camera, sigma=sigma)
            st = entry.map_stats
            if st.outside or st.behind or st.nonfinite:
                entry.notes.append(
                    f"frame {kid}: {st.outside} of {st.given} map points outside the image, "
                    f"{st.behind} behind the camera, {st.nonfinite} not finite"
                )
            entry.parts.append(points)
        except GPDepthError as exc:  # e.g. a bad sigma: the frame goes on without the map points
            entry.notes.append(f"frame {kid}: " + _describe_error("map points", exc))

    def flush(self) -> list[FrameResult]:
        """Refines and fuses the frames still waiting for later views (``config.lag``), oldest first.

        Call it at the end of a sequence (or before `mesh`, `save` or a pause): each waiting
        frame is triangulated from the views there are. Later `add_frame` calls go on as before.

        Returns:
            The frames' `FrameResult` (empty when none waits).
        """
        results = []
        points: dict = {}
        if self._lagged and self._tracker is not None:
            t0 = time.perf_counter()
            try:
                points = dict(self._tracker.flush())
            except Exception as exc:  # noqa: BLE001 - the waiting frames get no points
                for p in self._queue:
                    p.notes.append(f"frame {p.kid}: " + _describe_error("triangulation", exc))
            t_points = (time.perf_counter() - t0) / max(1, len(self._queue))
        else:
            t_points = 0.0
        while self._queue:
            t_start = time.perf_counter()
            entry = self._queue.popleft()
            if points.get(entry.kid) is not None:
                self._check_tracks(entry, self._tracker.tracks_seen.pop(entry.kid, 0), len(points[entry.kid]))
                entry.triangulated = self._with_refound(entry, points[entry.kid])
            timings = dict.fromkeys(STAGES, 0.0)
            timings["points"] = t_points + time.perf_counter() - t_start
            results.append(self._finish(entry, timings, t_start))
        return results

    @property
    def pending(self) -> tuple[int, ...]:
        """Ids of the frames added but not yet refined and fused (waiting for ``config.lag`` later views)."""
        return tuple(p.kid for p in self._queue)

    @property
    def _refinds(self) -> bool:
        cfg = self.config
        return cfg.triangulate and cfg.triangulation.detector == "klt" and cfg.refind.detector != "none"

    def _with_refound(self, entry: _Pending, points: SparseDepth) -> SparseDepth:
        """The frame's track points, plus descriptor points when they are fewer than ``refind.below``."""
        if not self._refinds or len(points) >= self.config.refind.below or entry.mde is None:
            return points
        valid = entry.mde[entry.mde > 0]
        if not valid.size:
            return points
        try:
            extra = self._refinder.points(entry.kid, _median(valid))
        except Exception as exc:  # noqa: BLE001 - the frame keeps its track points
            entry.notes.append(f"frame {entry.kid}: " + _describe_error("descriptor re-finding", exc))
            return points
        return merge_sparse(points, extra, image_size=self.camera.shape)

    @property
    def _lagged(self) -> bool:
        cfg = self.config
        return cfg.triangulate and cfg.triangulation.detector == "klt" and cfg.lag > 0

    @staticmethod
    def _check_tracks(entry: "_Pending", seen: int, points: int) -> None:
        """Warns (on the frame and as `InvertedPoseWarning`) when the pose contradicts the image's tracks."""
        if seen < POSE_TRACK_MIN or points >= POSE_TRACK_SHARE * seen:
            return
        message = (
            f"frame {entry.kid}: only {points} of {seen} feature tracks triangulate with this pose and its "
            f"neighbours' (a pose that belongs to its image: 21-98 % on 7-Scenes): check that the poses are "
            f"T_world_camera of these images (not inverted, not another frame's); a camera that only rotated does "
            f"this too"
        )
        entry.notes.append(message)
        warnings.warn(message, InvertedPoseWarning, stacklevel=3)

    def _get_tracker(self) -> TrackTriangulator:
        if self._tracker is None:
            lag = int(self.config.lag) if self._lagged else 0
            self._tracker = TrackTriangulator(
                self.camera, self.config.triangulation, window=int(self.config.window), lag=lag
            )
        return self._tracker

    def _finish(self, entry: "_Pending", timings: dict, t_start: float) -> FrameResult:
        """GP and fusion of one frame whose measurements are complete; records and returns its result."""
        kid, T = entry.kid, entry.T
        notes = entry.notes
        empty = np.zeros((0, 0))
        t_prep = time.perf_counter()
        scale = 1.0
        scale_var = 0.0  # log-scale variance of the frame left after map_scale (scale_variance)
        parts = list(entry.parts)
        if entry.triangulated is not None and len(entry.triangulated):
            tri = entry.triangulated
            weight = float(self.config.map_scale_weight)
            if weight > 0 and self.keyframes:
                log_s, used = map_scale(
                    tri,
                    T,
                    self.camera,
                    self.keyframes.values(),
                    self.work_camera,
                    recent=int(self.config.map_scale_keyframes),
                    max_relative_sigma=float(self.config.map_scale_max_sigma),
                )
                if used:
                    scale = float(np.exp(weight * log_s))
                    scale_var = weight * (1.0 - weight) * log_s**2
                    tri = SparseDepth(tri.u, tri.v, tri.depth / scale, tri.image_size, tri.sigma / scale)
            parts.append(tri)
        measurements = merge_sparse(*parts, image_size=self.camera.shape)
        if len(measurements) > self.config.max_points:
            rel = np.nan_to_num(measurements.sigma / measurements.depth, nan=0.0)
            keep = np.sort(np.argsort(rel, kind="stable")[: int(self.config.max_points)])
            measurements = measurements.subset(keep)
        timings["points"] += time.perf_counter() - t_prep  # the frame's measurements: map scale, merge, selection

        def failed(stage: str, exc: BaseException, mde: np.ndarray = empty, posterior=None) -> FrameResult:
            message = f"frame {kid}: " + _describe_error(stage, exc)
            self.failures.append(message)
            timings["total"] = time.perf_counter() - t_start
            self.timings.append(timings)
            return FrameResult(
                empty,
                empty,
                mde,
                measurements,
                posterior,
                timings,
                kid,
                False,
                message,
                tuple(notes),
                0,
                entry.map_stats,
                entry.pose_check,
                scale,
            )

        if entry.error is not None:
            return failed(entry.error[0], entry.error[1])
        check = entry.pose_check
        if check is not None and check.inverted and not self.config.fuse_inverted_poses:
            return failed(
                "pose check",
                CalibrationError(
                    "T_world_camera",
                    "a pose that sees its map points (not fused: MapperConfig.fuse_inverted_poses)",
                    f"{check.visible:.0%} of {check.points} points visible, {check.visible_inverse:.0%} under its inverse",
                ),
            )
        mde = entry.mde
        work_shape = self.work_camera.shape

        # 3. GP
        t0 = time.perf_counter()
        posterior = None
        try:
            if self.config.refine:
                # the frame's name goes into the posterior's warnings (a duck-typed completer may not take it)
                named = {"frame": str(kid)} if isinstance(self.completer, DepthCompleter) else {}
                posterior = self.completer.complete(mde, measurements, output_shape=work_shape, **named)
                depth, variance = fused_depth(posterior, self.config.fuse_depth), posterior.variance
                if self.config.scale_variance and scale_var > 0:
                    variance = variance + scale_var * np.square(depth)
            else:
                depth, variance = mde, np.full(work_shape, np.nan)
        except Exception as exc:  # noqa: BLE001 - e.g. an empty MDE frame; recorded, the run goes on
            timings["gp"] = time.perf_counter() - t0
            return failed("gp", exc, mde)
        timings["gp"] = time.perf_counter() - t0

        # 4. fusion (what is fused is what the keyframe store keeps: float32 at the working size)
        t0 = time.perf_counter()
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(depth) | (depth < 0) | ((depth == 0) & (mde > 0))
        masked = int(bad.sum())
        if masked:
            notes.append(f"frame {kid}: {masked} pixels with depth <= 0 or not finite masked")
        depth32 = np.where(bad, 0.0, depth).astype(np.float32)
        var32 = np.asarray(variance, dtype=np.float32)
        try:
            stats = self._integrate(
                depth32, var32, T, entry.work_rgb, points=len(measurements) if self.config.refine else 0
            )
        except Exception as exc:  # noqa: BLE001 - e.g. nothing in range; recorded, the run goes on
            timings["fusion"] = time.perf_counter() - t0
            result = failed("fusion", exc, mde, posterior)
            return replace(
                result, depth=depth32.astype(np.float64), variance=var32.astype(np.float64), masked_pixels=masked
            )
        fallback = self.fusion.config.fallback_for(len(measurements)) if self.config.refine else 1.0
        if stats.pixels == 0:
            notes.append(f"frame {kid}: no pixel informed by points and no fallback weight left: nothing fused")
        elif self.config.refine and len(measurements) == 0:
            notes.append(f"frame {kid}: no points: fused as the MDE with its prior variance, weight {fallback:.2f}")
        if self.config.keep_keyframes:
            self.keyframes[kid] = Keyframe(kid, T, depth32, var32, entry.work_rgb, stats.block_keys, len(measurements))
        timings["fusion"] = time.perf_counter() - t0
        self.frames += 1
        timings["total"] = time.perf_counter() - t_start
        self.timings.append(timings)
        return FrameResult(
            depth32.astype(np.float64),
            var32.astype(np.float64),
            mde,
            measurements,
            posterior,
            timings,
            kid,
            True,
            None,
            tuple(notes),
            masked,
            entry.map_stats,
            entry.pose_check,
            scale,
            fallback,
        )

    def _check_frame_args(self, rgb: np.ndarray, mde_depth, sparse, keyframe_id) -> int:
        """Validates `add_frame`'s image, MDE source, measurements and id; returns the keyframe id."""
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ShapeError("rgb", "an (H, W, 3) uint8 RGB image", describe(rgb))
        self.camera.check_image(rgb, "rgb")
        if mde_depth is None and self.mde is None:
            raise InvalidInputError("mde_depth", "an MDE depth map (or an mde front-end in Mapper)", None)
        if sparse is not None and not isinstance(sparse, SparseDepth):
            raise InvalidInputError("sparse", "a SparseDepth", type(sparse).__name__)
        kid = self._next_id if keyframe_id is None else _keyframe_id(keyframe_id)
        if kid in self.keyframes or any(p.kid == kid for p in self._queue):
            raise InvalidInputError("keyframe_id", "an id not in the keyframe store", kid)
        return kid

    def _check_mde(self, mde_depth: np.ndarray) -> np.ndarray:
        mde_depth = np.asarray(mde_depth, dtype=np.float64)
        if mde_depth.ndim != 2 or min(mde_depth.shape) < 2:
            raise ShapeError("mde_depth", "a 2-D (h, w) depth map", describe(mde_depth))
        h, w = mde_depth.shape
        if abs((w / h) / (self.camera.width / self.camera.height) - 1) > 0.01:
            raise ShapeError(
                "mde_depth",
                f"a depth map with the aspect ratio of the {self.camera.width}x{self.camera.height} image",
                (h, w),
            )
        return mde_depth

    def _integrate(
        self, depth32: np.ndarray, var32: np.ndarray, T: np.ndarray, rgb: np.ndarray, blocks=None, points: int = 0
    ) -> IntegrationStats:
        weights = self.fusion.weights_for(var32, depth32, points=points)
        if weights is not None and not np.any(weights > 0):
            # every pixel uninformed and no fallback weight left: nothing to fuse, not a failure
            return IntegrationStats(0, 0, 0, np.zeros(0, np.int64))
        return self.fusion.integrate(
            depth32,
            T,
            rgb=rgb,
            weights=weights,
            variance=var32 if self.fusion.config.integrate_variance else None,
            blocks=blocks,
        )

    def _work_rgb(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        if self.work_camera is self.camera:
            return rgb
        return cv2.resize(rgb, (self.work_camera.width, self.work_camera.height), interpolation=cv2.INTER_AREA)

    def _triangulate(self, rgb: np.ndarray, T: np.ndarray, kid: int) -> SparseDepth:
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

    # ------------------------------------------------------------------ loop closure
    def update_poses(self, poses: dict) -> PoseUpdate:
        """Moves keyframes to new poses (after a loop closure) and re-integrates what moved.

        The TSDF blocks a moved keyframe reached under its old pose or reaches under its new
        one are zeroed and rebuilt from every stored keyframe that reaches them, in the order
        the keyframes were fused; all other blocks are left alone. The volume is then the one
        fusing all keyframes from scratch with the new poses gives (voxel for voxel; see
        `gpdepth3d.mapping.fusion`).

        Args:
            poses: keyframe id -> new 4x4 ``T_world_camera``.

        Returns:
            `PoseUpdate` (which keyframes moved and were re-integrated, blocks rebuilt).

        Raises:
            InvalidInputError: for an unknown keyframe id, or without a keyframe store.
            CalibrationError: for a pose that is not rigid.
        """
        t0 = time.perf_counter()
        if not self.config.keep_keyframes:
            raise InvalidInputError("config.keep_keyframes", "True (update_poses needs the keyframe store)", False)
        if not isinstance(poses, dict):
            raise InvalidInputError("poses", "a dict keyframe id -> 4x4 T_world_camera", type(poses).__name__)
        new = {}
        waiting = {p.kid: p for p in self._queue}
        for kid, T in poses.items():
            if kid not in self.keyframes and kid not in waiting:
                raise InvalidInputError("poses", "ids of stored keyframes (or of frames waiting to be fused)", kid)
            new[kid] = check_pose(T, f"poses[{kid}]")
        for kid in [k for k in new if k in waiting]:  # not in the volume yet: fused later with the new pose
            waiting[kid].T = new.pop(kid)
        if self._tracker is not None:
            self._tracker.update_poses({p.kid: p.T for p in self._queue})
        self._refinder.update_poses({**{k: new[k] for k in new}, **{p.kid: p.T for p in self._queue}})
        moved = [kid for kid, T in new.items() if not np.array_equal(T, self.keyframes[kid].T_world_camera)]
        if not moved:
            return PoseUpdate((), (), 0, time.perf_counter() - t0)
        affected = [self.keyframes[k].block_keys for k in moved]
        affected += [self.fusion.block_keys(self.keyframes[k].depth, new[k], self.keyframes[k].variance) for k in moved]
        blocks = np.unique(np.concatenate(affected))
        for k in moved:
            self.keyframes[k].T_world_camera = new[k]
        for item in self._window:
            if item[3] in new:
                item[1] = new[item[3]]
        if self._tracker is not None:  # the poses the next triangulations use
            self._tracker.update_poses(new)
        frames_before = self.fusion.frames_integrated
        self.fusion.reset_blocks(blocks)
        redone = []
        for kid, kf in self.keyframes.items():
            if kid in new and kid in moved or np.intersect1d(kf.block_keys, blocks, assume_unique=True).size:
                stats = self._integrate(
                    kf.depth, kf.variance, kf.T_world_camera, kf.rgb, blocks=blocks, points=kf.points
                )
                if kid in moved:
                    kf.block_keys = stats.block_keys
                redone.append(kid)
        self.fusion.frames_integrated = frames_before
        return PoseUpdate(tuple(moved), tuple(redone), int(blocks.size), time.perf_counter() - t0)

    # ------------------------------------------------------------------ the map
    def mesh(self) -> Any:
        """The current map as a `trimesh.Trimesh` (world frame, metres, vertex colours).

        Extraction is incremental (`TSDFFusion.extract_mesh_incremental`): only the chunks of
        the volume that frames or pose updates changed since the last call are meshed again,
        the rest comes from a cache; the surface is the one a full extraction gives, as a
        triangle soup (``mesh.merge_vertices()`` shares the vertices). A map whose surface does
        not yet pass the fusion's ``weight_threshold`` gives a mesh without faces. Frames still
        waiting for later views (`pending`) are not in it yet (`flush`).

        Raises:
            EmptyInputError: before the first fused frame.
        """
        return self.fusion.extract_mesh_incremental(allow_empty=True)

    def point_cloud(self) -> ColoredCloud:
        """The current map's surface points as a `ColoredCloud`.

        With refinement each point carries the fused depth variance of its voxel (the
        keyframes' posterior variances averaged with the fusion weights, m^2); without, NaN.
        A map whose surface does not yet pass ``weight_threshold`` gives an empty cloud.

        Raises:
            EmptyInputError: before the first fused frame.
        """
        return self.fusion.extract_point_cloud(allow_empty=True)

    def save_mesh(self, path: str | Path) -> Path:
        """Writes the current mesh (PLY, GLB or OBJ) atomically."""
        return save_mesh(self.mesh(), path)

    # ------------------------------------------------------------------ persistence
    def save(self, folder: str | Path) -> Path:
        """Writes the map to a folder: the TSDF volume (``volume.npz`` + ``volume.json``), the
        keyframe store (``keyframes.npz``) and the mapper's settings (``mapper.json``), each
        file atomically. Frames still waiting for later views (`pending`) are not in the map
        yet: call `flush` first to include them.

        Returns:
            The folder.
        """
        folder = Path(folder)
        ids = list(self.keyframes)
        kfs = [self.keyframes[k] for k in ids]
        h, w = self.work_camera.shape
        keys = [kf.block_keys for kf in kfs]
        save_npz(
            folder / "keyframes.npz",
            ids=np.array(ids, dtype=np.int64),
            poses=np.stack([kf.T_world_camera for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
            depth=np.stack([kf.depth for kf in kfs]) if kfs else np.zeros((0, h, w), np.float32),
            variance=np.stack([kf.variance for kf in kfs]) if kfs else np.zeros((0, h, w), np.float32),
            rgb=np.stack([kf.rgb for kf in kfs]) if kfs else np.zeros((0, h, w, 3), np.uint8),
            block_keys=np.concatenate(keys) if keys else np.zeros(0, np.int64),
            block_counts=np.array([k.size for k in keys], dtype=np.int64),
            points=np.array([kf.points for kf in kfs], dtype=np.int64),
        )
        self.fusion.save(folder / "volume.npz")
        c = self.camera
        meta = {
            "camera": [c.fx, c.fy, c.cx, c.cy, c.width, c.height],
            "config": asdict(self.config),
            "frames": self.frames,
            "next_id": self._next_id,
        }
        write_json(folder / "mapper.json", meta)
        return folder

    @classmethod
    def load(
        cls,
        folder: str | Path,
        *,
        config: MapperConfig | None = None,
        mde: MDEFrontEnd | None = None,
        completer: DepthCompleter | None = None,
    ) -> "Mapper":
        """Reads a map written by `save`; the returned `Mapper` goes on fusing and updating poses.

        Args:
            folder: The folder `save` wrote.
            config: Options (default: the saved ones; the fusion settings always come from the
                saved volume).
            mde: Front-end for later frames.
            completer: `DepthCompleter` for later frames.

        Raises:
            DataFormatError: if a file is missing or not what `save` writes.
        """
        folder = Path(folder)
        for name in ("mapper.json", "keyframes.npz", "volume.npz"):
            if not (folder / name).is_file():
                raise DataFormatError(folder / name, "file of a saved map not found")
        try:
            meta = json.loads((folder / "mapper.json").read_text())
            fx, fy, cx, cy, width, height = meta["camera"]
            camera = PinholeCamera(float(fx), float(fy), float(cx), float(cy), int(width), int(height))
            if config is None:
                saved = meta["config"]
                config = MapperConfig(
                    # maps saved before the local calibration of the variance existed had none
                    gp=DepthGPConfig.from_dict({"local_calibration": None, **saved["gp"]}),
                    fusion=FusionConfig(**saved["fusion"]),
                    triangulation=TriangulationConfig(**_tuples(saved["triangulation"])),
                    refind=RefindConfig(**saved.get("refind", {})),
                    **{k: v for k, v in saved.items() if k not in ("gp", "fusion", "triangulation", "refind")},
                )
        except (KeyError, TypeError, ValueError) as exc:
            raise DataFormatError(folder / "mapper.json", f"not a saved gpdepth3d map: {exc}") from None
        mapper = cls(camera, config, mde=mde, completer=completer)
        fusion = TSDFFusion.load(folder / "volume.npz")
        if fusion.camera != mapper.work_camera:
            raise DataFormatError(
                folder / "volume.npz", f"volume camera {fusion.camera} is not the map's {mapper.work_camera}"
            )
        mapper.fusion = fusion
        try:
            with np.load(folder / "keyframes.npz", allow_pickle=False) as d:
                offsets = np.concatenate([[0], np.cumsum(d["block_counts"])])
                keys = d["block_keys"]
                points = d["points"] if "points" in d.files else np.zeros(len(d["ids"]), np.int64)
                for i, kid in enumerate(d["ids"]):
                    mapper.keyframes[int(kid)] = Keyframe(
                        int(kid),
                        d["poses"][i].astype(np.float64),
                        d["depth"][i].astype(np.float32),
                        d["variance"][i].astype(np.float32),
                        d["rgb"][i].astype(np.uint8),
                        keys[offsets[i] : offsets[i + 1]].astype(np.int64),
                        int(points[i]),
                    )
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise DataFormatError(folder / "keyframes.npz", f"not a saved keyframe store: {exc}") from None
        mapper.frames = int(meta.get("frames", len(mapper.keyframes)))
        mapper._next_id = int(meta.get("next_id", len(mapper.keyframes)))
        return mapper


def _tuples(d: dict) -> dict:
    """JSON lists back to tuples (frozen config fields)."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


SEVEN_SCENES_RGB_K = COLOUR_INTRINSICS
"""Colour-camera intrinsics of 7-Scenes RGB (`gpdepth3d.datasets.sevenscenes.COLOUR_INTRINSICS`, f = 525:
the dataset's K, f = 585, is the depth camera's; triangulating the RGB frames with f = 525 agrees
with the Kinect depth, with f = 585 it is ~15-40 % too far and fails the epipolar check; see the
mapping tests). The 7-Scenes reader registers the depth to this camera and returns it as the
frames' ``camera``."""
