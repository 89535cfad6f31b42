"""One CLI vocabulary: --output, --mde NAME|FILE, --preset (+ --gp.FIELD), --frames; no other spelling.

Also: `complete --rgb IMAGE --mde fastdepth` runs the network itself, the compile notice, and that every
command ends by saying what it wrote.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.cli import main
from gpdepth3d.cli._options import PRESETS, normalize_argv
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.mapping.mapper_config import MAPPER_GP
from gpdepth3d.gp.engine import EngineConfig

ROOT = Path(__file__).resolve().parents[2]


class TestNormalizeArgv:
    def test_preset_moves_behind_the_command(self):
        argv = normalize_argv(["complete", "--mde", "m.npy", "--preset", "paper", "--gp.fit", "--output", "o"])
        assert argv == ["complete", "paper", "--mde", "m.npy", "--gp.fit", "--output", "o"]
        assert normalize_argv(["batch", "--data", "d", "--preset=residual"]) == ["batch", "residual", "--data", "d"]

    def test_other_commands_and_tokens_are_left_alone(self):
        assert normalize_argv(["view", "--posterior", "--out"]) == ["view", "--posterior", "--out"]
        assert normalize_argv(["complete", "--output", "--out"]) == ["complete", "--output", "--out"]
        assert normalize_argv([]) == []
        assert normalize_argv(["--help"]) == ["--help"]
        assert normalize_argv(["demo", "--output", "x"]) == ["demo", "--output", "x"]

    @pytest.mark.parametrize(
        "argv, got",
        [
            (["complete", "--preset", "nope"], "nope"),
            (["complete", "--preset"], "nothing"),
            (["complete", "--preset", "paper", "--preset", "residual"], "paper and residual"),
        ],
    )
    def test_bad_presets(self, argv, got):
        with pytest.raises(InvalidInputError, match="--preset") as info:
            normalize_argv(argv)
        assert got in str(info.value)

    def test_presets_are_the_library_configs(self):
        assert PRESETS == {
            "default": DepthGPConfig(),
            "paper": DepthGPConfig.paper(),
            "residual": DepthGPConfig.residual(),
        }


def _spy(monkeypatch, module, name):
    """Replaces a command by a recorder of the arguments the parser gave it."""
    calls = []
    original = getattr(module, name)

    @functools.wraps(original)
    def record(*args, **kwargs):
        calls.append(kwargs)

    monkeypatch.setattr(module, name, record)
    return calls


class TestEverySubcommand:
    """The same spelling means the same thing in every command, with the library's defaults."""

    def test_output_everywhere_and_no_other_spelling(self, monkeypatch, capsys):
        import gpdepth3d.cli.batch as batch
        import gpdepth3d.cli.complete as complete
        import gpdepth3d.cli.demo as demo
        import gpdepth3d.cli.eval as eval_
        import gpdepth3d.cli.fuse as fuse

        spies = {
            "complete": _spy(monkeypatch, complete, "complete_command"),
            "demo": _spy(monkeypatch, demo, "demo_command"),
            "eval": _spy(monkeypatch, eval_, "eval_command"),
            "fuse": _spy(monkeypatch, fuse, "fuse_command"),
            "batch": _spy(monkeypatch, batch, "batch_command"),
        }
        required = {
            "complete": ["--mde", "m.npy"],
            "demo": [],
            "eval": ["--data", "d"],
            "fuse": ["--data", "d"],
            "batch": ["--data", "d"],
        }
        for command, calls in spies.items():
            assert main([command, *required[command], "--output", "new"]) == 0
            assert Path(calls[-1]["output"]) == Path("new")  # complete takes a str: "out/" names a folder
            for old in ("--out", "--output-dir"):  # spellings of earlier versions are refused, in one line
                n = len(calls)
                assert main([command, *required[command], old, "old"]) == 1 and len(calls) == n
                err = capsys.readouterr().err.strip().splitlines()
                assert len(err) == 1 and f"unrecognised {old} old" in err[0]

    def test_gp_preset_defaults_and_frames(self, monkeypatch, capsys):
        import gpdepth3d.cli.batch as batch
        import gpdepth3d.cli.complete as complete
        import gpdepth3d.cli.fuse as fuse

        for module, name, command, required in (
            (complete, "complete_command", "complete", ["--mde", "m.npy", "--output", "o"]),
            (fuse, "fuse_command", "fuse", ["--data", "d"]),
            (batch, "batch_command", "batch", ["--data", "d", "--output", "o"]),
        ):
            calls = _spy(monkeypatch, module, name)
            # the library's default model; fuse's is the Mapper's (the same model with the stationary variance)
            default = MAPPER_GP if command == "fuse" else DepthGPConfig()
            assert main([command, *required]) == 0
            assert calls[-1]["gp"] == default
            for preset, config in PRESETS.items():
                assert main([command, *required, "--preset", preset, "--gp.fit"]) == 0
                assert calls[-1]["gp"] == (default if preset == "default" else config).replace(fit=True)
            if command != "fuse":  # the engine is an option of its own, not a field of the model
                assert main([command, *required, "--preset", "paper", "--engine.name", "exact"]) == 0
                assert calls[-1]["engine"] == EngineConfig(name="exact") and calls[-1]["gp"] == PRESETS["paper"]
                assert main([command, *required, "--engine.lattice-stride", "2"]) == 0
                assert calls[-1]["engine"] == EngineConfig(lattice_stride=2)
        calls = _spy(monkeypatch, batch, "batch_command")
        assert main(["batch", "--data", "d", "--output", "o", "--frames", "3"]) == 0
        assert calls[-1]["frames"] == 3 and calls[-1]["workers"] is None  # None: run_batch's default, the CPU count
        for old in (["--limit", "4"], ["--engine", "exact"]):
            assert main(["batch", "--data", "d", "--output", "o", *old]) == 1
            assert f"unrecognised {' '.join(old)}" in capsys.readouterr().err

    def test_help_lists_the_new_spellings_only(self, capsys):
        for command, new, old in (
            ("batch", "--output", "--output-dir"),
            ("demo", "--output", "--output-dir"),
            ("fuse", "--output", "--out "),
            ("complete", "--gp.fit", "--model.fit"),
        ):
            with pytest.raises(SystemExit):
                main([command, "--help"])
            text = capsys.readouterr().out
            assert new in text and old not in text, command


@pytest.mark.slow
class TestFrontEndOnTheCommandLine:
    def test_complete_runs_fastdepth_on_an_rgb_image(self, shared_data, tmp_path, capsys):
        """`complete --rgb IMAGE --mde fastdepth --sparse POINTS` on 7-Scenes: the network's depth is the MDE."""
        pytest.importorskip("ai_edge_litert", reason="the [tflite] extra (ai-edge-litert) runs FastDepth")
        import gpdepth3d as g
        from gpdepth3d.completion.complete import DepthPosterior
        from gpdepth3d.io import load_depth, load_rgb

        models = ROOT.parent / "shared" / "models"
        if not (models / "fast_depth_224.tflite").is_file():
            pytest.skip("FastDepth model not in ../shared/models")
        rgb = shared_data / "7scenes" / "frame-000000.color.jpg"
        gt = load_depth(shared_data / "7scenes" / "frame-000000.depth.png", png_scale=1e-3, invalid_value=65535)
        net_depth = g.load_frontend("fastdepth", models_dir=models)(load_rgb(rgb))
        rng = np.random.default_rng(0)
        v, u = np.nonzero(gt > 0)
        pick = rng.choice(v.size, 200, replace=False)
        scale = net_depth.shape[1] / gt.shape[1]
        pts = np.stack([u[pick] * scale, v[pick] * scale, gt[v[pick], u[pick]]], 1)
        np.savetxt(tmp_path / "points.txt", pts)
        code = main(
            [
                "complete",
                "--rgb",
                str(rgb),
                "--mde",
                "fastdepth",
                "--models-dir",
                str(models),
                "--sparse",
                str(tmp_path / "points.txt"),
                "--output",
                str(tmp_path / "f0"),
            ]
        )
        out = capsys.readouterr().out
        assert code == 0, out
        post = DepthPosterior.load(tmp_path / "f0.npz")
        np.testing.assert_allclose(post.mde, net_depth, rtol=1e-6)  # the network ran inside the command
        assert f"wrote {len(list(tmp_path.glob('f0*')))} files in {tmp_path.resolve()}" in out
        for name in ("f0.npz", "f0_mean.png", "f0_std.png", "f0_depth_preview.png", "f0_sigma_preview.png"):
            assert (tmp_path / name).is_file() and f"wrote {tmp_path / name}" in out


class TestCompileNotice:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_printed_on_a_cold_cache_and_not_on_a_warm_one(self, tmp_path):
        """Two `complete` runs with an empty numba cache folder: the first compiles and says so, the second not."""
        np.save(tmp_path / "mde.npy", np.full((24, 32), 2.0))
        np.savetxt(tmp_path / "p.txt", [[3, 4, 2.1], [20, 10, 1.9], [30, 20, 2.05]])
        env = dict(
            os.environ,
            NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"),
            PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        )
        cmd = [
            sys.executable,
            "-m",
            "gpdepth3d.cli",
            "complete",
            "--mde",
            str(tmp_path / "mde.npy"),
            "--sparse",
            str(tmp_path / "p.txt"),
            "--output",
            str(tmp_path / "o"),
            "--no-preview",
            "--preset",
            "residual",
        ]
        first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
        assert first.returncode == 0, first.stderr
        assert first.stdout.splitlines()[0] == "compiling kernels (once, ~1 min) ..."
        assert first.stdout.count("compiling kernels") == 1
        second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
        assert second.returncode == 0, second.stderr
        assert "compiling kernels" not in second.stdout and "wrote" in second.stdout
