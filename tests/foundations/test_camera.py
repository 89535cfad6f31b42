"""Tests of gpdepth3d.camera: PinholeCamera, check_pose, transform_points."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gpdepth3d.camera import PinholeCamera, check_pose, transform_points
from gpdepth3d.errors import CalibrationError, InvalidDepthError, ShapeError

CAM = PinholeCamera(500.0, 480.0, 319.5, 239.5, 640, 480)

finite = dict(allow_nan=False, allow_infinity=False)
cameras = st.builds(
    lambda fx, fy, w, h, ax, ay: PinholeCamera(fx, fy, ax * (w - 1), ay * (h - 1), w, h),
    st.floats(50.0, 2000.0, **finite),
    st.floats(50.0, 2000.0, **finite),
    st.integers(8, 2000),
    st.integers(8, 2000),
    st.floats(0.0, 1.0, **finite),
    st.floats(0.0, 1.0, **finite),
)


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def pose(rx=0.1, ry=-0.4, rz=1.2, t=(1.0, -2.0, 0.5)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation(rx, ry, rz)
    T[:3, 3] = t
    return T


class TestPinholeCamera:
    def test_fields_and_K(self):
        assert CAM.shape == (480, 640)
        np.testing.assert_array_equal(CAM.K, [[500, 0, 319.5], [0, 480, 239.5], [0, 0, 1]])
        assert isinstance(PinholeCamera(1, 1, 0, 0, 8.0, 8).width, int)

    @pytest.mark.parametrize(
        "args, argument",
        [
            ((0.0, 1.0, 1.0, 1.0, 4, 4), "fx"),
            ((1.0, -2.0, 1.0, 1.0, 4, 4), "fy"),
            ((float("nan"), 1.0, 1.0, 1.0, 4, 4), "fx"),
            ((1.0, float("inf"), 1.0, 1.0, 4, 4), "fy"),
            ((1.0, 1.0, float("nan"), 1.0, 4, 4), "cx"),
            ((1.0, 1.0, 1.0, 1.0, 0, 4), "width"),
            ((1.0, 1.0, 1.0, 1.0, 4, 2.5), "height"),
            ((1.0, 1.0, 10.0, 1.0, 4, 4), "cx, cy"),  # principal point outside the image
            ((1.0, 1.0, 1.0, -0.6, 4, 4), "cx, cy"),
            (("585", 1.0, 1.0, 1.0, 4, 4), "fx"),
            ((1.0, None, 1.0, 1.0, 4, 4), "fy"),
            ((1.0, 1.0, "1", 1.0, 4, 4), "cx"),
            ((1.0, 1.0, 1.0, 1.0, None, 4), "width"),
            ((1.0, 1.0, 1.0, 1.0, 4, float("inf")), "height"),
            ((True, 1.0, 1.0, 1.0, 4, 4), "fx"),
        ],
    )
    def test_bad_intrinsics(self, args, argument):
        with pytest.raises(CalibrationError) as info:
            PinholeCamera(*args)
        assert info.value.argument == argument

    def test_frozen(self):
        with pytest.raises(AttributeError):
            CAM.fx = 1.0  # type: ignore[misc]


class TestFromK:
    def test_round_trip(self):
        cam = PinholeCamera.from_K(CAM.K, 640, 480)
        assert cam == CAM

    @pytest.mark.parametrize(
        "K",
        [
            np.eye(4),
            np.eye(3)[:2],
            np.array([[1.0, 0, 1], [0, 1, 1], [0, 0, 2]]),
            np.array([[1.0, 0, 1], [0.5, 1, 1], [0, 0, 1]]),
        ],
    )
    def test_bad_K(self, K):
        with pytest.raises(CalibrationError):
            PinholeCamera.from_K(K, 4, 4)

    def test_intrinsics_must_fit_the_image(self):
        # A 640x480 calibration used for a 64x48 image: the principal point lies outside it.
        with pytest.raises(CalibrationError):
            PinholeCamera.from_K(CAM.K, 64, 48)


class TestCheckImage:
    def test_accepts_matching_images(self):
        CAM.check_image(np.zeros((480, 640)), "depth")
        CAM.check_image(np.zeros((480, 640, 3)), "rgb")

    @pytest.mark.parametrize("shape", [(640, 480), (480,), (480, 641, 3)])
    def test_rejects_mismatch(self, shape):
        with pytest.raises(ShapeError) as info:
            CAM.check_image(np.zeros(shape), "rgb")
        assert info.value.argument == "rgb"


class TestResized:
    def test_values(self):
        small = CAM.resized(320, 240)
        assert (small.fx, small.fy, small.cx, small.cy) == (250.0, 240.0, 159.5, 119.5)
        assert small.shape == (240, 320)

    @settings(max_examples=60, deadline=None)
    @given(cameras, st.floats(0.2, 4.0, **finite), st.floats(-2.0, 2.0, **finite), st.floats(-2.0, 2.0, **finite))
    def test_projection_scales_with_pixel_centre_convention(self, cam, factor, x, y):
        w, h = max(2, int(round(cam.width * factor))), max(2, int(round(cam.height * factor)))
        other = cam.resized(w, h)
        p = np.array([[x, y, 5.0]])
        uv, _ = cam.project(p)
        uv2, _ = other.project(p)
        expected = (uv + 0.5) * np.array([w / cam.width, h / cam.height]) - 0.5
        np.testing.assert_allclose(uv2, expected, rtol=1e-9, atol=1e-9)


class TestCropped:
    def test_values_and_projection(self):
        crop = CAM.cropped(100, 50, 200, 100)
        assert crop.shape == (100, 200) and crop.cx == 219.5 and crop.cy == 189.5
        p = np.array([[0.3, -0.1, 2.0]])
        np.testing.assert_allclose(crop.project(p)[0], CAM.project(p)[0] - [100, 50])

    def test_corner_crop_then_resize(self):
        # A corner crop has its principal point outside the crop: still a valid camera.
        crop = CAM.cropped(0, 0, 64, 48)
        assert (crop.cx, crop.cy) == (319.5, 239.5)
        half = crop.resized(32, 24)
        p = np.array([[-1.0, -0.8, 2.0]])
        np.testing.assert_allclose(half.project(p)[0], (crop.project(p)[0] + 0.5) / 2 - 0.5)

    @pytest.mark.parametrize("window", [(-1, 0, 10, 10), (0, 0, 641, 10), (600, 0, 50, 10), (0, 475, 10, 10)])
    def test_outside_window(self, window):
        with pytest.raises(CalibrationError):
            CAM.cropped(*window)


class TestPixelGrid:
    def test_grid(self):
        cam = PinholeCamera(10, 10, 1.5, 1.0, 4, 3)
        u, v = cam.pixel_grid()
        assert u.shape == v.shape == (3, 4)
        np.testing.assert_array_equal(u[0], [0, 1, 2, 3])
        np.testing.assert_array_equal(v[:, 0], [0, 1, 2])


class TestProject:
    def test_hand_values(self):
        uv, z = CAM.project(np.array([[1.0, -0.5, 2.0], [0.0, 0.0, 4.0]]))
        np.testing.assert_allclose(uv, [[319.5 + 250.0, 239.5 - 120.0], [319.5, 239.5]])
        np.testing.assert_allclose(z, [2.0, 4.0])

    @pytest.mark.parametrize("shape", [(3,), (4, 2), (2, 3, 1)])
    def test_bad_shape(self, shape):
        with pytest.raises(ShapeError):
            CAM.project(np.zeros(shape))

    def test_behind_camera_is_not_in_image(self):
        uv, z = CAM.project(np.array([[0.0, 0.0, 0.0], [0.1, 0.1, -1.0]]))
        assert z[1] < 0
        assert not CAM.in_image(uv)[0]


class TestInImage:
    def test_borders(self):
        cam = PinholeCamera(10, 10, 1.5, 1.0, 4, 3)
        uv = np.array([[-0.5, -0.5], [3.49, 2.49], [3.5, 0.0], [0.0, 2.5], [-0.51, 0.0], [np.nan, 0.0], [np.inf, 1]])
        np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, False, False, False])


class TestBackprojectPixels:
    def test_hand_values(self):
        p = CAM.backproject_pixels(np.array([[319.5 + 250.0, 239.5 - 120.0]]), np.array([2.0]))
        np.testing.assert_allclose(p, [[1.0, -0.5, 2.0]])

    @pytest.mark.parametrize(
        "uv, depth", [(np.zeros((3, 3)), np.ones(3)), (np.zeros((3, 2)), np.ones(2)), (np.zeros(2), np.ones(1))]
    )
    def test_bad_shapes(self, uv, depth):
        with pytest.raises(ShapeError):
            CAM.backproject_pixels(uv, depth)

    @settings(max_examples=50, deadline=None)
    @given(
        cameras,
        st.lists(
            st.tuples(st.floats(0, 1, **finite), st.floats(0, 1, **finite), st.floats(0.05, 500.0, **finite)),
            min_size=1,
            max_size=20,
        ),
    )
    def test_round_trip_backproject_then_project(self, cam, samples):
        s = np.array(samples)
        uv = np.stack([s[:, 0] * (cam.width - 1), s[:, 1] * (cam.height - 1)], axis=1)
        uv2, z = cam.project(cam.backproject_pixels(uv, s[:, 2]))
        np.testing.assert_allclose(uv2, uv, rtol=1e-9, atol=1e-7)
        np.testing.assert_allclose(z, s[:, 2], rtol=1e-12)
        assert cam.in_image(uv2).all()

    @settings(max_examples=60, deadline=None)
    @given(cameras, st.floats(-3, 3, **finite), st.floats(-3, 3, **finite), st.floats(0.1, 100, **finite))
    def test_round_trip_project_then_backproject(self, cam, x, y, z):
        p = np.array([[x, y, z]])
        uv, depth = cam.project(p)
        np.testing.assert_allclose(cam.backproject_pixels(uv, depth), p, rtol=1e-9, atol=1e-9)


class TestBackproject:
    def test_round_trip_returns_the_pixels(self):
        cam = PinholeCamera(40.0, 42.0, 7.5, 5.0, 16, 12)
        rng = np.random.default_rng(0)
        depth = rng.uniform(0.5, 10.0, size=cam.shape)
        depth[2, 3] = 0.0
        depth[4, 5] = np.nan
        depth[6, 7] = np.inf
        points, valid = cam.backproject(depth)
        assert points.shape == (cam.width * cam.height - 3, 3)
        assert not valid[2, 3] and not valid[4, 5] and not valid[6, 7] and valid.sum() == len(points)
        uv, z = cam.project(points)
        u, v = cam.pixel_grid()
        np.testing.assert_allclose(uv[:, 0], u[valid], atol=1e-9)
        np.testing.assert_allclose(uv[:, 1], v[valid], atol=1e-9)
        np.testing.assert_allclose(z, depth[valid])

    def test_wrong_size(self):
        with pytest.raises(ShapeError):
            CAM.backproject(np.ones((48, 64)))

    def test_negative_depth(self):
        d = np.ones(CAM.shape)
        d[0, 0] = -1.0
        with pytest.raises(InvalidDepthError):
            CAM.backproject(d)


class TestCheckPose:
    def test_valid(self):
        T = pose()
        out = check_pose(T.tolist())
        assert out.dtype == np.float64
        np.testing.assert_allclose(out, T, atol=1e-12)

    def test_bad_poses(self):
        bad = {"shape": np.eye(3), "nan": np.full((4, 4), np.nan), "last row": pose() + np.diag([0, 0, 0, 1.0])}
        reflect = pose()
        reflect[:3, 0] *= -1
        bad["reflection"] = reflect
        scaled = pose()
        scaled[:3, :3] *= 2.0
        bad["scale"] = scaled
        bad["strings"] = "identity"
        bad["string rows"] = [["a"] * 4] * 4
        bad["ragged"] = [[1.0, 0.0], [0.0]]
        bad["det 8"] = np.diag([2.0, 2.0, 2.0, 1.0])
        for name, T in bad.items():
            with pytest.raises(CalibrationError) as info:
                check_pose(T, "T_test")
            assert info.value.argument == "T_test", name


class TestTransformPoints:
    @settings(max_examples=50, deadline=None)
    @given(
        st.floats(-3, 3, **finite), st.floats(-3, 3, **finite), st.floats(-3, 3, **finite), st.integers(0, 2**31 - 1)
    )
    def test_matches_homogeneous_and_inverts(self, rx, ry, rz, seed):
        T = pose(rx, ry, rz, (0.5, 2.0, -1.0))
        p = np.random.default_rng(seed).normal(size=(7, 3))
        out = transform_points(T, p)
        homog = (T @ np.hstack([p, np.ones((7, 1))]).T).T[:, :3]
        np.testing.assert_allclose(out, homog, atol=1e-12)
        np.testing.assert_allclose(transform_points(np.linalg.inv(T), out), p, atol=1e-9)

    @pytest.mark.parametrize("T, points", [(np.eye(4), np.zeros((5, 2))), (np.eye(3), np.zeros((5, 3)))])
    def test_bad_shapes(self, T, points):
        with pytest.raises(ShapeError):
            transform_points(T, points)


class TestCheckPoseSnapsRecordedPoses:
    def test_snaps_recorded_poses_and_rejects_others(self):
        c, sn = np.cos(0.3), np.sin(0.3)
        T0 = np.array([[c, -sn, 0, 1.0], [sn, c, 0, 2.0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
        T = T0.copy()
        T[:3, :3] *= 1.0001  # as stored with few digits (7-Scenes: det 0.9998)
        snapped = check_pose(T)
        np.testing.assert_allclose(snapped[:3, :3] @ snapped[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(snapped, T0, atol=1e-9)
        T[:3, :3] *= 1.1
        with pytest.raises(CalibrationError):
            check_pose(T)


class TestReadIntrinsics:
    def test_four_numbers(self):
        from gpdepth3d.camera import read_intrinsics

        np.testing.assert_array_equal(
            read_intrinsics("721.5, 720,609.6,172.9"), [[721.5, 0, 609.6], [0, 720, 172.9], [0, 0, 1]]
        )

    def test_k_file_and_kitti_calibrations(self, tmp_path):
        from gpdepth3d.camera import read_intrinsics

        K = np.array([[585.0, 0, 320], [0, 586, 240], [0, 0, 1]])
        np.savetxt(tmp_path / "K.txt", K)
        np.testing.assert_array_equal(read_intrinsics(tmp_path / "K.txt"), K)
        P2 = "P2: 7.07e+02 0 6.04e+02 4.5e+01 0 7.08e+02 1.8e+02 -3.4e-01 0 0 1 2.7e-03"
        (tmp_path / "calib_000000.txt").write_text(f"P0: 1 0 0 0 0 1 0 0 0 0 1 0\n{P2}\nR0_rect: 1 0 0 0 1 0 0 0 1\n")
        np.testing.assert_allclose(
            read_intrinsics(tmp_path / "calib_000000.txt"), [[707, 0, 604], [0, 708, 180], [0, 0, 1]]
        )
        raw = tmp_path / "drive"
        raw.mkdir()
        (raw / "calib_cam_to_cam.txt").write_text(
            "P_rect_00: 1 0 0 0 0 1 0 0 0 0 1 0\nP_rect_02: 721.5 0 609.6 44.9 0 721.5 172.9 0.2 0 0 1 0.003\n"
        )
        np.testing.assert_allclose(read_intrinsics(raw), [[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]])

    def test_errors_name_the_problem(self, tmp_path):
        from gpdepth3d.camera import read_intrinsics
        from gpdepth3d.errors import CalibrationError, DataFormatError

        with pytest.raises(DataFormatError, match="not found"):
            read_intrinsics(tmp_path / "nope.txt")
        (tmp_path / "bad.txt").write_text("1 2 3\n")
        with pytest.raises(DataFormatError, match="3x3 K"):
            read_intrinsics(tmp_path / "bad.txt")
        with pytest.raises(CalibrationError, match="focal"):
            read_intrinsics("-5,5,1,1")
