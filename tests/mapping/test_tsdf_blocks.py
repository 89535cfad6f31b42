"""Tests of gpdepth3d.mapping.tsdf.blocks (block keys, grid, look-up, torch views) and tsdf.storage's volume files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import DataFormatError
from gpdepth3d.mapping.tsdf.fusion import FusionConfig, TSDFFusion
from gpdepth3d.mapping.tsdf.blocks import (
    KEY_BIAS,
    blocks_to_keys,
    find_blocks,
    grid_attributes,
    keys_to_blocks,
    new_grid,
    to_torch,
    torch_device,
)
from gpdepth3d.mapping.tsdf.storage import read_volume, write_volume

CAM = PinholeCamera(120.0, 120.0, 39.5, 29.5, 80, 60)


def test_keys_round_trip_and_sort_as_x_y_z():
    rng = np.random.default_rng(0)
    blocks = rng.integers(-1000, 1000, (500, 3))
    blocks = np.vstack([blocks, [[-KEY_BIAS, -KEY_BIAS, -KEY_BIAS], [KEY_BIAS - 1] * 3, [0, 0, -1], [0, -1, 0]]])
    keys = blocks_to_keys(blocks)
    assert keys.dtype == np.int64 and np.unique(keys).size == np.unique(blocks, axis=0).shape[0]
    back = keys_to_blocks(keys)
    assert back.dtype == np.int32
    np.testing.assert_array_equal(back, blocks)
    np.testing.assert_array_equal(np.argsort(keys, kind="stable"), np.lexsort(blocks.T[::-1]))


@pytest.mark.parametrize("color, variance", [(True, True), (True, False), (False, True), (False, False)])
def test_grid_holds_the_configs_attributes(color, variance):
    o3c = pytest.importorskip("open3d.core")
    cfg = FusionConfig(integrate_color=color, integrate_variance=variance, block_resolution=4)
    names = grid_attributes(cfg)
    assert names == ("tsdf", "weight") + ("color",) * color + ("variance",) * variance
    grid = new_grid(cfg, 7, o3c.Device("CPU:0"))
    for name in names:
        shape = tuple(grid.attribute(name).shape)
        assert shape[1:] == (4, 4, 4, 3 if name == "color" else 1), (name, shape)
    assert grid.hashmap().size() == 0


def test_find_blocks_reports_the_allocated_blocks():
    fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.02, truncation=0.06))
    keys = fusion.integrate(np.full(CAM.shape, 1.5), np.eye(4)).block_keys
    far = blocks_to_keys(np.array([[500, 500, 500], [-500, 3, 7]]))
    buf, found = find_blocks(fusion.vbg, np.r_[keys, far], fusion._device)
    assert found.dtype == bool and buf.dtype == np.int64
    np.testing.assert_array_equal(found, np.r_[np.ones(keys.size, bool), False, False])
    assert np.unique(buf[found]).size == keys.size == fusion.vbg.hashmap().size()


def test_torch_views_write_through_to_open3d():
    o3c = pytest.importorskip("open3d.core")
    tensor = o3c.Tensor(np.zeros((3, 2), np.float32))
    to_torch(tensor)[1, 0] = 5.0
    assert tensor.numpy()[1, 0] == 5.0 and tensor.numpy().sum() == 5.0
    assert torch_device(o3c.Device("CPU:0")) == "cpu"


def test_volume_files_round_trip_and_bad_files_are_refused(tmp_path: Path):
    cfg = FusionConfig(voxel_size=0.03, truncation=0.09, integrate_variance=True)
    fusion = TSDFFusion(CAM, cfg)
    fusion.integrate(np.full(CAM.shape, 1.2), np.eye(4), variance=np.full(CAM.shape, 1e-3))
    path = write_volume(tmp_path / "v.npz", fusion.vbg, CAM, cfg, 3)
    meta = json.loads((tmp_path / "v.json").read_text())
    assert meta["camera"] == [120.0, 120.0, 39.5, 29.5, 80, 60] and meta["frames_integrated"] == 3
    camera, config, vbg, meta = read_volume(path)
    assert camera == CAM and config == cfg and meta["frames_integrated"] == 3
    assert vbg.hashmap().size() == fusion.vbg.hashmap().size()
    (tmp_path / "v.json").write_text(json.dumps({"camera": [1, 2], "config": {}}))
    with pytest.raises(DataFormatError, match="not a saved gpdepth3d TSDF volume"):
        read_volume(path)
    with pytest.raises(DataFormatError, match="not found"):
        read_volume(tmp_path / "missing.npz")
