"""`run_fuse`, the work of `gpdepth3d fuse`: its refusals before any work, and the lines the command prints."""

from __future__ import annotations

from pathlib import Path

import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.pipelines.fuse_run import FuseOutcome, run_fuse


@pytest.mark.parametrize(
    "kwargs, flag",
    [({"metric_samples": 0}, "--metric-samples"), ({"metric_samples": True}, "--metric-samples"),
     ({"threshold": 0.0}, "--threshold"), ({"threshold": float("inf")}, "--threshold")],
)  # fmt: skip
def test_refuses_bad_options_before_loading_anything(tmp_path, kwargs, flag):
    with pytest.raises(InvalidInputError, match=flag):
        run_fuse(tmp_path / "no_data", tmp_path / "out", mde="no-such-front-end", **kwargs)
    assert not (tmp_path / "out").exists()


def test_report_lines():
    summary = {
        "frame_errors": ["frame 3: no depth"],
        "empty_meshes": ["gt"],
        "frames": 4,
        "frames_fused": 3,
        "metrics": {"mde": {"fscore": 0.25}, "gp_variance": {"fscore": 0.5}, "gt": None},
    }
    outcome = FuseOutcome(summary, [Path("o/mesh_mde.ply"), Path("o/mesh_gp_variance.ply")], Path("o/metrics.json"))
    lines = outcome.report(0.05)
    assert lines[0] == "skipped frame 3: no depth"
    assert lines[1] == "no surface above the weight threshold yet in: gt (no mesh written)"
    assert lines[2].startswith("3 of 4 frames fused; wrote 2 meshes and o/metrics.json (in ")
    assert lines[3:5] == ["wrote o/mesh_mde.ply", "wrote o/mesh_gp_variance.ply"]
    assert lines[5] == "F-score at 5 cm against the ground-truth mesh: mde 0.250, gp_variance 0.500"
