"""The `Mapper`'s parts on their own: inputs, a frame's points, map scale, keyframe store, loop closure, own points."""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.mapping.frame_inputs import check_keyframe_id, check_map_points_sigma, check_mde_depth, resize_depth
from gpdepth3d.mapping.frame_points import POSE_TRACK_MIN, PendingFrame, select_measurements
from gpdepth3d.mapping.tsdf.fusion import FusionConfig, TSDFFusion
from gpdepth3d.mapping.loop_closure import moved_blocks, reintegrate
from gpdepth3d.mapping.map_scale import scale_to_map
from gpdepth3d.mapping.map_store import (
    Keyframe,
    check_map_folder,
    config_from_dict,
    load_keyframes,
    read_map_meta,
    save_keyframes,
    write_map_meta,
)
from gpdepth3d.mapping.mapper_config import MapperConfig
from gpdepth3d.mapping.own_points import OwnPoints
from gpdepth3d.mapping.points.refinding import RefindConfig
from gpdepth3d.io.poses import InvertedPoseWarning
from gpdepth3d.mapping.points.triangulation_config import TriangulationConfig
from gpdepth3d.measurements import SparseDepth

CAM = PinholeCamera(60.0, 60.0, 31.5, 23.5, 64, 48)
NORMAL = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])


def _pose(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, 0.0]
    return T


def _plane_depth(T: np.ndarray, offset: float = 2.0) -> np.ndarray:
    """(h, w) z-depth of the plane NORMAL . x = offset seen from pose T (no rotation)."""
    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], -1)
    return (offset - NORMAL @ T[:3, 3]) / (rays @ T[:3, :3].T @ NORMAL)


def _keyframes(n: int = 5) -> dict[int, Keyframe]:
    out = {}
    for k in range(n):
        T = _pose(0.05 * k, 0.02 * k)
        d = _plane_depth(T).astype(np.float32)
        rgb = np.full(CAM.shape + (3,), 40 * k, np.uint8)
        out[k] = Keyframe(k, T, d, (0.01 * d) ** 2, rgb, np.arange(k, k + 3, dtype=np.int64), points=10 * k)
    return out


class TestFrameInputs:
    def test_resize_depth(self):
        d = np.arange(12.0).reshape(3, 4)
        assert resize_depth(d, (3, 4)) is d
        small = resize_depth(np.kron(d, np.ones((2, 2))), (3, 4))  # nearest when shrinking: no mixed depths
        assert small.dtype == np.float64 and set(np.unique(small)) <= set(d.ravel())
        big = resize_depth(d, (6, 8))
        assert big.shape == (6, 8) and big.min() >= d.min() and big.max() <= d.max()

    def test_keyframe_id(self):
        assert check_keyframe_id(3) == 3 and check_keyframe_id(np.int64(4)) == 4 and check_keyframe_id(5.0) == 5
        for bad in (True, "1", float("nan"), 1.5, None):
            with pytest.raises(InvalidInputError, match="keyframe_id"):
                check_keyframe_id(bad)

    def test_map_points_sigma(self):
        np.testing.assert_array_equal(check_map_points_sigma([0.1, 0.2]), [0.1, 0.2])
        assert check_map_points_sigma(0.05).shape == ()
        for bad in (0.0, -1.0, [0.1, np.inf], [[0.1]], "x"):
            with pytest.raises(InvalidInputError, match="map_points_sigma"):
                check_map_points_sigma(bad)

    def test_mde_depth(self):
        out = check_mde_depth(np.ones((24, 32), np.float32), CAM)  # half the resolution, same aspect
        assert out.dtype == np.float64 and out.shape == (24, 32)
        for bad in (np.ones(10), np.ones((1, 5)), np.ones((48, 48))):
            with pytest.raises(ShapeError, match="mde_depth"):
                check_mde_depth(bad, CAM)


class TestPendingFrame:
    def test_notes_name_the_frame_and_stage(self):
        p = PendingFrame(7, np.eye(4), np.zeros((2, 2, 3), np.uint8))
        p.note("triangulation", ValueError("no tracks"))
        assert p.notes == ["frame 7: triangulation: ValueError: no tracks"]
        assert p.describe("gp", RuntimeError("x")) == "frame 7: gp: RuntimeError: x"

    def test_map_points(self):
        T = _pose(0.1)
        uv = np.array([[10.0, 10.0], [30.0, 20.0], [50.0, 40.0]])
        cam_pts = np.vstack([CAM.backproject_pixels(uv, np.array([1.0, 2.0, 3.0])), [[0.0, 0.0, -1.0]]])
        p = PendingFrame(2, T, np.zeros(CAM.shape + (3,), np.uint8))
        p.add_map_points(cam_pts + T[:3, 3], np.float64(0.02), CAM)
        assert len(p.parts) == 1 and sorted(p.parts[0].depth) == pytest.approx([1.0, 2.0, 3.0])
        assert (p.map_stats.used, p.map_stats.behind) == (3, 1) and not p.pose_check.inverted
        assert p.notes == ["frame 2: 0 of 4 map points outside the image, 1 behind the camera, 0 not finite"]
        bad = PendingFrame(3, T, p.work_rgb)
        bad.add_map_points(cam_pts[:, :2], None, CAM)  # not (N, 3): noted, the frame goes on without them
        assert bad.parts == [] and bad.notes[0].startswith("frame 3: map points: ShapeError")

    def test_check_tracks(self):
        p = PendingFrame(4, np.eye(4), np.zeros((2, 2, 3), np.uint8))
        p.check_tracks(POSE_TRACK_MIN - 1, 0)  # too few tracks to tell
        p.check_tracks(200, 40)  # 20 % triangulate: a plausible pose
        assert p.notes == []
        with pytest.warns(InvertedPoseWarning, match="frame 4: only 5 of 200 feature tracks"):
            p.check_tracks(200, 5)
        assert len(p.notes) == 1


class TestSelectMeasurements:
    def test_merges_and_keeps_the_most_certain_in_order(self):
        a = SparseDepth.from_arrays([1.0, 5.0, 9.0], [1.0, 2.0, 3.0], [2.0, 2.0, 4.0], (10, 12), [0.2, 0.02, 0.04])
        b = SparseDepth.from_arrays([1.0, 3.0], [1.0, 7.0], [1.0, 1.0], (10, 12), [0.5, 0.001])
        merged = select_measurements([a, b], (10, 12), 10)
        assert len(merged) == 4  # pixel (1, 1) twice: the closer kept
        kept = select_measurements([a, b], (10, 12), 2)
        assert sorted(zip(kept.u, kept.v)) == [(3, 7), (5, 2)]  # sigma / depth 0.001 and 0.01
        assert len(select_measurements([], (10, 12), 5)) == 0


class TestScaleToMap:
    def _points(self, factor: float, n: int = 200) -> tuple[SparseDepth, np.ndarray]:
        T = _pose(0.12, 0.05)
        rng = np.random.default_rng(0)
        u, v = rng.integers(0, CAM.width, n), rng.integers(0, CAM.height, n)
        depth = factor * _plane_depth(T)[v, u]
        return SparseDepth.from_arrays(u.astype(float), v.astype(float), depth, CAM.shape, 0.02 * depth), T

    def test_takes_out_a_share_of_the_scale(self):
        points, T = self._points(1.2)
        stored = list(_keyframes().values())
        scaled, s, var = scale_to_map(points, T, CAM, stored, CAM, weight=0.5)
        assert s == pytest.approx(np.sqrt(1.2), rel=0.01)
        np.testing.assert_allclose(scaled.depth, points.depth / s)
        np.testing.assert_allclose(scaled.sigma, points.sigma / s)
        assert var == pytest.approx(0.25 * np.log(1.2) ** 2, rel=0.05)

    def test_leaves_points_alone_without_a_map(self):
        points, T = self._points(1.2)
        stored = list(_keyframes().values())
        for kw in (dict(stored=stored, weight=0.0), dict(stored=[], weight=0.5), dict(stored=stored[:2], weight=0.5)):
            out, s, var = scale_to_map(points, T, CAM, kw["stored"], CAM, weight=kw["weight"])
            assert out is points and (s, var) == (1.0, 0.0)


class TestMapStore:
    def test_keyframes_round_trip(self, tmp_path):
        kfs = _keyframes(3)
        save_keyframes(tmp_path / "k.npz", kfs, CAM.shape)
        back = load_keyframes(tmp_path / "k.npz")
        assert list(back) == [0, 1, 2]
        for k, kf in kfs.items():
            for name in ("T_world_camera", "rgb", "block_keys"):
                np.testing.assert_array_equal(getattr(back[k], name), getattr(kf, name), err_msg=name)
            np.testing.assert_allclose(back[k].depth, kf.depth, rtol=2.0**-11)  # stored in half precision
            np.testing.assert_allclose(back[k].variance, kf.variance, rtol=2.0**-10)  # a half-precision sigma
            assert back[k].points == kf.points and back[k].depth.dtype == np.float32
        save_keyframes(tmp_path / "empty.npz", {}, CAM.shape)
        assert load_keyframes(tmp_path / "empty.npz") == {}

    def test_older_stores_and_bad_files(self, tmp_path):
        with np.load(save_keyframes(tmp_path / "k.npz", _keyframes(2), CAM.shape)) as d:
            old = {k: d[k] for k in d.files if k != "points"}
        np.savez(tmp_path / "old.npz", **old)  # written before the store kept the points
        assert [kf.points for kf in load_keyframes(tmp_path / "old.npz").values()] == [0, 0]
        (tmp_path / "bad.npz").write_bytes(b"not a zip")
        with pytest.raises(DataFormatError, match="not a saved keyframe store"):
            load_keyframes(tmp_path / "bad.npz")

    def test_meta_round_trip(self, tmp_path):
        config = MapperConfig(lag=2, working_scale=0.5, triangulation=TriangulationConfig(detector="orb"))
        write_map_meta(tmp_path / "mapper.json", CAM, config, frames=7, next_id=9)
        camera, back, meta = read_map_meta(tmp_path / "mapper.json")
        assert camera == CAM and back == config and (meta["frames"], meta["next_id"]) == (7, 9)
        assert read_map_meta(tmp_path / "mapper.json", MapperConfig())[1] == MapperConfig()
        assert config_from_dict(json.loads(json.dumps(asdict(config), default=list))) == config
        saved = asdict(MapperConfig())
        del saved["refind"]  # maps saved before re-finding existed
        assert config_from_dict(saved).refind == RefindConfig()
        (tmp_path / "bad.json").write_text('{"camera": [1, 2]}')
        with pytest.raises(DataFormatError, match="not a saved gpdepth3d map"):
            read_map_meta(tmp_path / "bad.json")

    def test_check_map_folder(self, tmp_path):
        with pytest.raises(DataFormatError, match="mapper.json"):
            check_map_folder(tmp_path)
        for name in ("mapper.json", "keyframes.npz"):
            (tmp_path / name).write_text("")
        with pytest.raises(DataFormatError, match="volume.npz"):
            check_map_folder(str(tmp_path))
        (tmp_path / "volume.npz").write_text("")
        assert check_map_folder(str(tmp_path)) == tmp_path


class TestLoopClosure:
    @staticmethod
    def _fuse(poses: dict, depth_poses: dict) -> tuple[TSDFFusion, dict, callable]:
        """Keyframes of the plane seen from ``depth_poses``, fused at ``poses``."""
        fusion = TSDFFusion(CAM, FusionConfig(voxel_size=0.04, truncation=0.12, integrate_variance=True))

        def integrate(depth, variance, T, rgb, blocks=None, points=0):
            return fusion.integrate(depth, T, rgb=rgb, variance=variance, blocks=blocks)

        kfs = {}
        for k, T in poses.items():
            d = _plane_depth(depth_poses[k]).astype(np.float32)
            rgb = np.full(CAM.shape + (3,), 50 * k, np.uint8)
            var = (0.01 * d) ** 2
            kfs[k] = Keyframe(k, T, d, var, rgb, integrate(d, var, T, rgb).block_keys)
        return fusion, kfs, integrate

    def test_rebuilding_the_moved_blocks_equals_fusing_from_scratch(self):
        poses = {k: _pose(0.1 * k) for k in range(3)}
        fusion, kfs, integrate = self._fuse(poses, poses)
        frames = fusion.frames_integrated
        new = _pose(0.1, 0.08)
        blocks = moved_blocks(fusion, kfs, {1: new}, [1])
        assert np.all(np.isin(kfs[1].block_keys, blocks)) and np.all(np.diff(blocks) > 0)
        kfs[1].T_world_camera = new
        redone = reintegrate(fusion, kfs, blocks, [1], integrate)
        assert 1 in redone and redone == sorted(redone) and fusion.frames_integrated == frames
        scratch, scratch_kfs, _ = self._fuse({**poses, 1: new}, poses)  # the stored depth at the new pose
        np.testing.assert_array_equal(kfs[1].block_keys, scratch_kfs[1].block_keys)
        assert np.all(np.isin(kfs[1].block_keys, blocks))  # the blocks it reaches now, for the next update
        a, b = fusion.voxels(), scratch.voxels()
        oa, ob = np.lexsort(a["coords"].T), np.lexsort(b["coords"].T)
        for key in a:
            np.testing.assert_array_equal(a[key][oa], b[key][ob], err_msg=key)


class TestOwnPoints:
    def test_lag_and_waiting_frames(self):
        config = MapperConfig(lag=2, refind=RefindConfig(detector="none"))
        own = OwnPoints(CAM, config)
        assert own.lagged and not own.refinds
        rng = np.random.default_rng(0)
        ready = []
        for k in range(4):
            rgb = rng.integers(0, 255, CAM.shape + (3,), dtype=np.uint8)
            entry = PendingFrame(k, _pose(0.05 * k), rgb)
            out = own.step(entry, rgb)
            ready.append(None if out is None else out.kid)
        assert ready == [None, None, 0, 1] and [p.kid for p in own.queue] == [2, 3]
        new = own.move_waiting({3: _pose(0.5), 0: _pose(0.01)})
        assert list(new) == [0] and np.array_equal(own.queue[1].T, _pose(0.5))
        points, seconds = own.flush()
        assert set(points) <= {2, 3} and seconds >= 0

    def test_without_lag_each_frame_is_triangulated_at_once(self):
        own = OwnPoints(CAM, MapperConfig(lag=0, triangulate=False))
        assert not own.lagged and own.flush() == ({}, 0.0)
        rgb = np.zeros(CAM.shape + (3,), np.uint8)
        entry = PendingFrame(0, np.eye(4), rgb)
        assert own.step(entry, rgb) is entry and entry.triangulated is None and not own.queue
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            orb = OwnPoints(CAM, MapperConfig(lag=0, triangulation=TriangulationConfig(detector="orb")))
            assert len(orb.triangulate(rgb, np.eye(4), 0)) == 0  # no earlier view: no points
