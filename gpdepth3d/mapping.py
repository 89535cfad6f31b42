"""SLAM-facing incremental mapping: refine each frame's MDE depth with sparse points, fuse into a TSDF.

A `Mapper` takes posed frames one by one::

    mapper = Mapper(camera, MapperConfig(), mde=FastDepthTFLite(model_path))
    for rgb, T_world_camera, slam_points in stream:
        mapper.add_frame(rgb, T_world_camera, map_points_world=slam_points)
        mesh = mapper.mesh()          # at any time

Per frame: (1) the MDE depth (given, or from the front-end callable ``rgb -> depth``);
(2) sparse measurements from any of: a `SparseDepth`, SLAM map points in world coordinates
(transformed by the pose and projected, `sparse_from_map_points`), and features the library
triangulates itself between this frame and earlier frames of a sliding window
(`gpdepth3d.triangulation`); (3) the GP posterior (`DepthCompleter`, one kept for the whole
sequence); (4) TSDF fusion of the posterior mean with per-pixel weights from its variance
(`gpdepth3d.fusion`).

Resolution: ``camera`` describes the RGB images given to `Mapper.add_frame`; features are
detected at that resolution, while refinement and fusion run at ``working_scale`` times it
(e.g. 0.5 for 320x240 from 640x480).

`fuse_sequence` / `fuse_command` run the whole pipeline on a 7-Scenes-style sequence and build
the meshes from MDE-only, GP-refined and ground-truth depth with accuracy/completeness metrics.
"""

from __future__ import annotations

import json
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from .camera import PinholeCamera, check_pose, transform_points
from .cloud import ColoredCloud
from .complete import DepthCompleter, DepthPosterior
from .errors import EmptyInputError, InvalidInputError, ShapeError, describe
from .fusion import FusionConfig, TSDFFusion, save_mesh
from .gp.model import DepthGPConfig
from .io import atomic_write
from .measurements import SparseDepth, project_points
from .triangulation import Features, TriangulationConfig, detect_features, triangulate_frames

MDEFrontEnd = Callable[[np.ndarray], np.ndarray]


def sparse_from_map_points(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    sigma: float | np.ndarray | None = None,
    min_depth: float = 1e-3,
) -> SparseDepth:
    """SLAM map points (world frame) as sparse depth of one posed camera.

    Args:
        points_world: (N, 3) map points in the world frame, metres.
        T_world_camera: 4x4 pose of the camera.
        camera: Intrinsics; points projecting outside the image or behind the camera are dropped.
        sigma: Optional per-point (N,) or shared depth standard deviation, metres.
        min_depth: Points with z below this are dropped.

    Returns:
        `SparseDepth` on the camera's grid (closest point per pixel).
    """
    T = check_pose(T_world_camera)
    p = np.asarray(points_world, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError("points_world", "an (N, 3) array", describe(p))
    return project_points(transform_points(np.linalg.inv(T), p), camera, min_depth=min_depth, sigma=sigma)


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


def _resize_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resizes a depth map (nearest for shrinking keeps no mixed depths; linear when growing)."""
    import cv2

    if depth.shape == tuple(shape):
        return depth
    interp = cv2.INTER_NEAREST if shape[0] < depth.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(depth.astype(np.float32), (shape[1], shape[0]), interpolation=interp).astype(np.float64)


@dataclass(frozen=True)
class MapperConfig:
    """Options of the `Mapper`.

    Attributes:
        gp: GP model of the refinement (default: residual formulation).
        fusion: TSDF options (weighting "variance" uses the posterior variance).
        triangulation: Feature triangulation options.
        refine: False fuses the (resized) MDE depth itself, with uniform weights (a baseline).
        triangulate: Triangulate features against earlier frames of the window.
        window: Number of earlier frames kept for triangulation.
        min_baseline: Earlier frames closer than this to the current camera centre are not
            used for triangulation (metres).
        working_scale: Resolution of refinement and fusion relative to the RGB images.
        max_points: At most this many measurements per frame go to the GP, the most certain
            (smallest sigma / depth; points without sigma count as certain) - bounds the cost
            of the dense ``exact`` engine.
    """

    gp: DepthGPConfig = field(default_factory=DepthGPConfig.residual)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    triangulation: TriangulationConfig = field(default_factory=lambda: TriangulationConfig(detector="orb"))
    refine: bool = True
    triangulate: bool = True
    window: int = 4
    min_baseline: float = 0.05
    working_scale: float = 1.0
    max_points: int = 300

    def __post_init__(self) -> None:
        if int(self.max_points) != self.max_points or self.max_points < 1:
            raise InvalidInputError("max_points", "an integer >= 1", self.max_points)
        if int(self.window) != self.window or self.window < 1:
            raise InvalidInputError("window", "an integer >= 1", self.window)
        if not np.isfinite(self.min_baseline) or self.min_baseline < 0:
            raise InvalidInputError("min_baseline", "a distance >= 0 (metres)", self.min_baseline)
        if not np.isfinite(self.working_scale) or not 0 < self.working_scale <= 1:
            raise InvalidInputError("working_scale", "a factor in (0, 1]", self.working_scale)


@dataclass(frozen=True)
class FrameResult:
    """What `Mapper.add_frame` did with one frame.

    Attributes:
        depth: (h, w) depth that was fused (posterior mean, or the MDE when not refining), metres.
        variance: (h, w) its variance, m^2 (NaN when not refining).
        mde: (h, w) MDE depth at the working resolution, metres.
        sparse: The measurements used (at the RGB resolution).
        posterior: The GP posterior, or None when not refining.
        timings: Seconds per stage: "mde", "triangulate", "refine", "fuse".
    """

    depth: np.ndarray
    variance: np.ndarray
    mde: np.ndarray
    sparse: SparseDepth
    posterior: DepthPosterior | None
    timings: dict


class Mapper:
    """Incremental dense mapping from posed RGB frames, MDE depth and sparse SLAM measurements.

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
        fusion_cfg = self.config.fusion if self.config.refine else replace(self.config.fusion, weighting="uniform")
        self.fusion = TSDFFusion(self.work_camera, fusion_cfg)
        self._window: deque[tuple[np.ndarray, np.ndarray, Features]] = deque(maxlen=int(self.config.window))
        self.frames = 0
        self.timings: list[dict] = []

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
    ) -> FrameResult:
        """Refines and fuses one posed frame.

        Args:
            rgb: (H, W, 3) uint8 RGB image of ``camera``'s size.
            T_world_camera: 4x4 rigid pose.
            mde_depth: (h, w) MDE depth, metres, any resolution of the same image; default: the
                front-end's output for ``rgb``.
            sparse: Extra measurements (any resolution of the same image).
            map_points_world: (N, 3) SLAM map points in the world frame, metres.
            map_points_sigma: Their depth sigma(s), metres (default: the model's sigma_meas).

        Returns:
            `FrameResult` (depth fused, variance, measurements, timings).

        Raises:
            ShapeError: on image / depth size mismatches.
            CalibrationError: on a non-rigid pose.
            InvalidInputError: when neither mde_depth nor a front-end is given.
            EmptyInputError: when the frame has no depth to fuse.
        """
        timings: dict[str, float] = {}
        T = check_pose(T_world_camera)
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ShapeError("rgb", "an (H, W, 3) uint8 RGB image", describe(rgb))
        self.camera.check_image(rgb, "rgb")
        work_shape = self.work_camera.shape

        t0 = time.perf_counter()
        if mde_depth is None:
            if self.mde is None:
                raise InvalidInputError("mde_depth", "an MDE depth map (or an mde front-end in Mapper)", None)
            mde_depth = self.mde(rgb)
        mde_depth = np.asarray(mde_depth, dtype=np.float64)
        if mde_depth.ndim != 2:
            raise ShapeError("mde_depth", "a 2-D (h, w) depth map", describe(mde_depth))
        h, w = mde_depth.shape
        if abs((w / h) / (self.camera.width / self.camera.height) - 1) > 0.01:
            raise ShapeError(
                "mde_depth", f"a depth map with the aspect ratio of the {self.camera.width}x{self.camera.height} image", (h, w)
            )
        mde = _resize_depth(np.where(np.isfinite(mde_depth), mde_depth, 0.0), work_shape)
        timings["mde"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        parts = []
        if sparse is not None:
            if not isinstance(sparse, SparseDepth):
                raise InvalidInputError("sparse", "a SparseDepth", type(sparse).__name__)
            parts.append(sparse.rasterize(self.camera.shape))
        if map_points_world is not None:
            parts.append(sparse_from_map_points(map_points_world, T, self.camera, sigma=map_points_sigma))
        if self.config.triangulate:
            parts.append(self._triangulate(rgb, T))
        measurements = merge_sparse(*parts, image_size=self.camera.shape)
        if len(measurements) > self.config.max_points:
            rel = np.nan_to_num(measurements.sigma / measurements.depth, nan=0.0)
            keep = np.sort(np.argsort(rel, kind="stable")[: int(self.config.max_points)])
            measurements = measurements.subset(keep)
        timings["triangulate"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        posterior = None
        if self.config.refine:
            posterior = self.completer.complete(mde, measurements, output_shape=work_shape)
            depth, variance = posterior.mean, posterior.variance
        else:
            depth, variance = mde, np.full(work_shape, np.nan)
        timings["refine"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        work_rgb = self._work_rgb(rgb)
        self.fusion.integrate(depth, T, rgb=work_rgb, weights=self.fusion.weights_for(variance))
        timings["fuse"] = time.perf_counter() - t0
        self.frames += 1
        self.timings.append(timings)
        return FrameResult(depth, variance, mde, measurements, posterior, timings)

    def _work_rgb(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        if self.work_camera is self.camera:
            return rgb
        return cv2.resize(rgb, (self.work_camera.width, self.work_camera.height), interpolation=cv2.INTER_AREA)

    def _triangulate(self, rgb: np.ndarray, T: np.ndarray) -> SparseDepth:
        cfg = self.config
        feats = detect_features(rgb, config=cfg.triangulation)
        partners = [
            item for item in self._window if np.linalg.norm(item[1][:3, 3] - T[:3, 3]) >= cfg.min_baseline
        ]
        self._window.append((rgb, T, feats))
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

    # ------------------------------------------------------------------ the map
    def mesh(self) -> Any:
        """The current map as a `trimesh.Trimesh` (world frame, metres, vertex colours)."""
        return self.fusion.extract_mesh()

    def point_cloud(self) -> ColoredCloud:
        """The current map's surface points as a `ColoredCloud`."""
        return self.fusion.extract_point_cloud()

    def save_mesh(self, path: str | Path) -> Path:
        """Writes the current mesh (PLY, GLB or OBJ) atomically."""
        return save_mesh(self.mesh(), path)


# ---------------------------------------------------------------------- evaluation
def mesh_metrics(
    mesh: Any, reference: Any, *, threshold: float = 0.05, samples: int = 50_000, seed: int = 0
) -> dict[str, float]:
    """Accuracy and completeness of a mesh against a reference mesh (both in metres).

    Both surfaces are sampled uniformly (``samples`` points each, seeded). Accuracy is the mean
    distance from the mesh's samples to the nearest reference sample, completeness the mean
    distance the other way; Chamfer is their mean; precision / recall are the fractions of
    samples within ``threshold`` metres of the other surface; F-score their harmonic mean.

    Returns:
        ``accuracy``, ``completeness``, ``chamfer`` (metres), ``precision``, ``recall``,
        ``fscore`` (0..1), and ``threshold``.
    """
    import trimesh
    from scipy.spatial import cKDTree

    for name, m in (("mesh", mesh), ("reference", reference)):
        if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
            raise EmptyInputError(name, "a trimesh.Trimesh with faces", type(m).__name__)
    if not threshold > 0:
        raise InvalidInputError("threshold", "a distance > 0 (metres)", threshold)
    a, _ = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    b, _ = trimesh.sample.sample_surface(reference, samples, seed=seed + 1)
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    precision = float(np.mean(d_ab < threshold))
    recall = float(np.mean(d_ba < threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "accuracy": float(d_ab.mean()),
        "completeness": float(d_ba.mean()),
        "chamfer": float((d_ab.mean() + d_ba.mean()) / 2),
        "precision": precision,
        "recall": recall,
        "fscore": float(fscore),
        "threshold": float(threshold),
    }


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
    variance weights; one GP solve per frame feeds both), ``gt`` (the Kinect depth with the
    depth camera's intrinsics, the reference).

    Args:
        data: Sequence folder (see `gpdepth3d.datasets.sevenscenes.SevenScenes`).
        mde: Front-end ``rgb -> depth`` in metres.
        rgb_K: 3x3 intrinsics of the *colour* camera (default: the dataset's K). 7-Scenes gives
            only the depth camera's K (f = 585); its colour camera is closer to f = 525.
        config: Mapper options (``fusion.weighting`` is overridden per variant).
        max_frames: Use only the first frames.
        threshold: Precision / recall distance, metres.
        metric_samples: Surface samples per mesh for the metrics.
        progress: Print one line per frame.

    Returns:
        ``meshes`` (variant -> trimesh), ``metrics`` (variant -> `mesh_metrics` against ``gt``),
        ``timing`` (mean seconds per frame per stage), ``frames``, ``sparse_points``
        (mean measurements per frame) and ``depth_median_abs_error`` (per-frame median
        |depth - ground truth| in metres, averaged over frames, for "mde" and "gp"; the Kinect
        depth is registered to the colour camera by lifting and re-projecting it) and
        ``sparse_bias_per_frame`` (per frame with measurements: median signed relative error
        of the measurements against the Kinect depth).
    """
    from .datasets.sevenscenes import SevenScenes

    config = config or MapperConfig(working_scale=0.5)
    reader = SevenScenes(data)
    n = len(reader) if max_frames is None else min(len(reader), int(max_frames))
    if n < 1:
        raise EmptyInputError("data", "a sequence with frames", "none")
    first = reader[0]
    rgb_cam = first.camera if rgb_K is None else PinholeCamera.from_K(np.asarray(rgb_K), first.camera.width, first.camera.height)
    depth_cam = first.camera
    mapper = Mapper(rgb_cam, replace(config, fusion=replace(config.fusion, weighting="variance")), mde=mde)
    work = mapper.work_camera
    depth_work = depth_cam.resized(work.width, work.height)
    extra = {
        "mde": TSDFFusion(work, replace(config.fusion, weighting="uniform")),
        "gp_uniform": TSDFFusion(work, replace(config.fusion, weighting="uniform")),
        "gt": TSDFFusion(depth_work, replace(config.fusion, weighting="uniform")),
    }
    times: list[dict] = []
    npoints = []
    depth_err: dict[str, list[float]] = {"mde": [], "gp": []}
    sparse_err: list[float] = []
    for i in range(n):
        frame = reader[i]
        result = mapper.add_frame(frame.rgb, frame.pose)
        work_rgb = mapper._work_rgb(frame.rgb)
        t0 = time.perf_counter()
        extra["gp_uniform"].integrate(result.depth, frame.pose, rgb=work_rgb)
        t_uniform = time.perf_counter() - t0
        extra["mde"].integrate(result.mde, frame.pose, rgb=work_rgb)
        gt = _resize_depth(frame.depth, depth_work.shape)
        extra["gt"].integrate(gt, frame.pose, rgb=work_rgb)
        times.append({**result.timings, "fuse_uniform": t_uniform})
        # Ground truth registered to the colour camera: lift with the depth camera, project (z-buffer).
        pts, _ = frame.camera.backproject(frame.depth)
        gt_rgb = project_points(pts, work).to_depth_map()
        ok = gt_rgb > 0
        if len(result.sparse):
            # signed relative error of the measurements against the Kinect depth (depth camera)
            lifted = rgb_cam.backproject_pixels(result.sparse.uv, result.sparse.depth)
            uv, z = depth_cam.project(lifted)
            inside = depth_cam.in_image(uv)
            iu = np.rint(uv[inside]).astype(np.int64)
            kinect = frame.depth[iu[:, 1], iu[:, 0]]
            good = kinect > 0
            if good.any():
                sparse_err.append(float(np.median((z[inside][good] - kinect[good]) / kinect[good])))
        if ok.any():
            depth_err["mde"].append(float(np.median(np.abs(result.mde[ok] - gt_rgb[ok]))))
            depth_err["gp"].append(float(np.median(np.abs(result.depth[ok] - gt_rgb[ok]))))
        npoints.append(len(result.sparse))
        if progress:
            print(f"frame {i + 1}/{n}: {len(result.sparse)} points, " + ", ".join(f"{k} {v:.3f}s" for k, v in result.timings.items()))
    meshes = {
        "mde": extra["mde"].extract_mesh(),
        "gp_uniform": extra["gp_uniform"].extract_mesh(),
        "gp_variance": mapper.mesh(),
        "gt": extra["gt"].extract_mesh(),
    }
    metrics = {
        k: mesh_metrics(m, meshes["gt"], threshold=threshold, samples=metric_samples)
        for k, m in meshes.items()
        if k != "gt"
    }
    timing = {k: float(np.mean([t[k] for t in times])) for k in times[0]}
    return {
        "meshes": meshes,
        "metrics": metrics,
        "timing": timing,
        "frames": n,
        "sparse_points": float(np.mean(npoints)),
        "depth_median_abs_error": {k: float(np.mean(v)) if v else float("nan") for k, v in depth_err.items()},
        "sparse_bias_per_frame": sparse_err,
    }


SEVEN_SCENES_RGB_K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
"""Colour-camera intrinsics used for 7-Scenes RGB (the dataset's K, f = 585, is the depth camera's;
triangulating the RGB frames with f = 525 agrees with the Kinect depth, with f = 585 it is ~15-40 %
too far and fails the epipolar check; see the mapping tests)."""


def fuse_command(
    data: Path,
    out: Path = Path("fuse_out"),
    *,
    model: Path = Path("../shared/models/fast_depth_224.tflite"),
    frames: int | None = None,
    working_scale: float = 0.5,
    voxel_size: float = 0.02,
    truncation: float = 0.08,
    depth_max: float = 5.0,
    sigma_ref: float = 0.1,
    rgb_focal: float = 525.0,
    mesh_format: Literal["ply", "glb", "obj"] = "ply",
    threshold: float = 0.05,
    metric_samples: int = 50_000,
    engine: Literal["exact", "kissgp", "fast"] = "exact",
) -> dict[str, Any]:
    """Builds meshes of a posed RGB-D sequence from MDE-only, GP-refined and ground-truth depth.

    The MDE is FastDepth (TFLite); the sparse points are features the library triangulates
    from the posed RGB frames themselves (not the ground truth). Writes
    ``mesh_mde``, ``mesh_gp_uniform``, ``mesh_gp_variance``, ``mesh_gt`` (``.<mesh_format>``) and
    ``metrics.json`` (accuracy/completeness/Chamfer/precision/recall against the ground-truth
    mesh, timings) into ``out``, all atomically.

    Args:
        data: 7-Scenes-style sequence folder (e.g. ../shared/data/7scenes).
        out: Output folder.
        model: FastDepth TFLite model file.
        frames: Use only the first this many frames (default: all).
        working_scale: Resolution of refinement and fusion relative to the images (0.5 = 320x240).
        voxel_size: TSDF voxel size, metres.
        truncation: TSDF truncation distance, metres.
        depth_max: Depths beyond this are not fused, metres.
        sigma_ref: Variance weighting: sigma (metres) at which a pixel counts half.
        rgb_focal: Focal length of the colour camera, pixels (7-Scenes: 525; the given K is the depth camera's).
        mesh_format: File format of the meshes.
        threshold: Precision/recall distance, metres.
        metric_samples: Surface samples per mesh for the metrics.
        engine: GP engine of the refinement (all give the same posterior; "exact" is dense and,
            with at most 300 points per frame, the quickest at 320x240; use "fast" for
            working_scale 1).

    Returns:
        The metrics dictionary written to ``metrics.json``.
    """
    from .mde.tflite import FastDepthTFLite

    fusion = FusionConfig(voxel_size=voxel_size, truncation=truncation, depth_max=depth_max, sigma_ref=sigma_ref)
    config = MapperConfig(fusion=fusion, working_scale=working_scale, gp=DepthGPConfig.residual(engine=engine))
    K = SEVEN_SCENES_RGB_K.copy()
    K[0, 0] = K[1, 1] = rgb_focal
    result = fuse_sequence(
        data,
        mde=FastDepthTFLite(model),
        rgb_K=K,
        config=config,
        max_frames=frames,
        threshold=threshold,
        metric_samples=metric_samples,
    )
    out = Path(out)
    for name, mesh in result["meshes"].items():
        save_mesh(mesh, out / f"mesh_{name}.{mesh_format}")
    summary = {
        "data": str(data),
        "frames": result["frames"],
        "sparse_points_per_frame": result["sparse_points"],
        "depth_median_abs_error_m": result["depth_median_abs_error"],
        "metrics": result["metrics"],
        "timing_s_per_frame": result["timing"],
        "config": {"mapper": _jsonable(asdict(config)), "rgb_focal": rgb_focal, "model": str(model)},
    }
    atomic_write(out / "metrics.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    return summary


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x
