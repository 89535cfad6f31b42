"""Tests of gpdepth3d.evaluation.evaluation: methods, protocols, tables, files, and an end-to-end run."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.datasets import Frame
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.evaluation.evaluation import (
    METHODS,
    MethodSuite,
    draw_sparse,
    evaluate,
    level_label,
    markdown_table,
    plot_rmse_vs_level,
    protocol_levels,
    relative_residual,
    summarize,
    write_csv,
)
from gpdepth3d.cli.eval import eval_command
from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.io import write_json
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.mde import ArrayMDE
from gpdepth3d.sampling import sample_uniform


def _room(h=24, w=32):
    """A tiny 'room': a tilted wall at 2-4 m and a near box, with an MDE that is off by 20 %."""
    v, u = np.mgrid[0:h, 0:w]
    gt = 2.0 + 2.0 * u / w
    gt[8:16, 10:20] = 1.5
    mde = 1.2 * gt + 0.1 * np.sin(u / 3.0)
    rgb = np.zeros((h, w, 3), np.uint8)
    return gt, mde, rgb


class TestMethods:
    @pytest.mark.parametrize("method", METHODS)
    def test_each_method_runs(self, method):
        gt, mde, _ = _room()
        sparse = sample_uniform(gt, n=40, rng=0)
        suite = MethodSuite(
            residual=DepthGPConfig.residual(lengthscale=8.0),
            balanced=DepthGPConfig.paper(),
            engine=EngineConfig(name="exact"),
            relative=DepthGPConfig.residual(lengthscale=8.0),
            balanced_factor=0.5,
        )
        out = suite.run(method, mde, sparse)
        assert out.mean.shape == gt.shape and np.all(np.isfinite(out.mean))
        err = np.sqrt(np.mean((out.mean - gt) ** 2))
        mde_err = np.sqrt(np.mean((mde - gt) ** 2))
        if method == "mde":
            assert err == pytest.approx(mde_err)
        elif method in ("mde_scale", "gp_residual", "gp_relative"):
            assert err < 0.6 * mde_err  # the 20 % scale error is removed
        if method.startswith("gp_"):
            assert out.variance.shape == gt.shape and np.all(out.variance > 0)
        if method == "gp_default_fit":  # the default model, but fitted: another posterior
            fixed = suite.run("gp_default", mde, sparse)
            assert not np.allclose(out.mean, fixed.mean)
        with pytest.raises(InvalidInputError):
            suite.run("nothing", mde, sparse)

    def test_relative_residual_interpolates_points(self):
        gt, mde, _ = _room()
        sparse = sample_uniform(gt, n=60, rng=1).with_sigma(1e-3)
        completer = DepthCompleter(DepthGPConfig.residual(lengthscale=6.0, sigma_meas=1e-4))
        mean, var = relative_residual(mde, sparse, completer, white=0.0)
        r, c = sparse.v.astype(int), sparse.u.astype(int)
        np.testing.assert_allclose(mean[r, c], sparse.depth, atol=5e-3)
        _, var_w = relative_residual(mde, sparse, completer, white=0.1)
        assert np.all(var_w - var >= (mde * 0.1) ** 2 * (1 - 1e-9))  # white term added on top
        with pytest.raises(InvalidInputError):
            relative_residual(mde, sparse, DepthCompleter(DepthGPConfig.paper()))
        with pytest.raises(InvalidInputError):
            relative_residual(mde, sparse, completer, white=-1)


class TestProtocols:
    def test_levels_and_labels(self):
        assert protocol_levels("uniform", None) == [50.0, 200.0, 500.0]
        assert len(protocol_levels("density", None)) == 8
        assert protocol_levels("uniform", [7]) == [7.0]
        assert level_label("density", 1 / 16) == "1/16" and level_label("density", 1.0) == "1x"
        assert level_label("uniform", 200) == "200 pts"

    def test_draw(self):
        gt, _, _ = _room()
        avail = SparseDepth.from_depth_map(gt)
        rng = np.random.default_rng(0)
        assert len(draw_sparse("uniform", 30, avail, rng=rng)) == 30
        assert len(draw_sparse("density", 0.5, avail, rng=rng)) == avail.depth.size // 2
        hb = draw_sparse("hband", 30, avail, rng=rng)
        assert np.all(hb.v >= 12)
        vb = draw_sparse("vband", 30, avail, rng=rng)
        assert np.all(vb.u < 16)
        beams = (avail.v // 2).astype(int)
        sl = draw_sparse("scanlines", 2, avail, rng=rng, beams=beams)
        assert len(sl) == int(np.sum(beams % 2 == 0))
        with pytest.raises(InvalidInputError):
            draw_sparse("scanlines", 2, avail, rng=rng)
        with pytest.raises(InvalidInputError):
            draw_sparse("spiral", 2, avail, rng=rng)


class TestEvaluateAndOutputs:
    def _rows(self):
        gt, mde, rgb = _room()
        frames = [Frame(name=f"f{i}", rgb=rgb, depth=gt) for i in range(2)]
        suite = MethodSuite(residual=DepthGPConfig.residual(lengthscale=8.0))
        return evaluate(
            frames,
            ArrayMDE(mde),
            protocols=("uniform", "hband"),
            levels={"uniform": [20, 60], "hband": [20]},
            methods=("mde", "mde_scale", "gp_residual"),
            suite=suite,
            resolution=1.0,
            progress=False,
        )

    def test_rows_and_summary(self):
        rows = self._rows()
        assert len(rows) == 2 * 3 * 3
        summary = summarize(rows)
        assert len(summary) == 3 * 3
        by = {(s["protocol"], s["level"], s["method"]): s for s in summary}
        assert by[("uniform", 60.0, "gp_residual")]["rmse"] < by[("uniform", 60.0, "mde")]["rmse"]
        assert math.isnan(by[("uniform", 60.0, "mde")]["nll"])  # no variance
        assert 0 < by[("uniform", 60.0, "gp_residual")]["coverage_2sigma"] <= 1
        assert by[("uniform", 20.0, "mde")]["frames"] == 2
        md = markdown_table(summary)
        assert md.count("\n") == len(summary) + 1 and "gp_residual" in md

    def test_files(self, tmp_path: Path):
        rows = self._rows()
        summary = summarize(rows)
        p = write_csv(summary, tmp_path / "s.csv")
        with open(p) as f:
            read = list(csv.DictReader(f))
        assert len(read) == len(summary) and float(read[0]["rmse"]) == pytest.approx(summary[0]["rmse"])
        j = write_json(tmp_path / "s.json", {"summary": summary})
        loaded = json.loads(j.read_text())
        assert loaded["summary"][0]["nll"] is None  # NaN written as null
        png = plot_rmse_vs_level(summary, "uniform", tmp_path / "plot.png")
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporaries

    def test_bad_arguments(self):
        gt, mde, rgb = _room()
        frames = [Frame(name="f", rgb=rgb, depth=gt)]
        with pytest.raises(InvalidInputError):
            evaluate(frames, ArrayMDE(mde), protocols=("nope",), progress=False)
        with pytest.raises(InvalidInputError):
            evaluate(frames, ArrayMDE(mde), methods=("nope",), progress=False)


class TestEvalCommand:
    def test_two_frames_end_to_end(self, shared_data, tmp_path, capsys):
        pytest.importorskip("ai_edge_litert")
        data = shared_data / "7scenes"
        if not (shared_data.parent / "models" / "fast_depth_224.tflite").is_file():
            pytest.skip("FastDepth model not found")
        out = tmp_path / "eval"
        summary = eval_command(
            data,
            mde="fastdepth",
            protocol="uniform",
            points="40,150",
            output=out,
            frames=2,
            stride=30,
            resolution=0.25,
            progress=False,
            methods="mde,mde_scale,ip_basic,gp_balanced,gp_residual,gp_relative",
        )
        for name in ("results.csv", "summary.csv", "results.json", "summary.md", "rmse_uniform.png", "qualitative.png"):
            assert (out / name).is_file(), name
        printed = capsys.readouterr().out  # the CLI prints the table the library wrote to summary.md
        table, wrote = printed.strip().rsplit("\n", 1)
        assert table == (out / "summary.md").read_text().strip() == markdown_table(summary)
        assert wrote.startswith(f"wrote 6 files in {out.resolve()}: ") and "summary.md" in wrote  # and where
        result = json.loads((out / "results.json").read_text())
        assert result["frames"] == ["frame-000000", "frame-000150"]
        assert len(result["rows"]) == 2 * 2 * 6
        by = {(s["level"], s["method"]): s for s in summary}
        mde = by[(150.0, "mde")]["rmse"]
        assert 300 < mde < 900  # FastDepth on 7-Scenes
        assert by[(150.0, "gp_residual")]["rmse"] < 0.8 * mde
        assert by[(150.0, "gp_relative")]["rmse"] < 0.8 * mde

    def test_bad_arguments(self, shared_data, tmp_path):
        data = shared_data / "7scenes"
        with pytest.raises(InvalidInputError):
            eval_command(data, protocol="zigzag", output=tmp_path)
        with pytest.raises(InvalidInputError):
            eval_command(data, points="a,b", output=tmp_path)
        with pytest.raises(InvalidInputError):
            eval_command(data, methods="mde,magic", output=tmp_path)
        with pytest.raises(InvalidInputError):
            eval_command(data, mde="midas", output=tmp_path)


class TestRunEvaluation:
    """The library's whole run (the CLI's `eval_command` only splits its comma lists and prints)."""

    def test_bad_arguments_before_any_work(self, tmp_path):
        from gpdepth3d.evaluation.evaluation import run_evaluation

        missing = tmp_path / "no_such_dataset"  # the arguments are checked before the dataset is opened
        for kwargs, name in (
            ({"protocols": ["zigzag"]}, "protocols"),
            ({"methods": ["mde", "magic"]}, "methods"),
            ({"levels": [50, float("nan")]}, "levels"),
            ({"levels": ["50"]}, "levels"),
            ({"stride": 0}, "stride"),
            ({"frames": 0}, "frames"),
            ({"mde": "midas"}, "mde"),
        ):
            with pytest.raises(InvalidInputError, match=name):
                run_evaluation(missing, output=tmp_path / "out", **kwargs)
        assert not (tmp_path / "out").exists()


class TestQualitativeChoice:
    def test_the_default_model_at_its_highest_level_first(self):
        from types import SimpleNamespace

        from gpdepth3d.evaluation.evaluation import qualitative_choice

        var, none = SimpleNamespace(variance=np.ones(1)), SimpleNamespace(variance=None)
        outputs = {
            ("uniform", 50, "gp_relative"): (var, None),
            ("uniform", 500, "gp_residual"): (var, None),
            ("uniform", 50, "gp_default"): (var, None),
            ("uniform", 200, "gp_default"): (var, None),
            ("uniform", 500, "mde"): (none, None),
        }
        assert qualitative_choice(outputs) == ("uniform", 200, "gp_default")
        del outputs[("uniform", 50, "gp_default")], outputs[("uniform", 200, "gp_default")]
        assert qualitative_choice(outputs) == ("uniform", 500, "gp_residual")
        assert qualitative_choice({("uniform", 500, "mde"): (none, None)}) is None
