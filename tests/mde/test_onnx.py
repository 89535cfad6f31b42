"""ONNX front-ends (RT-MonoDepth-S), the named-preset loader and `complete --rgb --mde NAME`.

Real networks live in ../shared/models (beside ../shared/data); tests that need them skip when absent.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import gpdepth3d
from gpdepth3d.errors import DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.mde import FRONTENDS, ONNXDepthModel, RTMonoDepthONNX, load_frontend
from gpdepth3d.mde.onnx import KNOWN_SHA256, RTMONODEPTH_FILES, default_providers, file_sha256

onnxruntime = pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def models_dir(shared_data: Path) -> Path:
    path = shared_data.parent / "models"
    if not (path / RTMONODEPTH_FILES[True]).is_file():
        pytest.skip(f"RT-MonoDepth-S model not found in {path}")
    return path


@pytest.fixture(scope="module")
def kitti_rgb(shared_data: Path) -> np.ndarray:
    path = shared_data / "kitti_tiny" / "image_02" / "0000000000.png"
    if not path.is_file():
        pytest.skip(f"kitti_tiny frame {path} not found")
    return gpdepth3d.io.load_rgb(path)


@pytest.fixture(scope="module")
def kitti_lidar(shared_data: Path) -> np.ndarray:
    with np.load(shared_data / "kitti_tiny" / "velodyne_02" / "0000000000.npz") as data:
        return np.asarray(data["velodyne_depth"], dtype=np.float64)


@pytest.fixture(scope="module")
def metric_model(models_dir: Path) -> RTMonoDepthONNX:
    return RTMonoDepthONNX(models_dir / RTMONODEPTH_FILES[True], num_threads=2)


class TestRTMonoDepthONNX:
    def test_matches_direct_onnxruntime_call(self, metric_model, kitti_rgb, models_dir):
        """The front-end equals onnxruntime on the documented pre-processing and monodepth2's conversion."""
        session = onnxruntime.InferenceSession(
            str(models_dir / RTMONODEPTH_FILES[True]), providers=["CPUExecutionProvider"]
        )
        x = cv2.resize(kitti_rgb, (640, 192), interpolation=cv2.INTER_AREA).astype(np.float32) / np.float32(255.0)
        (disp,) = session.run(["disp"], {"rgb": x.transpose(2, 0, 1)[None].copy()})
        assert disp.shape == (1, 1, 192, 640)
        np.testing.assert_array_equal(metric_model.predict_raw(kitti_rgb), disp[0, 0])
        s = 0.01 + 9.99 * disp[0, 0].astype(np.float64)
        s = cv2.resize(s, (kitti_rgb.shape[1], kitti_rgb.shape[0]), interpolation=cv2.INTER_LINEAR)
        expected = 5.4 / s
        depth = metric_model(kitti_rgb)
        assert depth.shape == kitti_rgb.shape[:2] and depth.dtype == np.float64
        np.testing.assert_array_equal(depth, expected)

    def test_metric_scale_against_lidar(self, metric_model, kitti_rgb, kitti_lidar):
        """Metric model: median ratio LiDAR / MDE near 1 (README: 1.09), plausible street depths."""
        depth = metric_model(kitti_rgb)
        valid = kitti_lidar > 0
        ratio = float(np.median(kitti_lidar[valid] / depth[valid]))
        assert 0.8 < ratio < 1.4
        assert np.all(depth > 0) and 0.54 <= depth.min() and depth.max() <= 540.0  # 5.4 / [0.01, 10]

    def test_mono_only_model_is_relative(self, models_dir, kitti_rgb, kitti_lidar):
        path = models_dir / RTMONODEPTH_FILES[False]
        if not path.is_file():
            pytest.skip(f"{path} not found")
        rel = RTMonoDepthONNX(path, metric=False)
        assert not rel.metric and rel.depth_factor == 1.0
        depth = rel(kitti_rgb)
        valid = kitti_lidar > 0
        ratio = float(np.median(kitti_lidar[valid] / depth[valid]))
        assert 8.0 < ratio < 30.0  # README: about 15.6: no metric scale
        with pytest.raises(InvalidInputError, match="metric"):
            RTMonoDepthONNX(path, metric=True)

    def test_default_path_from_models_dir(self, models_dir):
        model = RTMonoDepthONNX(models_dir=models_dir)
        assert model.model_path == models_dir / RTMONODEPTH_FILES[True]
        assert model.input_size == (192, 640) and model.providers[-1] == "CPUExecutionProvider"

    @pytest.mark.parametrize("shape", [(37, 100), (192, 640), (400, 300)])
    def test_any_image_size(self, metric_model, shape):
        rgb = np.random.default_rng(0).integers(0, 256, (*shape, 3), dtype=np.uint8)
        depth = metric_model(rgb)
        assert depth.shape == shape and depth.dtype == np.float64 and np.all(np.isfinite(depth) & (depth > 0))

    def test_bad_images(self, metric_model):
        with pytest.raises(InvalidInputError, match="uint8"):
            metric_model(np.zeros((50, 60, 3), dtype=np.float32))
        with pytest.raises(ShapeError, match="rgb"):
            metric_model(np.zeros((50, 60), dtype=np.uint8))
        with pytest.raises(ShapeError):
            metric_model(np.zeros((1, 60, 3), dtype=np.uint8))


class TestONNXDepthModel:
    def test_output_conventions(self, models_dir, kitti_rgb, metric_model):
        """'depth' multiplies, 'disparity' inverts the raw output resized to the image."""
        path = models_dir / RTMONODEPTH_FILES[True]
        raw = metric_model.predict_raw(kitti_rgb).astype(np.float64)
        size = (kitti_rgb.shape[1], kitti_rgb.shape[0])
        as_depth = ONNXDepthModel(path, output="depth", depth_factor=2.0)(kitti_rgb)
        np.testing.assert_allclose(as_depth, cv2.resize((raw * 2.0).astype(np.float32), size), rtol=1e-6)
        as_disp = ONNXDepthModel(path, output="disparity", depth_factor=3.0)(kitti_rgb)
        np.testing.assert_allclose(as_disp, 3.0 / cv2.resize(raw, size), rtol=1e-6)

    def test_missing_and_corrupt_files(self, tmp_path):
        with pytest.raises(DataFormatError, match="not found"):
            ONNXDepthModel(tmp_path / "none.onnx")
        bad = tmp_path / "bad.onnx"
        bad.write_bytes(b"not a protobuf at all" * 10)
        with pytest.raises(DataFormatError, match="not a loadable ONNX model"):
            ONNXDepthModel(bad)

    def test_bad_options(self, models_dir):
        path = models_dir / RTMONODEPTH_FILES[True]
        with pytest.raises(InvalidInputError, match="output"):
            ONNXDepthModel(path, output="inverse")  # type: ignore[arg-type]
        with pytest.raises(InvalidInputError, match="depth_factor"):
            ONNXDepthModel(path, depth_factor=0.0)
        with pytest.raises(InvalidInputError, match="min_disp"):
            ONNXDepthModel(path, output="sigmoid_disparity", min_disp=1.0, max_disp=0.5)
        with pytest.raises(InvalidInputError, match="input_size"):
            ONNXDepthModel(path, input_size=(100, 100))  # the graph is 192x640
        with pytest.raises(InvalidInputError, match="num_threads"):
            ONNXDepthModel(path, num_threads=0)

    def test_providers(self):
        providers = default_providers()
        assert providers[-1] == "CPUExecutionProvider"
        assert ("CUDAExecutionProvider" in providers) == (
            "CUDAExecutionProvider" in onnxruntime.get_available_providers()
        )

    def test_known_hashes(self, models_dir):
        for metric, name in RTMONODEPTH_FILES.items():
            path = models_dir / name
            if path.is_file():
                assert KNOWN_SHA256[file_sha256(path)] == (path.stem, metric)


class TestLoadFrontend:
    def test_names(self, models_dir):
        assert isinstance(load_frontend("rtmonodepth", models_dir=models_dir), RTMonoDepthONNX)
        assert load_frontend("RTMonoDepth", models_dir=models_dir).metric
        if (models_dir / RTMONODEPTH_FILES[False]).is_file():
            assert not load_frontend("rtmonodepth-mono", models_dir=models_dir).metric
        assert set(FRONTENDS) == {"fastdepth", "rtmonodepth", "rtmonodepth-mono"}

    def test_fastdepth(self, models_dir, kitti_rgb):
        pytest.importorskip("ai_edge_litert")
        if not (models_dir / "fast_depth_224.tflite").is_file():
            pytest.skip("fast_depth_224.tflite not found")
        front = load_frontend("fastdepth", models_dir=models_dir)
        assert type(front).__name__ == "FastDepthTFLite"
        assert front(kitti_rgb[:100, :200]).shape == (100, 200)

    def test_paths_recognise_the_published_models(self, models_dir):
        model = load_frontend(models_dir / RTMONODEPTH_FILES[True])
        assert isinstance(model, RTMonoDepthONNX) and model.metric and model.depth_factor == 5.4
        mono = models_dir / RTMONODEPTH_FILES[False]
        if mono.is_file():
            assert not load_frontend(str(mono)).metric

    def test_unknown_onnx_file_is_generic_depth(self, models_dir, monkeypatch):
        """An .onnx file that is not a known export is read as a depth network (no conversion)."""
        import gpdepth3d.mde.onnx as onnx_module

        monkeypatch.setattr(onnx_module, "KNOWN_SHA256", {})
        model = load_frontend(models_dir / RTMONODEPTH_FILES[True])
        assert type(model) is ONNXDepthModel and model.output == "depth" and model.depth_factor == 1.0

    def test_errors(self, tmp_path):
        with pytest.raises(InvalidInputError, match="name_or_path"):
            load_frontend("midas")
        with pytest.raises(DataFormatError, match="rtmonodepth"):
            load_frontend("rtmonodepth", models_dir=tmp_path)
        with pytest.raises(DataFormatError, match="not found"):
            load_frontend(tmp_path / "x.onnx")

    def test_env_models_dir(self, models_dir, monkeypatch):
        monkeypatch.setenv("GPDEPTH3D_MODELS", str(models_dir))
        assert gpdepth3d.mde.default_models_dir() == models_dir
        assert load_frontend("rtmonodepth").model_path == models_dir / RTMONODEPTH_FILES[True]

    def test_exported(self):
        assert gpdepth3d.load_frontend is load_frontend
        assert gpdepth3d.RTMonoDepthONNX is RTMonoDepthONNX and gpdepth3d.ONNXDepthModel is ONNXDepthModel


class TestCompleteCommand:
    def test_complete_runs_the_network(self, models_dir, kitti_rgb, kitti_lidar, tmp_path, capsys):
        """`gpdepth3d complete --rgb IMAGE --mde rtmonodepth ...` on a crop of a kitti_tiny frame."""
        from gpdepth3d.cli import main
        from gpdepth3d.completion.complete import DepthPosterior

        rgb, lidar = kitti_rgb[183:375, 300:940], kitti_lidar[183:375, 300:940]
        cv2.imwrite(str(tmp_path / "rgb.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        np.save(tmp_path / "lidar.npy", lidar)
        code = main(
            [
                "complete",
                "--rgb",
                str(tmp_path / "rgb.png"),
                "--mde",
                "rtmonodepth",
                "--models-dir",
                str(models_dir),
                "--sparse",
                str(tmp_path / "lidar.npy"),
                "--output",
                str(tmp_path / "out"),
                "--no-png",
            ]
        )
        assert code == 0, capsys.readouterr().err
        post = DepthPosterior.load(tmp_path / "out.npz")
        expected_mde = RTMonoDepthONNX(models_dir=models_dir)(rgb)
        np.testing.assert_allclose(post.mde, expected_mde, rtol=1e-6)
        valid = lidar > 0
        # the paper preset follows the dense LiDAR closely at the measured pixels
        assert np.median(np.abs(post.mean[valid] - lidar[valid])) < 0.1 * np.median(lidar[valid])

    def test_unknown_front_end_is_one_line_error(self, tmp_path, capsys):
        from gpdepth3d.cli import main

        cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((20, 30, 3), np.uint8))
        np.save(tmp_path / "s.npy", np.ones((20, 30)))
        code = main(
            [
                "complete",
                "--rgb",
                str(tmp_path / "rgb.png"),
                "--mde",
                "midas",
                "--sparse",
                str(tmp_path / "s.npy"),
                "--output",
                str(tmp_path / "o"),
            ]
        )
        assert code == 1
        err = capsys.readouterr().err
        assert "--mde:" in err and "name_or_path" not in err  # the option the user typed, not the argument


class TestEvalAndBatchWithNetwork:
    def test_eval_command_rtmonodepth(self, shared_data, models_dir, tmp_path):
        """`gpdepth3d eval --data kitti_tiny --mde rtmonodepth` runs the network (one frame, two cheap methods)."""
        from gpdepth3d.cli.eval import eval_command

        data = shared_data / "kitti_tiny"
        assert gpdepth3d.mde.default_models_dir(near=data) == models_dir  # the rule run_evaluation uses
        summary = eval_command(
            data,
            mde="rtmonodepth",
            protocol="uniform",
            points="200",
            output=tmp_path,
            frames=1,
            methods="mde,mde_scale",
            qualitative=False,
            progress=False,
        )
        by = {s["method"]: s for s in summary}
        # README: RT-MonoDepth-S alone on kitti_tiny ~5.3 m RMSE against the LiDAR; scaling by the points helps
        assert 2000 < by["mde"]["rmse"] < 9000
        assert by["mde_scale"]["rmse"] < by["mde"]["rmse"]
        assert (tmp_path / "results.json").is_file()

    def test_batch_loader_runs_the_network(self, shared_data, models_dir):
        from gpdepth3d.pipelines.batch import FrameSpec, HoldoutInputs

        loader = HoldoutInputs(mde="rtmonodepth", models_dir=str(models_dir), n_input=100)
        spec = FrameSpec("f0", str(shared_data / "kitti_tiny"), "0000000000", "kitti_tiny")
        inputs = loader(spec)
        assert inputs.mde.shape == (125, 414) and inputs.info["mde"] == "rtmonodepth"
        rgb = gpdepth3d.io.load_rgb(shared_data / "kitti_tiny" / "image_02" / "0000000000.png")
        full = RTMonoDepthONNX(models_dir=models_dir)(rgb)
        np.testing.assert_allclose(inputs.mde, cv2.resize(full, (414, 125), interpolation=cv2.INTER_AREA))
        with pytest.raises(InvalidInputError, match="mde_map"):
            loader.from_maps("f0", points=np.ones((30, 30)))
        with pytest.raises(InvalidInputError, match="mde"):
            HoldoutInputs(mde="midas")  # type: ignore[arg-type]
