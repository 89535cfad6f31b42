"""Tests of gpdepth3d.measurements: SparseDepth, projection, downsampling, LiDAR calibration."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, DataFormatError, InvalidDepthError, ShapeError
from gpdepth3d.measurements import LidarCalibration, SparseDepth, downsample_depth, load_velodyne, project_points

CAM = PinholeCamera(50.0, 50.0, 15.5, 11.5, 32, 24)


def sd(u, v, d, size=(4, 6), sigma=None):
    return SparseDepth(np.asarray(u, float), np.asarray(v, float), np.asarray(d, float), size, sigma)


class TestSparseDepth:
    def test_fields(self):
        s = sd([0, 5], [3, 0], [1.0, 2.0], sigma=0.1)
        assert len(s) == 2 and s.image_size == (4, 6)
        np.testing.assert_array_equal(s.sigma, [0.1, 0.1])
        np.testing.assert_array_equal(s.uv, [[0, 3], [5, 0]])
        assert np.all(np.isnan(sd([0], [0], [1.0]).sigma))
        with pytest.raises(ValueError):
            s.depth[0] = 5.0  # read-only

    @pytest.mark.parametrize(
        "kwargs, error",
        [
            (dict(u=[[0.0]], v=[0.0], d=[1.0]), ShapeError),
            (dict(u=[0.0, 1.0], v=[0.0], d=[1.0]), ShapeError),
            (dict(u=[0.0], v=[0.0], d=[1.0], sigma=[0.1, 0.2]), ShapeError),
            (dict(u=[np.nan], v=[0.0], d=[1.0]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[np.nan]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[np.inf]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[-1.0]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[0.0]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[1.0], sigma=0.0), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[1.0], sigma=np.inf), InvalidDepthError),
            (dict(u=[5.5], v=[0.0], d=[1.0]), InvalidDepthError),  # outside the 6-wide image
            (dict(u=[0.0], v=[-0.6], d=[1.0]), InvalidDepthError),
            (dict(u=[0.0], v=[0.0], d=[1.0], size=(0, 4)), ShapeError),
            (dict(u=[0.0], v=[0.0], d=[1.0], size=(4,)), ShapeError),
            (dict(u=[0.0], v=[0.0], d=[1.0], size=(4.5, 4)), ShapeError),
        ],
    )
    def test_bad_input(self, kwargs, error):
        with pytest.raises(error):
            sd(kwargs["u"], kwargs["v"], kwargs["d"], kwargs.get("size", (4, 6)), kwargs.get("sigma"))

    def test_edges_of_the_image_are_inside(self):
        s = sd([-0.5, 5.49], [-0.5, 3.49], [1.0, 1.0])
        assert len(s) == 2


class TestEmpty:
    def test_empty(self):
        e = SparseDepth.empty((3, 5))
        assert len(e) == 0 and e.image_size == (3, 5) and e.uv.shape == (0, 2)
        assert len(e.rasterize((6, 10))) == 0 and e.rasterize((6, 10)).image_size == (6, 10)
        np.testing.assert_array_equal(e.to_depth_map(), np.zeros((3, 5)))


class TestFromArrays:
    def test_drops_invalid(self):
        u = [0, 1, np.nan, 2, 3, 10, 4]
        v = [0, 1, 1, 1, 1, 1, -3]
        d = [1.0, np.inf, 2.0, -1.0, 0.0, 1.0, 1.0]
        s = SparseDepth.from_arrays(u, v, d, (4, 6), sigma=[0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7])
        assert len(s) == 1 and s.depth[0] == 1.0 and s.sigma[0] == 0.1

    def test_all_invalid_gives_empty(self):
        s = SparseDepth.from_arrays([np.nan], [0], [1.0], (4, 6))
        assert len(s) == 0

    def test_mismatched_lengths(self):
        with pytest.raises(ShapeError):
            SparseDepth.from_arrays([0, 1], [0], [1.0], (4, 6))


class TestFromDepthMap:
    def test_invalid_pixels_ignored(self):
        m = np.zeros((3, 4))
        m[0, 1] = 2.0
        m[2, 3] = 5.0
        m[1, 1] = np.nan
        m[1, 2] = np.inf
        s = SparseDepth.from_depth_map(m, sigma=0.5)
        assert s.image_size == (3, 4)
        np.testing.assert_array_equal(s.uv, [[1, 0], [3, 2]])
        np.testing.assert_array_equal(s.depth, [2.0, 5.0])
        np.testing.assert_array_equal(s.sigma, [0.5, 0.5])
        np.testing.assert_array_equal(s.to_depth_map(), np.where(np.isfinite(m), m, 0.0))

    def test_errors(self):
        with pytest.raises(ShapeError):
            SparseDepth.from_depth_map(np.ones((2, 3, 1)))
        with pytest.raises(InvalidDepthError):
            SparseDepth.from_depth_map(-np.ones((2, 3)))

    def test_all_invalid_map_gives_empty(self):
        assert len(SparseDepth.from_depth_map(np.zeros((2, 3)))) == 0


class TestSubsetAndSigma:
    def test_subset(self):
        s = sd([0, 1, 2], [0, 1, 2], [1.0, 2.0, 3.0], sigma=[0.1, 0.2, 0.3])
        t = s.subset(np.array([True, False, True]))
        np.testing.assert_array_equal(t.depth, [1.0, 3.0])
        np.testing.assert_array_equal(t.sigma, [0.1, 0.3])
        np.testing.assert_array_equal(s.subset(np.array([2])).u, [2.0])

    def test_with_sigma(self):
        s = sd([0, 1], [0, 1], [1.0, 2.0])
        np.testing.assert_array_equal(s.with_sigma(0.05).sigma, [0.05, 0.05])
        np.testing.assert_array_equal(s.with_sigma(np.array([0.1, 0.2])).sigma, [0.1, 0.2])
        with pytest.raises(InvalidDepthError):
            s.with_sigma(-1.0)


class TestPixelIndices:
    def test_same_and_other_resolution(self):
        s = sd([0, 3, 5, 2.4], [0, 1, 3, 2.6], [1.0] * 4)
        r, c = s.pixel_indices()
        np.testing.assert_array_equal(c, [0, 3, 5, 2])
        np.testing.assert_array_equal(r, [0, 1, 3, 3])
        # Half resolution (2x3): centre (u + 0.5) / 2 - 0.5.
        r, c = s.pixel_indices((2, 3))
        np.testing.assert_array_equal(c, [0, 1, 2, 1])  # -0.25, 1.25, 2.25, 0.95 rounded
        np.testing.assert_array_equal(r, [0, 0, 1, 1])


class TestRasterize:
    def test_closest_point_per_pixel_is_kept(self):
        s = sd([1.2, 0.8, 1.0, 4.0], [2.1, 1.9, 2.0, 0.0], [5.0, 3.0, 4.0, 7.0], sigma=[0.5, 0.3, 0.4, 0.7])
        r = s.rasterize()
        assert len(r) == 2
        i = int(np.argmin(r.u))
        assert (r.u[i], r.v[i], r.depth[i], r.sigma[i]) == (1.0, 2.0, 3.0, 0.3)
        assert r.depth[1 - i] == 7.0

    def test_to_coarser_and_finer_grid(self):
        s = sd([0, 1, 4], [0, 1, 2], [2.0, 1.0, 3.0])
        coarse = s.rasterize((2, 3))
        assert coarse.image_size == (2, 3)
        m = coarse.to_depth_map()
        assert m[0, 0] == 1.0  # (0,0) and (1,1) share the coarse pixel: the nearer wins
        assert m[1, 2] == 3.0 and np.count_nonzero(m) == 2
        fine = s.rasterize((8, 12))
        assert len(fine) == 3
        np.testing.assert_array_equal(np.sort(fine.depth), [1.0, 2.0, 3.0])
        np.testing.assert_allclose(np.sort(fine.u), [0.0, 2.0, 8.0])  # 2u + 0.5 on the tie, rounded to even

    @pytest.mark.parametrize("n", [5, 100, 300, 2000])  # sparse (sorted) and dense (pixel table) points
    def test_pixel_order_and_nearest_at_any_density(self, n):
        rng = np.random.default_rng(n)
        flat = rng.choice(40 * 60, n, replace=False)
        u, v = (flat % 60).astype(float), (flat // 60).astype(float)
        r = sd(u, v, rng.uniform(1.0, 9.0, n), size=(40, 60)).rasterize()
        order = np.argsort(flat)
        np.testing.assert_array_equal(r.u, u[order])  # one point per pixel: all kept, by pixel
        np.testing.assert_array_equal(r.v, v[order])
        twice = sd(np.r_[u, u], np.r_[v, v], np.r_[np.full(n, 5.0), np.full(n, 2.0)], size=(40, 60)).rasterize()
        assert len(twice) == n and np.all(twice.depth == 2.0)  # two per pixel: the nearer

    def test_a_rasterisation_comes_back_as_it_is(self):
        rng = np.random.default_rng(3)
        flat = np.sort(rng.choice(40 * 60, 500, replace=False))  # one point per pixel, by pixel: the shortcut
        u, v = flat % 60 + rng.uniform(-0.4, 0.4, 500), flat // 60 + rng.uniform(-0.4, 0.4, 500)
        s = sd(u, v, rng.uniform(1.0, 9.0, 500), size=(40, 60))
        r = s.rasterize()
        np.testing.assert_array_equal(r.u, flat % 60)  # snapped to the pixel centres
        np.testing.assert_array_equal(r.v, flat // 60)
        np.testing.assert_array_equal(r.depth, s.depth)
        again = r.rasterize()
        assert all(
            np.array_equal(getattr(again, k), getattr(r, k), equal_nan=True) for k in ("u", "v", "depth", "sigma")
        )
        one = sd([2.3], [1.6], [4.0], size=(40, 60)).rasterize()
        assert (one.u[0], one.v[0], one.depth[0]) == (2.0, 2.0, 4.0)

    def test_to_depth_map_matches(self):
        s = sd([0.4, 0.2, 3], [0, 0.3, 2], [4.0, 2.0, 1.0])
        m = s.to_depth_map()
        assert m.shape == (4, 6) and m[0, 0] == 2.0 and m[2, 3] == 1.0 and np.count_nonzero(m) == 2


class TestProjectPoints:
    def test_occlusion_keeps_the_nearest(self):
        ray = np.array([0.1, -0.05, 1.0])
        pts = np.stack([ray * 8.0, ray * 2.0, ray * 5.0, [0.0, 0.0, 3.0]])
        s = project_points(pts, CAM)
        assert len(s) == 2
        m = s.to_depth_map()
        uv, _ = CAM.project(ray[None])
        assert m[int(round(uv[0, 1])), int(round(uv[0, 0]))] == pytest.approx(2.0)

    def test_drops_behind_outside_and_nonfinite(self):
        pts = np.array([[0, 0, -1.0], [0, 0, 0.0], [10.0, 0, 1.0], [np.nan, 0, 1.0], [0, 0, 2.0]])
        s = project_points(pts, CAM)
        assert len(s) == 1 and s.depth[0] == 2.0
        assert len(project_points(pts[:4], CAM)) == 0

    def test_sigma_follows_the_kept_point(self):
        pts = np.array([[0, 0, 4.0], [0, 0, 2.0], [0.2, 0.1, 2.0]])
        s = project_points(pts, CAM, sigma=np.array([0.4, 0.2, 0.9]))
        order = np.argsort(s.u)
        np.testing.assert_array_equal(s.sigma[order], [0.2, 0.9])

    def test_pixel_positions(self, street_frame):
        # Back-projecting a dense depth map and projecting it again returns every pixel.
        f = street_frame
        points, valid = f.camera.backproject(f.depth_gt)
        s = project_points(points, f.camera)
        np.testing.assert_allclose(s.to_depth_map(), f.depth_gt, rtol=1e-12)
        assert len(s) == valid.sum()

    @pytest.mark.parametrize("shape", [(3,), (4, 2)])
    def test_bad_shape(self, shape):
        with pytest.raises(ShapeError):
            project_points(np.zeros(shape), CAM)


class TestDownsampleDepth:
    def test_closest_per_block(self):
        d = np.array(
            [
                [4.0, 0.0, 9.0, 8.0, 1.0],
                [3.0, np.nan, 7.0, np.inf, 1.0],
                [0.0, 0.0, 2.0, 6.0, 1.0],
                [0.0, 0.0, 5.0, 5.0, 1.0],
                [1.0, 1.0, 1.0, 1.0, 1.0],
            ]
        )
        out = downsample_depth(d, 2)
        np.testing.assert_array_equal(out, [[3.0, 7.0], [0.0, 2.0]])  # trailing row/col dropped

    def test_factor_one_cleans_invalid(self):
        d = np.array([[1.0, np.nan], [np.inf, 2.0]])
        np.testing.assert_array_equal(downsample_depth(d, 1), [[1.0, 0.0], [0.0, 2.0]])

    def test_occlusion_on_a_scene(self, street_frame):
        d = street_frame.depth_gt
        out = downsample_depth(d, 4)
        assert out.shape == (24, 80)
        blocks = np.where(d > 0, d, np.inf).reshape(24, 4, 80, 4)
        np.testing.assert_array_equal(out, np.where(np.isinf(blocks.min(axis=(1, 3))), 0, blocks.min(axis=(1, 3))))

    @pytest.mark.parametrize(
        "depth, factor",
        [(np.ones((4, 4, 1)), 2), (np.ones(4), 1), (np.ones((4, 4)), 0), (np.ones((4, 4)), 1.5), (np.ones((4, 4)), 5)],
    )
    def test_errors(self, depth, factor):
        with pytest.raises(ShapeError):
            downsample_depth(depth, factor)


def _kitti_projection_by_hand(calib_path, points):
    """Reference: x = P2 * R0_rect * Tr_velo_to_cam * X (KITTI devkit), depth = third coordinate."""
    vals = {}
    for line in open(calib_path).read().splitlines():
        if ":" in line:
            k, rest = line.split(":", 1)
            vals[k] = np.array([float(x) for x in rest.split()])
    P2 = vals["P2"].reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = vals["R0_rect"].reshape(3, 3)
    Tr = np.vstack([vals["Tr_velo_to_cam"].reshape(3, 4), [0, 0, 0, 1]])
    X = np.hstack([points[:, :3], np.ones((len(points), 1))])
    x = (P2 @ R0 @ Tr @ X.T).T
    return x[:, 0] / x[:, 2], x[:, 1] / x[:, 2], x[:, 2]


class TestLidarCalibration:
    def test_construction(self):
        c = LidarCalibration(np.hstack([CAM.K, np.zeros((3, 1))]), np.eye(4)[:3])
        assert c.T_camera_lidar.shape == (4, 4)

    @pytest.mark.parametrize(
        "P, T",
        [
            (np.eye(3), np.eye(4)),
            (np.full((3, 4), np.nan), np.eye(4)),
            (np.eye(3, 4), np.eye(3)),
            (np.eye(3, 4), np.full((4, 4), np.inf)),
        ],
    )
    def test_bad_matrices(self, P, T):
        with pytest.raises(CalibrationError):
            LidarCalibration(P, T)

    def test_project_matches_project_points(self):
        rng = np.random.default_rng(0)
        pts = np.stack([rng.uniform(-3, 3, 500), rng.uniform(-2, 2, 500), rng.uniform(1, 20, 500)], 1)
        # LiDAR axes (x forward, y left, z up) -> camera axes.
        T = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])
        lidar_pts = (np.linalg.inv(T) @ np.hstack([pts, np.ones((500, 1))]).T).T
        c = LidarCalibration(np.hstack([CAM.K, np.zeros((3, 1))]), T)
        a = c.project(lidar_pts, CAM.shape)
        b = project_points(pts, CAM)
        np.testing.assert_array_equal(a.uv, b.uv)
        np.testing.assert_allclose(a.depth, b.depth)

    def test_project_bad_points(self):
        c = LidarCalibration(np.hstack([CAM.K, np.zeros((3, 1))]), np.eye(4))
        with pytest.raises(ShapeError):
            c.project(np.zeros((5, 2)), CAM.shape)

    @pytest.mark.parametrize("frame", [0, 1, 2])
    def test_kitti_object_frame(self, shared_data, frame):
        folder = shared_data / "kitti_object"
        calib_path = folder / f"calib_{frame:06d}.txt"
        calib = LidarCalibration.from_kitti(calib_path)
        scan = load_velodyne(folder / f"{frame:06d}.bin")
        s = calib.project(scan, (375, 1242))
        assert 5000 < len(s) < 40000
        assert np.all((s.u >= 0) & (s.u <= 1241) & (s.v >= 0) & (s.v <= 374))
        assert 2.0 < s.depth.min() and np.percentile(s.depth, 99) < 80.0 and s.depth.max() < 120.0
        assert 5.0 < np.median(s.depth) < 30.0
        # Same as the KITTI devkit formula computed by hand (closest point per rounded pixel).
        u, v, z = _kitti_projection_by_hand(calib_path, scan)
        ok = (z > 1e-3) & (u >= -0.5) & (u < 1241.5) & (v >= -0.5) & (v < 374.5) & (scan[:, 0] > 0)
        m = np.zeros((375, 1242))
        order = np.argsort(-z[ok])  # far first: the nearest overwrites
        m[np.rint(v[ok][order]).astype(int), np.rint(u[ok][order]).astype(int)] = z[ok][order]
        np.testing.assert_allclose(s.to_depth_map(), m, rtol=1e-6)
        # The ground in front of the car (LiDAR 1.73 m up) lands in the lower part of the image.
        ground = (scan[:, 2] < -1.5) & (scan[:, 0] > 5) & (scan[:, 0] < 20) & (np.abs(scan[:, 1]) < 3)
        gs = calib.project(scan[ground], (375, 1242))
        assert len(gs) > 100 and np.all(gs.v > 375 / 2)

    def test_kitti_raw_folder(self, shared_data):
        folder = shared_data / "kitti_tiny"
        calib = LidarCalibration.from_kitti(folder, camera=2)
        K = np.loadtxt(folder / "cam.txt")
        np.testing.assert_allclose(calib.P[:, :3], K, rtol=1e-6)
        np.testing.assert_allclose(calib.P[:, 3], [44.85728, 0.2163791, 0.002745884], rtol=1e-6)
        # velodyne_02 holds the scan projected into camera 02. Lift every point back into the
        # LiDAR frame with this calibration and project again: the same map comes back ...
        path = sorted((folder / "velodyne_02").glob("*.npz"))[0]
        depth = np.load(path)["velodyne_depth"].astype(np.float64)
        s = SparseDepth.from_depth_map(depth)
        t = np.linalg.solve(K, calib.P[:, 3])
        cam = (np.linalg.solve(K, np.stack([s.u * s.depth, s.v * s.depth, s.depth])).T) - t
        lidar = (np.linalg.inv(calib.T_camera_lidar) @ np.hstack([cam, np.ones((len(s), 1))]).T).T[:, :3]
        again = calib.project(lidar, depth.shape)
        np.testing.assert_array_equal(again.uv, s.uv)
        np.testing.assert_allclose(again.depth, s.depth, rtol=1e-9)
        # ... and the points lie where a roof LiDAR 1.73 m above the road sees them: the road
        # surface (lowest points) at z = -1.73 m, everything ahead (x > 0).
        assert np.percentile(lidar[:, 2], 5) == pytest.approx(-1.73, abs=0.1)
        assert np.all(lidar[:, 0] > 0)

    def test_missing_and_malformed_files(self, tmp_path):
        with pytest.raises(DataFormatError):
            LidarCalibration.from_kitti(tmp_path / "nope.txt")
        bad = tmp_path / "bad.txt"
        bad.write_text("hello world\n")
        with pytest.raises(DataFormatError):
            LidarCalibration.from_kitti(bad)
        partial = tmp_path / "partial.txt"
        partial.write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\n")
        with pytest.raises(DataFormatError):
            LidarCalibration.from_kitti(partial)  # no Tr_velo_to_cam
        short = tmp_path / "short.txt"
        short.write_text("P2: 1 0 0\nTr_velo_to_cam: 1 0 0 0 0 1 0 0 0 0 1 0\n")
        with pytest.raises(DataFormatError):
            LidarCalibration.from_kitti(short)
        with pytest.raises(DataFormatError):
            LidarCalibration.from_kitti(tmp_path)  # a folder without the raw calibration files

    def test_plain_object_file(self, tmp_path):
        p = tmp_path / "calib.txt"
        p.write_text("P2: 2 0 1 0 0 2 1 0 0 0 1 0\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n")
        c = LidarCalibration.from_kitti(p)  # R0_rect absent: identity
        s = c.project(np.array([[4.0, 0.0, 0.0]]), (3, 3))
        assert (s.u[0], s.v[0], s.depth[0]) == (1.0, 1.0, 4.0)


class TestCalibrationImageSize:
    def test_real_calibration_against_image_sizes(self, shared_data):
        calib = LidarCalibration.from_kitti(shared_data / "kitti_object" / "calib_000000.txt")
        calib.check_image_size((375, 1242))  # the calibrated image
        for size in ((240, 320), (125, 414)):  # a 320x240 MDE, KITTI at 1/3: P2 is not theirs
            with pytest.raises(CalibrationError, match=f"{size[1]}x{size[0]}"):
                calib.check_image_size(size, "--lidar-image-size")
        with pytest.raises(ShapeError):
            calib.check_image_size((375,))

    def test_binary_calibration_file(self, tmp_path):
        (tmp_path / "calib.txt").write_bytes(bytes(range(256)) * 4)
        with pytest.raises(DataFormatError, match="binary"):
            LidarCalibration.from_kitti(tmp_path / "calib.txt")


class TestImageSizeValidation:
    @pytest.mark.parametrize(
        "size", [(float("nan"), 5), (float("inf"), 5), None, 10, "ab", (2.5, 4), (0, 4), (True, 4), (1, 2, 3)]
    )
    def test_bad_image_sizes(self, size):
        with pytest.raises(ShapeError, match="image_size"):
            SparseDepth.empty(size)

    def test_integral_floats_accepted(self):
        assert SparseDepth.empty((4.0, np.int64(5))).image_size == (4, 5)


class TestLoadVelodyne:
    def test_round_trip(self, tmp_path):
        pts = np.arange(20, dtype=np.float32).reshape(5, 4)
        pts.tofile(tmp_path / "scan.bin")
        out = load_velodyne(tmp_path / "scan.bin")
        assert out.dtype == np.float32
        np.testing.assert_array_equal(out, pts)

    def test_errors(self, tmp_path):
        with pytest.raises(DataFormatError):
            load_velodyne(tmp_path / "missing.bin")
        (tmp_path / "empty.bin").write_bytes(b"")
        with pytest.raises(DataFormatError):
            load_velodyne(tmp_path / "empty.bin")
        np.arange(7, dtype=np.float32).tofile(tmp_path / "odd.bin")
        with pytest.raises(DataFormatError):
            load_velodyne(tmp_path / "odd.bin")

    def test_size_not_a_whole_number_of_records(self, tmp_path):
        np.arange(8, dtype=np.float32).tofile(tmp_path / "ok.bin")
        assert load_velodyne(tmp_path / "ok.bin").shape == (2, 4)
        (tmp_path / "cut.bin").write_bytes((tmp_path / "ok.bin").read_bytes()[:-2])  # 30 bytes: np.fromfile drops 2
        with pytest.raises(DataFormatError, match="30 bytes"):
            load_velodyne(tmp_path / "cut.bin")

    def test_real_scan(self, shared_data):
        scan = load_velodyne(shared_data / "kitti_object" / "000000.bin")
        assert scan.shape == (115384, 4)
        assert np.all(np.abs(scan[:, :3]) < 130) and 0 <= scan[:, 3].min() and scan[:, 3].max() <= 1.0
