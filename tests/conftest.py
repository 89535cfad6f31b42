"""Shared pytest fixtures: the real-data folder, one 7-Scenes frame and small synthetic frames.

Keep this file small and stable: other test modules rely on these fixtures. Real data lives in
``../shared/data`` beside the repository (override with the environment variable
``GPDEPTH3D_DATA``); tests that need it are skipped with a message when it is absent.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.datasets.synthetic import SyntheticFrame, make_scene

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """The real-data folder: $GPDEPTH3D_DATA, else ../shared/data from the repository root."""
    env = os.environ.get("GPDEPTH3D_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of the real-data folder; skips the test when it is absent."""
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set GPDEPTH3D_DATA to the shared/data folder)")
    return path


@dataclass(frozen=True)
class SevenScenesFrame:
    """One 7-Scenes RGB-D frame: rgb (480, 640, 3) uint8, depth (480, 640) metres (0 = invalid)."""

    rgb: np.ndarray
    depth: np.ndarray
    camera: PinholeCamera
    T_world_camera: np.ndarray
    path: Path


def load_seven_scenes_frame(root: Path, index: int = 0) -> SevenScenesFrame:
    """Reads frame ``index`` of ``root/7scenes`` (Kinect depth in mm, 65535 = invalid)."""
    from gpdepth3d.io import load_depth, load_rgb

    folder = root / "7scenes"
    stem = folder / f"frame-{index:06d}"
    if not Path(f"{stem}.depth.png").is_file():
        pytest.skip(f"7-Scenes frame {stem}.depth.png not found")
    depth = load_depth(f"{stem}.depth.png", png_scale=1e-3, invalid_value=65535)
    K = np.loadtxt(folder / "camera-intrinsics.txt")
    camera = PinholeCamera.from_K(K, depth.shape[1], depth.shape[0])
    return SevenScenesFrame(load_rgb(f"{stem}.color.jpg"), depth, camera, np.loadtxt(f"{stem}.pose.txt"), stem)


@pytest.fixture(scope="session")
def seven_scenes_frame(shared_data: Path) -> SevenScenesFrame:
    """Frame 0 of ../shared/data/7scenes (skips when absent)."""
    return load_seven_scenes_frame(shared_data, 0)


@pytest.fixture(scope="session")
def street_frame() -> SyntheticFrame:
    """Simulated street frame (320x96, seed 0, default LiDAR and MDE)."""
    return make_scene(0, kind="street")


@pytest.fixture(scope="session")
def room_frame() -> SyntheticFrame:
    """Simulated room frame (160x120, seed 0, default LiDAR and MDE)."""
    return make_scene(0, kind="room")


@pytest.fixture(scope="session")
def tiny_street_frame() -> SyntheticFrame:
    """Small simulated street frame (64x24) for tests with the dense exact engine."""
    return make_scene(0, kind="street", width=64, height=24)


@pytest.fixture
def break_writes(monkeypatch):
    """``break_writes("gpdepth3d.mapping.cloud")`` makes ``open`` inside that module return files whose writes
    store half the data and then raise ``OSError("disk full")`` (to test that failed exports leave no file)."""
    real_open = open

    class HalfWritten:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            self.f.write(data[: len(data) // 2])
            raise OSError("disk full")

    def apply(module: str) -> None:
        monkeypatch.setattr(f"{module}.open", lambda p, m: HalfWritten(real_open(p, m)), raising=False)

    return apply
