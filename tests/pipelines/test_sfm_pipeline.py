"""Maps from SfM and SLAM output: `map` without poses (pycolmap), given points with --poses, pieces mapped apart."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gpdepth3d.cli import main

SEVEN = ["--intrinsics", "525,525,320,240", "--depth-invalid", "65535"]


@pytest.fixture(scope="module")
def seven(shared_data):
    pytest.importorskip("pycolmap")
    from pathlib import Path

    folder = shared_data / "7scenes"
    if not (folder / "frame-000000.color.jpg").is_file():
        pytest.skip("7-Scenes frames not found in the shared data")
    if not (Path(__file__).resolve().parents[2].parent / "shared" / "models" / "fast_depth_224.tflite").is_file():
        pytest.skip("FastDepth model not found in ../shared/models")
    return folder


def _depth(folder):
    return ["--depth", str(folder), "--depth-intrinsics", str(folder / "camera-intrinsics.txt")]


@pytest.mark.slow
def test_images_alone_register_scale_and_map(seven, tmp_path, capsys):
    """12 frames: pycolmap may leave a frame out, and a piece needs `PieceRule`'s 8 frames to be mapped."""
    out = tmp_path / "map"
    code = main(["map", "--images", str(seven), "--frames", "12", *SEVEN, *_depth(seven), "--output", str(out)])
    text = capsys.readouterr().out
    assert code == 0
    summary = json.loads((out / "metrics.json").read_text())
    pieces = summary["pieces"]
    assert pieces["frames"] == 12 and pieces["registered"] == 12 and len(pieces["pieces"]) == 1
    scale = pieces["pieces"][0]["scale"]
    assert scale["sigma"] > 0 and scale["interval"][0] <= scale["scale"] <= scale["interval"][1]
    assert "registered 12 of 12 images" in text and f"scale {scale['scale']:.4f}" in text
    assert summary["frames_fused"] == 12 and summary["metrics"]["map"]["fscore"] > 0
    assert (out / "sparse" / "0" / "points3D.bin").is_file() and (out / "mesh.ply").is_file()


@pytest.mark.slow
def test_restarted_reconstruction_is_mapped_as_pieces(seven, tmp_path, capsys):
    """Two COLMAP models of two stretches (a SLAM that lost tracking): two maps, each with its own scale.

    Each stretch has 12 frames, so that its piece keeps `PieceRule`'s 8 should pycolmap leave some out. A
    third model of a few frames, inside the first stretch, is not mapped (`PieceRule`: too few
    frames for a trusted scale), says so, and its frames are not counted twice as registered.
    """
    from gpdepth3d.datasets.posed import IMAGE_SUFFIXES, list_files, read_intrinsics
    from gpdepth3d.mapping.points.colmap_sfm import reconstruct_sequence

    from gpdepth3d.io.poses import read_colmap_model

    files = list_files(seven, IMAGE_SUFFIXES, "color", "images")
    camera = read_intrinsics("525,525,320,240", 640, 480)
    sizes = []
    for k, part in enumerate((files[:12], files[40:52], files[2:7])):
        (model,) = reconstruct_sequence(part, camera, tmp_path / f"sfm{k}")
        shutil.copytree(model, tmp_path / "sparse" / str(k))
        sizes.append(len(read_colmap_model(model).images))
    assert min(sizes[:2]) >= 4 and 3 <= sizes[2] < 8
    out = tmp_path / "map"
    argv = ["map", "--images", str(seven), "--points", str(tmp_path / "sparse"), *SEVEN, *_depth(seven)]
    assert main([*argv, "--output", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"registered {sizes[0] + sizes[1]} of 60 images in 3 piece(s)" in text
    assert f"piece 2 of {sizes[2]} frames not mapped, scale " in text and "fewer than 8 frames" in text
    first, second = (json.loads((f / "metrics.json").read_text()) for f in (out, out / "piece1"))
    assert not (out / "piece2").exists()
    assert second["piece"] == 1 and sorted([first["frames_fused"], second["frames_fused"]]) == sorted(sizes[:2])
    rows = first["pieces"]["pieces"]
    assert [r["error"] is None for r in rows] == [True, True, False] and rows[2]["frames_fused"] == 0
    starts = sorted(p["first"] for p in rows[:2])
    assert starts[0] <= files[11].name and files[40].name <= starts[1] <= files[51].name
    assert all(p["scale"]["scale"] > 0 for p in rows)


@pytest.mark.slow
def test_world_points_with_sigma_and_poses(seven, tmp_path, capsys):
    """An NPZ of world points with sigma (here: lifted from frame 0's Kinect depth) goes in with the poses."""
    from gpdepth3d.camera import PinholeCamera, transform_points
    from gpdepth3d.io import load_depth

    depth = load_depth(seven / "frame-000000.depth.png", png_scale=1e-3, invalid_value=65535)
    camera = PinholeCamera.from_K(np.loadtxt(seven / "camera-intrinsics.txt"), 640, 480)
    pts, _ = camera.backproject(depth)
    pts = pts[:: max(1, len(pts) // 2000)]
    world = transform_points(np.loadtxt(seven / "frame-000000.pose.txt"), pts)
    np.savez(tmp_path / "points.npz", xyz=world, sigma=np.full(len(world), 0.01))
    out = tmp_path / "map"
    argv = ["map", "--images", str(seven), "--poses", str(seven), "--points", str(tmp_path / "points.npz")]
    assert main([*argv, "--frames", "5", *SEVEN, *_depth(seven), "--output", str(out)]) == 0
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["inputs"]["points"].endswith("points.npz") and summary["frames_fused"] == 5
    assert summary["sparse_points_per_frame_median"] > 100
