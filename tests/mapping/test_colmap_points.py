"""Tests of gpdepth3d.mapping.points.colmap_points: pycolmap's points with the poses held fixed, read back and mapped."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.points.colmap_points import triangulate_with_colmap
from gpdepth3d.io.poses import read_colmap_model


def _hololens(root: Path, indices):
    import cv2

    folder = root / "hololens"
    if not folder.is_dir():
        pytest.skip(f"HoloLens sequence not found at {folder}")
    names = sorted(p.name for p in (folder / "images").glob("*.png"))
    poses = np.loadtxt(folder / "poses_images.txt").reshape(-1, 4, 4)
    K = np.loadtxt(folder / "K.txt").reshape(3, 3)
    rgbs = [cv2.cvtColor(cv2.imread(str(folder / "images" / names[i])), cv2.COLOR_BGR2RGB) for i in indices]
    depths = [cv2.imread(str(folder / "depth" / names[i]), cv2.IMREAD_UNCHANGED) / 1000.0 for i in indices]
    return rgbs, [poses[i] for i in indices], depths, PinholeCamera.from_K(K, rgbs[0].shape[1], rgbs[0].shape[0])


def test_pycolmap_points_with_fixed_poses_agree_with_the_sensor_and_feed_the_mapper(shared_data, tmp_path):
    pytest.importorskip("pycolmap")
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.mapping.tsdf.fusion import FusionConfig
    from gpdepth3d.mapping.mapper import Mapper
    from gpdepth3d.mapping.mapper_config import MapperConfig

    rgbs, poses, depths, cam = _hololens(shared_data, range(6))
    model = read_colmap_model(triangulate_with_colmap(rgbs, poses, cam, tmp_path / "colmap", max_features=2000))
    assert len(model.images) == 6 and len(model.points) > 100
    for image_id, image in model.images.items():  # the poses came back as given (held fixed)
        k = int(image.name[:5])
        np.testing.assert_allclose(image.T_world_camera, poses[k], atol=1e-4)  # the file has 6 digits
    # the points lie on the sensor's surface: projected into each image, their depth agrees with the depth map
    errors = []
    for image_id, image in model.images.items():
        k = int(image.name[:5])
        T = poses[k]
        pc = (model.map_points(image_id) - T[:3, 3]) @ T[:3, :3]
        uv, z = cam.project(pc)
        inside = cam.in_image(uv) & (z > 0)
        iu = np.rint(uv[inside]).astype(int)
        d = depths[k][iu[:, 1], iu[:, 0]]
        errors.append(np.abs(z[inside][d > 0] - d[d > 0]) / d[d > 0])
    assert np.median(np.concatenate(errors)) < 0.03
    # and the Mapper takes them as SLAM map points (no own triangulation)
    config = MapperConfig(
        triangulate=False,
        working_scale=0.5,
        gp=DepthGPConfig.residual(),
        fusion=FusionConfig(voxel_size=0.05, truncation=0.15),
    )
    mapper = Mapper(cam, config)
    image_id = model.image_by_name("00003.png")
    pts = model.map_points(image_id)
    res = mapper.add_frame(
        rgbs[3],
        poses[3],
        mde_depth=np.full((180, 270), 2.0),
        map_points_world=pts,
        map_points_sigma=0.03 * np.linalg.norm(pts - poses[3][:3, 3], axis=1),
    )
    assert res.fused and res.map_points.used > 50


def test_too_few_frames_are_refused(tmp_path):
    cam = PinholeCamera(100.0, 100.0, 39.5, 29.5, 80, 60)
    with pytest.raises(InvalidInputError, match="rgbs, poses"):
        triangulate_with_colmap([np.zeros((60, 80, 3), np.uint8)], [np.eye(4)], cam, tmp_path)


def test_pycolmap_info_log_is_held_back_while_triangulating():
    pycolmap = pytest.importorskip("pycolmap")
    from gpdepth3d.mapping.points.colmap_points import _pycolmap_quiet

    before = pycolmap.logging.minloglevel
    with _pycolmap_quiet(pycolmap):
        assert pycolmap.logging.minloglevel >= 1  # warnings and errors only
    assert pycolmap.logging.minloglevel == before
