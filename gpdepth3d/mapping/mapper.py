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
(`gpdepth3d.mapping.own_points`; with ``lag`` > 0 a frame is refined and fused ``lag`` calls
after it was added, see `MapperConfig.lag`) and, where tracks break, SIFT matches with views chosen
by parallax (`gpdepth3d.mapping.points.refinding`), their depth scale pulled towards the keyframes already
fused (`gpdepth3d.mapping.map_scale`), and the points of the last frames in the parts of the image
the frame's own points leave empty (`gpdepth3d.mapping.points.local_map`); (3) the GP posterior (`DepthCompleter`, one kept for the whole
sequence); (4) TSDF fusion of the posterior median (`fused_depth`) with per-pixel weights from
its variance (`gpdepth3d.mapping.tsdf.fusion`).

Resolution: ``camera`` describes the RGB images given to `Mapper.add_frame`; features are
detected at that resolution, while refinement and fusion run at ``working_scale`` times it
(e.g. 0.5 for 320x240 from 640x480).

Robustness: after its arguments are validated, a frame never raises. A posterior mean <= 0 or
not finite is masked and counted before fusion; a stage that fails (the MDE front-end, the GP,
the fusion of a frame with nothing in range) is recorded on the `FrameResult` and in
`Mapper.failures`, naming the frame, and the sequence goes on. Map points outside the image,
behind the camera or not finite are counted (`MapPointStats`), and a pose under which the map
points look inverted warns (`gpdepth3d.io.poses.InvertedPoseWarning`).

Back-end interface: every fused frame is kept in a keyframe store (depth, variance, pose and
colour at the working resolution, by keyframe id). `Mapper.update_poses` applies a loop
closure by rebuilding only the TSDF blocks the moved keyframes reached before or reach now,
which gives exactly the volume of fusing every keyframe from scratch with the new poses
(`gpdepth3d.mapping.loop_closure`). `Mapper.save` / `Mapper.load` write and read the map (volume
and keyframe store, `gpdepth3d.mapping.map_store`). Poses of a
back-end's trajectory file (TUM, ORB-SLAM3, KITTI, COLMAP) come from `gpdepth3d.io.poses`.

`gpdepth3d.pipelines.mapping_run.fuse_sequence` (and ``gpdepth3d fuse``) runs the whole pipeline on a
7-Scenes-style sequence and compares the meshes from MDE-only, GP-refined and ground-truth depth.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..camera import PinholeCamera, check_pose
from ..completion.complete import DepthCompleter, DepthPosterior
from ..datasets.sevenscenes import COLOUR_INTRINSICS
from ..errors import CalibrationError, DataFormatError, InvalidInputError, ShapeError, describe
from ..io import output_set
from ..measurements import SparseDepth
from .cloud import ColoredCloud
from .frame_inputs import check_keyframe_id, check_map_points_sigma, check_mde_depth, resize_depth
from .frame_points import PendingFrame, select_measurements
from .frame_result import STAGES, FrameResult
from .tsdf.fusion import IntegrationStats, TSDFFusion, save_mesh
from .points.local_map import LocalMap
from .loop_closure import PoseUpdate, moved_blocks, reintegrate
from .map_scale import fused_depth, scale_to_map
from .points.map_points import merge_sparse
from .map_store import (
    MAP_FILES,
    MAP_SET,
    Keyframe,
    check_map_folder,
    load_keyframes,
    read_map_meta,
    recover_map_folder,
    save_keyframes,
    write_map_meta,
)
from .mapper_config import MapperConfig
from .mde_check import HeldOutCheck, held_out_check, held_out_shape, mde_fallback
from .own_points import OwnPoints
from .point_calibration import SigmaCalibration, misplacement_sigma, paired_z_scores

MDEFrontEnd = Callable[[np.ndarray], np.ndarray]


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
        self._points = OwnPoints(camera, self.config)
        frames = int(self.config.local_map_frames) if self.config.refine else 0
        self._local_map = LocalMap(frames, self.config.local_map_cell) if frames else None
        calibrate = self._local_map is not None and self.config.sigma_calibration_frames > 0
        self._calibration = SigmaCalibration(self.config.sigma_calibration_frames) if calibrate else None
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
        rgb = np.asarray(rgb)
        entry, mde_depth, map_points_sigma = self._new_frame(
            rgb, T_world_camera, mde_depth, sparse, map_points_sigma, keyframe_id
        )

        # 1. MDE of the frame given
        t0 = time.perf_counter()
        try:
            if mde_depth is None:
                mde_depth = check_mde_depth(self.mde(rgb), self.camera)
            entry.mde = resize_depth(np.where(np.isfinite(mde_depth), mde_depth, 0.0), self.work_camera.shape)
        except Exception as exc:  # noqa: BLE001 - a front-end failing on one frame must not end the run
            entry.error = ("mde", exc)
        timings["mde"] = time.perf_counter() - t0

        # 2. points: the frame's own measurements now, one tracking step (triangulates the frame whose turn it is)
        t0 = time.perf_counter()
        if sparse is not None:
            entry.parts.append(sparse.rasterize(self.camera.shape))
        if map_points_world is not None:
            entry.add_map_points(map_points_world, map_points_sigma, self.camera)
        ready = self._points.step(entry, rgb)
        timings["points"] = time.perf_counter() - t0
        if ready is None:
            timings["total"] = time.perf_counter() - t_start
            self.timings.append(timings)
            return None
        return self._finish(ready, timings, t_start)

    def flush(self) -> list[FrameResult]:
        """Refines and fuses the frames still waiting for later views (``config.lag``), oldest first.

        Call it at the end of a sequence (or before `mesh`, `save` or a pause): each waiting
        frame is triangulated from the views there are. Later `add_frame` calls go on as before.

        Returns:
            The frames' `FrameResult` (empty when none waits).
        """
        points, t_points = self._points.flush()
        results = []
        while self._points.queue:
            t_start = time.perf_counter()
            entry = self._points.queue.popleft()
            self._points.take(entry, points.get(entry.kid))
            timings = dict.fromkeys(STAGES, 0.0)
            timings["points"] = t_points + time.perf_counter() - t_start
            results.append(self._finish(entry, timings, t_start))
        return results

    @property
    def pending(self) -> tuple[int, ...]:
        """Ids of the frames added but not yet refined and fused (waiting for ``config.lag`` later views)."""
        return tuple(p.kid for p in self._points.queue)

    def _finish(self, entry: PendingFrame, timings: dict, t_start: float) -> FrameResult:
        """GP and fusion of one frame whose measurements are complete; records and returns its result."""
        result = self._refine_and_fuse(entry, timings)
        timings["total"] = time.perf_counter() - t_start
        self.timings.append(timings)
        return result

    def _refine_and_fuse(self, entry: PendingFrame, timings: dict) -> FrameResult:
        """The frame's measurements, GP and fusion, each timed in ``timings``; a failed stage ends it."""
        t0 = time.perf_counter()
        self._choose_measurements(entry)
        timings["points"] += time.perf_counter() - t0  # the frame's measurements: map scale, merge, selection
        refused = self._refusal(entry)
        if refused is not None:
            return self._failed(entry, timings, *refused)
        t0 = time.perf_counter()
        try:
            posterior, depth, variance = self._refine(entry)
        except Exception as exc:  # noqa: BLE001 - e.g. an empty MDE frame; recorded, the run goes on
            timings["gp"] = time.perf_counter() - t0
            return self._failed(entry, timings, "gp", exc, mde=entry.mde)
        timings["gp"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = self._fuse(entry, posterior, depth, variance, timings)
        timings["fusion"] = time.perf_counter() - t0
        return result

    def _choose_measurements(self, entry: PendingFrame) -> None:
        """Sets the frame's measurements: its own points pulled towards the map's scale, the local map's in
        the gaps they leave, merged, the most certain."""
        cfg = self.config
        parts = list(entry.parts)
        own = None
        if entry.triangulated is not None and len(entry.triangulated):
            own, entry.scale, entry.scale_var = scale_to_map(
                entry.triangulated,
                entry.T,
                self.camera,
                self.keyframes.values(),
                self.work_camera,
                weight=float(cfg.map_scale_weight),
                recent=int(cfg.map_scale_keyframes),
                max_relative_sigma=float(cfg.map_scale_max_sigma),
            )
            own_index = len(parts)
            parts.append(own)
        if self._local_map is not None:
            if not entry.pose_in_doubt:  # the local map's points land where the frame's pose puts them
                seen = self._misplaced(self._local_map.seen(entry.T, self.camera), entry)
                if own is not None and self._calibration is not None:
                    cell = self._local_map.cell * self.camera.width
                    self._calibration.add(paired_z_scores(own, seen, cell))
                fill = self._local_map.fill(
                    merge_sparse(*parts, image_size=self.camera.shape), entry.T, self.camera, seen
                )
                parts.append(self._calibrated(fill))
            if own is not None:  # remembered with the triangulation's sigma: the z-scores compare those
                self._local_map.add(entry.kid, own, entry.T, self.camera)
        if own is not None:
            parts[own_index] = self._calibrated(own)
        entry.measurements = select_measurements(parts, self.camera.shape, cfg.max_points)

    def _misplaced(self, points: SparseDepth, entry: PendingFrame) -> SparseDepth:
        """The local map's points in a frame with what carrying them through two inexact poses adds to their sigma.

        The depth range of the frame's MDE within twice the distance its pose and its neighbours' move its
        tracks' points across the images (`PendingFrame.pose_displacement`, `misplacement_sigma`), in quadrature.
        """
        if entry.mde is None or entry.pose_displacement <= 0 or not len(points):
            return points
        extra = misplacement_sigma(points, entry.mde, 2.0 * entry.pose_displacement)
        return points.with_sigma(np.hypot(points.sigma, extra)) if np.any(extra > 0) else points

    def _calibrated(self, points: SparseDepth) -> SparseDepth:
        """The Mapper's own points with their sigma times the running factor (`SigmaCalibration`)."""
        if self._calibration is None or self._calibration.factor == 1.0:
            return points
        return points.with_sigma(points.sigma * self._calibration.factor)

    def _refusal(self, entry: PendingFrame) -> tuple[str, BaseException] | None:
        """Why the frame is not refined (stage, error): an earlier stage failed or its pose looks inverted."""
        if entry.error is not None:
            return entry.error
        check = entry.pose_check
        if check is not None and check.inverted and not self.config.fuse_inverted_poses:
            return "pose check", CalibrationError(
                "T_world_camera",
                "a pose that sees its map points (not fused: MapperConfig.fuse_inverted_poses)",
                f"{check.visible:.0%} of {check.points} points visible, {check.visible_inverse:.0%} under its inverse",
            )
        return None

    def _refine(self, entry: PendingFrame) -> tuple[DepthPosterior | None, np.ndarray, np.ndarray]:
        """The GP step: (posterior, depth to fuse, its variance); without refinement the MDE with NaN variance."""
        work_shape = self.work_camera.shape
        if not self.config.refine:
            return None, entry.mde, np.full(work_shape, np.nan)
        # the frame's name goes into the posterior's warnings (a duck-typed completer may not take it)
        named = {"frame": str(entry.kid)} if isinstance(self.completer, DepthCompleter) else {}
        if self.config.held_out > 0 and len(entry.measurements):
            entry.held_out = self._held_out_check(entry, work_shape)
            if entry.mde_fallback:
                entry.notes.append(entry.held_out.describe(entry.kid))
                depth, variance = mde_fallback(entry.mde, entry.held_out)
                return None, depth, variance
        posterior = self.completer.complete(entry.mde, entry.measurements, output_shape=work_shape, **named)
        depth, variance = fused_depth(posterior, self.config.fuse_depth), posterior.variance
        if self.config.scale_variance and entry.scale_var > 0:
            variance = variance + entry.scale_var * np.square(depth)
        return posterior, depth, variance

    def _held_out_check(self, entry: PendingFrame, work_shape: tuple[int, int]) -> HeldOutCheck:
        """The frame's GP on most of its points against its rescaled MDE at the others (`held_out_check`), its
        posterior on the coarser `held_out_shape` grid: only its values at the held-out points count."""
        shape = held_out_shape(work_shape)

        def refine(kept: SparseDepth) -> np.ndarray:
            with warnings.catch_warnings():  # the full posterior's warnings are the frame's
                warnings.simplefilter("ignore")
                posterior = self.completer.complete(entry.mde, kept, output_shape=shape)
            return fused_depth(posterior, self.config.fuse_depth)

        cfg = self.config
        return held_out_check(
            refine,
            entry.mde,
            entry.measurements,
            fraction=float(cfg.held_out),
            min_held_out=int(cfg.min_held_out),
            seed=entry.kid,
        )

    def _fuse(
        self,
        entry: PendingFrame,
        posterior: DepthPosterior | None,
        depth: np.ndarray,
        variance: np.ndarray,
        timings: dict,
    ) -> FrameResult:
        """The fusion step; what is fused (float32 at the working size) is what the keyframe store keeps."""
        kid, n = entry.kid, len(entry.measurements)
        # a frame fused as its rescaled MDE is weighted as one without points (its variance is the MDE's)
        weighted_points = n if self.config.refine and not entry.mde_fallback else 0
        depth32, var32, masked = _masked(entry, depth, variance)
        depth64, var64 = depth32.astype(np.float64), var32.astype(np.float64)
        try:
            stats = self._integrate(depth32, var32, entry.T, entry.work_rgb, points=weighted_points)
        except Exception as exc:  # noqa: BLE001 - e.g. nothing in range; recorded, the run goes on
            result = self._failed(entry, timings, "fusion", exc, mde=entry.mde, posterior=posterior)
            return replace(result, depth=depth64, variance=var64, masked_pixels=masked)
        fallback = self.fusion.config.fallback_for(weighted_points) if self.config.refine else 1.0
        if stats.pixels == 0:
            entry.notes.append(f"frame {kid}: no pixel informed by points and no fallback weight left: nothing fused")
        elif self.config.refine and n == 0 and not entry.mde_fallback:
            entry.notes.append(
                f"frame {kid}: no points: fused as the MDE with its prior variance, weight {fallback:.2f}"
            )
        if self.config.keep_keyframes:
            self.keyframes[kid] = Keyframe(
                kid, entry.T, depth32, var32, entry.work_rgb, stats.block_keys, weighted_points
            )
        self.frames += 1
        return _frame_result(entry, timings, depth64, var64, entry.mde, posterior, masked=masked, fallback=fallback)

    def _failed(
        self, entry: PendingFrame, timings: dict, stage: str, exc: BaseException, *, mde=None, posterior=None
    ) -> FrameResult:
        """Records a frame that was not fused (in `failures`, naming the frame) and returns its `FrameResult`."""
        message = entry.describe(stage, exc)
        self.failures.append(message)
        empty = np.zeros((0, 0))
        return _frame_result(entry, timings, empty, empty, empty if mde is None else mde, posterior, error=message)

    def _new_frame(
        self, rgb: np.ndarray, T_world_camera, mde_depth, sparse, map_points_sigma, keyframe_id
    ) -> tuple[PendingFrame, np.ndarray | None, np.ndarray | None]:
        """Validates `add_frame`'s arguments: (the frame as it waits, its MDE depth, its map points' sigma)."""
        T = check_pose(T_world_camera)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ShapeError("rgb", "an (H, W, 3) uint8 RGB image", describe(rgb))
        self.camera.check_image(rgb, "rgb")
        if mde_depth is None and self.mde is None:
            raise InvalidInputError("mde_depth", "an MDE depth map (or an mde front-end in Mapper)", None)
        if sparse is not None and not isinstance(sparse, SparseDepth):
            raise InvalidInputError("sparse", "a SparseDepth", type(sparse).__name__)
        kid = self._next_id if keyframe_id is None else check_keyframe_id(keyframe_id)
        if kid in self.keyframes or any(p.kid == kid for p in self._points.queue):
            raise InvalidInputError("keyframe_id", "an id not in the keyframe store", kid)
        if map_points_sigma is not None:
            map_points_sigma = check_map_points_sigma(map_points_sigma)
        if mde_depth is not None:
            mde_depth = check_mde_depth(mde_depth, self.camera)
        self._next_id = max(self._next_id, kid + 1)
        return PendingFrame(kid=kid, T=T, work_rgb=self._work_rgb(rgb)), mde_depth, map_points_sigma

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

    # ------------------------------------------------------------------ loop closure
    def update_poses(self, poses: dict) -> PoseUpdate:
        """Moves keyframes to new poses (after a loop closure) and re-integrates what moved.

        The TSDF blocks a moved keyframe reached under its old pose or reaches under its new
        one are zeroed and rebuilt from every stored keyframe that reaches them, in the order
        the keyframes were fused; all other blocks are left alone. The volume is then the one
        fusing all keyframes from scratch with the new poses gives (voxel for voxel; see
        `gpdepth3d.mapping.tsdf.fusion`).

        Args:
            poses: keyframe id -> new 4x4 ``T_world_camera``.

        Returns:
            `PoseUpdate` (which keyframes moved and were re-integrated, blocks rebuilt).

        Raises:
            InvalidInputError: for an unknown keyframe id, or without a keyframe store.
            CalibrationError: for a pose that is not rigid.
        """
        t0 = time.perf_counter()
        new = self._checked_poses(poses)
        new = self._points.move_waiting(new)
        moved = [kid for kid, T in new.items() if not np.array_equal(T, self.keyframes[kid].T_world_camera)]
        if not moved:
            return PoseUpdate((), (), 0, time.perf_counter() - t0)
        blocks = moved_blocks(self.fusion, self.keyframes, new, moved)
        for k in moved:
            self.keyframes[k].T_world_camera = new[k]
        self._points.update_poses(new)
        if self._local_map is not None:
            self._local_map.update_poses(new)
        redone = reintegrate(self.fusion, self.keyframes, blocks, moved, self._integrate)
        return PoseUpdate(tuple(moved), tuple(redone), int(blocks.size), time.perf_counter() - t0)

    def _checked_poses(self, poses: dict) -> dict[int, np.ndarray]:
        """`update_poses`'s argument checked: keyframe id (stored or waiting) -> rigid 4x4 pose."""
        if not self.config.keep_keyframes:
            raise InvalidInputError("config.keep_keyframes", "True (update_poses needs the keyframe store)", False)
        if not isinstance(poses, dict):
            raise InvalidInputError("poses", "a dict keyframe id -> 4x4 T_world_camera", type(poses).__name__)
        waiting = {p.kid for p in self._points.queue}
        new = {}
        for kid, T in poses.items():
            if kid not in self.keyframes and kid not in waiting:
                raise InvalidInputError("poses", "ids of stored keyframes (or of frames waiting to be fused)", kid)
            new[kid] = check_pose(T, f"poses[{kid}]")
        return new

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
        keyframe store (``keyframes.npz``) and the mapper's settings (``mapper.json``), as one
        output set (`gpdepth3d.mapping.map_store`). Frames still waiting for later views
        (`pending`) are not in the map yet: call `flush` first to include them.

        Returns:
            The folder.
        """
        folder = Path(folder)
        with output_set(folder / MAP_SET, members=[*MAP_FILES, "volume.json"]):
            save_keyframes(folder / "keyframes.npz", self.keyframes, self.work_camera.shape)
            self.fusion.save(folder / "volume.npz")
            write_map_meta(folder / "mapper.json", self.camera, self.config, frames=self.frames, next_id=self._next_id)
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

        A save that a kill interrupted is first finished (its commit had begun) or its
        temporaries removed (the map before it stays), `map_store.recover_map_folder`.

        Args:
            folder: The folder `save` wrote.
            config: Options (default: the saved ones; the fusion settings always come from the
                saved volume).
            mde: Front-end for later frames.
            completer: `DepthCompleter` for later frames.

        Raises:
            DataFormatError: if a file is missing or not what `save` writes, or an interrupted
                save cannot be finished.
        """
        if Path(folder).is_dir():
            recover_map_folder(folder)
        folder = check_map_folder(folder)
        camera, config, meta = read_map_meta(folder / "mapper.json", config)
        # the saved volume replaces the new mapper's: give that one no room to allocate
        mapper = cls(
            camera, replace(config, fusion=replace(config.fusion, block_count=1)), mde=mde, completer=completer
        )
        mapper.config = config
        fusion = TSDFFusion.load(folder / "volume.npz")
        if fusion.camera != mapper.work_camera:
            raise DataFormatError(
                folder / "volume.npz", f"volume camera {fusion.camera} is not the map's {mapper.work_camera}"
            )
        mapper.fusion = fusion
        mapper.keyframes = load_keyframes(folder / "keyframes.npz")
        mapper.frames = int(meta.get("frames", len(mapper.keyframes)))
        mapper._next_id = int(meta.get("next_id", len(mapper.keyframes)))
        return mapper


def _frame_result(
    entry: PendingFrame, timings: dict, depth, variance, mde, posterior, *, error=None, masked=0, fallback=0.0
) -> FrameResult:
    """The `FrameResult` of a frame: fused (``error`` None) or not (``error`` names the frame and stage)."""
    return FrameResult(
        depth=depth,
        variance=variance,
        mde=mde,
        sparse=entry.measurements,
        posterior=posterior,
        timings=timings,
        keyframe_id=entry.kid,
        fused=error is None,
        error=error,
        warnings=tuple(entry.notes),
        masked_pixels=masked,
        map_points=entry.map_stats,
        pose_check=entry.pose_check,
        map_scale=entry.scale,
        fallback_weight=fallback,
        pose_in_doubt=entry.pose_in_doubt,
        mde_fallback=entry.mde_fallback,
        held_out=entry.held_out,
    )


def _masked(entry: PendingFrame, depth: np.ndarray, variance: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """float32 depth with pixels <= 0 or not finite set to 0 (noted on the frame), float32 variance, pixels masked."""
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(depth) | (depth < 0) | ((depth == 0) & (entry.mde > 0))
    masked = int(bad.sum())
    if masked:
        entry.notes.append(f"frame {entry.kid}: {masked} pixels with depth <= 0 or not finite masked")
    return np.where(bad, 0.0, depth).astype(np.float32), np.asarray(variance, dtype=np.float32), masked


SEVEN_SCENES_RGB_K = COLOUR_INTRINSICS
"""Colour-camera intrinsics of 7-Scenes RGB (`gpdepth3d.datasets.sevenscenes.COLOUR_INTRINSICS`, f = 525:
the dataset's K, f = 585, is the depth camera's; triangulating the RGB frames with f = 525 agrees
with the Kinect depth, with f = 585 it is ~15-40 % too far and fails the epipolar check; see the
mapping tests). The 7-Scenes reader registers the depth to this camera and returns it as the
frames' ``camera``."""
