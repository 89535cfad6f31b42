"""Tests of gpdepth3d.mapping.points.refinding: views chosen by parallax, descriptor points across large motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.points.refinding import RefindConfig, Refinder, select_views
from gpdepth3d.mapping.points.triangulation import TrackTriangulator


def _at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[0, 3] = x
    return T


class TestSelectViews:
    def test_parallax_range_target_and_angle(self):
        candidates = {
            "same place": _at(0.01),  # baseline / depth 0.005: no parallax
            "near": _at(0.1),  # 0.05
            "ideal": _at(0.3),  # 0.15, the target
            "far": _at(1.0),  # 0.5
            "too far": _at(2.0),  # 1.0
            "turned away": _at(0.3, yaw_deg=90.0),
        }
        cfg = RefindConfig(views=3)
        assert select_views(_at(0.0), 2.0, candidates, cfg) == [
            "ideal",
            "near",
            "far",
        ]  # |log(p / 0.15)|: 0, 1.10, 1.20
        assert select_views(_at(0.0), 2.0, candidates, RefindConfig(views=1)) == ["ideal"]
        # the same baselines seen from farther away: less parallax, the far view becomes the best one
        assert select_views(_at(0.0), 6.0, candidates, RefindConfig(views=1)) == ["far"]
        assert select_views(_at(0.0), 2.0, {"same place": _at(0.01)}, cfg) == []

    def test_bad_options(self):
        with pytest.raises(InvalidInputError, match="detector"):
            RefindConfig(detector="akaze")
        with pytest.raises(InvalidInputError, match="min_parallax"):
            RefindConfig(min_parallax=0.5, max_parallax=0.1)
        with pytest.raises(InvalidInputError, match="views"):
            RefindConfig(views=0)
        with pytest.raises(InvalidInputError, match="depth"):
            select_views(_at(0.0), float("nan"), {}, RefindConfig())


def _hololens(root: Path, indices) -> tuple[list, list, list, PinholeCamera]:
    import cv2

    folder = root / "hololens"
    if not folder.is_dir():
        pytest.skip(f"HoloLens sequence not found at {folder}")
    names = sorted(p.name for p in (folder / "images").glob("*.png"))
    poses = np.loadtxt(folder / "poses_images.txt").reshape(-1, 4, 4)
    K = np.loadtxt(folder / "K.txt").reshape(3, 3)
    rgbs, depths = [], []
    for i in indices:
        rgbs.append(cv2.cvtColor(cv2.imread(str(folder / "images" / names[i])), cv2.COLOR_BGR2RGB))
        depths.append(cv2.imread(str(folder / "depth" / names[i]), cv2.IMREAD_UNCHANGED) / 1000.0)
    cam = PinholeCamera.from_K(K, rgbs[0].shape[1], rgbs[0].shape[0])
    return rgbs, [poses[i] for i in indices], depths, cam


class TestRealMotion:
    def test_descriptors_refind_what_klt_loses_with_honest_sigma(self, shared_data):
        # HoloLens walk, every 4th frame: frames 19-26 move ~0.3 m and turn between images. KLT tracks
        # through the window triangulate (almost) nothing in frame 22; the descriptor points are many,
        # and +-2 sigma covers most of their errors against the sensor depth
        idx = list(range(16, 27))
        rgbs, poses, depths, cam = _hololens(shared_data, idx)
        ref = idx.index(22)
        tracker = TrackTriangulator(cam, window=8, lag=4)
        klt = {}
        for k, (rgb, T) in enumerate(zip(rgbs, poses)):
            sp = tracker.add(rgb, T, key=k)
            if tracker.last_key is not None:
                klt[tracker.last_key] = len(sp)
        refinder = Refinder(cam)
        for k, (rgb, T) in enumerate(zip(rgbs, poses)):
            refinder.add(rgb, T, key=k)
        d = depths[ref]
        points = refinder.points(ref, float(np.median(d[d > 0])))
        assert klt[ref] < 30 and len(points) > 60
        iu, iv = np.rint(points.u).astype(int), np.rint(points.v).astype(int)
        gt = d[iv, iu]
        ok = gt > 0
        within = np.abs(points.depth[ok] - gt[ok]) <= 2 * points.sigma[ok]
        assert ok.sum() > 50 and 0.85 <= within.mean() <= 0.98  # honest: neither too tight nor too wide
        assert np.median(np.abs(points.depth[ok] - gt[ok]) / gt[ok]) < 0.1  # ~0.25 m baselines
        # nothing remembered under that key, or re-finding off: no points, no error
        assert len(refinder.points("unknown", 2.0)) == 0
        off = Refinder(cam, RefindConfig(detector="none"))
        off.add(rgbs[ref], poses[ref], key=0)
        assert len(off.points(0, 2.0)) == 0

    def test_pool_forgets_oldest_and_takes_new_poses(self, shared_data):
        rgbs, poses, _, cam = _hololens(shared_data, [0, 1, 2])
        refinder = Refinder(cam, RefindConfig(pool=2))
        for k in range(3):
            refinder.add(rgbs[k], poses[k], key=k)
        assert list(refinder._frames) == [1, 2]
        moved = poses[1].copy()
        moved[0, 3] += 1.0
        refinder.update_poses({1: moved, 7: np.eye(4)})
        np.testing.assert_array_equal(refinder._frames[1][1], moved)


@pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
def test_mapper_refinds_where_tracks_fail_and_reports_frames_without_points(shared_data):
    # the Mapper's defaults (KLT, window 8, lag 4) on the HoloLens walk, frames 16-29, with a stand-in MDE
    # (the sensor depth hole-filled, 12 % too far): with re-finding the frames whose tracks break get
    # descriptor points; without it some frames have (almost) none and fall back to their MDE, reported
    # (the local map, which fills such frames from the earlier ones' points, is off to see re-finding alone)
    from scipy.ndimage import distance_transform_edt

    from gpdepth3d.mapping.mapper import Mapper
    from gpdepth3d.mapping.mapper_config import MapperConfig

    idx = list(range(16, 30))
    rgbs, poses, depths, cam = _hololens(shared_data, idx)

    def standin(depth):
        _, (ri, ci) = distance_transform_edt(depth <= 0, return_indices=True)
        return 1.12 * depth[ri, ci]

    def run(refind: RefindConfig):
        # held_out off: the stand-in MDE is the sensor depth hole-filled, rescaled it can beat the GP
        mapper = Mapper(cam, MapperConfig(working_scale=0.5, refind=refind, local_map_frames=0, held_out=0.0))
        results = [mapper.add_frame(rgb, T, mde_depth=standin(d)) for rgb, T, d in zip(rgbs, poses, depths)]
        return [r for r in results if r is not None] + mapper.flush()

    on, off = run(RefindConfig()), run(RefindConfig(detector="none"))
    points_on, points_off = np.array([len(r.sparse) for r in on]), np.array([len(r.sparse) for r in off])
    assert len(on) == len(off) == len(idx) and all(r.fused for r in on)
    assert (
        np.all(points_on >= points_off)
        and (points_off < 20).sum() >= 2
        and (points_on < 20).sum() < (points_off < 20).sum()
    )
    lonely = [r for r in off if len(r.sparse) == 0]
    assert len(lonely) >= 2
    for r in lonely:  # a frame without points: fused down-weighted, and said so
        assert r.fused and r.fallback_weight == 0.5 and any("no points" in w for w in r.warnings)
    assert all(r.fallback_weight < 0.01 for r in on if len(r.sparse) > 60)
