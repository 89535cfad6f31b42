"""`read_frame_inputs`: a frame's files read, checked against each other and converted to metres before any work.

Millimetre 16-bit PNGs (Kinect, HoloLens, 7-Scenes) read at KITTI's default 1/256 m are 3.9 times too
far: refused with the option that says their unit, whichever of --sparse, --gt or --mde they are.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gpdepth3d import cli
from gpdepth3d.completion.frame_inputs import PNGScales, read_frame_inputs
from gpdepth3d.errors import InvalidDepthError, InvalidInputError, ShapeError

H, W = 24, 32


@pytest.fixture(scope="module")
def frame(tmp_path_factory) -> Path:
    """A 24x32 scene 2-3 m away: the MDE in metres (.npy), the truth and a sparse map as millimetre PNGs."""
    t = tmp_path_factory.mktemp("frame")
    rng = np.random.default_rng(0)
    truth = 2.0 + rng.random((H, W))
    np.save(t / "mde.npy", truth * 0.9)
    mm = np.round(truth * 1000).astype(np.uint16)
    cv2.imwrite(str(t / "gt_mm.png"), mm)
    sparse = np.zeros_like(mm)
    sparse[::4, ::4] = mm[::4, ::4]
    cv2.imwrite(str(t / "sparse_mm.png"), sparse)
    cv2.imwrite(str(t / "mde_mm.png"), np.round(truth * 900).astype(np.uint16))
    kitti = np.zeros_like(mm)
    kitti[::4, ::4] = np.round(truth[::4, ::4] * 256).astype(np.uint16)
    cv2.imwrite(str(t / "sparse_kitti.png"), kitti)
    np.savetxt(t / "points.txt", np.stack([np.arange(0, W, 4), np.full(W // 4, 5), truth[5, ::4]], 1))
    cv2.imwrite(str(t / "sparse_big.png"), np.ones((36, 54), np.uint16) * 500)
    return t


@pytest.mark.parametrize(
    "kwargs, option",
    [
        ({"sparse": "sparse_mm.png"}, "--sparse-png-scale 0.001"),
        ({"sparse": "points.txt", "gt": "gt_mm.png"}, "--gt-png-scale 0.001"),
        ({"mde": "mde_mm.png", "sparse": "points.txt"}, "--mde-png-scale 0.001"),
    ],
)
def test_millimetre_pngs_are_refused_with_the_option_that_fixes_them(frame, kwargs, option):
    args = {"mde": "mde.npy", **kwargs}
    mde = str(frame / args.pop("mde"))
    with pytest.raises(InvalidDepthError, match=option) as info:
        read_frame_inputs(mde, **{k: frame / v for k, v in args.items()})
    assert "--depth-scale 0.001" in str(info.value) and "3.91" in str(info.value)


def test_the_unit_given_reads_millimetres_right(frame):
    for scales in (PNGScales(depth=0.001), PNGScales(sparse=0.001, gt=0.001)):
        inputs = read_frame_inputs(
            str(frame / "mde.npy"), sparse=frame / "sparse_mm.png", gt=frame / "gt_mm.png", png_scales=scales
        )
        assert 2.0 <= np.median(inputs.measurements.depth) <= 3.0
        assert 2.0 <= np.median(inputs.gt[inputs.gt > 0]) <= 3.0


def test_kitti_pngs_pass_at_the_default_scale(frame):
    inputs = read_frame_inputs(str(frame / "mde.npy"), sparse=frame / "sparse_kitti.png")
    assert 2.0 <= np.median(inputs.measurements.depth) <= 3.0


def test_a_sparse_map_of_another_size_names_both_sizes_the_right_way_round(frame):
    with pytest.raises(ShapeError, match="--sparse") as info:
        read_frame_inputs(str(frame / "mde.npy"), sparse=frame / "sparse_big.png")
    assert info.value.expected.startswith("a sparse depth map of the MDE's size 32x24") and info.value.got == "54x36"


def test_a_mistyped_front_end_is_named_by_its_option_with_a_suggestion(frame):
    with pytest.raises(InvalidInputError, match=r"--mde: .*fastdeph \(did you mean fastdepth\?\)"):
        read_frame_inputs("fastdeph", sparse=frame / "points.txt", rgb=frame / "gt_mm.png")


def test_cli_millimetre_sparse_png_is_one_line_and_depth_scale_fixes_it(frame, tmp_path, capsys):
    argv = ["complete", "--mde", str(frame / "mde.npy"), "--sparse", str(frame / "sparse_mm.png")]
    argv += ["--output", str(tmp_path / "o"), "--no-preview", "--no-png", "--engine.name", "exact"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--sparse-png-scale 0.001" in err
    assert not (tmp_path / "o.npz").exists()
    assert cli.main(argv + ["--depth-scale", "0.001"]) == 0
    mean = np.load(tmp_path / "o.npz")["mean"]
    assert 1.8 <= float(np.median(mean)) <= 3.2


def test_cli_bad_depth_scale_is_named(frame, tmp_path, capsys):
    argv = ["complete", "--mde", str(frame / "mde.npy"), "--sparse", str(frame / "sparse_mm.png")]
    assert cli.main(argv + ["--output", str(tmp_path / "o"), "--depth-scale", "-1"]) == 1
    assert "--depth-scale" in capsys.readouterr().err
