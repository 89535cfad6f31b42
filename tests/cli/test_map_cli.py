"""``gpdepth3d map`` from the command line: the recipes for both shared sequences exactly as written, and its errors.

`RECIPES` are the command lines docs/mapping.md (and the README) give, run from the repository root on
../shared/data through the CLI entry point; each writes into gpdepth3d_out/ (ignored by git).
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.cli import main

ROOT = Path(__file__).resolve().parents[2]

RECIPES = {
    "hololens": "gpdepth3d map --images ../shared/data/hololens/images --poses ../shared/data/hololens/poses_images.txt "
    "--intrinsics ../shared/data/hololens/K.txt --depth ../shared/data/hololens/depth "
    "--output gpdepth3d_out/map_hololens",
    "7scenes": "gpdepth3d map --images ../shared/data/7scenes --poses ../shared/data/7scenes --intrinsics 525,525,320,240 "
    "--depth ../shared/data/7scenes --depth-invalid 65535 "
    "--depth-intrinsics ../shared/data/7scenes/camera-intrinsics.txt --output gpdepth3d_out/map_7scenes",
}
FRAMES = {"hololens": 94, "7scenes": 60}
UNPOSED = (
    "gpdepth3d map --images ../shared/data/7scenes --frames 20 --intrinsics 525,525,320,240 "
    "--depth ../shared/data/7scenes --depth-invalid 65535 "
    "--depth-intrinsics ../shared/data/7scenes/camera-intrinsics.txt --output gpdepth3d_out/sfm_7scenes20",
    "gpdepth3d map --images ../shared/data/7scenes --frames 20 --points gpdepth3d_out/sfm_7scenes20/sparse "
    "--intrinsics 525,525,320,240 --output gpdepth3d_out/points_7scenes20",
)
"""The README's lines without poses: pycolmap SfM on 20 frames, then its model again through --points."""
MAP_FILES = ("mesh.ply", "cloud.ply", "mapper.json", "keyframes.npz", "volume.npz", "volume.json", "metrics.json")


def _lines(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8") if path.is_file() else ""
    return [line.strip() for line in re.findall(r"^gpdepth3d map [^\n]*", text, flags=re.M)]


def test_docs_give_the_recipes_as_tested():
    lines = _lines(ROOT / "docs" / "mapping.md")
    for recipe in RECIPES.values():
        assert recipe in lines
    for line in _lines(ROOT / "README.md"):  # the README's map lines on the shared data are these too
        if "../shared/data" in line:
            assert line.split("  #")[0].strip() in (*RECIPES.values(), *UNPOSED), line


@pytest.fixture()
def at_root(shared_data, models_dir, monkeypatch):
    if shared_data.resolve() != (ROOT.parent / "shared" / "data").resolve():
        pytest.skip("the recipes read ../shared/data from the repository root")
    monkeypatch.chdir(ROOT)
    return ROOT


@pytest.fixture(scope="session")
def models_dir():
    folder = ROOT.parent / "shared" / "models"
    if not (folder / "fast_depth_224.tflite").is_file():
        pytest.skip("FastDepth model not found in ../shared/models")
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(RECIPES))
def test_recipe_runs_as_written(name, at_root, capsys):
    from gpdepth3d.mapping.cloud import ColoredCloud
    from gpdepth3d.mapping.mapper import Mapper

    argv = shlex.split(RECIPES[name])[1:]
    out_dir = ROOT / argv[argv.index("--output") + 1]
    code = main(argv)
    out = capsys.readouterr()
    assert code == 0, out.err[-3000:]
    for file in MAP_FILES:
        assert (out_dir / file).is_file(), file
        assert f"wrote {out_dir.relative_to(ROOT)}/{file}" in out.out or f"wrote {out_dir / file}" in out.out, file
    summary = json.loads((out_dir / "metrics.json").read_text())
    assert summary["frames"] == FRAMES[name] and summary["frames_fused"] >= 0.9 * FRAMES[name]
    f_map, f_mde = summary["metrics"]["map"]["fscore"], summary["metrics"]["mde"]["fscore"]
    assert 0 < f_map <= 1 and 0 < f_mde <= 1
    assert f"F-score at 5 cm against the sensor depth: map {f_map:.3f}" in out.out
    assert summary["working_size"][0] == 320
    cloud = ColoredCloud.load_ply(out_dir / "cloud.ply")
    assert len(cloud) == summary["cloud_points"] > 0
    assert np.all(np.isfinite(cloud.sigma)) and np.all(cloud.sigma >= 0)
    mapper = Mapper.load(out_dir)
    assert len(mapper.keyframes) == summary["frames_fused"]
    print(f"{name}: F map {f_map:.3f}, MDE alone {f_mde:.3f}, {summary['wall_s']:.0f} s")


@pytest.mark.slow
def test_unposed_recipes_run_as_written(at_root, capsys):
    """SfM poses 20 frames (all registered, one piece, a scale with its sigma); --points maps its model again."""
    pytest.importorskip("pycolmap")
    for line in UNPOSED:
        argv = shlex.split(line)[1:]
        out_dir = ROOT / argv[argv.index("--output") + 1]
        assert main(argv) == 0, capsys.readouterr().err[-3000:]
        out = capsys.readouterr().out
        summary = json.loads((out_dir / "metrics.json").read_text())
        assert "registered 20 of 20 images in 1 piece(s)" in out
        piece = summary["pieces"]["pieces"][0]
        assert summary["frames_fused"] == 20 and piece["scale"]["sigma"] > 0
        assert (out_dir / "mesh.ply").is_file()
    assert summary["inputs"]["points"].endswith("sparse")


def _run(argv, capsys) -> tuple[int, str, str]:
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


class TestErrors:
    """Bad inputs: one line on stderr naming what is wrong, exit code 1, nothing written."""

    def test_inputs(self, shared_data, tmp_path, capsys):
        holo = shared_data / "hololens"
        base = [
            "map",
            "--images",
            str(holo / "images"),
            "--intrinsics",
            str(holo / "K.txt"),
            "--output",
            str(tmp_path / "o"),
        ]
        bad_tum = tmp_path / "traj.txt"
        bad_tum.write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 2\n")
        xyz = tmp_path / "points.txt"
        xyz.write_text("0 0 1\n1 0 2\n")
        cases = [
            (["--poses", str(tmp_path / "missing.txt")], "missing.txt: trajectory file not found"),
            (
                ["--poses", str(shared_data / "kitti_tiny" / "poses.txt")],
                "one pose per image in order (94 images), got 474 poses",
            ),
            (["--poses", str(holo / "poses.txt")], "got 373 poses"),
            (["--poses", str(bad_tum)], "line 2: quaternion of norm 2"),
            (["--poses", str(holo / "poses_images.txt"), "--intrinsics", "500,500,270"], "intrinsics"),
            (["--poses", str(holo / "poses_images.txt"), "--depth", str(tmp_path)], "depth: no files"),
            (["--poses", str(holo / "poses_images.txt"), "--stride", "0"], "stride: expected an integer >= 1"),
            (["--poses", str(holo / "poses_images.txt"), "--voxel-size", "0"], "--voxel-size"),
            (["--view"], "--view: expected --poses"),
            (["--points", str(xyz)], "points: expected a COLMAP model when no poses are given"),
            (["--poses", str(holo / "poses_images.txt"), "--points", str(tmp_path / "none.npz")], "none.npz"),
        ]
        for extra, message in cases:
            code, out, err = _run(base + extra, capsys)
            assert code == 1, (extra, out, err)
            lines = [line for line in err.splitlines() if line.startswith("gpdepth3d: error:")]
            assert len(lines) == 1 and message in lines[0], (extra, err)
            assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())

    def test_fuse_metric_samples(self, shared_data, tmp_path, capsys):
        for n in ("0", "-1"):
            code, _, err = _run(
                [
                    "fuse",
                    "--data",
                    str(shared_data / "7scenes"),
                    "--output",
                    str(tmp_path / "f"),
                    "--metric-samples",
                    n,
                ],
                capsys,
            )
            assert code == 1 and "--metric-samples: expected an integer >= 1" in err


@pytest.mark.slow
def test_view_and_fuse_print_f(shared_data, models_dir, tmp_path, capsys):
    """`map --view` serves the growing map and says where; `fuse` prints its F-scores."""
    holo = shared_data / "hololens"
    code, out, err = _run(
        [
            "map",
            "--images",
            str(holo / "images"),
            "--poses",
            str(holo / "poses_images.txt"),
            "--intrinsics",
            str(holo / "K.txt"),
            "--frames",
            "6",
            "--view",
            "--port",
            "0",
            "--view-duration",
            "0",
            "--models-dir",
            str(models_dir),
            "--output",
            str(tmp_path / "v"),
        ],
        capsys,
    )
    assert code == 0, err
    assert re.search(r"viewer running at http://127.0.0.1:\d+ \(the map appears as it grows\)", out)
    assert "F-score" not in out  # no depth given: no metrics
    assert json.loads((tmp_path / "v" / "metrics.json").read_text())["metrics"] is None
    code, out, err = _run(
        [
            "fuse",
            "--data",
            str(shared_data / "7scenes"),
            "--output",
            str(tmp_path / "f"),
            "--frames",
            "4",
            "--working-scale",
            "0.25",
            "--voxel-size",
            "0.05",
            "--metric-samples",
            "2000",
            "--models-dir",
            str(models_dir),
        ],
        capsys,
    )
    assert code == 0, err
    assert re.search(r"F-score at 5 cm against the ground-truth mesh: mde \d\.\d{3}", out)


def test_pose_choices_come_from_the_one_format_table(capsys):
    """`map --pose-format` offers exactly `auto` and the formats `gpdepth3d.io.poses` reads."""
    import typing

    from gpdepth3d.cli.map import Association, PoseFormat
    from gpdepth3d.io.poses import ASSOCIATIONS, POSE_FORMATS

    assert typing.get_args(PoseFormat) == ("auto", *POSE_FORMATS)
    assert typing.get_args(Association) == ASSOCIATIONS
    with pytest.raises(SystemExit):
        main(["map", "--help"])
    help_text = capsys.readouterr().out
    assert all(name in help_text for name in POSE_FORMATS)
