"""Whole-sequence mapping experiment: a 7-Scenes-style sequence fused four ways and scored against its depth.

`fuse_sequence` runs the `gpdepth3d.mapping.Mapper` on every frame and fuses the MDE-only, GP-refined
(uniform and variance weights) and ground-truth depth into TSDF meshes, compared with `mesh_metrics`.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..camera import PinholeCamera
from ..errors import EmptyInputError, GPDepthError
from ..mapping.fusion import TSDFFusion
from ..mapping.mapper import FrameResult, Mapper, MapperConfig, MDEFrontEnd, _resize_depth
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
        progress: Print one line per frame.

    Bad data never ends the run: a frame that cannot be read or fused is named in
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
    from ..datasets.sevenscenes import SevenScenes

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
    frame_errors: list[str] = []
    frame_warnings: list[str] = []
    masked = 0
    fused = 0
    frames: dict[int, Any] = {}  # frames added and not yet fused (the Mapper's lag)

    def evaluate(result: FrameResult) -> None:
        """Records one fused (or failed) frame and fuses the comparison variants of it."""
        nonlocal masked, fused
        i = result.keyframe_id
        frame = frames.pop(i)
        frame_warnings.extend(result.warnings)
        masked += result.masked_pixels
        if result.error is not None:
            frame_errors.append(result.error)
        fused += int(result.fused)
        work_rgb = mapper._work_rgb(frame.rgb)
        others = [("gt", _resize_depth(frame.depth, depth_work.shape), work_rgb)]
        if result.mde.size:
            others.insert(0, ("mde", result.mde, work_rgb))
        if result.depth.size:
            others.insert(0, ("gp_uniform", result.depth, work_rgb))
        for name, depth, colour in others:
            t0 = time.perf_counter()
            try:
                if depth.size:
                    extra[name].integrate(depth, frame.pose, rgb=colour)
            except GPDepthError as exc:
                frame_errors.append(f"frame {i}: {name} volume: {type(exc).__name__}: {exc}")
            if name == "gp_uniform":
                times[-1]["fuse_uniform"] = time.perf_counter() - t0
        if not result.depth.size:
            return
        # Ground truth at the working resolution: lift with the frame's camera, project (z-buffer).
        pts, _ = frame.camera.backproject(frame.depth)
        gt_rgb = project_points(pts, work).to_depth_map()
        ok = gt_rgb > 0
        if len(result.sparse):
            # signed relative error of the measurements against the Kinect depth (the frame's camera)
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

    for i in range(n):
        try:
            frame = reader[i]
            frames[i] = frame
            result = mapper.add_frame(frame.rgb, frame.pose, keyframe_id=i)
        except GPDepthError as exc:  # unreadable frame, bad pose...: named, recorded, the run goes on
            frames.pop(i, None)
            frame_errors.append(f"frame {i}: {type(exc).__name__}: {exc}")
            continue
        times.append(dict(mapper.timings[-1]))
        if result is not None:
            evaluate(result)
    for result in mapper.flush():
        times.append(dict(result.timings))
        evaluate(result)
    volumes = {"mde": extra["mde"], "gp_uniform": extra["gp_uniform"], "gp_variance": mapper.fusion, "gt": extra["gt"]}
    meshes = {}
    for name, volume in volumes.items():
        meshes[name] = volume.extract_mesh(allow_empty=True) if volume.frames_integrated else None
    empty = sorted(k for k, m in meshes.items() if m is None or len(m.faces) == 0)
    metrics: dict[str, Any] = {}
    for k, m in meshes.items():
        if k == "gt":
            continue
        metrics[k] = (
            None if k in empty or "gt" in empty else mesh_metrics(m, meshes["gt"], threshold=threshold, samples=metric_samples)
        )
    keys = sorted({k for t in times for k in t})
    timing = {k: float(np.mean([t[k] for t in times if k in t])) for k in keys}
    # the names bench/fusion.py reads
    timing.update({"triangulate": timing.get("points", 0.0), "refine": timing.get("gp", 0.0), "fuse": timing.get("fusion", 0.0)})
    return {
        "meshes": meshes,
        "metrics": metrics,
        "timing": timing,
        "timing_median": {k: float(np.median([t[k] for t in times if k in t])) for k in keys},
        "frames": n,
        "frames_fused": fused,
        "frame_errors": frame_errors,
        "frame_warnings": frame_warnings,
        "masked_pixels": masked,
        "empty_meshes": empty,
        "sparse_points": float(np.mean(npoints)) if npoints else 0.0,
        "depth_median_abs_error": {k: float(np.mean(v)) if v else float("nan") for k, v in depth_err.items()},
        "sparse_bias_per_frame": sparse_err,
    }
