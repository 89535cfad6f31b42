"""``gpdepth3d fuse``: the 7-Scenes experiment, meshes from MDE-only, GP-refined and ground-truth depth.

A user's own sequence (any layout and pose format) is mapped by ``gpdepth3d map`` (`gpdepth3d.cli.map`).
"""

from __future__ import annotations

import warnings

from dataclasses import asdict
from pathlib import Path
from typing import Any, Literal

from ..io import write_json, write_together
from ..mapping.fusion import FusionConfig, save_mesh
from ..experiments.mapping_run import fuse_sequence
from ..datasets.sevenscenes import COLOUR_INTRINSICS
from ..errors import InvalidInputError
from ..mapping.mapper_config import MAPPER_GP, MapperConfig
from ._options import GPPreset


def fuse_command(
    data: Path,
    output: Path = Path("fuse_out"),
    *,
    mde: str = "fastdepth",
    models_dir: Path | None = None,
    gp: GPPreset = MAPPER_GP,
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
) -> dict[str, Any]:
    """Builds meshes of a posed RGB-D sequence from MDE-only, GP-refined and ground-truth depth.

    The MDE is a front-end run on every image (default FastDepth, TFLite); the sparse points are
    features the library triangulates from the posed RGB frames themselves (not the ground truth);
    the GP is `MapperConfig`'s (the library's default model with the stationary GP's variance and
    the mapper's length scale, `MAPPER_GP`; also what --preset default means here) or --preset paper|residual, and its fields
    --gp.FIELD (e.g. --gp.calibration.reach 1.5). Writes
    ``mesh_mde``, ``mesh_gp_uniform``, ``mesh_gp_variance``, ``mesh_gt`` (``.<mesh_format>``) and
    ``metrics.json`` (accuracy/completeness/Chamfer/precision/recall against the ground-truth
    mesh, timings, frames that failed) into ``output``, all atomically. A frame that fails is
    named and skipped; a mesh without triangles (few frames) is reported, not written.

    Args:
        data: 7-Scenes-style sequence folder (e.g. ../shared/data/7scenes).
        output: Output folder.
        mde: Monocular front-end: "fastdepth" (FastDepth TFLite, indoor; the [tflite] extra), "rtmonodepth"
            (RT-MonoDepth-S ONNX, outdoor) or a .tflite/.onnx model file.
        models_dir: Folder of the named front-ends' models (default: $GPDEPTH3D_MODELS or ../shared/models).
        gp: The GP: --preset default|paper|residual, then --gp.FIELD.
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

    Returns:
        The metrics dictionary written to ``metrics.json``.
    """
    from ..io import check_output_folder
    from ..mde import load_frontend
    from ._warnings import quiet_third_party, report_warnings

    if isinstance(metric_samples, bool) or not isinstance(metric_samples, int) or metric_samples < 1:
        raise InvalidInputError("--metric-samples", "an integer >= 1", metric_samples)
    if not (isinstance(threshold, (int, float)) and threshold > 0 and threshold < float("inf")):
        raise InvalidInputError("--threshold", "a distance > 0 (metres)", threshold)
    check_output_folder(Path(output), "--output")
    network = load_frontend(mde, models_dir=models_dir)
    fusion = FusionConfig(voxel_size=voxel_size, truncation=truncation, depth_max=depth_max, sigma_ref=sigma_ref)
    config = MapperConfig(fusion=fusion, working_scale=working_scale, gp=gp)
    K = COLOUR_INTRINSICS.copy()
    K[0, 0] = K[1, 1] = rgb_focal
    with warnings.catch_warnings(record=True) as caught:  # one line per kind of warning, with its count
        warnings.simplefilter("always")
        quiet_third_party()
        result = fuse_sequence(
            data,
            mde=network,
            rgb_K=K,
            config=config,
            max_frames=frames,
            threshold=threshold,
            metric_samples=metric_samples,
        )
    report_warnings(caught)
    out = Path(output)
    written = []
    with write_together():  # the meshes and metrics.json appear together, or none of them
        for name, mesh in result["meshes"].items():
            if name not in result["empty_meshes"]:
                written.append(str(save_mesh(mesh, out / f"mesh_{name}.{mesh_format}")))
        summary = {
            "data": str(data),
            "frames": result["frames"],
            "frames_fused": result["frames_fused"],
            "frame_errors": result["frame_errors"],
            "masked_pixels": result["masked_pixels"],
            "empty_meshes": result["empty_meshes"],
            "meshes_written": written,
            "sparse_points_per_frame": result["sparse_points"],
            "depth_median_abs_error_m": result["depth_median_abs_error"],
            "metrics": result["metrics"],
            "timing_s_per_frame": result["timing"],
            "timing_median_s_per_frame": result["timing_median"],
            "config": {"mapper": asdict(config), "rgb_focal": rgb_focal, "mde": str(mde)},
        }
        write_json(out / "metrics.json", summary)
    for message in result["frame_errors"]:
        print(f"skipped {message}")
    if result["empty_meshes"]:
        print(f"no surface above the weight threshold yet in: {', '.join(result['empty_meshes'])} (no mesh written)")
    print(
        f"{result['frames_fused']} of {result['frames']} frames fused; wrote {len(written)} meshes and "
        f"{out / 'metrics.json'} (in {out.resolve()})"
    )
    for path in written:
        print(f"wrote {path}")
    scores = [f"{name} {m['fscore']:.3f}" for name, m in result["metrics"].items() if m is not None]
    if scores:
        print(f"F-score at {threshold * 100:g} cm against the ground-truth mesh: " + ", ".join(scores))
    return summary
