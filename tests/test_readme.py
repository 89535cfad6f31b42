"""The README's Python quick start runs exactly as written (from the repository root, on ../shared)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 250


def test_command_one_installs_what_every_line_needs():
    """Command 1 runs scripts/install.sh, which installs the [all] extra (and libusb for Open3D) by default."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    first_block = re.search(r"```bash\n(.*?)```", text, flags=re.S).group(1)
    assert "bash scripts/install.sh && gpdepth3d demo" in first_block
    script = (ROOT / "scripts" / "install.sh").read_text(encoding="utf-8")
    assert 'extra="${1:-all}"' in script and "libusb-1.0-0" in script and '-e ".[$extra]"' in script


def test_readme_has_the_quick_start_and_the_own_arrays_blocks():
    blocks = _python_blocks((ROOT / "README.md").read_text(encoding="utf-8"))
    assert len(blocks) == 2 and "g.complete(" in blocks[0]
    assert "g.SparseDepth(" in blocks[1] and "image_size=" in blocks[1] and "backproject_posterior" in blocks[1]


def test_own_arrays_recipe_runs_as_written(shared_data, monkeypatch):
    """SparseDepth from your own arrays (image_size: the MDE map's height, width) and a camera from a KITTI calib."""
    if shared_data.resolve() != (ROOT.parent / "shared" / "data").resolve():
        pytest.skip("the recipe reads ../shared/data from the repository root")
    block = _python_blocks((ROOT / "README.md").read_text(encoding="utf-8"))[1]
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(compile(block, "README.md own arrays", "exec"), scope)  # noqa: S102 - the README's own code
    post, camera = scope["post"], scope["camera"]
    assert post.shape == scope["rgb"].shape[:2] and len(post.sparse) == 3
    assert camera.fx == pytest.approx(707.0493) and (ROOT / "gpdepth3d_out" / "own_arrays.ply").is_file()


def test_core_install_names_what_needs_tflite():
    """The README's core paragraph says which commands and recipes need the [tflite] extra (FastDepth)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    core = text[text.index("`pip install -e .` alone") :].split("\n\n")[0]
    assert "[tflite]" in core and "--mde fastdepth" in core and "eval" in core


@pytest.mark.slow
def test_quick_start_runs_as_written(shared_data, monkeypatch):
    if shared_data.resolve() != (ROOT.parent / "shared" / "data").resolve():
        pytest.skip("the quick start reads ../shared/data from the repository root")
    if not (ROOT.parent / "shared" / "models" / "rtmonodepth_s_ms_640_192.onnx").is_file():
        pytest.skip("RT-MonoDepth-S model not found in ../shared/models")
    block = _python_blocks((ROOT / "README.md").read_text(encoding="utf-8"))[0]
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(compile(block, "README.md quick start", "exec"), scope)  # noqa: S102 - the README's own code
    post = scope["post"]
    assert post.mean.shape == (125, 414) and (post.mean > 0).all()  # the loop's last frame, at 1/3
    assert (ROOT / "gpdepth3d_out" / "kitti0.npz").is_file()
    assert (ROOT / "gpdepth3d_out" / "kitti0_mean.png").is_file()


def _command_lines(text: str) -> list[str]:
    lines, inside = [], False
    for raw in text.splitlines():
        if raw.startswith("```"):
            inside = raw.strip() == "```bash" if not inside else False
            continue
        line = raw.split("  #")[0].strip()
        if inside and line.startswith("gpdepth3d "):
            lines.append(line)
    return lines


def test_readme_command_lines_are_found():
    lines = _command_lines((ROOT / "README.md").read_text(encoding="utf-8"))
    assert {line.split()[1] for line in lines} >= {"demo", "complete", "view", "eval", "fuse", "batch"}


@pytest.mark.slow
def test_readme_command_lines_run_as_written(shared_data, monkeypatch, capsys):
    """Each `gpdepth3d ...` line of the README through the CLI entry point, in order, from the repository root
    (`fuse`'s line is run by tests/mapping/test_mapping.py, `map`'s by tests/cli/test_map_cli.py; `batch --help` exits 0 through argparse/tyro)."""
    import shlex

    from gpdepth3d.cli import main

    if shared_data.resolve() != (ROOT.parent / "shared" / "data").resolve():
        pytest.skip("the README's command lines read ../shared/data from the repository root")
    monkeypatch.chdir(ROOT)
    for line in _command_lines((ROOT / "README.md").read_text(encoding="utf-8")):
        argv = shlex.split(line)[1:]
        if argv[0] in ("fuse", "map"):  # run (and their outputs checked) by test_mapping.py / test_map_cli.py
            continue
        try:
            code = main(argv)
        except SystemExit as exc:  # --help
            code = exc.code
        out = capsys.readouterr()
        assert code in (0, None), f"{line}\n{out.out[-2000:]}\n{out.err[-2000:]}"
        assert "deprecated" not in out.err, line  # the README speaks the current vocabulary
        if argv[0] in ("demo", "complete", "eval", "batch"):  # every command says what it wrote and where
            assert "wrote" in out.out, line
    out_dir = ROOT / "gpdepth3d_out"
    assert (out_dir / "k0.npz").is_file()
    for name in ("k0_depth_preview.png", "k0_sigma_preview.png", "ibims.npz", "ibims_error_preview.png"):
        assert (out_dir / name).is_file(), name
    assert sorted(p.name for p in (out_dir / "batch").glob("*.npz")) == sorted(
        f"{p.stem}.npz" for p in sorted((ROOT.parent / "shared" / "data" / "kitti_tiny" / "image_02").glob("*.png"))[:3]
    )


RETIRED = {"--out", "--output-dir", "--limit", "--model", "--engine"}
"""Spellings of earlier versions the CLI refuses; the README must not teach them."""


def test_readme_lines_use_one_vocabulary():
    """No retired spelling anywhere in the README; --output wherever a command writes."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert not [w for w in re.findall(r"`?(--[a-z][a-z.-]*)", text) if w in RETIRED or w.startswith("--model.")]
    for line in _command_lines(text):
        words = line.split()
        assert not any(w.startswith("--model.") for w in words), line
        if words[1] in ("complete", "batch", "fuse"):
            assert "--output" in words, line


@pytest.mark.slow
def test_readme_picture_is_drawn_from_real_data(shared_data, tmp_path):
    """docs/make_images.py draws the README's picture from KITTI with the default model."""
    import importlib.util

    from PIL import Image

    models = ROOT.parent / "shared" / "models"
    if not (models / "rtmonodepth_s_ms_640_192.onnx").is_file():
        pytest.skip("RT-MonoDepth-S model not found in ../shared/models")
    spec = importlib.util.spec_from_file_location("make_images", ROOT / "docs" / "make_images.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    path = module.draw(shared_data, models, tmp_path / "picture.png")
    with Image.open(path) as drawn, Image.open(ROOT / "docs" / "images" / "kitti_completion.png") as shipped:
        assert drawn.size == shipped.size
    assert "docs/images/kitti_completion.png" in (ROOT / "README.md").read_text(encoding="utf-8")
