"""Whole-sequence mapping: a user's posed sequence mapped by the `Mapper`, and the 7-Scenes experiment.

`open_posed_sequence` reads a user's sequence (images, poses in any format of
`gpdepth3d.io.poses`, intrinsics, optional sensor depth); `map_sequence` runs the
`gpdepth3d.mapping.Mapper` over it with the library's defaults (FastDepth or any front-end, its own
triangulated points, map points of a COLMAP model when the poses come from one) and, with sensor
depth, scores the mesh against the mesh fused from that depth (`mesh_metrics`, F-score at 5 cm);
`write_map` writes the mesh, the cloud with per-point sigma, the reloadable map and the metrics as
one set (``gpdepth3d map``).

`fuse_sequence` runs the `Mapper` on a 7-Scenes-style sequence and fuses the MDE-only, GP-refined
(uniform and variance weights) and ground-truth depth into TSDF meshes, compared with `mesh_metrics`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from ..camera import PinholeCamera
from ..datasets.base import Frame
from ..datasets.posed import IMAGE_SUFFIXES, FileSpec, PosedSequence, list_files
from ..errors import CalibrationError, EmptyInputError, GPDepthError, InvalidInputError
from ..mapping.points.given_points import GivenPoints, PointSigmaRule
from ..mapping.cloud import ColoredCloud
from ..mapping.tsdf.fusion import TSDFFusion, save_mesh
from ..io.poses import POSE_FORMATS, associate_poses, detect_pose_format, read_colmap_model, read_trajectory
from ..mapping.frame_inputs import resize_depth
from ..mapping.frame_result import FrameResult
from ..mapping.mapper import Mapper, MDEFrontEnd
from ..mapping.mapper_config import MapperConfig
from ..measurements import project_points
from ..metrics import mesh_metrics


Variant = Literal["mde", "gp_uniform", "gp_variance", "gt"]


def fuse_sequence(
    data: str | Path,
    *,
    mde: MDEFrontEnd,
    rgb_K: np.ndarray | None = None,
    config: MapperConfig | None = None,
    max_frames: int | None = None,
    threshold: float = 0.05,
    metric_samples: int = 50_000,
    progress: bool = False,
) -> dict[str, Any]:
    """Fuses a 7-Scenes-style sequence four ways and compares each mesh with the ground-truth one.

    Variants: ``mde`` (MDE depth, uniform weights), ``gp_uniform`` and ``gp_variance`` (GP
    posterior mean refined with the library's own triangulated features, fused with uniform or
    variance weights; one GP solve per frame feeds both), ``gt`` (the Kinect depth as the reader
    gives it, registered to the colour camera, the reference).

    Args:
        data: Sequence folder (see `gpdepth3d.datasets.sevenscenes.SevenScenes`).
        mde: Front-end ``rgb -> depth`` in metres.
        rgb_K: 3x3 intrinsics of the colour camera the Mapper uses (default: the frames' camera,
            the colour camera the reader registers the Kinect depth to, `SEVEN_SCENES_RGB_K`).
        config: Mapper options (``fusion.weighting`` is overridden per variant).
        max_frames: Use only the first frames.
        threshold: Precision / recall distance, metres.
        metric_samples: Surface samples per mesh for the metrics.
        progress: Show a progress bar.

    The frames go through `map_sequence` (the runner of ``gpdepth3d map``); the comparison volumes
    are fused from its `FrameEvent` records. Bad data never ends the run: a frame that cannot be read or fused is named in
    ``frame_errors`` and the next one goes on; a mesh without triangles (too few frames for
    ``weight_threshold``) is listed in ``empty_meshes`` and gets no metrics (None).

    Returns:
        ``meshes`` (variant -> trimesh, possibly without faces), ``metrics`` (variant ->
        `mesh_metrics` against ``gt``, or None for an empty mesh), ``timing`` (mean seconds
        per frame per stage; `Mapper` stages plus "fuse_uniform") and ``timing_median``,
        ``frames``, ``frames_fused``, ``frame_errors``, ``frame_warnings``, ``masked_pixels``
        (GP depths <= 0 or not finite masked before fusion), ``empty_meshes``, ``sparse_points``
        (mean measurements per frame) and ``depth_median_abs_error`` (per-frame median
        |depth - ground truth| in metres, averaged over frames, for "mde" and "gp"; the Kinect
        depth as the reader registers it, lifted and re-projected to the working resolution) and
        ``sparse_bias_per_frame`` (per frame with measurements: median signed relative error
        of the measurements against the Kinect depth).
    """
    # the optional dependency of the comparison volumes, checked before the run
    import cv2  # noqa: F401

    from ..datasets.sevenscenes import SevenScenes

    config = config or MapperConfig(working_scale=0.5)
    reader = SevenScenes(data)
    n = len(reader) if max_frames is None else min(len(reader), int(max_frames))
    if n < 1:
        raise EmptyInputError("data", "a sequence with frames", "none")
    first = reader[0]
    rgb_cam = (
        first.camera
        if rgb_K is None
        else PinholeCamera.from_K(np.asarray(rgb_K), first.camera.width, first.camera.height)
    )
    record = _FuseRecord(config, rgb_cam, first.camera)
    mapped = map_sequence(
        reader,
        mde=mde,
        config=replace(config, fusion=replace(config.fusion, weighting="variance")),
        working_width=None,
        camera=rgb_cam,
        max_frames=n,
        evaluate=False,
        progress=progress,
        on_frame=record,
        force=True,  # the dataset's own (ground-truth) poses
    )
    meshes = _variant_meshes(record.extra, mapped.mapper.fusion)
    empty = sorted(k for k, m in meshes.items() if m is None or len(m.faces) == 0)
    timing, timing_median = _fuse_timing(record.times)
    return {
        "meshes": meshes,
        "metrics": _variant_metrics(meshes, empty, threshold, metric_samples),
        "timing": timing,
        "timing_median": timing_median,
        "frames": n,
        "frames_fused": mapped.frames_fused,
        "frame_errors": mapped.frame_errors + record.volume_errors,
        "frame_warnings": record.frame_warnings,
        "masked_pixels": record.masked,
        "empty_meshes": empty,
        "sparse_points": float(np.mean(record.npoints)) if record.npoints else 0.0,
        "depth_median_abs_error": {k: float(np.mean(v)) if v else float("nan") for k, v in record.depth_err.items()},
        "sparse_bias_per_frame": record.sparse_err,
    }


@dataclass
class _FuseRecord:
    """The comparison volumes and per-frame records `fuse_sequence` gathers from `map_sequence`'s events."""

    config: MapperConfig
    rgb_cam: PinholeCamera
    depth_cam: PinholeCamera
    times: list[dict] = field(default_factory=list)
    npoints: list[int] = field(default_factory=list)
    depth_err: dict[str, list[float]] = field(default_factory=lambda: {"mde": [], "gp": []})
    sparse_err: list[float] = field(default_factory=list)
    volume_errors: list[str] = field(default_factory=list)
    frame_warnings: list[str] = field(default_factory=list)
    extra: dict[str, TSDFFusion] = field(default_factory=dict)
    masked: int = 0

    def __call__(self, event: FrameEvent) -> None:
        """Records one fused (or failed) frame and fuses the comparison variants of it."""
        self.times.append(dict(event.timings))
        result, frame, work = event.result, event.result_frame, event.mapper.work_camera
        if result is None or frame is None:
            return
        self._fuse_variants(result, frame, work)
        if not result.depth.size:
            return
        self._score_depth(result, frame, work)
        self.npoints.append(len(result.sparse))

    def _fuse_variants(self, result: FrameResult, frame: Frame, work: PinholeCamera) -> None:
        """Fuses the frame's MDE, uniform-weight GP and ground-truth depth into the comparison volumes."""
        import cv2

        depth_work = self.depth_cam.resized(work.width, work.height)
        if not self.extra:
            self.extra.update(
                mde=TSDFFusion(work, replace(self.config.fusion, weighting="uniform")),
                gp_uniform=TSDFFusion(work, replace(self.config.fusion, weighting="uniform")),
                gt=TSDFFusion(depth_work, replace(self.config.fusion, weighting="uniform")),
            )
        i = result.keyframe_id
        self.frame_warnings.extend(result.warnings)
        self.masked += result.masked_pixels
        work_rgb = cv2.resize(frame.rgb, (work.width, work.height), interpolation=cv2.INTER_AREA)
        others = [("gt", resize_depth(frame.depth, depth_work.shape), work_rgb)]
        if result.mde.size:
            others.insert(0, ("mde", result.mde, work_rgb))
        if result.depth.size:
            others.insert(0, ("gp_uniform", result.depth, work_rgb))
        for name, depth, colour in others:
            t0 = time.perf_counter()
            try:
                if depth.size:
                    self.extra[name].integrate(depth, frame.pose, rgb=colour)
            except GPDepthError as exc:
                self.volume_errors.append(f"frame {i}: {name} volume: {type(exc).__name__}: {exc}")
            if name == "gp_uniform":
                self.times[-1]["fuse_uniform"] = time.perf_counter() - t0

    def _score_depth(self, result: FrameResult, frame: Frame, work: PinholeCamera) -> None:
        """Records the frame's sparse bias and the MDE's and GP's median depth errors against the Kinect."""
        # Ground truth at the working resolution: lift with the frame's camera, project (z-buffer).
        pts, _ = frame.camera.backproject(frame.depth)
        gt_rgb = project_points(pts, work).to_depth_map()
        ok = gt_rgb > 0
        if len(result.sparse):
            # signed relative error of the measurements against the Kinect depth (the frame's camera)
            lifted = self.rgb_cam.backproject_pixels(result.sparse.uv, result.sparse.depth)
            uv, z = self.depth_cam.project(lifted)
            inside = self.depth_cam.in_image(uv)
            iu = np.rint(uv[inside]).astype(np.int64)
            kinect = frame.depth[iu[:, 1], iu[:, 0]]
            good = kinect > 0
            if good.any():
                self.sparse_err.append(float(np.median((z[inside][good] - kinect[good]) / kinect[good])))
        if ok.any():
            self.depth_err["mde"].append(float(np.median(np.abs(result.mde[ok] - gt_rgb[ok]))))
            self.depth_err["gp"].append(float(np.median(np.abs(result.depth[ok] - gt_rgb[ok]))))


def _variant_meshes(extra: dict[str, TSDFFusion], variance: TSDFFusion) -> dict[str, Any]:
    """The four variants' meshes (None for a volume that never got a frame)."""
    volumes = {
        "mde": extra.get("mde"),
        "gp_uniform": extra.get("gp_uniform"),
        "gp_variance": variance,
        "gt": extra.get("gt"),
    }
    meshes = {}
    for name, volume in volumes.items():
        meshes[name] = (
            volume.extract_mesh(allow_empty=True) if volume is not None and volume.frames_integrated else None
        )
    return meshes


def _variant_metrics(meshes: dict[str, Any], empty: list[str], threshold: float, samples: int) -> dict[str, Any]:
    """Scores each variant's mesh against the ground-truth one (None where either is empty)."""
    metrics: dict[str, Any] = {}
    for k, m in meshes.items():
        if k == "gt":
            continue
        metrics[k] = (
            None if k in empty or "gt" in empty else mesh_metrics(m, meshes["gt"], threshold=threshold, samples=samples)
        )
    return metrics


def _fuse_timing(times: list[dict]) -> tuple[dict[str, float], dict[str, float]]:
    """Mean (with the fusion benchmark's stage names) and median seconds per frame per stage."""
    keys = sorted({k for t in times for k in t})
    timing = {k: float(np.mean([t[k] for t in times if k in t])) for k in keys}
    # the names the fusion benchmark reads (docs/results.md)
    timing.update(
        {"triangulate": timing.get("points", 0.0), "refine": timing.get("gp", 0.0), "fuse": timing.get("fusion", 0.0)}
    )
    return timing, {k: float(np.median([t[k] for t in times if k in t])) for k in keys}


# ---------------------------------------------------------------------- a user's own sequence
DEFAULT_WORKING_WIDTH = 320
"""Width (pixels) the Mapper refines and fuses at by default: the resolution its defaults were chosen at
(320x240 for 640x480 images); wider images are scaled down to it, narrower ones kept."""


@dataclass(frozen=True)
class PosedInputs:
    """A user's sequence as `open_posed_sequence` read it.

    Attributes:
        sequence: The frames (rgb, camera, pose, optional depth).
        pose_format: The pose format read (one of `POSE_FORMATS`).
        map_points: Per frame, the world points of a COLMAP model its image observes ((K, 3),
            metres), or None when the poses are not a COLMAP model.
        map_points_sigma: Per frame, the depth sigma of its map points ((K,) metres), or None (the
            GP's measurement sigma).
        given: The files and options it was opened from, as given (recorded in ``metrics.json``).
    """

    sequence: PosedSequence
    pose_format: str
    map_points: list | None = None
    map_points_sigma: list | None = None
    given: dict = field(default_factory=dict)


def open_posed_sequence(
    images: FileSpec,
    poses: str | Path,
    intrinsics: str | Path | None = None,
    *,
    pose_format: str = "auto",
    association: str = "auto",
    max_time_difference: float = 0.02,
    depth: FileSpec | None = None,
    depth_scale: float = 1e-3,
    depth_invalid: int | None = None,
    depth_intrinsics: str | Path | None = None,
) -> PosedInputs:
    """Reads a posed sequence: images, their poses (any format), intrinsics and optional depth.

    Args:
        images: Image folder (its ``*.color.*`` files if any), glob pattern or list of files.
        poses: Pose file or folder (`gpdepth3d.io.poses.read_trajectory`).
        intrinsics: K file or ``"fx,fy,cx,cy"``; optional only with a COLMAP model (its camera).
        pose_format: One of `POSE_FORMATS` or "auto".
        association: How poses find their images (`associate_poses`): auto, name, timestamp, order.
        max_time_difference: Largest image-pose time difference for timestamp association, seconds.
        depth: Sensor depth files for evaluation (folder, glob or list).
        depth_scale: Metres per 16-bit PNG unit.
        depth_invalid: PNG value of invalid pixels besides 0.
        depth_intrinsics: K of the depth camera when it is not the colour camera.

    Raises:
        DataFormatError / ShapeError / CalibrationError / InvalidInputError: as the readers do,
            naming the file or argument.
    """
    files = list_files(images, IMAGE_SUFFIXES, "color", "images")
    if pose_format == "auto":
        pose_format = detect_pose_format(poses)
    if pose_format not in POSE_FORMATS:
        raise InvalidInputError("pose_format", f"'auto' or one of {', '.join(POSE_FORMATS)}", pose_format)
    names = [f.name for f in files]
    map_points = None
    camera = intrinsics
    if pose_format == "colmap":
        model = read_colmap_model(poses, ignore_distortion=True)
        trajectory = model.trajectory()
        ids = sorted(model.images)
        by_pose = dict(zip(trajectory.names, ids))
        matched = associate_poses(trajectory, names, by="name" if association == "auto" else association)
        if association in ("auto", "name"):
            keys = _colmap_keys(list(trajectory.names), names)
            map_points = [model.map_points(by_pose[k]) for k in keys]
        if camera is None:
            cameras = {model.images[i].camera_id for i in ids}
            if len(cameras) != 1:
                raise InvalidInputError("intrinsics", "a K file or fx,fy,cx,cy (the model has several cameras)", None)
            camera = model.cameras[cameras.pop()]
    else:
        if camera is None:
            raise InvalidInputError("intrinsics", "a K file or fx,fy,cx,cy", None)
        trajectory = read_trajectory(poses, pose_format)
        matched = associate_poses(trajectory, names, by=association, max_difference=max_time_difference)
    sequence = PosedSequence(
        files,
        matched,
        camera,
        depth=depth,
        depth_scale=depth_scale,
        depth_invalid=depth_invalid,
        depth_intrinsics=depth_intrinsics,
    )
    return PosedInputs(sequence, pose_format, map_points)


def _colmap_keys(model_names: list[str], image_names: list[str]) -> list[str]:
    """The model's image name of each image (whole name, else the name up to the first dot)."""
    whole = {Path(n).name: n for n in model_names}
    short = {Path(n).name.split(".", 1)[0]: n for n in model_names}
    if all(n in whole for n in image_names):
        return [whole[n] for n in image_names]
    return [short[n.split(".", 1)[0]] for n in image_names]


@dataclass
class MapResult:
    """What `map_sequence` made.

    Attributes:
        mapper: The `Mapper` holding the map (volume and keyframes).
        mesh: The map's mesh (trimesh, world frame, metres; may have no faces).
        cloud: The map's surface points with per-point fused variance (`ColoredCloud`).
        frames: Frames given (after stride and limit).
        frames_fused: Frames that reached the volume.
        frame_errors: One line per frame that was not fused (unreadable file, failed stage), naming it.
        frames_without_points: Names of frames fused without any sparse point (MDE and GP prior only).
        sparse_points: Median sparse points per fused frame.
        metrics: With sensor depth: ``map`` and ``mde`` (the MDE alone, uniform weights) scored by
            `mesh_metrics` against the mesh fused from the sensor depth, or None when a mesh is empty;
            None without depth.
        timing: Median seconds per `Mapper.add_frame` call by stage, and ``wall`` (the whole run).
    """

    mapper: Mapper
    mesh: Any
    cloud: ColoredCloud
    frames: int
    frames_fused: int
    frame_errors: list
    frames_without_points: list
    sparse_points: float
    metrics: dict | None
    timing: dict


@dataclass(frozen=True)
class FrameEvent:
    """What `map_sequence` tells its ``on_frame`` callback after each `Mapper` call.

    Attributes:
        mapper: The `Mapper`.
        added: The frame added in this call (None for the last frames, finished by `Mapper.flush`).
        result: The `FrameResult` of the frame refined and fused in this call, or None (frames wait
            ``MapperConfig.lag`` calls for later views).
        result_frame: The frame ``result`` belongs to, or None.
        timings: Seconds per stage of this call (`FrameResult.timings`).
    """

    mapper: Mapper
    added: Frame | None
    result: FrameResult | None
    result_frame: Frame | None
    timings: dict


FrameCallback = Callable[[FrameEvent], None]


def map_sequence(
    inputs: PosedInputs | Any,
    *,
    mde: MDEFrontEnd,
    config: MapperConfig | None = None,
    working_width: int | None = DEFAULT_WORKING_WIDTH,
    camera: PinholeCamera | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    evaluate: bool = True,
    threshold: float = 0.05,
    metric_samples: int = 50_000,
    progress: bool = False,
    on_frame: FrameCallback | None = None,
    force: bool = False,
) -> MapResult:
    """Maps a posed sequence with the `Mapper` and, when it has depth, scores the mesh against it.

    Args:
        inputs: The sequence (`open_posed_sequence`), a `PosedSequence`, or any dataset reader whose
            frames carry a pose (``len``, ``reader[i]`` -> `Frame`, ``names``).
        mde: Front-end ``rgb -> depth`` in metres.
        config: Mapper options (default `MapperConfig()`).
        working_width: Width of refinement and fusion, pixels: ``config.working_scale`` becomes
            ``working_width / image width`` (at most 1); None keeps ``config.working_scale``.
        camera: Intrinsics the Mapper uses (default: the sequence's camera).
        stride: Use every ``stride``-th frame.
        max_frames: Use at most this many frames (after the stride).
        evaluate: With sensor depth in the frames, score the map (and the MDE alone, uniform
            weights) against the mesh fused from that depth (`mesh_metrics`).
        threshold: F-score distance, metres.
        metric_samples: Surface samples per mesh for the metrics.
        progress: Show a progress bar (tqdm) on stderr.
        on_frame: Called after each `Mapper` call with a `FrameEvent` (the live viewer, the
            7-Scenes experiment's comparison volumes).
        force: Map on when most frames fail the pose check (`check_poses_agree`), e.g. a camera
            that only rotates; by default the run stops there.

    Bad data never ends the run: a frame that cannot be read or fused is named in
    ``frame_errors`` and the next one goes on.

    Raises:
        InvalidInputError: bad ``stride``, ``max_frames``, ``working_width``, ``threshold`` or
            ``metric_samples``. EmptyInputError: an empty sequence, or no frame could be fused.
        CalibrationError: most frames fail the pose check (unless ``force``), naming the likely cause.
    """
    from tqdm.auto import tqdm

    inputs = inputs if isinstance(inputs, PosedInputs) else PosedInputs(inputs, "given")
    sequence = inputs.sequence
    _check_map_args(stride, metric_samples, working_width, max_frames, threshold)
    if len(sequence) == 0:
        raise EmptyInputError("inputs", "a sequence with frames", "none")
    indices = list(range(0, len(sequence), int(stride)))[:max_frames]
    camera = camera or getattr(sequence, "camera", None) or sequence[indices[0]].camera
    config = config or MapperConfig()
    if working_width is not None:
        config = replace(config, working_scale=min(1.0, int(working_width) / camera.width))
    t_start = time.perf_counter()
    mapper = Mapper(camera, config, mde=mde)
    uniform = replace(config.fusion, weighting="uniform", integrate_variance=False)
    run = _MapRun(mapper, inputs, force, uniform)
    bar = tqdm(indices, desc="map", unit="frame", disable=not progress, leave=False)
    for i in bar:
        run.step(i, evaluate, on_frame)
    for result in mapper.flush():
        result_frame = run.record(result)
        if on_frame is not None:
            on_frame(FrameEvent(mapper, None, result, result_frame, dict(result.timings)))
    bar.close()
    if not force:
        check_poses_agree(run.checked, inputs.pose_format, final=True)
    if run.fused == 0:
        raise EmptyInputError(
            "images",
            "at least one frame that can be fused",
            f"none of {len(indices)}: " + "; ".join(run.frame_errors[:3]),
        )
    mesh, cloud = _map_surface(mapper)
    stages = sorted({k for t in mapper.timings for k in t})
    timing = {k: float(np.median([t[k] for t in mapper.timings if k in t])) for k in stages}
    timing["wall"] = time.perf_counter() - t_start
    return MapResult(
        mapper=mapper,
        mesh=mesh,
        cloud=cloud,
        frames=len(indices),
        frames_fused=run.fused,
        frame_errors=run.frame_errors,
        frames_without_points=run.without_points,
        sparse_points=float(np.median(run.points)) if run.points else 0.0,
        metrics=_map_metrics(run.volumes, mesh, threshold, metric_samples),
        timing=timing,
    )


def _check_map_args(stride: Any, metric_samples: Any, working_width: Any, max_frames: Any, threshold: Any) -> None:
    """Refuses a bad ``stride``, ``metric_samples``, ``working_width``, ``max_frames`` or ``threshold``."""
    for name, value, low in (("stride", stride, 1), ("metric_samples", metric_samples, 1)) + (
        (("working_width", working_width, 2),) if working_width is not None else ()
    ):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise InvalidInputError(name, f"an integer >= {low}", value)
    if max_frames is not None and (
        isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1
    ):
        raise InvalidInputError("max_frames", "an integer >= 1 (or None for all)", max_frames)
    if not (isinstance(threshold, (int, float)) and np.isfinite(threshold) and threshold > 0):
        raise InvalidInputError("threshold", "a distance > 0 (metres)", threshold)


@dataclass
class _MapRun:
    """The state of one `map_sequence` run: frames waiting for their result, errors, counts, sensor volumes."""

    mapper: Mapper
    inputs: PosedInputs
    force: bool
    uniform: Any
    volumes: dict[str, TSDFFusion] = field(default_factory=dict)  # the sensor depth's and the MDE's
    frame_errors: list[str] = field(default_factory=list)
    without_points: list[str] = field(default_factory=list)
    points: list[int] = field(default_factory=list)
    fused: int = 0
    waiting: dict[int, Frame] = field(default_factory=dict)
    checked: list[bool] = field(default_factory=list)  # per frame returned: its pose failed the pose check

    def step(self, i: int, evaluate: bool, on_frame: FrameCallback | None) -> None:
        """Adds frame ``i`` to the Mapper (a failure named, the run goes on) and records what it returned."""
        sequence, inputs = self.inputs.sequence, self.inputs
        try:
            frame = sequence[i]
            extra = {}
            if inputs.map_points is not None and len(inputs.map_points[i]):
                extra["map_points_world"] = inputs.map_points[i]
                if inputs.map_points_sigma is not None:
                    extra["map_points_sigma"] = inputs.map_points_sigma[i]
            self.waiting[i] = frame
            result = self.mapper.add_frame(frame.rgb, frame.pose, keyframe_id=i, **extra)
        except GPDepthError as exc:  # an unreadable frame or a bad pose: named, the run goes on
            self.waiting.pop(i, None)
            self.frame_errors.append(f"image {sequence.names[i]}: {type(exc).__name__}: {exc}")
            return
        if evaluate and frame.depth is not None:
            self._fuse_sensor_depth(frame)
        result_frame = self.record(result) if result is not None else None
        if on_frame is not None:
            on_frame(FrameEvent(self.mapper, frame, result, result_frame, dict(self.mapper.timings[-1])))

    def _fuse_sensor_depth(self, frame: Frame) -> None:
        """Fuses the frame's sensor depth into the reference volume (made with the first frame with depth)."""
        work = self.mapper.work_camera
        if not self.volumes:
            self.volumes.update(reference=TSDFFusion(work, self.uniform), mde=TSDFFusion(work, self.uniform))
        depth = _sensor_depth_at(frame, self.mapper.camera, work)
        _integrate(self.volumes["reference"], depth, frame, work, self.frame_errors, "sensor-depth volume")

    def record(self, result: FrameResult) -> Frame:
        """Books one returned frame: pose check, error, counts, its MDE in the MDE-only volume."""
        frame = self.waiting.pop(result.keyframe_id)
        self.checked.append(bool(getattr(result, "pose_in_doubt", False)))
        if not self.force:
            check_poses_agree(self.checked, self.inputs.pose_format, final=False)
        if result.error is not None:
            self.frame_errors.append(f"image {frame.name}: {result.error}")
        if result.fused:
            self.fused += 1
            self.points.append(len(result.sparse))
            if len(result.sparse) == 0:
                self.without_points.append(frame.name)
        if "mde" in self.volumes and result.mde.size:
            _integrate(
                self.volumes["mde"], result.mde, frame, self.mapper.work_camera, self.frame_errors, "MDE-only volume"
            )
        return frame


def _sensor_depth_at(frame: Frame, camera: PinholeCamera, work: PinholeCamera) -> np.ndarray:
    """The frame's sensor depth on the working camera ``work`` (metres, 0 = none): the reference the maps are
    scored against.

    When the frame is seen by ``camera`` (the camera ``work`` was resized from), the depth is resized to the
    working size (`resize_depth`: nearest when shrinking, so no mixed depths), the reference `fuse_sequence`
    fuses too; a frame from another camera is lifted with its own and projected into ``work`` (z-buffer).
    """
    if frame.camera == camera:
        return resize_depth(frame.depth, work.shape)
    points, _ = frame.camera.backproject(frame.depth)
    return project_points(points, work).to_depth_map()


def _map_metrics(volumes: dict[str, TSDFFusion], mesh: Any, threshold: float, samples: int) -> dict | None:
    """Scores the map and the MDE-only mesh against the sensor-depth mesh (None without sensor depth)."""
    if not (volumes and volumes["reference"].frames_integrated):
        return None
    ref_mesh = volumes["reference"].extract_mesh(allow_empty=True)
    mde_mesh = volumes["mde"].extract_mesh(allow_empty=True) if volumes["mde"].frames_integrated else None
    metrics = {}
    for name, m in (("map", mesh), ("mde", mde_mesh)):
        ok = m is not None and len(m.faces) and len(ref_mesh.faces)
        metrics[name] = mesh_metrics(m, ref_mesh, threshold=threshold, samples=samples) if ok else None
    return metrics


POSE_CHECK_SHARE = 0.5
"""`map_sequence` stops when more than this share of its frames fail the pose check."""

POSE_CHECK_MIN_FRAMES = 5
"""... and at least this many do: the first frames of a walk often fail it (a short baseline), so a short run goes
on with its warnings."""

POSE_CHECK_EARLY = 8
"""Frames returned after which the check may stop a run before its end (no time spent on a hopeless run)."""


def check_poses_agree(failed: list[bool], pose_format: str = "", *, final: bool = True) -> None:
    """Refuses a run where most frames fail the pose check: the poses do not belong to the images as given.

    A frame fails when its feature tracks do not triangulate with its pose and its neighbours'
    (or its map points look inverted under it). One such frame is a fast turn; most of them are
    poses inverted (``T_camera_world`` given for ``T_world_camera``), TUM quaternions written
    w-first, or poses associated with other frames' images.

    Args:
        failed: Per frame checked so far, whether it failed.
        pose_format: The poses' format (the message names the likely cause for it).
        final: All frames are in; else judged only after `POSE_CHECK_EARLY` frames.

    Raises:
        CalibrationError: more than `POSE_CHECK_SHARE` of the frames (and at least
            `POSE_CHECK_MIN_FRAMES`) failed.
    """
    n, bad = len(failed), int(sum(failed))
    if (not final and n < POSE_CHECK_EARLY) or bad < POSE_CHECK_MIN_FRAMES or bad <= POSE_CHECK_SHARE * n:
        return
    causes = ["inverted poses (T_camera_world given as T_world_camera)"]
    if pose_format in ("tum", "auto", ""):
        causes.append("quaternions written w-first (TUM is tx ty tz qx qy qz qw)")
    causes.append("another frame's poses (check the image-to-pose association)")
    raise CalibrationError(
        "poses",
        "camera-to-world poses of these images (most frames' feature tracks triangulate with their pose)",
        f"{bad} of {n} frames failing the pose check: likely {', or '.join(causes)}; "
        "force=True (map --force) maps them anyway",
    )


def _map_surface(mapper: Mapper) -> tuple[Any, ColoredCloud]:
    """The map's mesh and cloud; both empty when no pixel reached the volume (every frame cut away)."""
    import trimesh

    try:
        return mapper.mesh(), mapper.point_cloud()
    except EmptyInputError:
        empty = ColoredCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0), np.zeros(0))
        return trimesh.Trimesh(), empty


def _integrate(
    volume: TSDFFusion, depth: np.ndarray, frame: Frame, work: PinholeCamera, errors: list, what: str
) -> None:
    """Fuses one comparison depth (uniform weights) with the frame's colour; a failure is recorded, not raised."""
    import cv2

    try:
        rgb = cv2.resize(frame.rgb, (work.width, work.height), interpolation=cv2.INTER_AREA)
        volume.integrate(depth, frame.pose, rgb=rgb)
    except GPDepthError as exc:
        errors.append(f"image {frame.name}: {what}: {type(exc).__name__}: {exc}")


MAP_FILES = ("mesh", "cloud.ply", "mapper.json", "keyframes.npz", "volume.npz", "volume.json", "metrics.json")
"""What `write_map` writes into its folder (``mesh`` with the mesh format's ending): the mesh, the cloud,
the files of `Mapper.save` (what `Mapper.load` reads back from that folder) and the metrics."""


def write_map(
    result: MapResult, output: str | Path, *, mesh_format: str = "ply", summary: dict | None = None
) -> list[Path]:
    """Writes the mesh, the cloud with per-point sigma, the map and the metrics into ``output``, as one set.

    The files (`MAP_FILES`) appear together or not at all (`gpdepth3d.io.output_set`): each is
    written to a temporary file in ``output`` itself and renamed into place in one journalled
    commit, so nothing is staged elsewhere; what an earlier run killed there left is finished or
    removed first. The folder reloads with `Mapper.load`. An empty mesh or cloud is not written
    (named in the metrics).

    Args:
        result: `map_sequence`'s result.
        output: Output folder.
        mesh_format: "ply", "glb" or "obj".
        summary: The JSON written as ``metrics.json`` (default: `map_summary` of ``result``).

    Returns:
        The paths written.

    Raises:
        OutputError: a file cannot be written (full disk, file-size limit, ...); the files there
            before are kept.
    """
    from ..errors import OutputError
    from ..io import check_output_folder, clean_output_set, output_set, write_json, write_problem

    if mesh_format not in ("ply", "glb", "obj"):
        raise InvalidInputError("mesh_format", "ply, glb or obj", mesh_format)
    out = check_output_folder(output, "output")
    summary = summary if summary is not None else map_summary(result)
    members = list(dict.fromkeys([f"mesh.{f}" for f in ("ply", "glb", "obj")] + list(MAP_FILES[1:])))
    if out.is_dir():
        clean_output_set(out / "map", members)
    written = []
    try:
        with output_set(out / "map", members=members):
            if len(result.mesh.faces):
                written.append(save_mesh(result.mesh, out / f"mesh.{mesh_format}"))
            if len(result.cloud):
                written.append(result.cloud.save_ply(out / "cloud.ply"))
            result.mapper.save(out)
            written += [out / n for n in ("keyframes.npz", "mapper.json", "volume.json", "volume.npz")]
            written.append(write_json(out / "metrics.json", summary))
    except OutputError:
        raise
    except OSError as exc:  # a writer's own failure (its files are discarded with the set)
        raise OutputError(out, write_problem(exc)) from None
    return [Path(p) for p in written]


def open_map_inputs(
    images: str | Path,
    poses: str | Path,
    intrinsics: str | None = None,
    *,
    output: str | Path,
    depth: str | Path | None = None,
    points: str | Path | None = None,
    **options: Any,
) -> PosedInputs:
    """The inputs of ``gpdepth3d map`` opened and checked before any work, the output folder included.

    Args:
        images, poses, intrinsics, depth: As `open_posed_sequence` (paths or glob patterns).
        output: The output folder (checked writable now).
        points: Given world points for the frames (`gpdepth3d.mapping.points.given_points.read_given_points`:
            a COLMAP model, or PLY / NPZ / text points in the poses' frame), with their calibrated sigma.
        **options: The other keywords of `open_posed_sequence` (pose_format, association, ...).

    Raises:
        OutputError: an output folder that cannot be written. See `open_posed_sequence`.
    """
    from ..io import check_output_folder

    check_output_folder(Path(output), "--output")
    depth = None if depth is None else str(depth)
    inputs = open_posed_sequence(str(images), poses, intrinsics, depth=depth, **options)
    if points is not None:
        from ..mapping.points.given_points import read_given_points

        inputs = points_for_frames(inputs, read_given_points(points))
    given = {"images": str(images), "poses": str(poses), "points": None if points is None else str(points)}
    given.update(intrinsics=intrinsics, depth=depth)
    return replace(inputs, given={**given, "depth_scale": options.get("depth_scale", 0.001)})


def map_files(
    inputs: PosedInputs,
    output: str | Path,
    *,
    mde: str | MDEFrontEnd = "fastdepth",
    models_dir: str | Path | None = None,
    voxel_size: float = 0.02,
    depth_max: float = 5.0,
    mesh_format: str = "ply",
    frames: int | None = None,
    **options: Any,
) -> tuple[MapResult, dict[str, Any], list[Path]]:
    """Maps an opened sequence and writes the map's files (``gpdepth3d map`` between parsing and printing).

    Args:
        inputs: The sequence (`open_map_inputs`).
        output: The output folder (`write_map`).
        mde: A front-end name or model file (`gpdepth3d.mde.load_frontend`), or a front-end.
        models_dir: Folder of the named front-ends' models.
        voxel_size: TSDF voxel size, metres. depth_max: Depths beyond it are not fused, metres.
        mesh_format: "ply", "glb" or "obj".
        frames: At most this many frames (after the stride).
        **options: The other keywords of `map_sequence` (stride, working_width, threshold, force, ...).

    Returns:
        (the `MapResult`, the summary written to ``metrics.json``, the files written).

    Raises:
        InvalidInputError: a bad voxel size or depth limit (named by their options). See `map_sequence`.
    """
    for name, value in (("--voxel-size", voxel_size), ("--depth-max", depth_max)):
        if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
            raise InvalidInputError(name, "a distance > 0 (metres)", value)
    base = MapperConfig()
    config = replace(base, fusion=replace(base.fusion, voxel_size=voxel_size, depth_max=depth_max))
    if isinstance(mde, (str, Path)):
        from ..mde import load_frontend

        network = load_frontend(mde, models_dir=models_dir, argument="--mde")
    else:
        network = mde
    result = map_sequence(inputs, mde=network, config=config, max_frames=frames, **options)
    summary = map_summary(result)
    summary["inputs"] = {
        **inputs.given,
        "pose_format": inputs.pose_format,
        "mde": str(mde),
        "stride": options.get("stride", 1),
        "frames": frames,
        "working_width": options.get("working_width", DEFAULT_WORKING_WIDTH),
    }
    written = write_map(result, output, mesh_format=mesh_format, summary=summary)
    return result, summary, written


def map_summary(result: MapResult) -> dict[str, Any]:
    """The JSON record of a run: frames, errors, points, metrics, timings and the Mapper's settings."""
    from dataclasses import asdict

    return {
        "frames": result.frames,
        "frames_fused": result.frames_fused,
        "frame_errors": result.frame_errors,
        "frames_without_points": result.frames_without_points,
        "sparse_points_per_frame_median": result.sparse_points,
        "metrics": result.metrics,
        "mesh_faces": int(len(result.mesh.faces)),
        "cloud_points": int(len(result.cloud)),
        "timing_median_s_per_frame": {k: v for k, v in result.timing.items() if k != "wall"},
        "wall_s": result.timing.get("wall"),
        "camera": [
            result.mapper.camera.fx,
            result.mapper.camera.fy,
            result.mapper.camera.cx,
            result.mapper.camera.cy,
            result.mapper.camera.width,
            result.mapper.camera.height,
        ],
        "working_size": [result.mapper.work_camera.width, result.mapper.work_camera.height],
        "config": asdict(result.mapper.config),
    }


def piece_frames(piece: GivenPoints, names: list[str]) -> list[tuple[int, int]]:
    """(index into ``names``, model image id) of the images the piece registered, in sequence order."""
    by_name = {Path(image.name).name: image_id for image_id, image in piece.model.images.items()}
    return [(i, by_name[n]) for i, n in enumerate(names) if n in by_name]


def points_for_frames(
    inputs: PosedInputs, pieces: list[GivenPoints], *, sigma_rule: PointSigmaRule | None = None
) -> PosedInputs:
    """A posed sequence with given world points for each frame, with the calibrated sigma of ``sigma_rule``.

    The points are in the poses' world frame and metric (a COLMAP model triangulated with these poses,
    a SLAM's map). A COLMAP model says which image observes which point (matched by file name; every
    piece counts); for a points file each frame gets the points it sees (`visible_points`).

    Args:
        inputs: The posed sequence (`open_posed_sequence`).
        pieces: `read_given_points`' pieces.
        sigma_rule: The depth sigma of the points (default `PointSigmaRule()`).
    """
    from dataclasses import replace

    from ..mapping.points.given_points import visible_points

    rule = sigma_rule or PointSigmaRule()
    seq = inputs.sequence
    names = [f.name for f in seq.image_files]
    observed: list[list[tuple[GivenPoints, np.ndarray]]] = [[] for _ in names]
    for piece in pieces:
        if piece.model is not None:
            for i, image_id in piece_frames(piece, names):
                observed[i].append((piece, piece.observed_by(image_id)))
        else:
            for i in range(len(names)):
                observed[i].append((piece, visible_points(piece.points, seq.poses[i], seq.camera)))
    points, sigmas = [], []
    for i, parts in enumerate(observed):
        c = seq.poses[i][:3, 3]
        p_all, s_all = [np.zeros((0, 3))], [np.zeros(0)]
        for piece, rows in parts:
            p = piece.points[rows]
            pick = lambda a: None if a is None else a[rows]  # noqa: E731 - the piece's per-point arrays
            s_all.append(
                rule.sigma(
                    np.linalg.norm(p - c, axis=1),
                    stated=pick(piece.sigma),
                    reprojection_error=pick(piece.reprojection_error),
                    angle_deg=pick(piece.angle_deg),
                    focal=seq.camera.fx,
                )
            )
            p_all.append(p)
        points.append(np.concatenate(p_all))
        sigmas.append(np.concatenate(s_all))
    return replace(inputs, map_points=points, map_points_sigma=sigmas)
