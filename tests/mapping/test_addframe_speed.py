"""What `Mapper.add_frame` does ahead for speed gives the results of doing it when needed.

Descriptors found on a background thread (`Refinder.add(prefetch=True)`) and a frame's descriptor matches
computed ahead (`Refinder.prepare`).
"""

from __future__ import annotations


import numpy as np
import pytest

from gpdepth3d.mapping.points.refinding import Refinder


def _six_hololens_frames(shared_data):
    """Frames 19-24 of the HoloLens walk: (RGB images, their poses T_world_camera, the camera)."""
    import cv2

    from gpdepth3d.camera import PinholeCamera

    folder = shared_data / "hololens"
    if not folder.is_dir():
        pytest.skip(f"HoloLens sequence not found at {folder}")
    names = sorted(p.name for p in (folder / "images").glob("*.png"))
    poses = np.loadtxt(folder / "poses_images.txt").reshape(-1, 4, 4)[19:25]
    rgbs = [cv2.cvtColor(cv2.imread(str(folder / "images" / names[i])), cv2.COLOR_BGR2RGB) for i in range(19, 25)]
    K = np.loadtxt(folder / "K.txt").reshape(3, 3)
    return rgbs, poses, PinholeCamera.from_K(K, rgbs[0].shape[1], rgbs[0].shape[0])


@pytest.mark.slow  # SIFT on six real images, twice
def test_prefetched_descriptors_equal_the_ones_computed_when_needed(shared_data):
    """`Refinder.add(prefetch=True)` gives the same features, and so the same points, as computing them lazily."""
    rgbs, poses, cam = _six_hololens_frames(shared_data)
    lazy, ahead = Refinder(cam), Refinder(cam)
    for k, rgb in enumerate(rgbs):
        lazy.add(rgb, poses[k], key=k)
        ahead.add(rgb, poses[k], key=k, prefetch=True)
    a, b = lazy.points(3, 2.0), ahead.points(3, 2.0)
    assert len(a) > 20
    for field in ("u", "v", "depth", "sigma"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    for k in range(len(rgbs)):
        fa, fb = lazy._features(k), ahead._features(k)
        np.testing.assert_array_equal(fa.uv, fb.uv)
        np.testing.assert_array_equal(fa.descriptors, fb.descriptors)


@pytest.mark.slow  # SIFT on six real images, twice
def test_matches_prepared_ahead_give_the_same_points(shared_data):
    """`Refinder.prepare` matches a frame's views on the background thread; `points` then gives what it gives
    without (a view `prepare` did not pick is matched there), and `triangulate_frames(matches=)` checks them."""
    from gpdepth3d.errors import InvalidInputError
    from gpdepth3d.mapping.points.tracks import build_tracks

    rgbs, poses, cam = _six_hololens_frames(shared_data)
    plain, ahead = Refinder(cam), Refinder(cam)
    for k in range(5):
        plain.add(rgbs[k], poses[k], key=k)
        ahead.add(rgbs[k], poses[k], key=k)
    ahead.prepare(2, 2.0)  # before the last frame comes: a view it picks later is matched in `points`
    assert ahead._ahead and all(pair[0] == 2 for pair in ahead._ahead)
    plain.add(rgbs[5], poses[5], key=5)
    ahead.add(rgbs[5], poses[5], key=5)
    a, b = plain.points(2, 2.0), ahead.points(2, 2.0)
    assert len(a) > 20 and not ahead._ahead  # taken (or dropped) by `points`
    for field in ("u", "v", "depth", "sigma"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    with pytest.raises(InvalidInputError, match="matches"):
        build_tracks(rgbs[:2], list(poses[:2]), cam, config=plain.triangulation, matches=[None])
