"""Given world points: the readers (COLMAP models and pieces, PLY, NPZ, text), the calibrated sigma, visibility."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import DataFormatError, InvalidInputError, ShapeError
from gpdepth3d.mapping.points.given_points import (
    PointSigmaRule,
    fit_sigma_rule,
    ray_angles,
    read_given_points,
    sigma_coverage,
    visible_points,
)

POINTS = np.array([[0.0, 0.0, 2.0], [0.2, 0.1, 3.0], [-0.3, 0.1, 2.5]])


def write_model(folder, centres, points=POINTS, *, binary=False, first_id=1):
    """A COLMAP model of cameras at ``centres`` (identity rotation) all observing ``points``."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=64, height=48, params=[50, 50, 32, 24], camera_id=1)
    )
    for k, c in enumerate(centres):
        q = points - c
        uv = np.stack([50 * q[:, 0] / q[:, 2] + 32, 50 * q[:, 1] / q[:, 2] + 24], axis=1)
        image = pycolmap.Image(name=f"{first_id + k:05d}.png", camera_id=1, image_id=first_id + k)
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.array(x)) for x in uv])
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), -np.asarray(c)))
    for j, p in enumerate(points):
        track = pycolmap.Track()
        for k in range(len(centres)):
            track.add_element(first_id + k, j)
        rec.add_point3D(p, track, np.array([255, 0, 0], dtype=np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write if binary else rec.write_text)(str(folder))
    return folder


class TestReaders:
    def test_colmap_model_text_and_binary(self, tmp_path):
        for binary in (False, True):
            folder = write_model(tmp_path / f"m{binary}", [np.zeros(3), np.array([0.3, 0, 0])], binary=binary)
            (piece,) = read_given_points(folder)
            np.testing.assert_allclose(piece.points, POINTS)
            assert piece.model is not None and len(piece.model.images) == 2
            assert sorted(piece.observed_by(1)) == [0, 1, 2]
            # the first point: rays from (0,0,0) and (0.3,0,0) to (0,0,2)
            assert piece.angle_deg[0] == pytest.approx(np.degrees(np.arctan2(0.3, 2.0)), rel=1e-6)

    def test_numbered_models_are_pieces_largest_first(self, tmp_path):
        write_model(tmp_path / "sparse" / "0", [np.zeros(3), np.array([0.3, 0, 0])])
        write_model(tmp_path / "sparse" / "1", [np.zeros(3), np.array([0.1, 0, 0]), np.array([0.2, 0, 0])], first_id=5)
        pieces = read_given_points(tmp_path / "sparse")
        assert [len(p.model.images) for p in pieces] == [3, 2]

    def test_files(self, tmp_path):
        sigma = np.array([0.01, 0.02, 0.03])
        np.savez(tmp_path / "p.npz", xyz=POINTS, sigma=sigma)
        np.savetxt(tmp_path / "p.txt", np.column_stack([POINTS, sigma]))
        np.savetxt(tmp_path / "q.txt", POINTS)
        o3d = pytest.importorskip("open3d")
        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(POINTS.astype(np.float32)))
        cloud.point.sigma = o3d.core.Tensor(sigma.astype(np.float32).reshape(-1, 1))
        o3d.t.io.write_point_cloud(str(tmp_path / "p.ply"), cloud)
        for name in ("p.npz", "p.txt", "p.ply"):
            (piece,) = read_given_points(tmp_path / name)
            np.testing.assert_allclose(piece.points, POINTS, atol=1e-6)
            np.testing.assert_allclose(piece.sigma, sigma, atol=1e-6)
            assert piece.model is None
        assert read_given_points(tmp_path / "q.txt")[0].sigma is None

    def test_bad_inputs(self, tmp_path):
        with pytest.raises(DataFormatError):
            read_given_points(tmp_path / "missing.npz")
        with pytest.raises(DataFormatError):
            read_given_points(tmp_path)  # a folder without models
        np.savetxt(tmp_path / "five.txt", np.ones((2, 5)))
        with pytest.raises(DataFormatError, match="columns"):
            read_given_points(tmp_path / "five.txt")
        np.savez(tmp_path / "bad.npz", xyz=np.ones((3, 2)))
        with pytest.raises(ShapeError):
            read_given_points(tmp_path / "bad.npz")
        np.savez(tmp_path / "neg.npz", xyz=POINTS, sigma=-np.ones(3))
        with pytest.raises(DataFormatError, match="sigma"):
            read_given_points(tmp_path / "neg.npz")
        (tmp_path / "x.csv").write_text("1,2,3\n")
        with pytest.raises(DataFormatError):
            read_given_points(tmp_path / "x.csv")


class TestSigmaRule:
    def test_relative_only_is_a_share_of_the_distance(self):
        rule = PointSigmaRule(relative=0.03)
        np.testing.assert_allclose(rule.sigma(np.array([1.0, 2.0])), [0.03, 0.06])

    def test_stated_sigma_is_widened(self):
        s = PointSigmaRule(relative=0.02).sigma(np.array([2.0]), stated=np.array([0.03]))
        assert s[0] == pytest.approx(np.hypot(0.03, 0.04))

    def test_geometry_widens_small_angles_and_large_errors(self):
        rule = PointSigmaRule(relative=0.01, geometric=1.0)
        d = np.ones(3)
        s = rule.sigma(
            d, reprojection_error=np.array([1.0, 1.0, 4.0]), angle_deg=np.array([10.0, 1.0, 10.0]), focal=500
        )
        assert s[1] > s[0] and s[2] > s[0] and np.all(s > 0.01)
        expected = np.sqrt(0.01**2 + (1.0 / (500 * np.sin(np.radians(10.0)))) ** 2)
        assert s[0] == pytest.approx(expected)

    def test_bad_settings(self):
        with pytest.raises(InvalidInputError):
            PointSigmaRule(relative=0.0)
        with pytest.raises(InvalidInputError):
            PointSigmaRule(geometric=-1.0)

    def test_fit_covers_the_asked_share(self):
        rng = np.random.default_rng(0)
        errors = rng.normal(0.0, 0.03, 20_000)
        rule = fit_sigma_rule(errors)
        assert rule.relative == pytest.approx(0.03 * 1.96 / 2, rel=0.05)
        assert sigma_coverage(errors, rule.sigma(np.ones_like(errors))) == pytest.approx(0.95, abs=0.005)

    def test_fit_prefers_geometry_when_it_explains_the_errors(self):
        rng = np.random.default_rng(1)
        angle = rng.uniform(0.5, 20.0, 20_000)
        reproj = np.full_like(angle, 1.0)
        rel_sigma = 1.0 / (500 * np.sin(np.radians(angle)))
        errors = rng.normal(0.0, rel_sigma)
        rule = fit_sigma_rule(errors, reprojection_error=reproj, angle_deg=angle, focal=500)
        assert rule.geometric > 0
        width = rule.sigma(np.ones_like(errors), reprojection_error=reproj, angle_deg=angle, focal=500)
        assert sigma_coverage(errors, width) >= 0.945

    def test_coverage_checks_shapes(self):
        with pytest.raises(ShapeError):
            sigma_coverage(np.ones(3), np.ones(2))


def test_visible_points_drops_hidden_and_outside():
    camera = PinholeCamera(100.0, 100.0, 32.0, 24.0, 64, 48)
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0], [0.01, 0.0, 2.1], [5.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    assert sorted(visible_points(pts, np.eye(4), camera)) == [0, 2]


def test_ray_angles_of_a_single_view_are_zero(tmp_path):
    (piece,) = read_given_points(write_model(tmp_path / "m", [np.zeros(3)]))
    np.testing.assert_array_equal(ray_angles(piece.model), 0.0)
