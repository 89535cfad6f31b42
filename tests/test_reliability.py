"""Reliability: typed errors at every boundary, one-line CLI errors, outputs written as one set, sizes refused early.

* `API_CASES` / `CLI_CASES`: one row per bad input; each must raise its typed error (API) or print one
  line and exit 1 (CLI), and leave no output behind.
* A hypothesis property test: for small random inputs (shapes, dtypes, magnitudes, configs) the
  default engine gives a typed error or a finite posterior that matches the ``exact`` engine.
* Kill tests: `DepthPosterior.save` killed at every step of its write (forked child, ``os._exit``),
  ``gpdepth3d complete`` (previews included) killed by SIGKILL at random moments, and two concurrent
  ``complete`` processes on one output: after recovery the files on disk are one complete set (old or new).
* Sizes: each request too large for the memory limit gets `ProblemTooLargeError` (or a forged file
  header `DataFormatError`) within a second, in a process capped at one more GiB (``RLIMIT_AS``).
* The CLI sweep (``GPDEPTH3D_FUZZ_CLI=1``) behind the summary in docs/reliability.md.
"""

from __future__ import annotations

import errno
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import gpdepth3d as g
import gpdepth3d.pipelines.batch
import gpdepth3d.datasets
import gpdepth3d.viewer
from gpdepth3d import cli
from gpdepth3d import io as gio
from gpdepth3d.camera import PinholeCamera, check_pose
from gpdepth3d.mapping.cloud import backproject_depth
from gpdepth3d.completion.complete import DepthPosterior, complete
from gpdepth3d.completion.problem import check_output_shape
from gpdepth3d.errors import (
    CalibrationError,
    DataFormatError,
    GPDepthError,
    InvalidDepthError,
    InvalidInputError,
    OutputError,
    ProblemTooLargeError,
    ShapeError,
)
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.measurements import LidarCalibration, SparseDepth, load_velodyne
from gpdepth3d.sampling import sample_uniform

EXACT = DepthGPConfig.residual()
EXACT_ENGINE = EngineConfig(name="exact")


RECORD_ENV = "GPDEPTH3D_RELIABILITY_OUT"
"""Set to a JSON path (`python bench/reliability.py` does), each sweep adds its outcome counts to that file: the
table of docs/reliability.md is generated from it (`python bench/report.py`), never typed."""


def record(row: str, key: str, n: int = 1) -> None:
    """Adds ``n`` to the count ``key`` of ``row`` in the file named by `RECORD_ENV` (nothing when unset)."""
    import json

    path = os.environ.get(RECORD_ENV)
    if not path:
        return
    data = json.loads(Path(path).read_text()) if Path(path).is_file() else {}
    counts = data.setdefault(row, {})
    counts[key] = counts.get(key, 0) + n
    Path(path).write_text(json.dumps(data, indent=1, sort_keys=True))


def small_problem(seed: int = 0, h: int = 12, w: int = 16, scale: float = 1.0):
    rng = np.random.default_rng(seed)
    mde = scale * (2.0 + rng.random((h, w)))
    sparse = SparseDepth.from_arrays(
        rng.uniform(0, w - 1, 6), rng.uniform(0, h - 1, 6), scale * (2.0 + rng.random(6)), (h, w)
    )
    return mde, sparse


def visible_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith(".")) if folder.exists() else []


# ------------------------------------------------------------------------------------------ API cases
def _write(tmp: Path, name: str, data: bytes) -> Path:
    path = tmp / name
    path.write_bytes(data)
    return path


def _npy(tmp: Path, name: str, array: np.ndarray) -> Path:
    path = tmp / name
    np.save(path, array)
    return path


def _points(tmp: Path, rows: list[list[float]]) -> Path:
    path = tmp / "points.txt"
    np.savetxt(path, np.array(rows))
    return path


def _truncated_jpeg(tmp: Path) -> Path:
    img = (np.random.default_rng(0).random((60, 80, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return _write(tmp, "cut.jpg", buf.tobytes()[: len(buf) * 2 // 3])


def _kitti_tiny_with_pose(tmp: Path, scale: float) -> Path:
    root = tmp / f"kitti_tiny_{scale:g}"
    (root / "image_02").mkdir(parents=True)
    (root / "velodyne_02").mkdir()
    cv2.imwrite(str(root / "image_02" / "0000000000.png"), np.zeros((10, 20, 3), np.uint8))
    np.savez(root / "velodyne_02" / "0000000000.npz", velodyne_depth=np.ones((10, 20), np.float32))
    np.savetxt(root / "cam.txt", [[20.0, 0, 10], [0, 20.0, 5], [0, 0, 1]])
    np.savetxt(root / "poses.txt", (scale * np.eye(4))[:3].reshape(1, 12))
    return root


def _seven_scenes_with_pose(tmp: Path, scale: float) -> Path:
    root = tmp / f"7scenes_{scale:g}"
    root.mkdir()
    cv2.imwrite(str(root / "frame-000000.color.jpg"), np.zeros((10, 20, 3), np.uint8))
    cv2.imwrite(str(root / "frame-000000.depth.png"), np.full((10, 20), 1000, np.uint16))
    np.savetxt(root / "camera-intrinsics.txt", [[20.0, 0, 10], [0, 20.0, 5], [0, 0, 1]])
    np.savetxt(root / "frame-000000.pose.txt", scale * np.eye(4) + np.diag([0, 0, 0, 1 - scale]))
    return root


def _complete_with(**kwargs):
    mde, sparse = small_problem()
    return complete(mde, sparse, **kwargs)


SP = SparseDepth.from_arrays([1.0], [1.0], [2.0], (8, 8))
CAM = PinholeCamera(10.0, 10.0, 4.0, 4.0, 8, 8)
RGB = np.zeros((8, 8, 3), np.uint8)

# (id, function of tmp_path, expected error type, text the message must contain)
API_CASES = [
    ("output_shape 1 element", lambda t: _complete_with(output_shape=(240,)), ShapeError, "output_shape"),
    ("output_shape str", lambda t: _complete_with(output_shape="ab"), ShapeError, "output_shape"),
    ("output_shape nan", lambda t: _complete_with(output_shape=float("nan")), ShapeError, "output_shape"),
    ("output_shape 3 elements", lambda t: _complete_with(output_shape=(12, 16, 3)), ShapeError, "output_shape"),
    ("output_shape non-integer", lambda t: _complete_with(output_shape=(12.5, 16)), ShapeError, "output_shape"),
    ("output_shape zero", lambda t: _complete_with(output_shape=(0, 16)), ShapeError, "output_shape"),
    ("output_shape huge", lambda t: check_output_shape((100000, 100000), (12, 16)), ShapeError, "at most"),
    ("config dict", lambda t: _complete_with(config={"nu": 0.5}), InvalidInputError, "config"),
    ("lengthscale str", lambda t: DepthGPConfig(lengthscale="30"), InvalidInputError, "lengthscale"),
    ("lengthscale None", lambda t: DepthGPConfig(lengthscale=None), InvalidInputError, "lengthscale"),
    ("lengthscale bool", lambda t: DepthGPConfig(lengthscale=True), InvalidInputError, "lengthscale"),
    ("nu 3.7", lambda t: DepthGPConfig(nu=3.7), InvalidInputError, "nu"),
    ("sigma_dl denormal", lambda t: DepthGPConfig(sigma_dl=1e-320), InvalidInputError, "sigma_dl"),
    ("lengthscale 1e300", lambda t: DepthGPConfig(lengthscale=1e300), InvalidInputError, "lengthscale"),
    (
        "load a .npy as posterior",
        lambda t: DepthPosterior.load(_npy(t, "p.npy", np.ones((3, 3)))),
        DataFormatError,
        "npz",
    ),
    ("max_exact_points -5", lambda t: EngineConfig(max_exact_points=-5), InvalidInputError, "max_exact_points"),
    ("max_exact_points str", lambda t: EngineConfig(max_exact_points="many"), InvalidInputError, "max_exact_points"),
    ("image_size nan", lambda t: SparseDepth.empty((float("nan"), 5)), ShapeError, "image_size"),
    ("image_size inf", lambda t: SparseDepth.empty((float("inf"), 5)), ShapeError, "image_size"),
    ("image_size None", lambda t: SparseDepth.empty(None), ShapeError, "image_size"),
    ("image_size scalar", lambda t: SparseDepth.empty(10), ShapeError, "image_size"),
    ("camera width None", lambda t: PinholeCamera(585.0, 585.0, 320.0, 240.0, None, 480), CalibrationError, "width"),
    ("camera fx str", lambda t: PinholeCamera("585", 585.0, 320.0, 240.0, 640, 480), CalibrationError, "fx"),
    ("check_pose str", lambda t: check_pose("identity"), CalibrationError, "T_world_camera"),
    ("check_pose str rows", lambda t: check_pose([["a"] * 4] * 4), CalibrationError, "T_world_camera"),
    ("check_pose det 8", lambda t: check_pose(2 * np.eye(4) + np.diag([0, 0, 0, -1])), CalibrationError, "det"),
    ("sample_uniform rng -1", lambda t: sample_uniform(np.ones((4, 4)), n=2, rng=-1), InvalidInputError, "rng"),
    ("sample_uniform n inf", lambda t: sample_uniform(np.ones((4, 4)), n=float("inf")), InvalidInputError, "n"),
    (
        "calib binary",
        lambda t: LidarCalibration.from_kitti(_write(t, "c.txt", bytes(range(256)) * 4)),
        DataFormatError,
        "binary",
    ),
    (
        "variance -1",
        lambda t: backproject_depth(np.ones((8, 8)), RGB, CAM, variance=-np.ones((8, 8))),
        InvalidInputError,
        "variance",
    ),
    (
        "load_depth png_scale -1",
        lambda t: gio.load_depth(_npy(t, "d.npy", np.ones((4, 4))), png_scale=-1),
        InvalidInputError,
        "png_scale",
    ),
    (
        "load_depth png_scale nan",
        lambda t: gio.load_depth(_npy(t, "d.npy", np.ones((4, 4))), png_scale=float("nan")),
        InvalidInputError,
        "png_scale",
    ),
    ("complex npy", lambda t: gio.load_depth(_npy(t, "c.npy", np.ones((4, 4)) * (1 + 1j))), DataFormatError, "complex"),
    (
        "string npy",
        lambda t: gio.load_depth(_npy(t, "s.npy", np.array([["a", "b"], ["c", "d"]]))),
        DataFormatError,
        "dtype",
    ),
    (
        "point NaN depth",
        lambda t: gio.load_sparse(_points(t, [[1, 1, 2.0], [2, 2, np.nan]]), (8, 8)),
        InvalidDepthError,
        "1 of 2 rows",
    ),
    (
        "point negative depth",
        lambda t: gio.load_sparse(_points(t, [[1, 1, -2.0], [2, 2, 3]]), (8, 8)),
        InvalidDepthError,
        "1 of 2 rows",
    ),
    (
        "point outside image",
        lambda t: gio.load_sparse(_points(t, [[1, 1, 2.0], [20, 2, 3]]), (8, 8)),
        InvalidDepthError,
        "outside",
    ),
    (
        "bin not 16-byte records",
        lambda t: load_velodyne(_write(t, "s.bin", b"\0" * 36)),
        DataFormatError,
        "multiple of 16",
    ),
    ("truncated JPEG", lambda t: gio.load_rgb(_truncated_jpeg(t)), DataFormatError, "truncated"),
    (
        "kitti_tiny pose det 8",
        lambda t: g.datasets.open_dataset(_kitti_tiny_with_pose(t, 2.0)),
        DataFormatError,
        "rigid",
    ),
    (
        "7scenes pose det 8",
        lambda t: g.datasets.open_dataset(_seven_scenes_with_pose(t, 2.0))[0],
        DataFormatError,
        "rigid",
    ),
    (
        "save to a directory",
        lambda t: _complete_with(config=EXACT, engine=EXACT_ENGINE).save(_mkdir(t / "d.npz")),
        OutputError,
        "directory",
    ),
    (
        "save under a file",
        lambda t: _complete_with(config=EXACT, engine=EXACT_ENGINE).save(_write(t, "f", b"") / "x"),
        OutputError,
        "file",
    ),
    ("save empty name", lambda t: _complete_with(config=EXACT, engine=EXACT_ENGINE).save(""), OutputError, "name"),
    (
        "save a name too long",
        lambda t: _complete_with(config=EXACT, engine=EXACT_ENGINE).save(t / ("x" * 250)),
        OutputError,
        "too long",
    ),
    ("load posterior of mixed shapes", lambda t: DepthPosterior.load(_mixed_posterior(t)), DataFormatError, "2-D grid"),
    ("view host 999.1.1.1", lambda t: g.viewer.check_host("999.1.1.1"), InvalidInputError, "host"),
    ("view host 0.0.0.0", lambda t: g.viewer.check_host("0.0.0.0"), InvalidInputError, "allow_remote"),
    ("batch address", lambda t: g.pipelines.batch.check_address("not-an-address"), InvalidInputError, "address"),
    (
        "batch address no port",
        lambda t: g.pipelines.batch.check_address("tcp://127.0.0.1"),
        InvalidInputError,
        "address",
    ),
    (
        "sparse depth 1e-300",
        lambda t: SparseDepth([1.0], [1.0], [1e-300], (8, 8)),
        InvalidDepthError,
        "[1e-06, 1e+06] m",
    ),
    (
        "sparse depth 1e300",
        lambda t: SparseDepth.from_arrays([1.0], [1.0], [1e300], (8, 8)),
        InvalidDepthError,
        "1e+300",
    ),
    ("sparse sigma 1e300", lambda t: SparseDepth([1.0], [1.0], [2.0], (8, 8), [1e300]), InvalidDepthError, "sigma"),
    ("sparse sigma 1e-300", lambda t: SP.with_sigma(1e-300), InvalidDepthError, "sigma"),
    (
        "calib Tr_velo_to_cam x2",
        lambda t: LidarCalibration.from_kitti(_calib(t, tr=2.0)),
        CalibrationError,
        "Tr_velo_to_cam",
    ),
    ("calib P2 all zero", lambda t: LidarCalibration.from_kitti(_calib(t, p=0.0)), CalibrationError, "P2"),
    (
        "calib R0_rect no rotation",
        lambda t: LidarCalibration.from_kitti(_calib(t, r0=[1, 0.3, 0, 0, 1, 0, 0, 0, 1])),
        CalibrationError,
        "R0_rect",
    ),
    (
        "calib T scaled (API)",
        lambda t: LidarCalibration(np.eye(3, 4), 2 * np.eye(4)),
        CalibrationError,
        "T_camera_lidar",
    ),
    (
        "kitti_tiny corrupt npz",
        lambda t: g.datasets.open_dataset(_corrupt(_kitti_tiny_with_pose(t, 1.0) / "velodyne_02" / "0000000000.npz"))[
            0
        ],
        DataFormatError,
        "0000000000.npz",
    ),
    (
        "ibims corrupt sparse npz",
        lambda t: g.datasets.open_dataset(_ibims(t, corrupt="sparse_100.npz"))[0],
        DataFormatError,
        "sparse_100.npz",
    ),
    (
        "ibims corrupt gt npz",
        lambda t: g.datasets.open_dataset(_ibims(t, corrupt="gt.npz"))[0],
        DataFormatError,
        "gt.npz",
    ),
    (
        "posterior config_json a list",
        lambda t: DepthPosterior.load(_posterior(t, config_json=np.array("[1, 2]"))),
        DataFormatError,
        "JSON object",
    ),
    (
        "posterior mean all NaN",
        lambda t: DepthPosterior.load(_posterior(t, mean=np.full((3, 3), np.nan))),
        DataFormatError,
        "no finite",
    ),
    (
        "posterior negative variance",
        lambda t: DepthPosterior.load(_posterior(t, variance=-np.ones((3, 3)))),
        DataFormatError,
        "negative",
    ),
    (
        "dataset indexed by name",
        lambda t: g.datasets.open_dataset(_kitti_tiny_with_pose(t, 1.0))["0000000000"],
        InvalidInputError,
        ".load(",
    ),
    ("load_depth(None)", lambda t: gio.load_depth(None), InvalidInputError, "path"),
    ("load_sparse(3)", lambda t: gio.load_sparse(3, (8, 8)), InvalidInputError, "path"),
    ("Frame.resized('2')", lambda t: g.datasets.Frame(name="f", rgb=RGB).resized("2"), InvalidInputError, "factor"),
    (
        "posterior mean header claims 200000^2",
        lambda t: DepthPosterior.load(_forged_posterior(t)),
        DataFormatError,
        "header claims",
    ),
    ("JPEG header claims 60000^2", lambda t: gio.load_rgb(_forged_jpeg(t)), ProblemTooLargeError, "(60000, 60000, 3)"),
    ("npy header claims 200000^2", lambda t: gio.load_depth(_forged_npy(t)), DataFormatError, "header claims"),
    (
        "batch output under a file",
        lambda t: g.pipelines.batch.make_output_dir(_write(t, "f", b"") / "out"),
        OutputError,
        "file",
    ),
]


def _calib(tmp: Path, *, tr: float = 1.0, p: float = 1.0, r0=(1, 0, 0, 0, 1, 0, 0, 0, 1)) -> Path:
    """A KITTI object calibration file with its Tr_velo_to_cam, P2 and R0_rect changed."""
    P = p * np.array([721.5, 0, 609.6, 44.9, 0, 721.5, 172.9, 0.2, 0, 0, 1, 0.003])
    Tr = tr * np.array([0, -1, 0, 0, 0, 0, -1, 0, 1, 0, 0, 0.0])
    path = tmp / "calib.txt"
    path.write_text(
        f"P2: {' '.join(map(str, P))}\nR0_rect: {' '.join(map(str, r0))}\nTr_velo_to_cam: {' '.join(map(str, Tr))}\n"
    )
    return path


def _corrupt(path: Path) -> Path:
    path.write_bytes(b"PK\x03\x04 not really a zip archive")
    return path.parents[1]


def _ibims(tmp: Path, corrupt: str) -> Path:
    root = tmp / "ibims"
    root.mkdir()
    cv2.imwrite(str(root / "image.png"), np.zeros((10, 20, 3), np.uint8))
    np.savez(root / "gt.npz", depth=np.ones((10, 20), np.float32))
    np.savez(root / "sparse_100.npz", u=np.array([1, 2]), v=np.array([1, 2]), depth=np.array([1.0, 1.0]))
    (root / corrupt).write_bytes(b"\x00" * 64)
    return root


def _posterior(tmp: Path, **replace) -> Path:
    post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
    post.save(tmp / "src" / "ok")
    with np.load(tmp / "src" / "ok.npz") as d:
        arrays = {k: d[k] for k in d.files}
    for k, v in replace.items():
        arrays[k] = np.resize(v, arrays[k].shape) if k in ("mean", "variance") else v
    np.savez(tmp / "p.npz", **arrays)
    return tmp / "p.npz"


def _forged_posterior(tmp: Path) -> Path:
    import zipfile

    good = _posterior(tmp)
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(tmp / "src" / "forged.npz", "w") as dst:
        for name in src.namelist():
            dst.writestr(name, _forged_npy(tmp / "src").read_bytes() if name == "mean.npy" else src.read(name))
    return tmp / "src" / "forged.npz"


def _forged_jpeg(tmp: Path) -> Path:
    import struct

    ok, buf = cv2.imencode(".jpg", np.zeros((37, 53, 3), np.uint8))
    data = bytearray(buf.tobytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)
    (tmp / "big.jpg").write_bytes(bytes(data))
    return tmp / "big.jpg"


def _forged_npy(tmp: Path) -> Path:
    with open(tmp / "forged.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (200000, 200000)})
        f.write(b"\0" * 100)
    return tmp / "forged.npy"


def _mixed_posterior(tmp: Path) -> Path:
    np.savez(
        tmp / "p.npz",
        mean=np.ones((3, 3)),
        variance=np.ones((3, 2)),
        mde=np.ones((3, 3)),
        sparse_uvd=np.zeros((0, 3)),
        sparse_image_size=np.array([3, 3]),
        depth_scale=1.0,
        alignment=np.array([1.0, 0.0]),
    )
    return tmp / "p.npz"


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _far() -> DepthPosterior:
    post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
    from dataclasses import replace

    return replace(post, mean=post.mean + 300.0)


@pytest.mark.parametrize("case", API_CASES, ids=[c[0] for c in API_CASES])
def test_api_case_raises_typed_error(case, tmp_path):
    name, call, error, text = case
    with pytest.raises(error) as info:
        call(tmp_path)
    record("api_cases", type(info.value).__name__)
    assert isinstance(info.value, GPDepthError)
    assert text in str(info.value)
    assert "\n" not in str(info.value)
    # nothing visible was written by a failed save
    outputs = [p for p in tmp_path.iterdir() if p.suffix in (".npz", ".png") and p.is_file() and p.name != "p.npz"]
    assert not outputs


def test_real_data_cases(shared_data, tmp_path):
    """The same refusals on real files: a truncated 7-Scenes JPEG, a cut KITTI scan, its calibration vs 320x240."""
    jpg = sorted((shared_data / "7scenes").glob("*.color.jpg"))[0]
    assert gio.load_rgb(jpg).shape == (480, 640, 3)
    cut = _write(tmp_path, "cut.color.jpg", jpg.read_bytes()[:-5000])
    with pytest.raises(DataFormatError, match="truncated"):
        gio.load_rgb(cut)
    scan = shared_data / "kitti_object" / "000000.bin"
    assert load_velodyne(scan).shape[1] == 4
    with pytest.raises(DataFormatError, match="multiple of 16"):
        load_velodyne(_write(tmp_path, "cut.bin", scan.read_bytes()[:-6]))
    calib = LidarCalibration.from_kitti(shared_data / "kitti_object" / "calib_000000.txt")
    calib.check_image_size((375, 1242))
    with pytest.raises(CalibrationError, match="320x240"):
        calib.check_image_size((240, 320))


def test_masked_mde_pixels_are_no_mde():
    mde, sparse = small_problem()
    garbage = mde.copy()
    garbage[2:5, 3:9] = -7.0  # would be refused as negative depths if the mask were ignored
    masked = np.ma.masked_array(garbage, mask=garbage < 0)
    holes = np.where(garbage < 0, 0.0, garbage)
    a, b = (
        complete(masked, sparse, config=EXACT, engine=EXACT_ENGINE),
        complete(holes, sparse, config=EXACT, engine=EXACT_ENGINE),
    )
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.variance, b.variance)


def test_calibration_checks_keep_real_kitti(shared_data):
    for k in range(3):
        calib = LidarCalibration.from_kitti(shared_data / "kitti_object" / f"calib_{k:06d}.txt")
        assert calib.P[0, 0] > 0
    LidarCalibration.from_kitti(shared_data / "kitti_tiny", camera=2)


def test_dropped_points_are_counted(tmp_path):
    path = _points(tmp_path, [[1, 1, 2.0], [2, 2, np.nan], [3, 3, -1.0], [30, 3, 4.0]])
    with pytest.warns(UserWarning, match="dropped 3 of 4 rows \\(2 with a NaN"):
        sparse = gio.load_sparse(path, (8, 8), drop_invalid=True)
    assert len(sparse) == 1 and sparse.depth[0] == 2.0


def test_port_taken_is_detected():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        assert g.viewer.port_taken("127.0.0.1", s.getsockname()[1])
    assert g.viewer.check_host("127.0.0.1") is True
    assert g.viewer.check_host("0.0.0.0", allow_remote=True) is False


# ------------------------------------------------------------------------------------------ writes
class TestFailedWrites:
    def test_full_disk_leaves_old_set(self, tmp_path, monkeypatch):
        post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
        post.save(tmp_path / "f", png=True)
        before = {n: (tmp_path / n).read_bytes() for n in visible_files(tmp_path)}
        calls = {"n": 0}
        real = cv2.imwrite

        def full(path, img, *a):
            calls["n"] += 1
            if calls["n"] == 2:  # the std PNG: the npz and the mean PNG were written already
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(path, img, *a)

        monkeypatch.setattr(cv2, "imwrite", full)
        from dataclasses import replace

        with pytest.raises(OutputError, match="disk full"):
            replace(post, mean=post.mean + 1).save(tmp_path / "f", png=True)
        assert {n: (tmp_path / n).read_bytes() for n in visible_files(tmp_path)} == before
        assert sorted(p.name for p in tmp_path.iterdir()) == visible_files(tmp_path)  # no temporary left

    def test_full_disk_single_file(self, tmp_path, monkeypatch):
        def full(*a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(np, "savez_compressed", full)
        with pytest.raises(OutputError, match="disk full") as info:
            gio.save_npz(tmp_path / "x.npz", a=np.ones(3))
        assert isinstance(info.value, OSError)
        assert list(tmp_path.iterdir()) == []

    def test_unwritable_folder(self, tmp_path, monkeypatch):
        def denied(*a, **k):
            raise PermissionError(errno.EACCES, "Permission denied")

        monkeypatch.setattr(gio.durable.tempfile, "mkstemp", denied)
        monkeypatch.setattr(gio.durable.tempfile, "mkdtemp", denied)
        with pytest.raises(OutputError, match="permission denied"):
            gio.save_npz(tmp_path / "x.npz", a=np.ones(3))
        with pytest.raises(OutputError, match="permission denied"):
            _complete_with(config=EXACT, engine=EXACT_ENGINE).save(tmp_path / "y", png=True)
        assert visible_files(tmp_path) == []

    def test_write_together_all_or_nothing(self, tmp_path):
        gio.atomic_write(tmp_path / "a.txt", lambda p: p.write_text("old"))
        with pytest.raises(OutputError, match="disk full"):
            with gio.write_together():
                gio.atomic_write(tmp_path / "a.txt", lambda p: p.write_text("new"))
                gio.atomic_write(tmp_path / "b.txt", lambda p: p.write_text("new"))
                assert (tmp_path / "a.txt").read_text() == "old"  # nothing renamed yet

                def full(p):
                    raise OSError(errno.ENOSPC, "No space left on device")

                gio.atomic_write(tmp_path / "c.txt", full)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
        assert (tmp_path / "a.txt").read_text() == "old"
        with gio.write_together():
            gio.atomic_write(tmp_path / "a.txt", lambda p: p.write_text("new"))
            gio.atomic_write(tmp_path / "b.txt", lambda p: p.write_text("new"))
        assert [(tmp_path / n).read_text() for n in ("a.txt", "b.txt")] == ["new", "new"]

    def test_stale_files_of_killed_runs_are_removed(self, tmp_path):
        post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
        post.save(tmp_path / "f", png=True)
        stale = [tmp_path / ".f.abcd1234.tmp.npz", tmp_path / ".f_mean.abcd1234.tmp.png"]
        for p in stale:
            p.write_bytes(b"x" * 100)
        (tmp_path / ".other.abcd1234.tmp.npz").write_bytes(b"not ours")
        post.save(tmp_path / "f", png=True)
        assert not any(p.exists() for p in stale)
        assert (tmp_path / ".other.abcd1234.tmp.npz").exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == [
            ".other.abcd1234.tmp.npz",
            "f.npz",
            "f_mean.png",
            "f_std.png",
        ]

    def test_png_false_after_png_true_drops_old_pngs(self, tmp_path):
        post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
        post.save(tmp_path / "f", png=True)
        post.save(tmp_path / "f", png=False)
        assert visible_files(tmp_path) == ["f.npz"]

    def test_plain_files_of_older_versions_are_taken_over(self, tmp_path):
        post = _complete_with(config=EXACT, engine=EXACT_ENGINE)
        gio.save_npz(tmp_path / "f.npz", mean=np.zeros(2))
        gio.save_depth_png(tmp_path / "f_mean.png", np.ones((3, 3)))
        post.save(tmp_path / "f", png=True)
        assert visible_files(tmp_path) == ["f.npz", "f_mean.png", "f_std.png"]
        assert_one_set(tmp_path, "f")


# ------------------------------------------------------------------------------------------ CLI cases
@pytest.fixture(scope="module")
def cli_inputs(tmp_path_factory) -> Path:
    t = tmp_path_factory.mktemp("cli_inputs")
    mde, sparse = small_problem(h=24, w=32)
    np.save(t / "mde.npy", mde)
    far = mde * 10.0
    far[:4] = 500.0  # a band of sky beyond the 16-bit PNG's 256 m
    np.save(t / "far.npy", far)
    np.save(t / "mde_mm.npy", mde * 1000.0)
    np.savetxt(t / "points_mm.txt", np.stack([sparse.u, sparse.v, 1000.0 * sparse.depth], 1))
    np.savetxt(t / "points_cm.txt", np.stack([sparse.u, sparse.v, 100.0 * sparse.depth], 1))
    np.savetxt(t / "points.txt", np.stack([sparse.u, sparse.v, sparse.depth], 1))
    below = sparse.v >= 4.5  # the points see the street, not the sky
    np.savetxt(t / "points_far.txt", np.stack([sparse.u, sparse.v, 10.0 * sparse.depth], 1)[below])
    np.save(t / "strs.npy", np.array([["a", "b"], ["c", "d"]]))
    np.save(t / "zeros.npy", np.zeros_like(mde))
    (t / "binary.txt").write_bytes(bytes(range(256)) * 8)
    (t / "a_file").write_text("x")
    (t / "scan.bin").write_bytes(np.zeros((10, 4), np.float32).tobytes())
    np.save(t / "big_mde.npy", (2 + np.random.default_rng(0).random((1500, 2000))).astype(np.float32))
    (t / "calib_x2.txt").write_text(
        "P2: 721.5 0 609.6 44.9 0 721.5 172.9 0.2 0 0 1 0.003\n"
        "R0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -2 0 0 0 0 -2 0 2 0 0 0\n"
    )
    (t / "calib.txt").write_text(
        "P2: 721.5 0 609.6 44.9 0 721.5 172.9 0.2 0 0 1 0.003\n"
        "R0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n"
    )
    return t


def _complete_args(t: Path, out: Path, *extra: str, mde: str = "mde.npy", points: str = "points.txt") -> list[str]:
    return ["complete", "--mde", str(t / mde), "--sparse", str(t / points), "--output", str(out), *extra]


# (id, argv builder (inputs folder, output folder), text of the one-line error)
CLI_CASES = [
    ("bad option value", lambda t, o: _complete_args(t, o / "x", "--preset", "paper", "--gp.nu", "3.7"), "nu"),
    (
        "non-number option",
        lambda t, o: _complete_args(t, o / "x", "--preset", "paper", "--gp.lengthscale", "abc"),
        "lengthscale",
    ),
    ("unknown option", lambda t, o: ["complete", "--mdee", "x.npy"], "--mde"),
    ("mde of strings", lambda t, o: _complete_args(t, o / "x", mde="strs.npy"), "dtype"),
    (
        "binary calib",
        lambda t, o: [
            "complete",
            "--mde",
            str(t / "mde.npy"),
            "--lidar",
            str(t / "scan.bin"),
            "--calib",
            str(t / "binary.txt"),
            "--output",
            str(o / "x"),
        ],
        "binary",
    ),
    (
        "lidar without image size",
        lambda t, o: [
            "complete",
            "--mde",
            str(t / "mde.npy"),
            "--lidar",
            str(t / "scan.bin"),
            "--calib",
            str(t / "calib.txt"),
            "--output",
            str(o / "x"),
        ],
        "lidar-image-size",
    ),
    ("output size huge", lambda t, o: _complete_args(t, o / "x", "--output-size", "100000", "100000"), "output_shape"),
    ("mde png scale 0", lambda t, o: _complete_args(t, o / "x", "--mde-png-scale", "0"), "--mde-png-scale"),
    ("mde png scale nan", lambda t, o: _complete_args(t, o / "x", "--mde-png-scale", "nan"), "--mde-png-scale"),
    (
        "gt png scale negative",
        lambda t, o: _complete_args(t, o / "x", "--gt", str(t / "mde.npy"), "--gt-png-scale", "-1"),
        "--gt-png-scale",
    ),
    ("gt missing", lambda t, o: _complete_args(t, o / "x", "--gt", str(t / "missing.png")), "not found"),
    ("gt corrupt", lambda t, o: _complete_args(t, o / "x", "--gt", str(t / "binary.txt")), "binary.txt"),
    ("output empty", lambda t, o: _complete_args(t, ""), "name"),
    ("gt without a valid pixel", lambda t, o: _complete_args(t, o / "x", "--gt", str(t / "zeros.npy")), "--gt"),
    ("output is a directory", lambda t, o: _complete_args(t, (o / "d.npz").mkdir() or o / "d"), "directory"),
    ("output under a file", lambda t, o: _complete_args(t, t / "a_file" / "x"), "file"),
    ("gt invalid value", lambda t, o: _complete_args(t, o / "x", "--gt-invalid-value", "-1"), "--gt-invalid-value"),
    (
        "lidar image size 0",
        lambda t, o: _complete_args(t, o / "x", "--lidar-image-size", "0", "10"),
        "--lidar-image-size",
    ),
    (
        "lidar image size without lidar",
        lambda t, o: _complete_args(t, o / "x", "--lidar-image-size", "24", "32"),
        "without --lidar",
    ),
    (
        "calib without lidar",
        lambda t, o: _complete_args(t, o / "x", "--calib", str(t / "calib.txt")),
        "without --lidar",
    ),
    ("view a .npy", lambda t, o: ["view", "--posterior", str(t / "mde.npy"), "--duration", "0"], "npz"),
    ("view duration -1", lambda t, o: ["view", "--posterior", str(t / "x.npz"), "--duration", "-1"], "--duration"),
    (
        "view bad host",
        lambda t, o: ["view", "--posterior", str(t / "x.npz"), "--host", "999.1.1.1", "--duration", "1"],
        "host",
    ),
    (
        "view remote host",
        lambda t, o: ["view", "--posterior", str(t / "x.npz"), "--host", "0.0.0.0", "--duration", "1"],
        "--allow-remote",
    ),
    (
        "eval onto a file",
        lambda t, o: ["eval", "--data", str(t), "--output", str(t / "a_file")],
        "a file is in the way",
    ),
    ("demo onto a file", lambda t, o: ["demo", "--output", str(t / "a_file" / "d")], "is a file"),
    (
        "batch onto a file",
        lambda t, o: ["batch", "--data", str(t), "--output", str(t / "a_file" / "b"), "--workers", "0"],
        "file",
    ),
    (
        "batch bad address",
        lambda t, o: ["batch", "--data", str(t), "--output", str(o / "b"), "--address", "not-an-address"],
        "address",
    ),
    ("eval seed -1", lambda t, o: ["eval", "--data", str(t), "--output", str(o / "ev"), "--seed", "-1"], "--seed"),
    (
        "eval device tpu",
        lambda t, o: ["eval", "--data", str(t), "--output", str(o / "ev"), "--device", "tpu"],
        "--device",
    ),
    (
        "lidar calib scaled",
        lambda t, o: [
            "complete",
            "--mde",
            str(t / "mde.npy"),
            "--lidar",
            str(t / "scan.bin"),
            "--calib",
            str(t / "calib_x2.txt"),
            "--lidar-image-size",
            "375",
            "1242",
            "--output",
            str(o / "x"),
        ],
        "Tr_velo_to_cam",
    ),
    (
        "output size beyond the memory limit",
        lambda t, o: _complete_args(t, o / "x", "--output-size", "11000", "12000", mde="big_mde.npy"),
        "memory limit",
    ),
    (
        "points in millimetres",
        lambda t, o: _complete_args(t, o / "x", points="points_mm.txt"),
        "millimetres, convert them with --sparse-scale 0.001",
    ),
    (
        "points in millimetres, no png",
        lambda t, o: _complete_args(t, o / "x", "--no-png", points="points_mm.txt"),
        "--sparse-scale 0.001",
    ),
    (
        "points in centimetres",
        lambda t, o: _complete_args(t, o / "x", points="points_cm.txt"),
        "centimetres, convert them with --sparse-scale 0.01",
    ),
    (
        "mde in millimetres",
        lambda t, o: _complete_args(t, o / "x", mde="mde_mm.npy", points="points_mm.txt"),
        "--mde-scale 0.001",
    ),
    ("sparse scale 0", lambda t, o: _complete_args(t, o / "x", "--sparse-scale", "0"), "--sparse-scale"),
    ("unknown preset", lambda t, o: _complete_args(t, o / "x", "--preset", "nope"), "--preset"),
    ("two presets", lambda t, o: _complete_args(t, o / "x", "--preset", "paper", "--preset=residual"), "--preset"),
    ("preset without a name", lambda t, o: _complete_args(t, o / "x", "--preset"), "--preset"),
    (
        "front-end without --rgb",
        lambda t, o: ["complete", "--mde", "fastdepth", "--sparse", str(t / "points.txt"), "--output", str(o / "x")],
        "--rgb",
    ),
    (
        "unknown front-end",
        lambda t, o: [
            "complete",
            "--mde",
            "nonet",
            "--rgb",
            str(t / "mde.npy"),
            "--sparse",
            str(t / "points.txt"),
            "--output",
            str(o / "x"),
        ],
        "nonet",
    ),
]


@pytest.mark.parametrize("case", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_cli_case_one_line_exit_1(case, cli_inputs, tmp_path, capsys):
    name, build, text = case
    argv = build(cli_inputs, tmp_path)
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("gpdepth3d: warning")]
    assert len(lines) == 1 and lines[0].startswith("gpdepth3d: error: "), err
    assert "unexpected" not in lines[0] and "Traceback" not in err
    assert text in lines[0], lines[0]
    assert visible_files(tmp_path) in ([], ["d.npz"])  # nothing written
    record("cli_cases", "exit 1, one line, nothing written")


def test_png_saturates_at_its_range_and_npz_keeps_true_values(tmp_path):
    post = _far()
    with pytest.warns(gio.PNGRangeWarning, match=r"192 of 192 pixels beyond 256.0 m"):
        written = post.save(tmp_path / "far", png=True)
    assert [p.name for p in written] == ["far.npz", "far_mean.png", "far_std.png"]
    assert np.all(cv2.imread(str(written[1]), cv2.IMREAD_UNCHANGED) == 65535)
    np.testing.assert_allclose(DepthPosterior.load(written[0]).mean, post.mean, rtol=1e-6)
    with pytest.raises(InvalidDepthError, match="256"):  # without saturate the range is refused
        gio.depth_png_values(post.mean)


def test_cli_far_depths_saturate_the_png_with_one_warning(cli_inputs, tmp_path, capsys):
    argv = _complete_args(cli_inputs, tmp_path / "x", mde="far.npy", points="points_far.txt") + [
        "--preset",
        "residual",
        "--engine.name",
        "exact",
    ]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    warning = [line for line in out.splitlines() if "beyond 256.0 m" in line]
    assert len(warning) == 1 and warning[0].startswith("warning: posterior mean")
    assert visible_files(tmp_path) == ["x.npz", "x_depth_preview.png", "x_mean.png", "x_sigma_preview.png", "x_std.png"]
    assert np.load(tmp_path / "x.npz")["mean"].max() > 256


@pytest.mark.slow
def test_kitti_sky_pixel_beyond_png_range_does_not_fail_the_run(shared_data, tmp_path, capsys):
    """The README's `complete` line on KITTI object frame 000001 (sky pixels beyond 256 m): exit 0, a warning."""
    k = shared_data / "kitti_object"
    argv = [
        "complete",
        "--rgb",
        str(k / "000001.png"),
        "--mde",
        "rtmonodepth",
        "--lidar",
        str(k / "000001.bin"),
        "--calib",
        str(k / "calib_000001.txt"),
        "--output",
        str(tmp_path / "k1"),
        "--models-dir",
        str(shared_data.parent / "models"),
    ]
    assert cli.main(argv) == 0
    warning = [line for line in capsys.readouterr().out.splitlines() if "beyond 256.0 m" in line]
    assert len(warning) == 1 and warning[0].startswith("warning: posterior mean")
    n = int(warning[0].split(": ")[2].split(" of ")[0])
    mean = np.load(tmp_path / "k1.npz")["mean"]
    assert n == int(np.count_nonzero(np.rint(mean / gio.KITTI_PNG_SCALE) > 65535)) > 0
    png = cv2.imread(str(tmp_path / "k1_mean.png"), cv2.IMREAD_UNCHANGED)
    assert int(np.count_nonzero(png == 65535)) == n


def test_cli_scales_convert_millimetres(cli_inputs, tmp_path):
    base = ["--preset", "residual", "--engine.name", "exact", "--no-preview"]
    assert cli.main(_complete_args(cli_inputs, tmp_path / "m") + base) == 0
    argv = _complete_args(cli_inputs, tmp_path / "mm", mde="mde_mm.npy", points="points_mm.txt")
    assert cli.main(argv + base + ["--mde-scale", "0.001", "--sparse-scale", "0.001"]) == 0
    metres, converted = np.load(tmp_path / "m.npz"), np.load(tmp_path / "mm.npz")
    np.testing.assert_allclose(converted["mean"], metres["mean"], rtol=1e-5)


def test_likely_unit():
    from gpdepth3d.measurements import check_metres, likely_unit

    assert likely_unit(np.array([1.5, 3.0, 80.0, 0.0, np.nan])) is None  # metres, indoor to street
    assert likely_unit(np.array([2729.0, 1500.0, 4000.0])) == ("millimetres", 1e-3)
    assert likely_unit(np.array([273.0, 150.0, 400.0])) == ("centimetres", 1e-2)
    assert likely_unit(np.zeros(3)) is None
    with pytest.raises(InvalidDepthError, match="look like millimetres, convert them with --x 0.001"):
        check_metres(np.full((4, 4), 2500.0), "depths", "--x")


def test_cli_output_folder_writes_inside_it(cli_inputs, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    base = ["--preset", "residual", "--engine.name", "exact", "--no-preview", "--no-png"]
    assert cli.main(_complete_args(cli_inputs, "out/") + base) == 0  # a new folder, named with a slash
    assert visible_files(tmp_path) == ["out"] and visible_files(tmp_path / "out") == ["mde.npz"]
    assert cli.main(_complete_args(cli_inputs, tmp_path / "out") + base) == 0  # an existing folder
    assert visible_files(tmp_path / "out") == ["mde.npz"]


def test_cli_without_gt_removes_the_old_error_preview(cli_inputs, tmp_path):
    argv = _complete_args(cli_inputs, tmp_path / "x") + ["--preset", "residual", "--engine.name", "exact", "--no-png"]
    assert cli.main(argv + ["--gt", str(cli_inputs / "mde.npy")]) == 0
    assert "x_error_preview.png" in visible_files(tmp_path)
    assert cli.main(argv) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npz", "x_depth_preview.png", "x_sigma_preview.png"]


def test_cli_unwritable_output(cli_inputs, tmp_path, capsys, monkeypatch):
    """A read-only folder (simulated: the tests may run as root, which writes anyway) and a full disk."""
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, **k: False if str(p).startswith(str(tmp_path)) else real_access(p, mode, **k)
    )
    assert cli.main(_complete_args(cli_inputs, tmp_path / "ro" / "x")) == 1
    assert "not writable" in capsys.readouterr().err
    monkeypatch.setattr(os, "access", real_access)

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", full)
    argv = _complete_args(cli_inputs, tmp_path / "x") + ["--preset", "residual", "--engine.name", "exact"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "disk full" in err[0]
    assert visible_files(tmp_path) == []


def test_cli_full_disk_during_the_previews_keeps_the_old_set(cli_inputs, tmp_path, capsys, monkeypatch):
    """The previews are part of the set: a full disk while the sigma preview is written leaves the old files."""
    from matplotlib.figure import Figure

    base = ["--preset", "residual", "--engine.name", "exact"]
    assert cli.main(_complete_args(cli_inputs, tmp_path / "x") + base + ["--gt", str(cli_inputs / "mde.npy")]) == 0
    before = _fingerprint(tmp_path)
    assert "x_error_preview.png" in before
    real, calls = Figure.savefig, {"n": 0}

    def full(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", full)
    capsys.readouterr()
    assert cli.main(_complete_args(cli_inputs, tmp_path / "x", mde="far.npy", points="points_far.txt") + base) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "disk full" in err[0]
    assert _fingerprint(tmp_path) == before  # the old set, its error preview included; no temporary


def test_cli_eval_full_disk_leaves_no_partial_set(cli_inputs, tmp_path, capsys, monkeypatch):
    """eval's files are written together: a full disk at the third file leaves none of them."""
    import gpdepth3d.cli.eval as eval_cli

    def fake_run(data, *, output, **kwargs):  # the library's run: three files, the third onto a full disk
        gio.atomic_write(Path(output) / "results.csv", lambda p: p.write_text("a"))
        gio.atomic_write(Path(output) / "summary.csv", lambda p: p.write_text("b"))

        def full(p):
            raise OSError(errno.ENOSPC, "No space left on device")

        gio.atomic_write(Path(output) / "results.json", full)

    monkeypatch.setattr(eval_cli, "run_evaluation", fake_run)
    assert cli.main(["eval", "--data", str(cli_inputs), "--output", str(tmp_path / "ev")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "disk full" in err[0]
    assert visible_files(tmp_path / "ev") == [] and list((tmp_path / "ev").iterdir()) == []


# ------------------------------------------------------------------------------------------ property test
def test_property_typed_error_or_exact_posterior():
    """Random small inputs: a typed error, or a finite posterior (variance >= 0) equal to the exact engine's."""
    pytest.importorskip("hypothesis")
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    @st.composite
    def inputs(draw):
        h, w = draw(st.integers(2, 9)), draw(st.integers(2, 9))
        dtype = draw(st.sampled_from([np.float64, np.float32, np.int32, np.uint16]))
        magnitude = 10.0 ** draw(st.integers(-3, 5))
        seed = draw(st.integers(0, 2**16))
        rng = np.random.default_rng(seed)
        mde = (magnitude * (1.0 + rng.random((h, w)))).astype(dtype)
        holes = draw(st.sampled_from(["none", "nan", "zero", "all"]))
        if holes != "none" and np.issubdtype(mde.dtype, np.floating):
            mask = rng.random((h, w)) < (1.0 if holes == "all" else 0.3)
            mde[mask] = np.nan if holes == "nan" else 0.0
        n = draw(st.integers(0, 6))
        depth = magnitude * (1.0 + rng.random(n)) * draw(st.sampled_from([1.0, 1.0, 3.0, 0.2]))
        sh, sw = draw(st.sampled_from([(h, w), (2 * h, 2 * w), (h + 1, w)]))
        sparse = SparseDepth.from_arrays(
            rng.uniform(-0.5, sw - 0.6, n), rng.uniform(-0.5, sh - 0.6, n), depth, (sh, sw)
        )
        config = DepthGPConfig(
            formulation=draw(st.sampled_from(["balanced", "residual"])),
            nu=draw(st.sampled_from([0.5, 1.5, 2.5])),
            lengthscale=draw(st.sampled_from([0.5, 1.5, 4.0, 30.0])),
            outputscale=draw(st.sampled_from([0.05, 0.2, 1.0])),
            sigma_dl=draw(st.sampled_from([0.01, 0.05, 0.5])),
            sigma_meas=draw(st.sampled_from([0.001, 0.01, 0.1])),
            units=draw(st.sampled_from(["relative", "metres"])),
            align=draw(st.sampled_from(["none", "scale", "scale_shift"])),
        )
        out = draw(st.sampled_from([None, (h, w), (2 * h, 2 * w), (h + 1, max(2, w - 1))]))
        return mde, sparse, config, out

    examples = int(os.environ.get("GPDEPTH3D_FUZZ_EXAMPLES", "40"))  # a longer sweep: set it to 2000

    @settings(max_examples=examples, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
    @given(inputs())
    def check(args):
        mde, sparse, config, out = args
        try:
            fast = complete(mde, sparse, config=config, output_shape=out)
        except GPDepthError as exc:
            counts[type(exc).__name__] = counts.get(type(exc).__name__, 0) + 1
            return
        counts["posterior"] = counts.get("posterior", 0) + 1
        exact = complete(mde, sparse, config=config, engine=EXACT_ENGINE, output_shape=out)
        assert np.all(np.isfinite(fast.mean)) and np.all(np.isfinite(fast.variance))
        assert np.all(fast.variance >= -1e-9 * np.max(np.abs(exact.variance) + 1e-300))
        scale = max(float(np.max(np.abs(exact.mean))), 1e-12)
        np.testing.assert_allclose(fast.mean, exact.mean, atol=1e-6 * scale, rtol=1e-6)
        np.testing.assert_allclose(fast.variance, exact.variance, atol=1e-6 * scale**2, rtol=1e-5)

    counts: dict[str, int] = {}
    check()
    print(f"property sweep: {counts}")  # shown with pytest -s
    for key, n in counts.items():
        record("property_sweep", key, n)
    assert counts.get("posterior", 0) > 0


# ------------------------------------------------------------------------------------------ kills
def assert_one_set(folder: Path, stem: str, allowed_mdes: list[np.ndarray] | None = None) -> np.ndarray | None:
    """The files of ``stem`` are absent or one complete, consistent set; returns its MDE (None if absent)."""
    names = [f"{stem}.npz", f"{stem}_mean.png", f"{stem}_std.png"]
    present = [(folder / n).is_file() for n in names]
    if not any(present):
        return None
    assert all(present), f"incomplete set: {dict(zip(names, present))}"
    with np.load(folder / names[0]) as d:
        mean, std, mde = d["mean"].astype(np.float64), d["std"].astype(np.float64), d["mde"]
    np.testing.assert_allclose(gio.load_depth(folder / names[1]), np.where(mean > 0, mean, 0), atol=0.6 / 256)
    np.testing.assert_allclose(gio.load_depth(folder / names[2]), std, atol=0.6 / 256)
    if allowed_mdes is not None:
        assert any(np.allclose(mde, m, rtol=1e-6) for m in allowed_mdes), "a set of no known call"
    return mde


def _fork_save_killed_at(post: DepthPosterior, base: Path, step: int) -> bool:
    """Runs ``post.save(base, png=True)`` in a forked child that dies (os._exit) at its ``step``-th file-system
    change; returns whether the save finished before that step."""
    pid = os.fork()
    if pid == 0:  # child
        try:
            counter = {"n": 0}

            def dying(fn):
                def call(*a, **k):
                    counter["n"] += 1
                    if counter["n"] == step:
                        os._exit(3)
                    return fn(*a, **k)

                return call

            for mod, name in (
                (os, "replace"),
                (os, "symlink"),
                (os, "link"),
                (os, "unlink"),
                (shutil, "rmtree"),
                (gio.durable.tempfile, "mkdtemp"),
                (gio.durable.tempfile, "mkstemp"),
            ):
                setattr(mod, name, dying(getattr(mod, name)))
            post.save(base, png=True)
            os._exit(0)
        except BaseException:
            os._exit(4)
    _, status = os.waitpid(pid, 0)
    code = os.waitstatus_to_exitcode(status)
    assert code in (0, 3), f"child failed with {code}"
    return code == 0


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_save_killed_at_every_step_leaves_old_or_new_set(tmp_path):
    mde, sparse = small_problem()
    posts = [complete(mde * (1 + k), sparse, config=EXACT, engine=EXACT_ENGINE) for k in range(3)]
    known = [p.mde for p in posts]
    # first save into an empty folder, then over a plain (pre-set) npz, then over a set
    scenarios = [("empty", None), ("plain", "plain"), ("set", "set")]
    for label, prepare in scenarios:
        folder = tmp_path / label
        folder.mkdir()
        if prepare == "plain":
            posts[0].save(folder / "f", png=False)  # a plain f.npz ...
            gio.save_depth_png(folder / "f_mean.png", posts[0].mean)  # ... with plain PNGs beside it
            gio.save_depth_png(folder / "f_std.png", posts[0].std)
        elif prepare == "set":
            posts[0].save(folder / "f", png=True)
        step, finished = 1, False
        while not finished:
            finished = _fork_save_killed_at(posts[1 + step % 2], folder / "f", step)
            gio.clean_output_set(
                folder / "f", ["f.npz", "f_mean.png", "f_std.png"]
            )  # what a reader or the next run does
            got = assert_one_set(folder, "f", known)
            if prepare is not None:
                assert got is not None, f"{label}: the old set vanished at step {step}"
            step += 1
            assert step < 60
        assert assert_one_set(folder, "f", known) is not None
        print(f"save killed at each of its {step - 2} file-system steps ({label}): always one set")
        posts[0].save(folder / "f", png=True)  # the next save cleans what the kills left
        assert sorted(p.name for p in folder.iterdir()) == ["f.npz", "f_mean.png", "f_std.png"]


def _complete_cmd(inputs: Path, out: Path, mde: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "gpdepth3d.cli",
        "complete",
        "--mde",
        str(inputs / mde),
        "--sparse",
        str(inputs / "points.txt"),
        "--output",
        str(out),
        "--preset",
        "residual",
        "--engine.name",
        "exact",
    ]


SET_NAMES = ["f.npz", "f_mean.png", "f_std.png", "f_depth_preview.png", "f_sigma_preview.png", "f_error_preview.png"]


def _fingerprint(folder: Path) -> dict[str, bytes]:
    """Every file in ``folder`` (hidden ones included) -> its content (an npz: its arrays, a zip's time stamps aside)."""
    out = {}
    for p in sorted(folder.iterdir()):
        if p.suffix == ".npz" and not p.name.startswith("."):
            with np.load(p) as d:
                out[p.name] = b"".join(np.ascontiguousarray(d[k]).tobytes() for k in ("mean", "variance", "mde"))
        else:
            out[p.name] = p.read_bytes() if p.is_file() else b"<folder>"
    return out


@pytest.mark.slow
def test_complete_killed_at_random_moments(cli_inputs, tmp_path):
    """SIGKILL of `gpdepth3d complete` (previews included) at random moments, alternating a call with --gt
    and one without: after the next writer's recovery exactly the old or the new set is on disk (all six
    names: a call without --gt has no error preview), and the next run leaves no temporary."""
    mde = np.load(cli_inputs / "mde.npy")
    np.save(tmp_path / "a.npy", mde)
    np.save(tmp_path / "b.npy", mde * 1.5)
    shutil.copy(cli_inputs / "points.txt", tmp_path / "points.txt")
    calls = {
        "a": _complete_cmd(tmp_path, Path("OUT") / "f", "a.npy") + ["--gt", str(tmp_path / "a.npy")],
        "b": _complete_cmd(tmp_path, Path("OUT") / "f", "b.npy"),
    }
    refs, duration = {}, 0.0
    for k, argv in calls.items():  # the reference sets, each from an uninterrupted call
        (tmp_path / f"ref_{k}").mkdir()
        t0 = time.monotonic()
        subprocess.run([x.replace("OUT", str(tmp_path / f"ref_{k}")) for x in argv], check=True, capture_output=True)
        duration = max(duration, time.monotonic() - t0)
        refs[k] = _fingerprint(tmp_path / f"ref_{k}")
    assert "f_error_preview.png" in refs["a"] and "f_error_preview.png" not in refs["b"]
    assert set(refs["a"]) - {"f_error_preview.png"} == set(refs["b"])
    out = tmp_path / "out"
    out.mkdir()
    subprocess.run([x.replace("OUT", str(out)) for x in calls["a"]], check=True, capture_output=True)
    assert _fingerprint(out) == refs["a"]
    rng = random.Random(0)
    outcome = {"killed": 0, "finished": 0, "old set": 0, "new set": 0, "leftovers cleaned": 0}
    state = "a"
    rounds = int(os.environ.get("GPDEPTH3D_KILL_ROUNDS", "6"))
    for round_ in range(rounds):
        new = "b" if state == "a" else "a"
        proc = subprocess.Popen(
            [x.replace("OUT", str(out)) for x in calls[new]], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        time.sleep(rng.uniform(0.5, 1.15) * duration if round_ < rounds - 1 else 0.5 * duration)  # the last: killed
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        outcome["killed" if proc.wait() == -signal.SIGKILL else "finished"] += 1
        # what a reader (DepthPosterior.load) or the next writer does: finish a commit, remove dead temporaries
        outcome["leftovers cleaned"] += gio.clean_output_set(out / "f", SET_NAMES) > 0
        got = _fingerprint(out)
        assert got in (refs["a"], refs["b"]), f"round {round_}: a mixed set {sorted(got)}"
        outcome["new set" if got == refs[new] else "old set"] += 1
        state = "a" if got == refs["a"] else "b"
    print(f"random kills of complete: {outcome}")
    assert outcome["killed"] >= 1
    subprocess.run([x.replace("OUT", str(out)) for x in calls["b"]], check=True, capture_output=True)  # the next run
    assert _fingerprint(out) == refs["b"]  # its set, no temporary, nothing hidden, no stale error preview


@pytest.mark.slow
def test_concurrent_completes_leave_one_set(cli_inputs, tmp_path):
    """Two `gpdepth3d complete` processes on one --output: both succeed and one whole set is left."""
    mde = np.load(cli_inputs / "mde.npy")
    np.save(tmp_path / "a.npy", mde)
    np.save(tmp_path / "b.npy", mde * 2)
    shutil.copy(cli_inputs / "points.txt", tmp_path / "points.txt")
    known = [mde, mde * 2]
    for _ in range(int(os.environ.get("GPDEPTH3D_CONCURRENT_ROUNDS", "2"))):
        procs = [
            subprocess.Popen(
                _complete_cmd(tmp_path, tmp_path / "out" / "f", n), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            )
            for n in ("a.npy", "b.npy")
        ]
        for p in procs:
            _, err = p.communicate()
            assert p.returncode == 0, err
        assert assert_one_set(tmp_path / "out", "f", known) is not None


# ------------------------------------------------------------------------------------------ CLI sweep
def cli_sweep_cases(t: Path, out: Path) -> list[list[str]]:
    """Garbage for every option of every command: the CLI sweep summarised in docs/reliability.md."""
    import itertools

    rng = np.random.default_rng(0)
    np.save(t / "mde.npy", 2 + rng.random((24, 32)))
    np.savetxt(t / "p.txt", [[3, 4, 2.0], [10, 5, 2.5]])
    (t / "bin.txt").write_bytes(bytes(range(256)) * 4)
    (t / "afile").write_text("x")
    np.save(t / "c.npy", np.ones((4, 4)) * (1 + 1j))
    np.save(t / "obj.npy", np.array([1, None], dtype=object), allow_pickle=True)
    np.save(t / "d1.npy", np.ones(5))
    (t / "empty.txt").write_text("")
    seven, kitti = str(t / "no_7scenes"), str(t / "no_kitti")
    data = os.environ.get("GPDEPTH3D_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    if Path(data).is_dir():
        seven, kitti = f"{data}/7scenes", f"{data}/kitti_tiny"
    o = iter(range(10**6))
    base = lambda: ["complete", "--mde", f"{t}/mde.npy", "--sparse", f"{t}/p.txt", "--output", f"{out}/o{next(o)}"]  # noqa: E731
    bad_values = ["nan", "-1", "0", "inf", "abc", "", "1e400", "99999999999"]
    cases = []
    for opt in ["--mde-png-scale", "--sparse-png-scale", "--gt-png-scale", "--gt-invalid-value"]:
        cases += [base() + [opt, v] for v in bad_values]
    for opt in ["--output-size", "--lidar-image-size"]:
        cases += [
            base() + [opt, a, b] for a, b in itertools.product(["0", "-5", "nan", "2.5", "100000"], ["10", "abc"])
        ]
    for f in [
        f"{t}/c.npy",
        f"{t}/obj.npy",
        f"{t}/d1.npy",
        f"{t}/bin.txt",
        f"{t}/afile",
        f"{t}/empty.txt",
        "/nonexistent.npy",
        str(t),
    ]:
        cases.append(["complete", "--mde", f, "--sparse", f"{t}/p.txt", "--output", f"{out}/o{next(o)}"])
        cases.append(base()[:4] + [f, "--output", f"{out}/o{next(o)}"])
        cases.append(base() + ["--gt", f])
        cases.append(base() + ["--intrinsics", f, "--sparse-points", "xyz"])
        cases.append(["complete", "--mde", f"{t}/mde.npy", "--lidar", f, "--calib", f, "--output", f"{out}/o{next(o)}"])
    fields = [
        "--gp.nu",
        "--gp.lengthscale",
        "--gp.outputscale",
        "--gp.sigma-dl",
        "--gp.sigma-meas",
        "--gp.max-exact-points",
    ]
    for model, opt in itertools.product(["paper", "residual"], fields):
        cases += [base() + ["--preset", model, opt, v] for v in ["nan", "-1", "0", "abc", "inf", "1e-320"]]
    for model in ["paper", "residual"]:
        for opt, v in [
            ("--gp.units", "feet"),
            ("--gp.align", "x"),
            ("--engine.name", "gpu"),
            ("--gp.formulation", "x"),
        ]:
            cases.append(base() + ["--preset", model, opt, v])
    cases += [base()[:-1] + [o_] for o_ in ["", f"{t}/afile/x", str(t), "/proc/x"]]
    np.savetxt(t / "p_mm.txt", [[3, 4, 2000.0], [10, 5, 2500.0]])
    np.save(t / "mde_mm.npy", 1000 * (2 + rng.random((24, 32))))
    np.savetxt(t / "K.txt", [[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    cases += [base()[:4] + [f"{t}/p_mm.txt"] + base()[4:] + a for a in [[], ["--no-png"], ["--sparse-scale", "0.001"]]]
    cases += [
        ["complete", "--mde", f"{t}/mde_mm.npy", "--sparse", f"{t}/p.txt", "--output", f"{out}/o{next(o)}"] + a
        for a in [[], ["--mde-scale", "0.001"], ["--mde-scale", "-1"]]
    ]
    cases += [
        base() + [opt, v] for opt in ("--sparse-scale", "--mde-scale") for v in ["0", "nan", "-1", "abc", "1e400"]
    ]
    cases += [
        base() + a
        for a in [
            ["--ply", f"{out}/c.ply"],
            ["--ply", f"{out}/c.txt"],
            ["--ply", f"{t}/afile/c.ply"],
            ["--ply", f"{out}/c.ply", "--intrinsics", f"{t}/K.txt"],
            ["--ply", str(t)],
        ]
    ]
    cases += [base()[:-1] + [f"{out}/folder{next(o)}/"], base() + ["--gt", f"{t}/zeros.npy"]]
    np.save(t / "zeros.npy", np.zeros((24, 32)))
    cases += [["view", "--posterior", "x.npz", "--duration", v] for v in ["-1", "nan", "abc"]]
    cases += [
        ["view", "--posterior", "x.npz", "--host", h, "--duration", "0"]
        for h in ["999.1.1.1", "0.0.0.0", "", "::", "example.invalid", "1.2.3.4"]
    ]
    cases += [["view", "--posterior", "x.npz", "--port", p, "--duration", "0"] for p in ["-1", "70000", "abc"]]
    cases += [
        ["view", "--posterior", f"{t}/bin.txt", "--duration", "0"],
        ["view", "--posterior", f"{t}/mde.npy", "--duration", "0"],
    ]
    cases += [
        ["demo"] + a
        for a in [["--output", f"{t}/afile/x"], ["--output", f"{out}/demo"], ["--seed", "-1"], ["--seed", "abc"]]
    ]
    cases += [
        ["eval"] + a
        for a in [
            ["--data", str(t)],
            ["--data", "/nonexistent"],
            ["--data", seven, "--output", f"{t}/afile"],
            ["--data", seven, "--protocol", "bogus"],
            ["--data", seven, "--points", "a,b"],
            ["--data", seven, "--stride", "0"],
            ["--data", seven, "--frames", "-1"],
            ["--data", seven, "--resolution", "nan"],
            ["--data", seven, "--methods", "x"],
        ]
    ]
    cases += [
        ["batch", "--data", kitti, "--output", f"{out}/b"] + a
        for a in [
            ["--address", "not-an-address"],
            ["--output", f"{t}/afile/x"],
            ["--workers", "-1"],
            ["--frames", "-3"],
            ["--repeat", "0"],
            ["--factor", "0"],
            ["--n-input", "-5"],
            ["--connect-timeout", "-1"],
        ]
    ]
    cases += [["fuse"] + a for a in [["--data", "/nonexistent"], ["--data", str(t)], ["--output", f"{t}/afile/x"]]]
    return cases


@pytest.mark.skipif(
    not os.environ.get("GPDEPTH3D_FUZZ_CLI"), reason="the CLI sweep runs with GPDEPTH3D_FUZZ_CLI=1 (minutes)"
)
def test_cli_sweep(tmp_path):
    """Every command line of `cli_sweep_cases` exits 0 (a valid, if odd, input) or prints one line and exits 1."""
    import contextlib
    import io

    counts = {"exit 1, one line": 0, "exit 0": 0, "unexpected": 0, "several lines": 0, "other exit": 0}
    (tmp_path / "in").mkdir()
    for argv in cli_sweep_cases(tmp_path / "in", tmp_path / "out"):
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                rc = cli.main(argv)
            except SystemExit as exc:
                rc = exc.code
        lines = [
            line
            for line in err.getvalue().splitlines()
            if line.strip() and not line.startswith(("gpdepth3d: warning", "INFO:")) and "%|" not in line
        ]
        if rc == 1 and any("unexpected" in line for line in lines):
            key = "unexpected"
        elif rc == 1:
            key = "exit 1, one line" if len(lines) == 1 else "several lines"
        else:
            key = "exit 0" if rc == 0 else "other exit"
        counts[key] += 1
    leftovers = (
        [p for p in (tmp_path / "out").rglob("*") if p.name.startswith(".")] if (tmp_path / "out").exists() else []
    )
    print(f"CLI sweep: {sum(counts.values())} command lines: {counts}; leftover temporaries {len(leftovers)}")
    for key, n in counts.items():
        record("cli_sweep", key, n)
    record("cli_sweep", "leftover temporaries", len(leftovers))
    assert counts["unexpected"] == counts["several lines"] == counts["other exit"] == 0
    assert leftovers == []


def test_typed_errors_pickle_with_their_attributes():
    """Errors cross process boundaries (Dask workers, multiprocessing) intact."""
    import pickle

    from gpdepth3d.errors import ConnectionFailedError, ProblemTooLargeError

    for error in (
        InvalidInputError("a", "b", [1]),
        ShapeError("s", "t", (2,)),
        DataFormatError("p", "q"),
        OutputError("o", "disk full"),
        ConnectionFailedError("tcp://h:1", "no answer"),
        ProblemTooLargeError("big"),
    ):
        back = pickle.loads(pickle.dumps(error))
        assert type(back) is type(error) and str(back) == str(error) and vars(back) == vars(error)


# ------------------------------------------------------------------------------------------ sizes
MEMORY_GUARD_SCRIPT = r"""
import json, resource, struct, sys, time, zipfile, zlib
from pathlib import Path
import numpy as np
import cv2
import gpdepth3d as g
from gpdepth3d import io as gio
from gpdepth3d.datasets.base import Frame

t = Path(sys.argv[1])
rng = np.random.default_rng(0)
def points(h, w):
    return g.SparseDepth.from_arrays(rng.uniform(0, w - 1, 50), rng.uniform(0, h - 1, 50), 2 + rng.random(50), (h, w))
big_mde, small_mde = 2 + rng.random((1500, 2000)), 2 + rng.random((240, 320))
big_pts, small_pts = points(1500, 2000), points(240, 320)
g.complete(small_mde[:24, :32], points(24, 32))  # warm: the engine's kernels, BLAS threads, allocator arenas
header = {"descr": "<f8", "fortran_order": False, "shape": (200000, 200000)}
with open(t / "forged.npy", "wb") as f:
    np.lib.format.write_array_header_1_0(f, header)
    f.write(b"\0" * (300 - f.tell()))
with zipfile.ZipFile(t / "forged.npz", "w") as z:
    z.writestr("depth.npy", (t / "forged.npy").read_bytes())
cv2.imwrite(str(t / "small.png"), np.ones((4, 4), np.uint16))
png = bytearray((t / "small.png").read_bytes())
png[16:24] = struct.pack(">II", 100000, 100000)
png[29:33] = struct.pack(">I", zlib.crc32(bytes(png[12:29])) & 0xFFFFFFFF)
(t / "forged.png").write_bytes(bytes(png))
frame = Frame(name="f", rgb=np.zeros((375, 1242, 3), np.uint8), depth=np.ones((375, 1242)))
cases = {
    "output 11000x12000 from a 1500x2000 MDE": lambda: g.complete(big_mde, big_pts, output_shape=(11000, 12000)),
    "16x output 3840x5120 from a 240x320 MDE": lambda: g.complete(small_mde, small_pts, output_shape=(3840, 5120)),
    "Frame.resized(100)": lambda: frame.resized(100),
    "npy header claiming 200000^2": lambda: gio.load_depth(t / "forged.npy"),
    "npz header claiming 200000^2": lambda: gio.load_depth(t / "forged.npz"),
    "PNG header claiming 100000^2 (depth)": lambda: gio.load_depth(t / "forged.png"),
    "PNG header claiming 100000^2 (image)": lambda: gio.load_rgb(t / "forged.png"),
}
with open("/proc/self/statm") as f:
    vm = int(f.read().split()[0]) * resource.getpagesize()
cap = vm + 2**30  # one more GiB of address space than the process holds now
resource.setrlimit(resource.RLIMIT_AS, (cap, resource.getrlimit(resource.RLIMIT_AS)[1]))
out = {}
for name, call in cases.items():
    cpu, wall = time.process_time(), time.perf_counter()
    try:
        call()
        kind, message = "no error", ""
    except BaseException as exc:
        kind, message = type(exc).__name__, str(exc)
    out[name] = {"error": kind, "message": message, "cpu_s": time.process_time() - cpu, "wall_s": time.perf_counter() - wall}
print(json.dumps(out))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS and /proc/self/statm")
def test_sizes_refused_before_memory_is_spent_under_a_memory_cap(tmp_path):
    """Each size case of the fuzz gets its typed error within a second, in a process capped at +1 GiB of memory."""
    import json

    script = tmp_path / "guard.py"
    script.write_text(MEMORY_GUARD_SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    run = subprocess.run(
        [sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, env=env, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    results = json.loads(run.stdout.strip().splitlines()[-1])
    expected = {"npy header claiming 200000^2": "DataFormatError", "npz header claiming 200000^2": "DataFormatError"}
    for name, r in results.items():
        assert r["error"] == expected.get(name, "ProblemTooLargeError"), (name, r)
        assert r["cpu_s"] < 1.0, (name, r)
    sizes = {
        "output 11000x12000": "(11000, 12000)",
        "16x output": "(3840, 5120)",
        "Frame.resized": "(37500, 124200)",
        "PNG header": "(100000, 100000, 3)",
    }
    for name, r in results.items():
        if r["error"] == "ProblemTooLargeError":
            size = next(v for k, v in sizes.items() if name.startswith(k))
            assert size in r["message"] and "memory limit of" in r["message"], r["message"]
    print({k: (r["error"], round(r["cpu_s"], 3)) for k, r in results.items()})


def test_memory_limit_reads_its_setting(monkeypatch):
    from gpdepth3d import limits
    from gpdepth3d.errors import ProblemTooLargeError

    monkeypatch.setenv(limits.ENV_VAR, "1")
    assert limits.memory_limit() <= 2**20
    with pytest.raises(ProblemTooLargeError, match=r"output_shape \(48, 64\) from an MDE map of shape \(24, 32\)"):
        check_output_shape((48, 64), (24, 32))
    for bad in ("abc", "-5", "nan", "0"):
        monkeypatch.setenv(limits.ENV_VAR, bad)
        with pytest.raises(InvalidInputError, match=limits.ENV_VAR):
            limits.memory_limit()
    monkeypatch.setenv(limits.ENV_VAR, "100000000")
    assert limits.memory_limit() < 100000000 * 2**20  # capped by the free memory
    assert (
        limits.completion_bytes((10, 10), (20, 20))
        == 400 * limits.COMPLETION_BYTES_PER_OUTPUT_PIXEL + 100 * limits.COMPLETION_BYTES_PER_INPUT_PIXEL
    )


def test_cli_ply_cloud_with_sigma(cli_inputs, tmp_path):
    """complete --ply: one point per pixel, coloured by --rgb, with the posterior's sigma; part of the output set."""
    np.savetxt(tmp_path / "K.txt", [[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[..., 1] = 200
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb[..., ::-1])
    argv = _complete_args(cli_inputs, tmp_path / "out" / "x") + [
        "--preset",
        "residual",
        "--engine.name",
        "exact",
        "--intrinsics",
        str(tmp_path / "K.txt"),
        "--rgb",
        str(tmp_path / "rgb.png"),
        "--ply",
        str(tmp_path / "out" / "x.ply"),
        "--output-size",
        "48",
        "64",
    ]
    assert cli.main(argv) == 0
    from gpdepth3d.mapping.cloud import ColoredCloud

    post = DepthPosterior.load(tmp_path / "out" / "x.npz")
    cloud = ColoredCloud.load_ply(tmp_path / "out" / "x.ply")
    assert len(cloud) == 48 * 64 and np.all(cloud.colors == [0, 200, 0])
    np.testing.assert_allclose(np.sort(cloud.points[:, 2]), np.sort(post.mean.ravel()), rtol=1e-5)
    np.testing.assert_allclose(np.sort(cloud.variance), np.sort(post.variance.ravel()), rtol=1e-4)
    # the camera was resized to the output grid (fx 60, cx 31.5): the first point is pixel (0, 0)
    z = post.mean[0, 0]
    np.testing.assert_allclose(cloud.points[0], [-31.5 / 60 * z, -23.5 / 60 * z, z], rtol=1e-5)


@pytest.mark.parametrize("extra, text", [(["--ply", "x.txt"], ".ply"), (["--ply", "x.ply"], "--intrinsics")])
def test_cli_ply_refused_before_work(cli_inputs, tmp_path, capsys, extra, text):
    assert cli.main(_complete_args(cli_inputs, tmp_path / "x") + extra) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and text in err[0]
    assert visible_files(tmp_path) == []


def test_memory_guard_holds_without_an_output_size(monkeypatch):
    """The MDE's own size goes through the guard too: a large MDE with no output size is refused, not allocated."""
    monkeypatch.setenv("GPDEPTH3D_MAX_MEMORY_MB", "1")
    with pytest.raises(ProblemTooLargeError, match="GPDEPTH3D_MAX_MEMORY_MB"):
        check_output_shape(None, (300, 400))
    mde, sparse = small_problem(h=200, w=200)
    with pytest.raises(ProblemTooLargeError):
        complete(mde, sparse, config=EXACT)
    monkeypatch.delenv("GPDEPTH3D_MAX_MEMORY_MB")
    with pytest.raises(ProblemTooLargeError, match="above the memory limit of 4.00 GiB"):
        check_output_shape(None, (3000, 4000))  # the documented 4 GiB default; a 3000x4000 MDE needs more


def test_view_of_a_posterior_with_a_corrupt_member_is_one_line(tmp_path, capsys):
    """A posterior whose stored K fails its CRC: the viewer's intrinsics lookup leaves it to the loader's typed error."""
    import zipfile
    from dataclasses import replace

    mde, sparse = small_problem()
    post = replace(complete(mde, sparse, config=EXACT), K=np.array([[10.0, 0, 8], [0, 10, 6], [0, 0, 1]]))
    path = post.save(tmp_path / "p.npz")[0]
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("K.npy")
        at = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.compress_size - 4
    data = bytearray(path.read_bytes())
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))
    assert cli.main(["view", "--posterior", str(path), "--duration", "0"]) == 1
    err = capsys.readouterr().err
    assert "DataFormatError" not in err and "unexpected" not in err and "Bad CRC-32" in err


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: PinholeCamera(1e5, 1e5, 5e4, 5e4, 100_000, 100_000).pixel_grid(), "pixel grid"),
        (lambda: PinholeCamera(1e9, 1e9, 5e8, 5e8, 10**9, 10**9).pixel_grid(), "pixel grid"),
    ],
)
def test_sizes_beyond_memory_are_typed(call, match):
    with pytest.raises(ProblemTooLargeError, match=match):
        call()


def test_huge_resize_and_keyframe_id_are_typed():
    from gpdepth3d.datasets.base import Frame
    from gpdepth3d.mapping.frame_inputs import check_keyframe_id

    frame = Frame("a", np.zeros((48, 64, 3), np.uint8), PinholeCamera(50, 50, 32, 24, 64, 48))
    with pytest.raises(ProblemTooLargeError, match="more than 1e308 bytes"):
        frame.resized(1e300)
    with pytest.raises(InvalidInputError, match="int64"):
        check_keyframe_id(2**70)
    assert check_keyframe_id(2**62) == 2**62


# ------------------------------------------------------------------------------------------ messages
@pytest.mark.parametrize(
    "argv, hint",
    [
        (["complete", "--mde", "x.npy", "--outptu", "o"], "(did you mean --output?)"),
        (["map", "--images", "a", "--poses", "b", "--voxel-szie", "0.1"], "(did you mean --voxel-size?)"),
        (["complete", "--mde", "a.npy", "--output", "o", "--gp.lenghtscale", "2"], "(did you mean --gp.lengthscale?)"),
    ],
)
def test_cli_typos_get_a_suggestion(argv, hint, capsys):
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert hint in err and len(err.strip().splitlines()) == 1


def test_missing_extras_are_named_by_the_code_that_needs_them():
    from gpdepth3d.extras import missing_dependency

    def raised_in(path: str) -> BaseException:
        scope: dict = {}
        exec(compile("def f():\n    raise ModuleNotFoundError('No module', name='torch')\n", path, "exec"), scope)
        try:
            scope["f"]()
        except ModuleNotFoundError as exc:
            return exc

    assert 'pip install "gpdepth3d[kissgp]"' in str(missing_dependency(raised_in("/x/gpdepth3d/gp/kissgp.py")))
    assert 'pip install "gpdepth3d[mapping]"' in str(missing_dependency(raised_in("/x/gpdepth3d/mapping/fusion.py")))


def test_batch_without_dask_names_the_option(monkeypatch):
    from gpdepth3d.pipelines.batch import _import_dask

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match="--workers 0"):
        _import_dask()


def test_map_has_the_option_its_host_error_names():
    import inspect

    from gpdepth3d.cli.map import map_command
    from gpdepth3d.viewer.app import check_host

    with pytest.raises(InvalidInputError, match="--allow-remote"):
        check_host("0.0.0.0")
    assert "allow_remote" in inspect.signature(map_command).parameters


def test_warnings_are_grouped_plain_and_name_the_image(capsys):
    import warnings

    from gpdepth3d.cli._warnings import quiet_third_party, report_warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_third_party()  # numba's TBB notice stays out even under "always"
        warnings.warn_explicit(
            "\x1b[1mThe TBB threading layer requires TBB version 2021 update 6 or later\x1b[0m",
            UserWarning,
            "/site-packages/numba/np/ufunc/parallel.py",
            1,
            module="numba.np.ufunc.parallel",
        )
        for k in (3, 4, 19):
            warnings.warn(f"frame {k}: only {k} usable points: \x1b[31mthe MDE\x1b[0m", UserWarning)
    report_warnings(caught, {3: "img_a", 4: "img_b", 19: "img_c"})
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["gpdepth3d: warning: image img_a: only 3 usable points: the MDE (and 2 more like it)"]


def test_eval_device_reaches_the_default_model():
    """`eval --device cuda` is not ignored by the default GP: it runs there, or says the device is missing."""
    torch = pytest.importorskip("torch")

    from gpdepth3d.evaluation.evaluation import MethodSuite

    mde, sparse = small_problem()
    suite = MethodSuite(device="cuda")
    if torch.cuda.is_available():
        assert suite.run("gp_default", mde, sparse).mean.shape == mde.shape
    else:
        with pytest.raises(InvalidInputError, match="no CUDA GPU"):
            suite.run("gp_default", mde, sparse)
    assert MethodSuite().run("gp_default", mde, sparse).mean.shape == mde.shape


def test_jpeg_with_random_scan_bytes_is_refused(tmp_path):
    """OpenCV decodes random entropy-coded data without a word (a wrong image); the reader refuses it."""
    rng = np.random.default_rng(0)
    for progressive in (0, 1):
        ok, enc = cv2.imencode(
            ".jpg", rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive]
        )
        (tmp_path / f"ok{progressive}.jpg").write_bytes(enc.tobytes())
        assert gio.load_rgb(tmp_path / f"ok{progressive}.jpg").shape == (120, 160, 3)
    data = bytearray((tmp_path / "ok0.jpg").read_bytes())  # baseline: OpenCV decodes its random scan
    sos = data.find(b"\xff\xda")
    start = sos + 2 + int.from_bytes(data[sos + 2 : sos + 4], "big")
    data[start:-2] = rng.integers(0, 256, len(data) - 2 - start, dtype=np.uint8).tobytes()
    (tmp_path / "random.jpg").write_bytes(bytes(data))
    assert cv2.imread(str(tmp_path / "random.jpg")) is not None  # what the library used to return
    with pytest.raises(DataFormatError, match="corrupt JPEG data"):
        gio.load_rgb(tmp_path / "random.jpg")
