"""Tests of gpdepth3d.pipelines.batch: frame specs, holdout inputs, resumable runs, failures, kill and resume.

The data is a tiny KITTI-like folder written per test session (45 x 150 frames, 1/3 resolution
= 15 x 50 GP grid, 40 input points), so every frame takes milliseconds and the Dask tests are
dominated by cluster start-up.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d import DepthGPConfig, complete
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.pipelines.batch import (
    LOCK_NAME,
    REPORT_NAME,
    SETTINGS_NAME,
    BatchReport,
    FrameInputs,
    FramesFailedError,
    FrameSpec,
    HoldoutInputs,
    aggregate_metrics,
    check_frame_id,
    dataset_frames,
    evaluate_posterior,
    fingerprint,
    frame_seed,
    output_paths,
    process_frame,
    remove_stale_temp_files,
    run_batch,
)
from gpdepth3d.cli.batch import batch_command
from gpdepth3d.completion.complete import DepthPosterior
from gpdepth3d.errors import DataFormatError, EmptyInputError, InvalidInputError, ProblemTooLargeError
from gpdepth3d.io import load_depth
from gpdepth3d.measurements import SparseDepth
from gpdepth3d.metrics import depth_metrics

H, W = 45, 150
CONFIG = DepthGPConfig.residual()
ENGINE = EngineConfig(name="exact")
LOADER = HoldoutInputs(factor=3, n_input=40)
TEMP = ".{stem}.abc123.tmp.npz"  # the name pattern gpdepth3d.io.atomic_path uses


def write_kitti_like(root: Path, names: list[str], seed: int = 0) -> Path:
    """A kitti_tiny-layout folder: image_02/*.png, velodyne_02/*.npz (velodyne_depth), cam.txt."""
    import cv2

    rng = np.random.default_rng(seed)
    (root / "image_02").mkdir(parents=True)
    (root / "velodyne_02").mkdir()
    np.savetxt(root / "cam.txt", np.array([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]]))
    rows, cols = np.mgrid[0:H, 0:W]
    for i, name in enumerate(names):
        cv2.imwrite(str(root / "image_02" / f"{name}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        depth = 5.0 + 20.0 * rows / H + 3.0 * np.sin(cols / 15.0 + i)
        depth = np.where(rng.random((H, W)) < 0.3, depth, 0.0).astype(np.float32)
        np.savez_compressed(root / "velodyne_02" / f"{name}.npz", velodyne_depth=depth)
    return root


@pytest.fixture(scope="module")
def tiny_kitti(tmp_path_factory) -> Path:
    return write_kitti_like(tmp_path_factory.mktemp("data") / "kitti", [f"{i:010d}" for i in range(4)])


def npz_ids(folder: Path) -> list[str]:
    """Frame ids of the final .npz files (pathlib's glob also lists hidden temp files: skip them)."""
    return sorted(p.stem for p in folder.glob("*.npz") if not p.name.startswith("."))


def temp_files(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".") and ".tmp" in p.name]


class TestFrameSpecs:
    def test_dataset_frames_lists_detects_repeats_and_limits(self, tiny_kitti):
        specs = dataset_frames(tiny_kitti)
        assert [s.frame_id for s in specs] == [f"{i:010d}" for i in range(4)]
        assert all(s.kind == "kitti_tiny" and Path(s.root) == tiny_kitti.resolve() for s in specs)
        rep = dataset_frames(tiny_kitti, repeat=3, limit=10)
        assert len(rep) == 10 and len({s.frame_id for s in rep}) == 10
        assert rep[4].frame_id == "0000000000-r0001" and rep[4].name == "0000000000"
        assert rep[9].frame_id == "0000000001-r0002"

    def test_bad_arguments_raise(self, tiny_kitti):
        with pytest.raises(InvalidInputError, match="repeat"):
            dataset_frames(tiny_kitti, repeat=0)
        with pytest.raises(InvalidInputError, match="limit"):
            dataset_frames(tiny_kitti, limit=-1)
        with pytest.raises(DataFormatError):
            dataset_frames(tiny_kitti / "missing")

    @pytest.mark.parametrize("bad", ["", ".hidden", "-x", "a/b", "../up", "a b", 7])
    def test_check_frame_id_rejects_unsafe_names(self, bad):
        with pytest.raises(InvalidInputError, match="frame_id"):
            check_frame_id(bad)

    def test_check_frame_id_accepts_names(self):
        assert check_frame_id("0000000001-r0003") == "0000000001-r0003"
        assert check_frame_id("seq_05.f+1") == "seq_05.f+1"

    def test_frame_seed_is_stable_and_distinct(self):
        assert frame_seed(0, "a") == frame_seed(0, "a")
        assert len({frame_seed(0, "a"), frame_seed(0, "b"), frame_seed(1, "a")}) == 3


class TestHoldoutInputs:
    def test_holdout_shapes_counts_and_disjoint(self, tiny_kitti):
        spec = dataset_frames(tiny_kitti)[0]
        inputs = LOADER(spec)
        assert inputs.mde.shape == (15, 50) and not inputs.mde.any()
        assert inputs.sparse.image_size == (15, 50) and len(inputs.sparse) == 40
        gt = inputs.gt
        assert gt.shape == (15, 50)
        rows, cols = inputs.sparse.v.astype(int), inputs.sparse.u.astype(int)
        assert not gt[rows, cols].any(), "input points must not be held-out ground truth"
        n_avail = inputs.info["n_available"]
        assert inputs.info["n_gt"] == np.count_nonzero(gt) == round(0.2 * n_avail)
        # The points are the closest LiDAR depth per 3x3 block of the full-resolution map.
        with np.load(tiny_kitti / "velodyne_02" / f"{spec.name}.npz") as d:
            full = d["velodyne_depth"].astype(np.float64)
        block = np.where(full > 0, full, np.inf).reshape(15, 3, 50, 3).min(axis=(1, 3))
        np.testing.assert_allclose(inputs.sparse.depth, block[rows, cols])

    def test_draws_are_deterministic_per_frame_id(self, tiny_kitti):
        spec = dataset_frames(tiny_kitti)[0]
        a, b = LOADER(spec), LOADER(spec)
        np.testing.assert_array_equal(a.sparse.u, b.sparse.u)
        np.testing.assert_array_equal(a.gt, b.gt)
        other = LOADER(FrameSpec("copy-r0001", spec.root, spec.name, spec.kind))
        assert not np.array_equal(other.gt, a.gt), "a repeated frame (new id) draws new samples"

    def test_standin_mde_uses_only_the_input_points(self):
        rng = np.random.default_rng(3)
        points = np.where(rng.random((30, 60)) < 0.5, rng.uniform(5, 20, (30, 60)), 0.0)
        loader = HoldoutInputs(factor=1, n_input=50, mde="standin", standin_error=0.1)
        a = loader.from_maps("f", points=points)
        assert a.info["mde"].startswith("STAND-IN")
        assert np.all(a.mde > 0)
        ratio = a.mde[a.sparse.v.astype(int), a.sparse.u.astype(int)] / a.sparse.depth
        assert 0.6 < ratio.min() and ratio.max() < 1.6 and ratio.std() > 0.01  # perturbed, not copied
        # Changing the held-out depths changes nothing in the inputs: no leak of the ground truth.
        changed = points.copy()
        changed[a.gt > 0] *= 3.0
        b = loader.from_maps("f", points=changed)
        np.testing.assert_array_equal(a.mde, b.mde)
        np.testing.assert_array_equal(a.sparse.depth, b.sparse.depth)

    def test_dense_ground_truth_is_sampled_and_kept_whole(self):
        rng = np.random.default_rng(1)
        dense = rng.uniform(1, 4, (24, 36))
        dense[0, :] = 0
        out = HoldoutInputs(factor=2, n_input=30).from_maps("x", points=None, dense_gt=dense)
        small = dense.reshape(12, 2, 18, 2)
        small = np.where(small > 0, small, np.inf).min(axis=(1, 3))
        small[~np.isfinite(small)] = 0
        np.testing.assert_allclose(out.gt, small)
        assert out.info["gt"] == "dense" and len(out.sparse) == 30
        np.testing.assert_allclose(out.sparse.depth, small[out.sparse.v.astype(int), out.sparse.u.astype(int)])

    @pytest.mark.parametrize(
        "kwargs", [{"factor": 0}, {"n_input": 0}, {"holdout": 1.0}, {"mde": "net"}, {"standin_error": -1}]
    )
    def test_bad_options_raise(self, kwargs):
        with pytest.raises(InvalidInputError):
            HoldoutInputs(**kwargs)

    def test_no_source_raises(self):
        with pytest.raises(InvalidInputError, match="frame"):
            LOADER.from_maps("x", points=None, dense_gt=None)


class TestProcessFrame:
    def test_writes_the_posterior_of_the_inputs(self, tiny_kitti, tmp_path):
        spec = dataset_frames(tiny_kitti)[1]
        result = process_frame(spec, str(tmp_path), config=CONFIG, engine=ENGINE, loader=LOADER)
        assert result.ok and result.error is None and result.metrics is None
        saved = DepthPosterior.load(output_paths(tmp_path, spec.frame_id, "complete")["final"])
        inputs = LOADER(spec)
        direct = complete(inputs.mde, inputs.sparse, config=CONFIG, engine=ENGINE)
        np.testing.assert_allclose(saved.mean, direct.mean, rtol=1e-6)
        np.testing.assert_allclose(saved.variance, direct.variance, rtol=1e-5)

    def test_eval_writes_metrics_last_and_they_are_right(self, tiny_kitti, tmp_path):
        spec = dataset_frames(tiny_kitti)[2]
        result = process_frame(spec, str(tmp_path), config=CONFIG, engine=ENGINE, loader=LOADER, task="eval")
        paths = output_paths(tmp_path, spec.frame_id, "eval")
        assert paths["final"] == paths["metrics"] and paths["posterior"].is_file()
        record = json.loads(paths["metrics"].read_text())
        saved = DepthPosterior.load(paths["posterior"])
        expected = depth_metrics(saved.mean, LOADER(spec).gt)
        for key in ("rmse", "mae", "delta1", "n"):
            assert record["metrics"][key] == pytest.approx(expected[key], rel=1e-5)
            assert result.metrics[key] == pytest.approx(expected[key], rel=1e-5)
        assert 0 <= record["metrics"]["coverage_2sigma"] <= 1 and record["inputs"]["n_input"] == 40

    def test_errors_are_returned_not_raised(self, tmp_path):
        spec = FrameSpec("bad", str(tmp_path / "nowhere"), "x", "kitti_tiny")
        result = process_frame(spec, str(tmp_path), config=CONFIG, engine=ENGINE, loader=LOADER)
        assert not result.ok and result.frame_id == "bad"
        assert result.error.startswith("DataFormatError") and "Traceback" in result.traceback
        wrong = process_frame(spec, str(tmp_path), config=CONFIG, engine=ENGINE, loader=lambda s: "not inputs")
        assert not wrong.ok and "FrameInputs" in wrong.error
        assert not list(tmp_path.glob("*.npz"))

    def test_evaluate_posterior_needs_ground_truth(self):
        with pytest.raises(EmptyInputError, match="gt"):
            evaluate_posterior(np.ones((2, 2)), np.ones((2, 2)), None)


class TestRunBatchInProcess:
    def test_writes_every_frame_then_skips_them(self, tiny_kitti, tmp_path, capsys):
        frames = dataset_frames(tiny_kitti, repeat=2)
        out = tmp_path / "out"
        report = run_batch(frames, out, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, progress=True)
        bar = capsys.readouterr().err
        assert "8/8" in bar and "frame/s" in bar and "s/frame" not in bar
        assert isinstance(report, BatchReport) and report.ok
        assert (report.n_computed, report.n_skipped, report.failures) == (8, 0, ())
        assert npz_ids(out) == sorted(f.frame_id for f in frames)
        mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
        again = run_batch(frames, out, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, progress=False)
        assert (again.n_computed, again.n_skipped) == (0, 8) and again.ok
        assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == mtimes
        saved = json.loads((out / REPORT_NAME).read_text())
        assert saved["n_skipped"] == 8 and saved["ok"] is True

    def test_eval_aggregates_over_all_done_frames(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti)
        out = tmp_path / "eval"
        first = run_batch(
            frames[:2], out, config=CONFIG, engine=ENGINE, loader=LOADER, task="eval", workers=0, progress=False
        )
        assert first.aggregate["frames"] == 2
        report = run_batch(
            frames, out, config=CONFIG, engine=ENGINE, loader=LOADER, task="eval", workers=0, progress=False
        )
        assert (report.n_computed, report.n_skipped) == (2, 2)
        per_frame = [json.loads((out / f"{f.frame_id}.metrics.json").read_text())["metrics"] for f in frames]
        assert report.aggregate["frames"] == 4
        assert report.aggregate["rmse"] == pytest.approx(np.mean([m["rmse"] for m in per_frame]))
        assert report.aggregate["pixels"] == sum(m["n"] for m in per_frame)
        assert "rmse" in report.summary() and "4 frames" in report.summary()
        assert aggregate_metrics(out, ["none"]) is None

    def test_stale_temp_files_are_removed(self, tiny_kitti, tmp_path):
        out = tmp_path / "out"
        out.mkdir()
        stale = [out / TEMP.format(stem="0000000000"), out / ".x.q1w2e3.tmp.json"]
        for p in stale:
            p.write_bytes(b"partial")
        keep = out / "notes.tmp.txt"  # not a writer's temp name (no leading dot): kept
        keep.write_text("mine")
        report = run_batch(
            dataset_frames(tiny_kitti, limit=1),
            out,
            config=CONFIG,
            engine=ENGINE,
            loader=LOADER,
            workers=0,
            progress=False,
        )
        assert report.temp_files_removed == 2 and not any(p.exists() for p in stale) and keep.exists()
        assert remove_stale_temp_files(out) == 0

    def test_a_corrupt_frame_is_reported_and_the_others_finish(self, tmp_path):
        data = write_kitti_like(tmp_path / "data", ["a", "b", "c"])
        (data / "velodyne_02" / "b.npz").write_bytes(b"not a zip")
        out = tmp_path / "out"
        with pytest.raises(FramesFailedError, match=r"1 of 3 frames failed \(first: b: DataFormatError"):
            batch_command(
                data=data,
                output=out,
                workers=0,
                n_input=40,
                gp=DepthGPConfig(),
                engine=EngineConfig(name="exact"),
                progress=False,
            )
        assert npz_ids(out) == ["a", "c"]
        report = json.loads((out / REPORT_NAME).read_text())
        assert [f["frame_id"] for f in report["failures"]] == ["b"]
        assert report["failures"][0]["error"].startswith("DataFormatError")

    def test_bad_arguments_raise(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti)
        with pytest.raises(InvalidInputError, match="unique"):
            run_batch(frames + frames[:1], tmp_path, workers=0)
        with pytest.raises(InvalidInputError, match="task"):
            run_batch(frames, tmp_path, task="fit", workers=0)
        with pytest.raises(InvalidInputError, match="workers"):
            run_batch(frames, tmp_path, workers=-1)
        with pytest.raises(InvalidInputError, match="frames"):
            run_batch("0000000000", tmp_path, workers=0)
        with pytest.raises(InvalidInputError, match="config"):
            run_batch(frames, tmp_path, config={"engine": "exact"}, workers=0)

    def test_other_settings_in_the_same_folder_are_refused(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti, limit=1)
        run_batch(frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, progress=False)
        settings = json.loads((tmp_path / SETTINGS_NAME).read_text())
        assert settings["loader"] == repr(LOADER) and settings["config"]["lengthscale"] == CONFIG.lengthscale
        assert "engine" not in settings["config"]
        with pytest.raises(InvalidInputError, match="new output_dir"):
            run_batch(frames, tmp_path, config=CONFIG.replace(lengthscale=5.0), loader=LOADER, workers=0)
        with pytest.raises(InvalidInputError, match="new output_dir"):
            run_batch(
                frames, tmp_path, config=CONFIG, engine=ENGINE, loader=HoldoutInputs(factor=3, n_input=41), workers=0
            )
        same = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=HoldoutInputs(factor=3, n_input=40), workers=0
        )
        assert same.n_skipped == 1
        other_engine = run_batch(
            frames, tmp_path, config=CONFIG, engine=EngineConfig(name="fast"), loader=LOADER, workers=0
        )
        assert other_engine.n_skipped == 1, "engines compute the same posterior: resuming with another is allowed"
        with pytest.raises(InvalidInputError, match="new output_dir"):  # the stride sets the approximation
            run_batch(
                frames, tmp_path, config=CONFIG, engine=ENGINE.replace(lattice_stride=2), loader=LOADER, workers=0
            )
        assert fingerprint(process_frame) == "gpdepth3d.pipelines.batch.process_frame"

    def test_a_second_run_on_a_locked_folder_is_refused(self, tiny_kitti, tmp_path):
        fcntl = pytest.importorskip("fcntl")
        with open(tmp_path / LOCK_NAME, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            with pytest.raises(InvalidInputError, match="locked"):
                run_batch(dataset_frames(tiny_kitti), tmp_path, workers=0, progress=False)
        assert not list(tmp_path.glob("*.npz"))


@dataclass(frozen=True)
class FarAway(HoldoutInputs):
    """The default loader, with every depth times 30 on frames whose id is listed: beyond a 16-bit PNG's 256 m."""

    far: tuple[str, ...] = ()

    def __call__(self, spec: FrameSpec) -> FrameInputs:
        inputs = super().__call__(spec)
        if spec.frame_id not in self.far:
            return inputs
        s = inputs.sparse
        far = SparseDepth(s.u, s.v, 30.0 * s.depth, s.image_size, s.sigma)
        return FrameInputs(30.0 * inputs.mde, far, None if inputs.gt is None else 30.0 * inputs.gt, inputs.info)


class TestPngOutputs:
    @pytest.mark.filterwarnings("ignore::gpdepth3d.io.PNGRangeWarning")
    def test_a_frame_beyond_the_png_range_saturates_its_png(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti, limit=2)
        loader = FarAway(factor=3, n_input=40, far=(frames[0].frame_id,))
        first = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=loader, workers=0, png=True, progress=False
        )
        assert first.n_computed == 2 and first.ok  # the PNG's range is the format's, not an error of the frame
        paths = output_paths(tmp_path, frames[0].frame_id, "complete", png=True)
        mean = DepthPosterior.load(paths["posterior"]).mean
        assert mean.max() > 256 and load_depth(paths["mean_png"]).max() == 65535 / 256  # the npz keeps true values
        again = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=loader, workers=0, png=True, progress=False
        )
        assert again.n_skipped == 2 and again.ok

    def test_pngs_asked_for_later_make_frames_not_done(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti, limit=2)
        run_batch(frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, png=False, progress=False)
        assert not list(tmp_path.glob("*.png"))
        with_png = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, png=True, progress=False
        )
        assert with_png.n_computed == 2 and with_png.ok
        for f in frames:
            paths = output_paths(tmp_path, f.frame_id, "complete", png=True)
            assert all(p.is_file() for p in paths.values())
            np.testing.assert_allclose(
                load_depth(paths["mean_png"]), DepthPosterior.load(paths["posterior"]).mean, atol=0.6 / 256
            )
        resumed = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, png=True, progress=False
        )
        assert resumed.n_skipped == 2


@dataclass(frozen=True)
class DiesOn(HoldoutInputs):
    """The default loader, except that the worker process dies (os._exit) on one frame."""

    die_on: str = ""

    def __call__(self, spec: FrameSpec) -> FrameInputs:
        if spec.frame_id == self.die_on:
            os._exit(13)
        return super().__call__(spec)


class TestRunBatchDask:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_cluster_at_an_address_isolates_failing_frames_and_lost_workers(self, tmp_path):
        distributed = pytest.importorskip("distributed")
        import dask

        data = write_kitti_like(tmp_path / "data", ["a", "b", "c", "d", "e"])
        (data / "velodyne_02" / "c.npz").unlink()  # c raises DataFormatError; b kills its worker
        frames = dataset_frames(data)
        out = tmp_path / "out"
        loader = DiesOn(factor=3, n_input=40, die_on="b")
        # A running cluster reached by its scheduler address (the LocalCluster path is run by
        # the kill-and-resume test). allowed-failures=0: the first lost worker fails the frame
        # (default 3: Dask retries it on other workers first); max_in_flight=2 (the worker
        # threads): no frame waits on the dying worker, so only the frame that killed it is lost.
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            with distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster:
                report = run_batch(
                    frames,
                    out,
                    config=CONFIG,
                    engine=ENGINE,
                    loader=loader,
                    task="eval",
                    address=cluster.scheduler_address,
                    max_in_flight=2,
                    progress=False,
                )
                assert cluster.status.name == "running", "run_batch must not close a cluster it did not start"
        assert report.workers == 2 and report.startup_seconds > 0
        assert (report.n_computed, report.n_skipped) == (3, 0)
        failures = {f.frame_id: f.error for f in report.failures}
        assert sorted(failures) == ["b", "c"]
        assert failures["b"].startswith("KilledWorker")
        assert failures["c"].startswith("DataFormatError") and "projected LiDAR not found" in failures["c"]
        assert sorted(p.name.split(".")[0] for p in out.glob("*.metrics.json")) == ["a", "d", "e"]
        assert report.aggregate["frames"] == 3 and not report.ok
        # Results from the workers equal the in-process computation.
        serial = run_batch(
            frames[:1],
            tmp_path / "serial",
            config=CONFIG,
            engine=ENGINE,
            loader=loader,
            task="eval",
            workers=0,
            progress=False,
        )
        a = json.loads((out / "a.metrics.json").read_text())["metrics"]
        b = json.loads((tmp_path / "serial" / "a.metrics.json").read_text())["metrics"]
        assert a["rmse"] == pytest.approx(b["rmse"], rel=1e-9) and serial.ok


KILL_SCRIPT = textwrap.dedent(
    """
    import json, os, sys, time, uuid
    from dataclasses import dataclass
    from pathlib import Path

    from gpdepth3d import DepthGPConfig
    from gpdepth3d.gp.engine import EngineConfig
    from gpdepth3d.pipelines.batch import HoldoutInputs, dataset_frames, run_batch


    @dataclass(frozen=True)
    class LoggingInputs(HoldoutInputs):
        # Marks every start of a frame's computation with a unique file, then works slowly.
        # (Log folder and delay come from the environment: the loader's settings must not
        # change between the runs, or the resume is refused.)
        def __call__(self, spec):
            Path(os.environ["BATCH_TEST_LOG"], spec.frame_id + "." + uuid.uuid4().hex).touch()
            time.sleep(float(os.environ["BATCH_TEST_DELAY"]))
            return super().__call__(spec)


    if __name__ == "__main__":
        data, out = sys.argv[1], sys.argv[2]
        Path(os.environ["BATCH_TEST_LOG"]).mkdir(parents=True, exist_ok=True)
        frames = dataset_frames(data, repeat=3)
        loader = LoggingInputs(factor=3, n_input=40)
        report = run_batch(frames, out, config=DepthGPConfig.residual(),
                           engine=EngineConfig(name="exact"), loader=loader,
                           workers=1, progress=False)
        print("REPORT " + json.dumps({"computed": report.n_computed, "skipped": report.n_skipped,
                                      "failed": len(report.failures), "removed": report.temp_files_removed}))
    """
)


def _starts(log: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    for p in log.iterdir() if log.is_dir() else []:
        frame_id = p.name.rsplit(".", 1)[0]
        counts[frame_id] = counts.get(frame_id, 0) + 1
    return counts


class TestKillAndResume:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_killed_run_resumes_with_every_frame_exactly_once(self, tiny_kitti, tmp_path):
        pytest.importorskip("distributed")
        script = tmp_path / "run_batch_script.py"
        script.write_text(KILL_SCRIPT)
        out, log1, log2 = tmp_path / "out", tmp_path / "log1", tmp_path / "log2"
        all_ids = sorted(f.frame_id for f in dataset_frames(tiny_kitti, repeat=3))  # 12 frames
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}

        # Run 1: 0.4 s per frame on one worker; SIGKILL the whole process group after 3 frames.
        proc = subprocess.Popen(
            [sys.executable, str(script), str(tiny_kitti), str(out)],
            start_new_session=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**env, "BATCH_TEST_LOG": str(log1), "BATCH_TEST_DELAY": "0.4"},
        )
        deadline = time.monotonic() + 50
        try:
            while len(npz_ids(out) if out.is_dir() else []) < 3:
                assert proc.poll() is None, f"run 1 ended early: {proc.stdout.read().decode()[-2000:]}"
                assert time.monotonic() < deadline, "run 1 did not finish 3 frames in time"
                time.sleep(0.05)
        finally:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        done1 = set(npz_ids(out))
        started1 = _starts(log1)
        assert 3 <= len(done1) < len(all_ids), "the kill must land half way"
        assert all(started1[f] == 1 for f in done1)
        assert len(set(started1) - done1) <= 1, "one worker thread: at most one frame was in flight"
        # A writer killed mid-write leaves a temp file like this one.
        (out / TEMP.format(stem=sorted(set(all_ids) - done1)[0])).write_bytes(b"partial")

        # Run 2: resumes.
        res = subprocess.run(
            [sys.executable, str(script), str(tiny_kitti), str(out)],
            capture_output=True,
            text=True,
            timeout=60,
            env={**env, "BATCH_TEST_LOG": str(log2), "BATCH_TEST_DELAY": "0"},
        )
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
        report = json.loads(res.stdout.split("REPORT ", 1)[1].splitlines()[0])
        assert report == {
            "computed": len(all_ids) - len(done1),
            "skipped": len(done1),
            "failed": 0,
            "removed": report["removed"],
        }
        assert report["removed"] >= 1
        started2 = _starts(log2)
        # Every frame exactly once: the finished ones never again, the others once in run 2.
        assert npz_ids(out) == all_ids and len(list(out.glob("*.npz"))) == len(all_ids)  # no hidden temp .npz
        assert temp_files(out) == []
        assert set(started2) == set(all_ids) - done1 and all(n == 1 for n in started2.values())
        for frame_id in all_ids:
            DepthPosterior.load(out / f"{frame_id}.npz")  # complete, readable files


@pytest.mark.shared_data
def test_kitti_tiny_eval_beats_the_prior_on_held_out_lidar(shared_data, tmp_path):
    """Real data: the completed depth predicts held-out LiDAR far better than the prior (median depth)."""
    kitti = shared_data / "kitti_tiny"
    if not kitti.is_dir():
        pytest.skip(f"kitti_tiny not found in {shared_data}")
    loader = HoldoutInputs(factor=3, n_input=150)
    frames = dataset_frames(kitti, limit=1)
    report = run_batch(
        frames, tmp_path, config=CONFIG, engine=ENGINE, loader=loader, task="eval", workers=0, progress=False
    )
    assert report.ok and report.aggregate["frames"] == 1
    inputs = loader(frames[0])
    assert inputs.sparse.image_size == (125, 414) and len(inputs.sparse) == 150
    prior = depth_metrics(np.full(inputs.gt.shape, np.median(inputs.sparse.depth)), inputs.gt)
    got = report.aggregate
    assert got["pixels"] == prior["n"] > 2000
    assert got["rmse"] < 0.6 * prior["rmse"] and got["delta1"] > prior["delta1"] + 0.2
    assert 0.3 < got["coverage_2sigma"] <= 1.0


def test_frame_inputs_is_the_loader_contract():
    sparse = LOADER.from_maps("x", points=np.where(np.eye(30, 60) > 0, 5.0, 0.0)).sparse
    inputs = FrameInputs(mde=np.zeros((10, 20)), sparse=sparse)
    assert inputs.gt is None and inputs.info == {}


class TestChecks:
    @pytest.mark.parametrize(
        "good", ["tcp://10.0.0.5:8786", "127.0.0.1:8786", "tls://sched.example.org:1", "tcp://[::1]:8786"]
    )
    def test_addresses_accepted(self, good):
        from gpdepth3d.pipelines.batch import check_address

        assert check_address(f" {good} ") == good

    @pytest.mark.parametrize(
        "bad", ["not-an-address", "tcp://host", "tcp://host:0", "tcp://host:70000", "http://h:1", "", 8786]
    )
    def test_addresses_refused(self, bad):
        from gpdepth3d.pipelines.batch import check_address

        with pytest.raises(InvalidInputError, match="address"):
            check_address(bad)

    def test_make_output_dir_and_frame_done(self, tmp_path):
        from gpdepth3d.pipelines.batch import frame_done, make_output_dir
        from gpdepth3d.errors import OutputError

        out = make_output_dir(tmp_path / "a" / "b")
        assert out.is_dir()
        (tmp_path / "file").write_text("")
        with pytest.raises(OutputError, match="in the way"):
            make_output_dir(tmp_path / "file")
        with pytest.raises(OutputError, match="cannot create"):
            make_output_dir(tmp_path / "file" / "x")
        assert not frame_done(out, "f", "complete")
        (out / "f.npz").write_bytes(b"")
        assert frame_done(out, "f", "complete") and not frame_done(out, "f", "complete", png=True)
        (out / "f_mean.png").write_bytes(b"")
        (out / "f_std.png").write_bytes(b"")
        assert frame_done(out, "f", "complete", png=True) and not frame_done(out, "f", "eval", png=True)

    def test_unreachable_scheduler_is_a_typed_error(self, tmp_path):
        pytest.importorskip("distributed")
        from gpdepth3d.errors import ConnectionFailedError

        with pytest.raises(InvalidInputError, match="connect_timeout"):
            run_batch(
                [FrameSpec("a", str(tmp_path), "a")], tmp_path / "o", address="tcp://127.0.0.1:1", connect_timeout=0
            )
        with pytest.raises(ConnectionFailedError, match="1 s"):
            run_batch(
                [FrameSpec("a", str(tmp_path), "a")],
                tmp_path / "o",
                address="tcp://127.0.0.1:1",
                connect_timeout=1,
                progress=False,
            )


class TestPreviews:
    def test_written_per_frame_and_part_of_done(self, tiny_kitti, tmp_path):
        frames = dataset_frames(tiny_kitti, limit=2)
        run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, previews=True, progress=False
        )
        for f in frames:
            for kind in ("depth", "sigma"):
                assert (tmp_path / f"{f.frame_id}_{kind}_preview.png").is_file()
        (tmp_path / f"{frames[0].frame_id}_sigma_preview.png").unlink()  # a frame missing a preview is redone
        again = run_batch(
            frames, tmp_path, config=CONFIG, engine=ENGINE, loader=LOADER, workers=0, previews=True, progress=False
        )
        assert (again.n_computed, again.n_skipped) == (1, 1)
        assert (tmp_path / f"{frames[0].frame_id}_sigma_preview.png").is_file()

    def test_the_command_writes_them_unless_told_not_to(self, tiny_kitti, tmp_path, capsys):
        data = tiny_kitti
        batch_command(
            data=data,
            output=tmp_path / "on",
            workers=0,
            frames=1,
            n_input=40,
            gp=DepthGPConfig(),
            engine=EngineConfig(name="exact"),
            progress=False,
        )
        assert len(list((tmp_path / "on").glob("*_depth_preview.png"))) == 1
        batch_command(
            data=data,
            output=tmp_path / "off",
            workers=0,
            frames=1,
            n_input=40,
            gp=DepthGPConfig(),
            engine=EngineConfig(name="exact"),
            progress=False,
            preview=False,
        )
        assert not list((tmp_path / "off").glob("*.png")) and len(list((tmp_path / "off").glob("*.npz"))) == 1


class TestNoLeftovers:
    def test_a_failed_batch_leaves_no_settings_or_lock_file(self, tmp_path):
        data = write_kitti_like(tmp_path / "data", ["a"])
        (data / "velodyne_02" / "a.npz").write_bytes(b"not a zip")
        out = tmp_path / "out"
        report = run_batch(dataset_frames(data), out, workers=0, progress=False)
        assert report.failures and not report.n_computed
        assert sorted(p.name for p in out.iterdir()) == [REPORT_NAME]  # the report says what failed; nothing else

    def test_a_done_batch_keeps_its_settings_lists_them_and_drops_the_lock(self, tiny_kitti, tmp_path, capsys):
        out = tmp_path / "out"
        batch_command(data=tiny_kitti, output=out, workers=0, frames=1, preview=False, progress=False)
        names = sorted(p.name for p in out.iterdir())
        assert SETTINGS_NAME in names and LOCK_NAME not in names
        assert f"{out / SETTINGS_NAME}" in capsys.readouterr().out

    def test_a_frame_whose_posterior_fails_keeps_no_previews(self, tiny_kitti, tmp_path, monkeypatch):
        def full(self, *args, **kwargs):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(DepthPosterior, "save", full)
        out = tmp_path / "out"
        report = run_batch(dataset_frames(tiny_kitti, limit=1), out, workers=0, previews=True, progress=False)
        assert report.failures and "No space left" in report.failures[0].error
        assert not [p.name for p in out.iterdir() if "preview" in p.name]

    def test_a_huge_repeat_is_refused_before_any_frame_and_a_limit_makes_only_its_frames(self, tiny_kitti):
        with pytest.raises(ProblemTooLargeError, match="--repeat 1000000000"):
            dataset_frames(tiny_kitti, repeat=10**9)
        assert [s.frame_id for s in dataset_frames(tiny_kitti, repeat=10**9, limit=1)] == ["0000000000"]


def test_local_workers_start_no_process_compiling_ahead(monkeypatch):
    # the workers of a local cluster share the cores: none starts its own compile process, unless the user asks
    from gpdepth3d.gp.compile_ahead import ENV_SWITCH
    from gpdepth3d.pipelines.batch import warm_up

    monkeypatch.setenv(ENV_SWITCH, "1")  # recorded, so that the test leaves the variable as it found it
    monkeypatch.delenv(ENV_SWITCH)
    warm_up()
    assert os.environ[ENV_SWITCH] == "0"
    monkeypatch.setenv(ENV_SWITCH, "1")
    warm_up()
    assert os.environ[ENV_SWITCH] == "1"
