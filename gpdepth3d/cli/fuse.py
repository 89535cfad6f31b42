"""``gpdepth3d fuse``: the 7-Scenes experiment, meshes from MDE-only, GP-refined and ground-truth depth.

A user's own sequence (any layout and pose format) is mapped by ``gpdepth3d map`` (`gpdepth3d.cli.map`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Literal

from ..mapping.mapper_config import MAPPER_GP
from ..mapping.tsdf.fusion import FusionConfig
from ..pipelines.fuse_run import run_fuse
from ._options import GPPreset
from ._warnings import quiet_third_party, report_warnings


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

    The MDE runs on every image; the sparse points are features triangulated from the posed RGB frames
    (not the ground truth); the GP is `MapperConfig`'s (`MAPPER_GP`, also --preset default here) or
    --preset paper|residual, with --gp.FIELD. Writes ``mesh_mde``, ``mesh_gp_uniform``, ``mesh_gp_variance``,
    ``mesh_gt`` and ``metrics.json`` (accuracy/completeness/Chamfer/precision/recall against the ground-truth
    mesh, timings, failed frames) into ``output`` together; a mesh without triangles is reported, not written.

    Args:
        data: 7-Scenes-style sequence folder (e.g. ../shared/data/7scenes).
        output: Output folder.
        mde: Front-end: "fastdepth" (TFLite, indoor; [tflite]), "rtmonodepth" (ONNX, outdoor) or a model file.
        models_dir: Folder of the named front-ends' models (default: $GPDEPTH3D_MODELS or ../shared/models).
        gp: The GP: --preset default|paper|residual, then --gp.FIELD.
        frames: Use only the first this many frames (default: all).
        working_scale: Resolution of refinement and fusion relative to the images (0.5 = 320x240).
        voxel_size: TSDF voxel size, metres.
        truncation: TSDF truncation distance, metres.
        depth_max: Depths beyond this are not fused, metres.
        sigma_ref: Variance weighting: sigma (metres) at which a pixel counts half.
        rgb_focal: Focal length of the colour camera, pixels (7-Scenes: 525; its K is the depth camera's).
        mesh_format: File format of the meshes.
        threshold: Precision/recall distance, metres.
        metric_samples: Surface samples per mesh for the metrics.

    Returns:
        The metrics dictionary written to ``metrics.json``.
    """
    fusion = FusionConfig(voxel_size=voxel_size, truncation=truncation, depth_max=depth_max, sigma_ref=sigma_ref)
    with warnings.catch_warnings(record=True) as caught:  # one line per kind of warning, with its count
        warnings.simplefilter("always")
        quiet_third_party()
        outcome = run_fuse(data, output, mde=mde, models_dir=models_dir, gp=gp, frames=frames, fusion=fusion,
                           working_scale=working_scale, rgb_focal=rgb_focal, mesh_format=mesh_format,
                           threshold=threshold, metric_samples=metric_samples)  # fmt: skip
    report_warnings(caught)
    for line in outcome.report(threshold):
        print(line)
    return outcome.summary
