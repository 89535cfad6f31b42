"""Tests of the MDE front-ends: FastDepth TFLite, torch module wrapper, precomputed arrays/files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.errors import DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.mde import MDE, ArrayMDE, FileMDE, check_rgb
from gpdepth3d.mde.base import finish_depth

RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)


class TestCheckRgb:
    def test_accepts_uint8(self):
        assert check_rgb(RGB).shape == (30, 40, 3)

    @pytest.mark.parametrize(
        "bad", [np.zeros((30, 40)), np.zeros((30, 40, 4), np.uint8), np.zeros((1, 40, 3), np.uint8)]
    )
    def test_shape(self, bad):
        with pytest.raises(ShapeError):
            check_rgb(bad)

    def test_dtype(self):
        with pytest.raises(InvalidInputError, match="uint8"):
            check_rgb(RGB.astype(np.float32))


class TestFinishDepth:
    def test_resizes_and_cleans(self):
        d = np.full((4, 4), 2.0)
        d[0, 0] = np.nan
        d[1, 1] = -1.0
        out = finish_depth(d, (4, 4))
        assert out[0, 0] == 0 and out[1, 1] == 0 and out[2, 2] == 2.0
        assert finish_depth(np.full((4, 4), 3.0), (8, 6)).shape == (8, 6)


class TestArrayMDE:
    def test_protocol_and_resize(self):
        mde = ArrayMDE(np.full((10, 20), 2.5))
        assert isinstance(mde, MDE)
        out = mde(RGB)
        assert out.shape == (30, 40) and np.allclose(out, 2.5)

    def test_bad_depth(self):
        with pytest.raises(InvalidInputError):
            ArrayMDE(np.zeros(5))


class TestFileMDE:
    def test_reads_named_file(self, tmp_path: Path):
        np.save(tmp_path / "f1.npy", np.full((15, 20), 4.0))
        mde = FileMDE(tmp_path)
        assert np.allclose(mde.predict(RGB, "f1"), 4.0)
        mde.current = "f1"
        assert mde(RGB).shape == (30, 40)

    def test_errors(self, tmp_path: Path):
        with pytest.raises(DataFormatError):
            FileMDE(tmp_path / "missing")
        with pytest.raises(InvalidInputError):
            FileMDE(tmp_path, pattern="x.npy")
        mde = FileMDE(tmp_path)
        with pytest.raises(InvalidInputError):
            mde(RGB)  # no current frame
        with pytest.raises(DataFormatError):
            mde.predict(RGB, "absent")


def _model_path(shared_data: Path) -> Path:
    p = shared_data.parent / "models" / "fast_depth_224.tflite"
    if not p.is_file():
        pytest.skip(f"FastDepth model not found at {p}")
    return p


class TestFastDepthTFLite:
    def test_real_frame_indoor_range(self, shared_data, seven_scenes_frame):
        pytest.importorskip("ai_edge_litert")
        from gpdepth3d.mde.tflite import FastDepthTFLite

        mde = FastDepthTFLite(_model_path(shared_data))
        rgb = seven_scenes_frame.rgb
        depth = mde(rgb)
        assert depth.shape == rgb.shape[:2] and depth.dtype == np.float64
        assert np.all(np.isfinite(depth)) and depth.min() >= 0 and depth.max() <= 255 * 0.0718
        assert 1.0 < np.median(depth) < 5.0  # indoors
        gt = seven_scenes_frame.depth
        valid = gt > 0
        # a real network: far better than a constant at the median, correlated with the truth
        assert np.corrcoef(depth[valid], gt[valid])[0, 1] > 0.5
        assert abs(mde.output_scale - 0.0717) < 1e-3
        # every core this process may use by default (the runtime's own default is one thread)
        import os

        assert mde.num_threads == len(os.sched_getaffinity(0))
        one = FastDepthTFLite(_model_path(shared_data), num_threads=1)
        assert one.num_threads == 1
        np.testing.assert_allclose(one(rgb), depth)  # the same network output on one thread

    def test_wrong_file(self, tmp_path, shared_data):
        pytest.importorskip("ai_edge_litert")
        from gpdepth3d.mde.tflite import FastDepthTFLite

        bad = tmp_path / "bad.tflite"
        bad.write_bytes(b"not a flatbuffer at all" * 10)
        with pytest.raises(DataFormatError):
            FastDepthTFLite(bad)
        with pytest.raises(DataFormatError):
            FastDepthTFLite(tmp_path / "missing.tflite")

    def test_missing_package_message(self, monkeypatch, tmp_path):
        import builtins

        from gpdepth3d.mde import tflite

        real_import = builtins.__import__

        def fake_import(name, *args, **kwargs):
            if name.startswith("ai_edge_litert"):
                raise ImportError("no module")
            return real_import(name, *args, **kwargs)

        monkeypatch.setattr(builtins, "__import__", fake_import)
        (tmp_path / "m.tflite").write_bytes(b"x")
        with pytest.raises(ImportError, match=r"gpdepth3d\[tflite\]"):
            tflite.FastDepthTFLite(tmp_path / "m.tflite")


class TestTorchModuleMDE:
    def _net(self, value: float):
        torch = pytest.importorskip("torch")

        class Net(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.w = torch.nn.Parameter(torch.tensor(value))

            def forward(self, x):  # (1, 3, h, w) -> (1, 1, h, w): mean intensity * w
                return x.mean(dim=1, keepdim=True) * 0 + self.w

        return Net()

    def test_depth_output(self):
        from gpdepth3d.mde.torch_module import TorchModuleMDE, resize_preprocess

        mde = TorchModuleMDE(self._net(3.0), preprocess=resize_preprocess((16, 16)), output="depth")
        out = mde(RGB)
        assert out.shape == (30, 40) and np.allclose(out, 3.0)

    @pytest.mark.parametrize("kind", ["inverse", "disparity"])
    def test_inverse_output(self, kind):
        from gpdepth3d.mde.torch_module import TorchModuleMDE

        out = TorchModuleMDE(self._net(0.25), output=kind)(RGB)
        assert np.allclose(out, 4.0)

    def test_dict_and_select(self):
        torch = pytest.importorskip("torch")
        from gpdepth3d.mde.torch_module import TorchModuleMDE

        class DictNet(torch.nn.Module):
            def forward(self, x):
                return {("disp", 0): torch.full((1, 1, 8, 8), 0.5), "other": torch.zeros(1)}

        with pytest.raises(InvalidInputError):
            TorchModuleMDE(DictNet(), output="inverse")(RGB)
        mde = TorchModuleMDE(DictNet(), output="inverse", select=lambda o: o[("disp", 0)])
        assert np.allclose(mde(RGB), 2.0)

    def test_preprocess_normalises(self):
        from gpdepth3d.mde.torch_module import IMAGENET_MEAN, IMAGENET_STD, resize_preprocess

        x = resize_preprocess((28, 30), mean=IMAGENET_MEAN, std=IMAGENET_STD, multiple_of=14)(RGB)
        assert tuple(x.shape) == (1, 3, 28, 28)
        white = resize_preprocess(None)(np.full((4, 4, 3), 255, np.uint8))
        assert float(white.min()) == pytest.approx(1.0)

    def test_errors(self):
        from gpdepth3d.mde.torch_module import TorchModuleMDE, resize_preprocess

        with pytest.raises(InvalidInputError):
            TorchModuleMDE(object())
        with pytest.raises(InvalidInputError):
            TorchModuleMDE(self._net(1.0), output="metres")
        with pytest.raises(InvalidInputError):
            resize_preprocess((0, 5))


class TestDefaultModelsDir:
    def test_near_a_data_folder(self, tmp_path, monkeypatch):
        from gpdepth3d.mde import default_models_dir

        monkeypatch.delenv("GPDEPTH3D_MODELS", raising=False)
        data = tmp_path / "shared" / "data" / "7scenes"
        data.mkdir(parents=True)
        (tmp_path / "shared" / "models").mkdir()
        assert default_models_dir(near=data) == tmp_path / "shared" / "models"
        (tmp_path / "shared" / "models").rmdir()
        (tmp_path / "shared" / "data" / "models").mkdir()  # the next candidate: <near>/../models
        assert default_models_dir(near=data) == tmp_path / "shared" / "data" / "models"
        monkeypatch.setenv("GPDEPTH3D_MODELS", str(tmp_path / "elsewhere"))
        assert default_models_dir(near=data) == tmp_path / "elsewhere"  # the environment always wins


class TestRuntimeLogFilter:
    def test_info_lines_are_dropped_and_the_rest_kept(self, capfd):
        import os

        from gpdepth3d.mde.tflite import _runtime_info_dropped

        with _runtime_info_dropped():
            os.write(2, b"INFO: Created TensorFlow Lite XNNPACK delegate for CPU.\nERROR: a real problem\n")
        err = capfd.readouterr().err
        assert "INFO:" not in err and "ERROR: a real problem" in err

    def test_fastdepth_loads_without_the_info_line(self, capfd):
        from pathlib import Path

        pytest.importorskip("ai_edge_litert")
        model = Path(__file__).resolve().parents[3] / "shared" / "models" / "fast_depth_224.tflite"
        if not model.is_file():
            pytest.skip("FastDepth model not in ../shared/models")
        from gpdepth3d.mde.tflite import FastDepthTFLite

        FastDepthTFLite(model)
        assert "INFO:" not in capfd.readouterr().err
