"""What `Mapper.add_frame` does for speed gives the results of doing it the plain way.

The held-out GP on a worker thread beside the full one (`Mapper._side_by_side`), descriptors computed ahead on
a background thread (`Refinder.add(prefetch=True)`), and `DepthCompleter.complete(warn=False)`.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter, PosteriorWarning
from gpdepth3d.gp.model import DepthGPConfig
from gpdepth3d.mapping import Mapper, MapperConfig
from gpdepth3d.mapping.points.refinding import Refinder
from gpdepth3d.measurements import SparseDepth


def _scene(h: int = 48, w: int = 64) -> np.ndarray:
    """A tilted plane with a box in front of it, metres."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    depth = 2.0 + 0.02 * u + 0.01 * v
    depth[10:30, 20:40] = 1.2
    return depth


def _points(depth: np.ndarray, n: int, seed: int, relative_noise: float = 0.0) -> SparseDepth:
    rng = np.random.default_rng(seed)
    h, w = depth.shape
    u, v = rng.integers(0, w, n).astype(float), rng.integers(0, h, n).astype(float)
    d = depth[v.astype(int), u.astype(int)] * np.exp(relative_noise * rng.normal(size=n))
    return SparseDepth.from_arrays(u, v, d, depth.shape, 0.01)


def test_complete_without_warn_keeps_the_warnings_on_the_posterior_and_issues_none():
    """Disparity given as depth warns; with ``warn=False`` the same posterior and messages, nothing issued."""
    truth = _scene()
    disparity, sparse = 1.0 / truth, _points(truth, 80, 5)
    with pytest.warns(PosteriorWarning) as issued:
        loud = DepthCompleter().complete(disparity, sparse, frame="7")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning issued fails the test
        quiet = DepthCompleter().complete(disparity, sparse, frame="7", warn=False)
    assert quiet.warnings and quiet.warnings == loud.warnings
    assert [str(w.message) for w in issued if w.category is PosteriorWarning] == list(loud.warnings)
    assert issued[0].filename == __file__  # issued at the caller of complete, as before
    np.testing.assert_array_equal(quiet.mean, loud.mean)
    np.testing.assert_array_equal(quiet.variance, loud.variance)


def _run(frames, side_by_side: bool, monkeypatch) -> tuple[Mapper, list, list]:
    camera = frames[0][3]
    mapper = Mapper(camera, MapperConfig(triangulate=False, working_scale=1.0, local_map_frames=0))
    if not side_by_side:
        monkeypatch.setattr(mapper, "_side_by_side", lambda: False)
    results = []
    with warnings.catch_warnings(record=True) as issued:
        warnings.simplefilter("always")
        for k, (rgb, mde, sparse, _, T) in enumerate(frames):
            results.append(mapper.add_frame(rgb, T, mde_depth=mde, sparse=sparse, keyframe_id=k))
    return mapper, results, sorted(str(w.message) for w in issued if w.category is PosteriorWarning)


def test_held_out_gp_beside_the_full_one_gives_the_serial_results(monkeypatch):
    """Same depth, variance, held-out check, fallbacks and warnings as the serial order, frame by frame:
    frames with good points (the GP is kept) and with wrong ones (the frame falls back to its MDE)."""
    from gpdepth3d.camera import PinholeCamera

    truth = _scene()
    camera = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
    rgb = np.full((48, 64, 3), 128, np.uint8)
    mde = 1.1 * truth + 0.05 * np.sin(np.arange(64) / 5.0)[None, :]
    frames = []
    for k in range(4):
        T = np.eye(4)
        T[0, 3] = 0.01 * k
        noise = 0.0 if k % 2 == 0 else 0.6  # odd frames: points far off, the GP predicts held-out ones worse
        frames.append((rgb, mde, _points(truth, 120, k, noise), camera, T))
    serial_mapper, serial, serial_warned = _run(frames, False, monkeypatch)
    mapper, fast, fast_warned = _run(frames, True, monkeypatch)
    assert serial_mapper._held_out_pool is None and mapper._held_out_pool is not None  # each took its path
    for a, b in zip(serial, fast):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.variance, b.variance)
        assert a.held_out == b.held_out and a.mde_fallback == b.mde_fallback and a.warnings == b.warnings
    assert {r.mde_fallback for r in fast} == {True, False}  # both branches compared
    assert fast_warned == serial_warned


def test_a_fitted_completer_keeps_the_serial_order():
    """With per-frame fitting each call starts from the previous one's fit: no worker thread."""
    from gpdepth3d.camera import PinholeCamera

    camera = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
    fitted = Mapper(camera, MapperConfig(triangulate=False, gp=DepthGPConfig(fit=True)))
    assert not fitted._side_by_side() and Mapper(camera, MapperConfig(triangulate=False))._side_by_side()


@pytest.mark.slow  # SIFT on six real images, twice
def test_prefetched_descriptors_equal_the_ones_computed_when_needed(shared_data):
    """`Refinder.add(prefetch=True)` gives the same features, and so the same points, as computing them lazily."""
    import cv2

    from gpdepth3d.camera import PinholeCamera

    folder = shared_data / "hololens"
    if not folder.is_dir():
        pytest.skip(f"HoloLens sequence not found at {folder}")
    names = sorted(p.name for p in (folder / "images").glob("*.png"))
    poses = np.loadtxt(folder / "poses_images.txt").reshape(-1, 4, 4)
    idx = list(range(19, 25))
    rgbs = [cv2.cvtColor(cv2.imread(str(folder / "images" / names[i])), cv2.COLOR_BGR2RGB) for i in idx]
    K = np.loadtxt(folder / "K.txt").reshape(3, 3)
    cam = PinholeCamera.from_K(K, rgbs[0].shape[1], rgbs[0].shape[0])
    lazy, ahead = Refinder(cam), Refinder(cam)
    for k, rgb in enumerate(rgbs):
        lazy.add(rgb, poses[idx[k]], key=k)
        ahead.add(rgb, poses[idx[k]], key=k, prefetch=True)
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
    import cv2

    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.errors import InvalidInputError
    from gpdepth3d.mapping.points.tracks import build_tracks

    folder = shared_data / "hololens"
    if not folder.is_dir():
        pytest.skip(f"HoloLens sequence not found at {folder}")
    names = sorted(p.name for p in (folder / "images").glob("*.png"))
    poses = np.loadtxt(folder / "poses_images.txt").reshape(-1, 4, 4)
    idx = list(range(19, 25))
    rgbs = [cv2.cvtColor(cv2.imread(str(folder / "images" / names[i])), cv2.COLOR_BGR2RGB) for i in idx]
    K = np.loadtxt(folder / "K.txt").reshape(3, 3)
    cam = PinholeCamera.from_K(K, rgbs[0].shape[1], rgbs[0].shape[0])
    plain, ahead = Refinder(cam), Refinder(cam)
    for k in range(5):
        plain.add(rgbs[k], poses[idx[k]], key=k)
        ahead.add(rgbs[k], poses[idx[k]], key=k)
    ahead.prepare(2, 2.0)  # before the last frame comes: a view it picks later is matched in `points`
    assert ahead._ahead and all(pair[0] == 2 for pair in ahead._ahead)
    plain.add(rgbs[5], poses[idx[5]], key=5)
    ahead.add(rgbs[5], poses[idx[5]], key=5)
    a, b = plain.points(2, 2.0), ahead.points(2, 2.0)
    assert len(a) > 20 and not ahead._ahead  # taken (or dropped) by `points`
    for field in ("u", "v", "depth", "sigma"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    with pytest.raises(InvalidInputError, match="matches"):
        build_tracks(rgbs[:2], [poses[i] for i in idx[:2]], cam, config=plain.triangulation, matches=[None])
