"""pycolmap structure from motion on a sequence: settings, and a short real sequence registered in one piece."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.points.colmap_sfm import SfMConfig, reconstruct_sequence


@pytest.mark.parametrize(
    "field, value",
    [("max_features", 10), ("overlap", 0), ("threads", True), ("peak_threshold", 0.0), ("min_tri_angle", -1.0)]
    + [
        ("abs_pose_min_inlier_ratio", 1.0),
        ("init_min_num_inliers", 2.5),
        ("max_reg_trials", 0),
        ("min_keypoints", -1),
        ("min_registered", 1.5),
        ("upsample", "yes"),
    ],
)
def test_config_refuses_bad_values(field, value):
    with pytest.raises(InvalidInputError, match=field):
        SfMConfig(**{field: value})


def test_mapping_options_carry_the_config():
    """pycolmap's mapper gets our registration thresholds and retries, the intrinsics held fixed."""
    pytest.importorskip("pycolmap")
    from gpdepth3d.mapping.points.colmap_sfm import _mapping_options

    config = SfMConfig(abs_pose_min_num_inliers=7, abs_pose_min_inlier_ratio=0.1, max_reg_trials=4, min_model_size=5)
    options = _mapping_options(config)
    assert options.mapper.abs_pose_min_num_inliers == 7 and options.mapper.max_reg_trials == 4
    assert options.mapper.abs_pose_min_inlier_ratio == pytest.approx(0.1) and options.min_model_size == 5
    assert not options.ba_refine_focal_length and not options.mapper.abs_pose_refine_focal_length


def test_median_keypoints_of_a_database(tmp_path):
    import sqlite3

    from gpdepth3d.mapping.points.colmap_sfm import median_keypoints

    path = tmp_path / "database.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE keypoints (image_id INTEGER, rows INTEGER, cols INTEGER, data BLOB)")
        assert median_keypoints(path) == 0.0
        db.executemany("INSERT INTO keypoints VALUES (?, ?, 6, NULL)", [(1, 300), (2, 900), (3, 1200)])
    assert median_keypoints(path) == 900.0


@pytest.mark.slow
def test_extraction_upsamples_when_the_images_give_too_few_keypoints(shared_data, tmp_path):
    """Below ``min_keypoints`` SIFT runs again on the images upsampled twice: many more keypoints."""
    pytest.importorskip("pycolmap")
    from gpdepth3d.datasets.posed import IMAGE_SUFFIXES, list_files, read_intrinsics
    from gpdepth3d.mapping.points.colmap_sfm import _extract_and_match, median_keypoints

    files = list_files(shared_data / "7scenes", IMAGE_SUFFIXES, "color", "images")[:2]
    camera = read_intrinsics("525,525,320,240", 640, 480)
    counts = []
    for k, least in enumerate((0, 10**9)):
        _extract_and_match(files, camera, tmp_path / f"{k}.db", SfMConfig(min_keypoints=least))
        counts.append(median_keypoints(tmp_path / f"{k}.db"))
    assert counts[0] > 0 and counts[1] > 2 * counts[0]


def test_needs_two_images_of_one_folder(tmp_path):
    from gpdepth3d.camera import PinholeCamera

    camera = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    with pytest.raises(InvalidInputError, match="images"):
        reconstruct_sequence([tmp_path / "a.png"], camera, tmp_path / "w")
    with pytest.raises(InvalidInputError, match="images"):
        reconstruct_sequence([tmp_path / "a" / "x.png", tmp_path / "b" / "y.png"], camera, tmp_path / "w")


@pytest.mark.slow
def test_seven_scenes_frames_register_in_one_piece(shared_data, tmp_path):
    """Eight 7-Scenes frames: every one registered, camera centres spaced like the true ones (up to scale)."""
    pytest.importorskip("pycolmap")
    from gpdepth3d.datasets.posed import IMAGE_SUFFIXES, list_files, read_intrinsics
    from gpdepth3d.io.poses import read_colmap_model

    files = list_files(shared_data / "7scenes", IMAGE_SUFFIXES, "color", "images")[:8]
    camera = read_intrinsics("525,525,320,240", 640, 480)
    # one thread: pycolmap's runs are repeatable (with two they differ from run to run)
    (folder,) = reconstruct_sequence(files, camera, tmp_path / "sfm", config=SfMConfig(threads=1))
    model = read_colmap_model(folder)
    assert sorted(image.name for image in model.images.values()) == [f.name for f in files]
    assert len(model.points) > 200 and np.median(model.errors) < 1.5
    by_name = {image.name: image.T_world_camera[:3, 3] for image in model.images.values()}
    sfm = np.array([by_name[f.name] for f in files])
    true = np.array([np.loadtxt(str(f).replace(".color.jpg", ".pose.txt"))[:3, 3] for f in files])
    step_sfm, step_true = np.diff(sfm, axis=0), np.diff(true, axis=0)
    ratio = np.linalg.norm(step_true, axis=1) / np.linalg.norm(step_sfm, axis=1)
    assert np.std(ratio) / np.mean(ratio) < 0.25  # one scale fits every step
