"""The 7-Scenes fusion experiment as one call: meshes from MDE-only, GP-refined and ground-truth depth, written.

`run_fuse` is the work of ``gpdepth3d fuse``: it loads the front-end, builds the `MapperConfig`, maps the
sequence with `gpdepth3d.pipelines.mapping_run.fuse_sequence` and writes the meshes and ``metrics.json``
together (all or none, `gpdepth3d.io.write_together`). It returns the summary it wrote and the paths.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..datasets.sevenscenes import COLOUR_INTRINSICS
from ..errors import InvalidInputError
from ..gp.model import DepthGPConfig
from ..io import check_output_folder, write_json, write_together
from ..mapping.mapper_config import MAPPER_GP, MapperConfig
from ..mapping.tsdf.fusion import FusionConfig, save_mesh
from .mapping_run import fuse_sequence


@dataclass
class FuseOutcome:
    """What `run_fuse` wrote.

    Attributes:
        summary: The dictionary written to ``metrics.json`` (frames, failures, metrics, timings, config).
        written: The mesh files written, in order (a mesh without triangles is named in
            ``summary["empty_meshes"]`` instead).
        metrics_path: The ``metrics.json`` written.
    """

    summary: dict[str, Any]
    written: list[Path] = field(default_factory=list)
    metrics_path: Path = Path("metrics.json")

    def report(self, threshold: float) -> list[str]:
        """The lines ``gpdepth3d fuse`` prints: skipped frames, empty meshes, files written, F-scores at ``threshold`` m."""
        s = self.summary
        lines = [f"skipped {message}" for message in s["frame_errors"]]
        if s["empty_meshes"]:
            lines.append(
                f"no surface above the weight threshold yet in: {', '.join(s['empty_meshes'])} (no mesh written)"
            )
        lines.append(
            f"{s['frames_fused']} of {s['frames']} frames fused; wrote {len(self.written)} meshes and "
            f"{self.metrics_path} (in {self.metrics_path.parent.resolve()})"
        )
        lines += [f"wrote {path}" for path in self.written]
        scores = [f"{name} {m['fscore']:.3f}" for name, m in s["metrics"].items() if m is not None]
        if scores:
            lines.append(f"F-score at {threshold * 100:g} cm against the ground-truth mesh: " + ", ".join(scores))
        return lines


def run_fuse(
    data: str | Path,
    output: str | Path,
    *,
    mde: str = "fastdepth",
    models_dir: str | Path | None = None,
    gp: DepthGPConfig = MAPPER_GP,
    frames: int | None = None,
    fusion: FusionConfig | None = None,
    working_scale: float = 0.5,
    rgb_focal: float = 525.0,
    mesh_format: str = "ply",
    threshold: float = 0.05,
    metric_samples: int = 50_000,
) -> FuseOutcome:
    """Maps a 7-Scenes-style sequence three ways and writes ``mesh_<name>.<mesh_format>`` and ``metrics.json``.

    Args are those of ``gpdepth3d fuse`` (errors name its options): ``fusion`` carries the voxel size,
    truncation, depth range and variance weighting (metres); ``rgb_focal`` is the colour camera's focal
    length in pixels (7-Scenes: 525); ``threshold`` the precision/recall distance in metres.

    Raises:
        InvalidInputError: for a bad --metric-samples or --threshold, or an output that cannot be written.
    """
    from ..mde import load_frontend

    if isinstance(metric_samples, bool) or not isinstance(metric_samples, int) or metric_samples < 1:
        raise InvalidInputError("--metric-samples", "an integer >= 1", metric_samples)
    if not (isinstance(threshold, (int, float)) and threshold > 0 and threshold < float("inf")):
        raise InvalidInputError("--threshold", "a distance > 0 (metres)", threshold)
    out = check_output_folder(Path(output), "--output")
    network = load_frontend(mde, models_dir=models_dir)
    config = MapperConfig(fusion=fusion or FusionConfig(), working_scale=working_scale, gp=gp)
    K = COLOUR_INTRINSICS.copy()
    K[0, 0] = K[1, 1] = rgb_focal
    result = fuse_sequence(
        data, mde=network, rgb_K=K, config=config, max_frames=frames, threshold=threshold, metric_samples=metric_samples
    )
    written: list[Path] = []
    with write_together():  # the meshes and metrics.json appear together, or none of them
        for name, mesh in result["meshes"].items():
            if name not in result["empty_meshes"]:
                written.append(save_mesh(mesh, out / f"mesh_{name}.{mesh_format}"))
        summary = {
            "data": str(data),
            "frames": result["frames"],
            "frames_fused": result["frames_fused"],
            "frame_errors": result["frame_errors"],
            "masked_pixels": result["masked_pixels"],
            "empty_meshes": result["empty_meshes"],
            "meshes_written": [str(p) for p in written],
            "sparse_points_per_frame": result["sparse_points"],
            "depth_median_abs_error_m": result["depth_median_abs_error"],
            "metrics": result["metrics"],
            "timing_s_per_frame": result["timing"],
            "timing_median_s_per_frame": result["timing_median"],
            "config": {"mapper": asdict(config), "rgb_focal": rgb_focal, "mde": str(mde)},
        }
        metrics_path = write_json(out / "metrics.json", summary)
    return FuseOutcome(summary, written, metrics_path)
