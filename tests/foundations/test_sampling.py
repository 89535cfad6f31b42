"""Tests of gpdepth3d.sampling: uniform, density, bands, LiDAR scan lines, hold-out split."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import EmptyInputError, InvalidInputError, ShapeError
from gpdepth3d.measurements import LidarCalibration, SparseDepth
from gpdepth3d.sampling import (
    PAPER_DENSITIES,
    as_available,
    band_mask,
    beam_ids,
    holdout_split,
    lidar_elevation,
    make_rng,
    sample_band,
    sample_scanlines,
    sample_uniform,
)

DENSE = np.random.default_rng(0).uniform(1.0, 5.0, size=(40, 60))
DENSE[:5, :] = 0.0  # 300 invalid pixels


def _keys(s: SparseDepth) -> set:
    return set(zip(s.u.tolist(), s.v.tolist()))


class TestUniform:
    def test_count_and_validity(self):
        s = sample_uniform(DENSE, n=100, rng=1)
        assert len(s) == 100 and len(_keys(s)) == 100
        assert np.all(s.v >= 5)  # only valid pixels
        np.testing.assert_allclose(s.depth, DENSE[s.v.astype(int), s.u.astype(int)])

    def test_density(self):
        n_valid = int((DENSE > 0).sum())
        assert len(sample_uniform(DENSE, density=0.25, rng=0)) == round(0.25 * n_valid)
        assert len(sample_uniform(DENSE, density=1.0, rng=0)) == n_valid

    def test_seeding(self):
        a, b = sample_uniform(DENSE, n=50, rng=3), sample_uniform(DENSE, n=50, rng=3)
        c = sample_uniform(DENSE, n=50, rng=4)
        assert _keys(a) == _keys(b) and _keys(a) != _keys(c)

    def test_more_than_available(self):
        s = SparseDepth.from_arrays([1, 2], [1, 2], [1.0, 2.0], (5, 5))
        assert len(sample_uniform(s, n=10)) == 2

    def test_errors(self):
        with pytest.raises(InvalidInputError):
            sample_uniform(DENSE)
        with pytest.raises(InvalidInputError):
            sample_uniform(DENSE, n=5, density=0.1)
        with pytest.raises(InvalidInputError):
            sample_uniform(DENSE, density=1.5)
        with pytest.raises(InvalidInputError):
            sample_uniform(DENSE, n=-1)
        with pytest.raises(ShapeError):
            as_available(np.zeros(5))
        with pytest.raises(InvalidInputError):
            make_rng("seed")
        for bad in (
            dict(n=5, rng=-1),
            dict(n=float("inf")),
            dict(n=float("nan")),
            dict(n="5"),
            dict(n=True),
            dict(n=2.5),
            dict(density=float("nan")),
            dict(density="0.5"),
            dict(n=5, rng=True),
        ):
            with pytest.raises(InvalidInputError):
                sample_uniform(DENSE, **bad)
        assert len(sample_uniform(DENSE, n=5.0, rng=np.int64(2))) == 5  # integral floats and numpy seeds are fine

    def test_paper_densities(self):
        assert len(PAPER_DENSITIES) == 8 and PAPER_DENSITIES[0] == 1 / 64 and PAPER_DENSITIES[-1] == 1.0
        assert list(PAPER_DENSITIES) == sorted(PAPER_DENSITIES)


class TestBands:
    def test_horizontal_band_restricts_rows(self):
        s = sample_band(DENSE, axis="horizontal", start=0.5, stop=1.0, n=200, rng=0)
        assert len(s) == 200 and np.all(s.v >= 20) and np.all(s.v < 40)

    def test_vertical_band_restricts_columns(self):
        s = sample_band(DENSE, axis="vertical", start=0.0, stop=0.25, n=100, rng=0)
        assert len(s) == 100 and np.all(s.u < 15)

    def test_density_counts_all_points(self):
        n_valid = int((DENSE > 0).sum())
        s = sample_band(DENSE, axis="vertical", start=0.0, stop=0.5, density=0.1, rng=0)
        assert len(s) == round(0.1 * n_valid) and np.all(s.u < 30)

    def test_mask_and_errors(self):
        s = SparseDepth.from_depth_map(DENSE)
        m = band_mask(s, axis="horizontal", start=0.25, stop=0.5)
        assert np.all((s.v[m] >= 10) & (s.v[m] < 20)) and m.sum() == 10 * 60
        with pytest.raises(InvalidInputError):
            band_mask(s, axis="diagonal", start=0, stop=1)
        with pytest.raises(InvalidInputError):
            band_mask(s, axis="vertical", start=0.6, stop=0.5)


def _synthetic_lidar(n_beams=16, spacing=0.8, offset=0.1):
    """A LiDAR 1.7 m above a level camera, beams at known elevations, points on walls 5-30 m."""
    camera = PinholeCamera(300.0, 300.0, 200.0, 60.0, 400, 120)
    P = np.hstack([camera.K, np.zeros((3, 1))])
    # LiDAR frame: x forward, y left, z up; camera: x right, y down, z forward; LiDAR 0.1 m above.
    T = np.eye(4)
    T[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]])
    T[:3, 3] = [0.0, -offset, 0.0]
    calib = LidarCalibration(P, T)
    rng = np.random.default_rng(0)
    elev = -np.arange(n_beams) * spacing + 2.0
    pts, ids = [], []
    for b, e in enumerate(elev):
        az = np.radians(rng.uniform(-30, 30, 400))
        r = rng.uniform(5, 30, 400)
        x = r * np.cos(np.radians(e)) * np.cos(az)
        y = r * np.cos(np.radians(e)) * np.sin(az)
        z = r * np.sin(np.radians(e))
        pts.append(np.stack([x, y, z], 1))
        ids.append(np.full(400, b))
    pts, ids = np.concatenate(pts), np.concatenate(ids)
    cam = pts @ T[:3, :3].T + T[:3, 3]
    uv, zc = camera.project(cam)
    inside = camera.in_image(uv) & (zc > 0)
    sparse = SparseDepth(uv[inside, 0], uv[inside, 1], zc[inside], camera.shape)
    return sparse, ids[inside], calib, camera, elev


class TestScanlines:
    def test_elevation_recovered(self):
        sparse, ids, calib, _, elev = _synthetic_lidar()
        e = lidar_elevation(sparse, calib)
        np.testing.assert_allclose(e, elev[ids], atol=1e-6)

    def test_beam_ids_match_truth(self):
        sparse, ids, calib, _, _ = _synthetic_lidar()
        b = beam_ids(lidar_elevation(sparse, calib))
        present = np.unique(ids)
        assert b.max() + 1 == present.size
        # a bijection between found and true beams, ordered top to bottom
        np.testing.assert_array_equal(b, np.searchsorted(present, ids))

    def test_keep_every(self):
        sparse, ids, calib, _, _ = _synthetic_lidar()
        b = beam_ids(lidar_elevation(sparse, calib))
        sub = sample_scanlines(sparse, keep_every=4, calibration=calib)
        assert len(sub) == int(np.sum(b % 4 == 0))
        sub1 = sample_scanlines(sparse, keep_every=4, offset=1, beams=b)
        assert len(sub1) == int(np.sum(b % 4 == 1))
        assert len(sample_scanlines(sparse, keep_every=1, beams=b)) == len(sparse)

    def test_camera_only(self):
        sparse, ids, _, camera, _ = _synthetic_lidar(offset=0.0)  # coarse mode: LiDAR at the camera
        b = beam_ids(lidar_elevation(sparse, camera=camera))
        assert b.max() + 1 == np.unique(ids).size

    def test_real_kitti_beams(self, shared_data):
        path = shared_data / "kitti_tiny" / "velodyne_02" / "0000000000.npz"
        if not path.is_file():
            pytest.skip(f"{path} not found")
        d = np.load(path)["velodyne_depth"]
        sparse = SparseDepth.from_depth_map(d)
        calib = LidarCalibration.from_kitti(shared_data / "kitti_tiny", camera=2)
        b = beam_ids(lidar_elevation(sparse, calib))
        assert 35 <= b.max() + 1 <= 64  # the HDL-64E beams that reach the image
        sub = sample_scanlines(sparse, keep_every=4, beams=b)
        assert 0.15 < len(sub) / len(sparse) < 0.35

    def test_errors(self):
        sparse, ids, calib, camera, _ = _synthetic_lidar()
        with pytest.raises(InvalidInputError):
            sample_scanlines(sparse, keep_every=0, calibration=calib)
        with pytest.raises(InvalidInputError):
            sample_scanlines(sparse, keep_every=2, offset=2, calibration=calib)
        with pytest.raises(ShapeError):
            sample_scanlines(sparse, keep_every=2, beams=np.zeros(3))
        with pytest.raises(InvalidInputError):
            lidar_elevation(sparse)
        with pytest.raises(InvalidInputError):
            beam_ids(np.array([np.nan]))
        assert beam_ids(np.zeros(0)).size == 0


class TestHoldout:
    def test_split(self):
        s = SparseDepth.from_depth_map(DENSE)
        a, b = holdout_split(s, holdout=0.2, rng=0)
        assert len(b) == round(0.2 * len(s)) and len(a) + len(b) == len(s)
        assert not (_keys(a) & _keys(b))
        a2, b2 = holdout_split(s, holdout=0.2, rng=0)
        assert _keys(b) == _keys(b2)

    def test_mask_is_the_split(self):
        from gpdepth3d.sampling import holdout_mask

        s = SparseDepth.from_depth_map(DENSE)
        mask = holdout_mask(len(s), holdout=0.2, rng=3)
        assert mask.dtype == bool and mask.sum() == round(0.2 * len(s))
        a, b = holdout_split(s, holdout=0.2, rng=3)
        assert _keys(b) == _keys(s.subset(mask)) and _keys(a) == _keys(s.subset(~mask))
        # at least one point kept and one held out, whatever the share
        assert holdout_mask(2, holdout=0.99, rng=0).sum() == 1 and holdout_mask(2, holdout=0.01, rng=0).sum() == 1
        assert not np.array_equal(mask, holdout_mask(len(s), holdout=0.2, rng=4))
        with pytest.raises(InvalidInputError, match="n"):
            holdout_mask(2.0, holdout=0.5)
        with pytest.raises(EmptyInputError):
            holdout_mask(1, holdout=0.5)
        with pytest.raises(InvalidInputError, match="holdout"):
            holdout_mask(10, holdout=0.0)

    def test_errors(self):
        s = SparseDepth.from_depth_map(DENSE)
        with pytest.raises(InvalidInputError):
            holdout_split(s, holdout=1.0)
        with pytest.raises(EmptyInputError):
            holdout_split(s.subset(np.arange(1)))


class TestGrossOutliers:
    def test_share_factors_and_sigma(self):
        from gpdepth3d.sampling import gross_outliers

        sp = SparseDepth(np.arange(40.0), np.zeros(40), np.linspace(1.0, 5.0, 40), (10, 50), np.full(40, 0.01))
        bad = gross_outliers(sp, 0.1, rng=3)
        ratio = bad.depth / sp.depth
        changed = ratio != 1.0
        assert changed.sum() == 4 and np.all((ratio[changed] >= 0.1) & (ratio[changed] <= 3.0))
        np.testing.assert_array_equal(bad.sigma, sp.sigma)
        np.testing.assert_array_equal(bad.u, sp.u)
        np.testing.assert_array_equal(sp.depth, np.linspace(1.0, 5.0, 40))  # the input is not modified
        # the same draws as choice-then-uniform on the same generator (the benchmark's protocol)
        rng = np.random.default_rng(3)
        idx = rng.choice(40, 4, replace=False)
        np.testing.assert_allclose(bad.depth[idx], sp.depth[idx] * rng.uniform(0.1, 3.0, 4))
        assert np.array_equal(gross_outliers(sp, 0.0).depth, sp.depth)

    def test_bad_arguments(self):
        from gpdepth3d.sampling import gross_outliers

        sp = SparseDepth(np.arange(4.0), np.zeros(4), np.ones(4), (1, 4))
        with pytest.raises(InvalidInputError, match="share"):
            gross_outliers(sp, 1.5)
        with pytest.raises(InvalidInputError, match="low, high"):
            gross_outliers(sp, 0.5, low=2.0, high=1.0)
