"""Tests of gpdepth3d.mapping.points.triangulation: geometry, checks, uncertainty propagation, real 7-Scenes frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import CalibrationError, InvalidInputError, ShapeError
from gpdepth3d.mapping.points.triangulation import (
    Features,
    MultiViewPoints,
    TrackTriangulator,
    TriangulationConfig,
    build_tracks,
    detect_features,
    fundamental_from_poses,
    match_features,
    sampson_distance,
    triangulate_frames,
    triangulate_matches,
    triangulate_pair,
    triangulate_tracks,
)

CAM = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)


def _pose(tx: float, ty: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [tx, ty, 0.0]
    return T


def _scene(n: int = 200, seed: int = 0):
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 5.0, n)
    u = rng.uniform(50, 590, n)
    v = rng.uniform(50, 430, n)
    pts_ref = CAM.backproject_pixels(np.stack([u, v], 1), z)
    return pts_ref


def _project(points_world: np.ndarray, T_world_camera: np.ndarray) -> np.ndarray:
    Tcw = np.linalg.inv(T_world_camera)
    uv, _ = CAM.project(points_world @ Tcw[:3, :3].T + Tcw[:3, 3])
    return uv


class TestGeometry:
    def test_exact_correspondences_recover_depth(self):
        X = _scene()
        Ta, Tb = _pose(0.0), _pose(0.3, 0.05, 5.0)
        tp = triangulate_matches(_project(X, Ta), _project(X, Tb), CAM, Ta, Tb)
        assert len(tp) > 150
        # every kept point is one of the scene's points at its true depth
        idx = [int(np.argmin(np.linalg.norm(X - p, axis=1))) for p in tp.points_world]
        np.testing.assert_allclose(tp.points_world, X[idx], atol=1e-6)
        np.testing.assert_allclose(tp.depth, X[idx, 2], atol=1e-6)
        assert np.all(tp.reprojection_error < 1e-6)
        assert np.all(tp.parallax_deg >= 1.0)

    def test_sigma_matches_monte_carlo(self):
        rng = np.random.default_rng(1)
        X = _scene(60, seed=2)
        Ta, Tb = _pose(0.0), _pose(0.25)
        cfg = TriangulationConfig(
            max_relative_sigma=1.0, max_reprojection_error=10.0, min_parallax_deg=0.5, pixel_sigma=1.0
        )
        ua, ub = _project(X, Ta), _project(X, Tb)
        ref = triangulate_matches(ua, ub, CAM, Ta, Tb, config=cfg)
        assert len(ref) == 60
        samples = []
        for _ in range(400):
            noisy = triangulate_matches(
                ua + rng.normal(size=ua.shape), ub + rng.normal(size=ub.shape), CAM, Ta, Tb, config=cfg
            )
            if len(noisy) != 60:
                continue
            samples.append(noisy.depth)
        mc_std = np.std(np.array(samples), axis=0)
        ratio = mc_std / ref.sigma
        assert 0.85 < np.median(ratio) < 1.15
        # farther points are less certain
        assert np.corrcoef(ref.depth, ref.sigma)[0, 1] > 0.8

    def test_checks_drop_bad_points(self):
        X = _scene(100, seed=3)
        Ta, Tb = _pose(0.0), _pose(0.3)
        ua, ub = _project(X, Ta), _project(X, Tb)
        ub_bad = ub.copy()
        ub_bad[:10, 1] += 15.0  # off the epipolar line: large reprojection error
        tp = triangulate_matches(ua, ub_bad, CAM, Ta, Tb)
        kept = {int(np.argmin(np.linalg.norm(X - p, axis=1))) for p in tp.points_world}
        assert kept.isdisjoint(range(10)) and len(kept) > 60
        # a tiny baseline gives parallax below the threshold: nothing survives
        Tc = _pose(0.005)
        assert len(triangulate_matches(ua, _project(X, Tc), CAM, Ta, Tc)) == 0
        # behind the camera
        Xb = X.copy()
        Xb[:, 2] *= -1
        assert len(triangulate_matches(_project(Xb, Ta), _project(Xb, Tb), CAM, Ta, Tb)) == 0

    def test_fundamental_and_sampson(self):
        X = _scene(50, seed=4)
        Ta, Tb = _pose(0.1, 0.02, 3.0), _pose(-0.2, 0.0, -4.0)
        F = fundamental_from_poses(CAM, Ta, Tb)
        ua, ub = _project(X, Ta), _project(X, Tb)
        assert np.max(sampson_distance(F, ua, ub)) < 1e-6
        assert np.min(sampson_distance(F, ua, ub + [0.0, 5.0])) > 0.1

    def test_triangulate_frames_combines_views(self):
        X = _scene(150, seed=5)
        poses = [_pose(-0.3), _pose(0.0), _pose(0.3, 0.1)]
        uvs = [_project(X, T) for T in poses]
        desc = np.eye(150, 128, dtype=np.float32) * 10  # unique descriptors: match by identity
        feats = [Features(uv, desc, "sift") for uv in uvs]
        rgbs = [np.zeros((480, 640, 3), np.uint8)] * 3
        # pixel noise only (tiny pose priors), as the pair's sigma
        sift = TriangulationConfig(
            detector="sift", depth_sigma_floor=0.0, rotation_sigma_deg=1e-5, translation_sigma=1e-6
        )
        sparse = triangulate_frames(rgbs, poses, CAM, reference=1, features=feats, config=sift)
        pair = triangulate_pair(rgbs[1], rgbs[0], CAM, poses[1], poses[0], features=(feats[1], feats[0]), config=sift)
        assert len(sparse) >= len(pair) > 100
        z = CAM.project(X)[1]
        uv_ref = uvs[1]
        for u, v, d in zip(sparse.u[:20], sparse.v[:20], sparse.depth[:20]):
            k = int(np.argmin(np.hypot(uv_ref[:, 0] - u, uv_ref[:, 1] - v)))
            assert d == pytest.approx(z[k], abs=1e-5)
        # two views of a point give a smaller sigma than the best single pair
        assert np.median(sparse.sigma) < np.median(pair.sigma)

    def test_errors(self):
        X = _scene(10)
        Ta, Tb = _pose(0.0), _pose(0.3)
        ua, ub = _project(X, Ta), _project(X, Tb)
        bad = Tb.copy()
        bad[:3, :3] *= 1.1
        with pytest.raises(CalibrationError):
            triangulate_matches(ua, ub, CAM, Ta, bad)
        with pytest.raises(ShapeError):
            triangulate_matches(ua, ub[:5], CAM, Ta, Tb)
        with pytest.raises(InvalidInputError):
            triangulate_frames([np.zeros((480, 640, 3), np.uint8)], [Ta], CAM)
        with pytest.raises(ShapeError):
            triangulate_pair(np.zeros((10, 10, 3), np.uint8), np.zeros((480, 640, 3), np.uint8), CAM, Ta, Tb)
        with pytest.raises(ShapeError):
            detect_features(np.zeros((10, 10, 3), np.float32))
        with pytest.raises(InvalidInputError):
            TriangulationConfig(detector="surf")
        with pytest.raises(InvalidInputError):
            TriangulationConfig(min_views=1)
        with pytest.raises(InvalidInputError):
            TriangulationConfig(translation_sigma=0.0)
        with pytest.raises(InvalidInputError):
            TriangulationConfig(depth_sigma_floor=-0.1)
        with pytest.raises(InvalidInputError):  # KLT corners carry no descriptors to match
            match_features(
                Features(ua, np.zeros((10, 0), np.float32), "klt"), Features(ub, np.zeros((10, 0), np.float32), "klt")
            )
        with pytest.raises(InvalidInputError):  # features of another detector than configured
            triangulate_frames(
                [np.zeros((480, 640, 3), np.uint8)] * 2,
                [Ta, Tb],
                CAM,
                features=[Features(ua, np.zeros((10, 128), np.float32), "sift")] * 2,
            )
        with pytest.raises(InvalidInputError):
            TriangulationConfig(ratio=1.5)
        with pytest.raises(InvalidInputError):
            match_features(
                Features(ua, np.zeros((10, 32), np.uint8), "orb"), Features(ub, np.zeros((10, 128), np.float32), "sift")
            )


def _rot(rx: float, ry: float, rz: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.radians([rx, ry, rz]))[0]


def _posed(t, angles_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rot(*angles_deg)
    T[:3, 3] = t
    return T


def _views():
    """Four posed views: the reference at the origin and three neighbours 8-30 cm away."""
    return [
        _posed([0.0, 0.0, 0.0]),
        _posed([0.08, 0.0, 0.0], (0.0, 1.0, 0.0)),
        _posed([0.18, 0.03, 0.01], (0.5, 2.0, 0.0)),
        _posed([0.30, -0.02, 0.04], (0.0, 3.0, 1.0)),
    ]


def _tracks(X: np.ndarray, poses) -> np.ndarray:
    return np.stack([_project(X, T) for T in poses], axis=1)


class TestTriangulateTracks:
    def test_exact_without_noise(self):
        X = _scene(200, seed=10)
        poses = _views()
        tracks = _tracks(X, poses)
        tracks[:50, 2] = np.nan  # not every track is seen in every view
        for refine in (False, True):
            cfg = TriangulationConfig(depth_sigma_floor=0.0, refine_poses=refine, max_relative_sigma=1.0)
            mv = triangulate_tracks(tracks, poses, CAM, reference=0, config=cfg)
            assert isinstance(mv, MultiViewPoints)
            assert len(mv) == 200
            np.testing.assert_allclose(mv.depth, X[mv.index, 2], rtol=1e-9)
            np.testing.assert_allclose(mv.points_world, X[mv.index], atol=1e-8)
            np.testing.assert_allclose(mv.poses, np.stack(poses), atol=1e-9)  # nothing to correct
            assert np.all(mv.reprojection_error < 1e-6)
            assert np.all(mv.n_views[:50] == 3) and np.all(mv.n_views[50:] == 4)
        # any view can be the reference
        mv = triangulate_tracks(tracks, poses, CAM, reference=3, config=TriangulationConfig(max_relative_sigma=1.0))
        Tcw = np.linalg.inv(poses[3])
        np.testing.assert_allclose(mv.depth, (X[mv.index] @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2], rtol=1e-9)

    def test_wrong_matches_do_not_move_the_points(self):
        rng = np.random.default_rng(11)
        X = _scene(200, seed=11)
        poses = _views()
        tracks = _tracks(X, poses) + rng.normal(0, 0.3, (200, 4, 2))
        tracks[:, 0] = _tracks(X, poses)[:, 0]
        bad = np.arange(20)
        tracks[bad, 2] += rng.choice([-1, 1], (20, 2)) * rng.uniform(15, 40, (20, 2))  # one wrong match each
        tracks[20:30, 1:] = _tracks(X[rng.permutation(200)[:10]], poses)[:, 1:]  # wrong in every view
        for refine in (False, True):  # poses held, and the robust bundle adjustment
            mv = triangulate_tracks(tracks, poses, CAM, reference=0, config=TriangulationConfig(refine_poses=refine))
            err = np.abs(mv.depth - X[mv.index, 2])
            # the tracks with one wrong observation keep their point, from the other views
            assert np.isin(bad, mv.index).sum() >= 18
            assert np.all(err[np.isin(mv.index, bad)] < 3 * mv.sigma[np.isin(mv.index, bad)])
            # tracks wrong in every view are dropped or honestly uncertain; no kept point is far off
            assert np.all(err < 4 * mv.sigma)
            # the wrong observations were rejected: at most 3 views support the first 20
            assert np.all(mv.n_views[np.isin(mv.index, bad)] <= 3)
            # the wrong matches did not drag the neighbours' poses away
            np.testing.assert_allclose(mv.poses, np.stack(poses), atol=1e-3)

    def test_sigma_covers_pixel_and_pose_noise(self):
        """+-2 sigma covers ~95 % of the errors when pixels and poses carry the assumed noise."""
        rng = np.random.default_rng(12)
        X = _scene(150, seed=12)
        poses = _views()
        clean = _tracks(X, poses)
        cfg = TriangulationConfig(
            pixel_sigma=0.5,
            rotation_sigma_deg=0.1,
            translation_sigma=0.005,
            depth_sigma_floor=0.0,
            max_relative_sigma=1.0,
            variance_factor=False,
        )
        inside, z_scores = [], []
        for _ in range(40):
            noisy_poses = [poses[0]] + [
                T @ _posed(rng.normal(0, 0.005, 3), np.degrees(rng.normal(0, np.radians(0.1), 3))) for T in poses[1:]
            ]
            tracks = clean + rng.normal(0, 0.5, clean.shape)
            mv = triangulate_tracks(tracks, noisy_poses, CAM, reference=0, config=cfg)
            e = mv.depth - X[mv.index, 2]
            inside.append(np.abs(e) <= 2 * mv.sigma)
            z_scores.append(e / mv.sigma)
        coverage = np.mean(np.concatenate(inside))
        assert 0.90 <= coverage <= 0.99
        assert 0.8 < np.std(np.concatenate(z_scores)) < 1.25
        # the pose uncertainty is what makes sigma grow with the depth faster than pixel noise
        # alone does: without it (tiny pose priors) the same tracks get much smaller sigmas
        tight = TriangulationConfig(
            pixel_sigma=0.5,
            rotation_sigma_deg=1e-5,
            translation_sigma=1e-6,
            depth_sigma_floor=0.0,
            max_relative_sigma=1.0,
        )
        a = triangulate_tracks(clean, poses, CAM, reference=0, config=tight)
        b = triangulate_tracks(clean, poses, CAM, reference=0, config=cfg)
        assert np.median(b.sigma / a.sigma) > 1.5
        # the a posteriori variance factor widens sigma when the residuals exceed pixel_sigma
        # (here: poses 0.3 deg off, far beyond their prior) and leaves it alone otherwise
        off = [poses[0]] + [T @ _posed([0.0, 0.0, 0.0], (0.3, -0.3, 0.0)) for T in poses[1:]]
        with_factor = replace(cfg, variance_factor=True)
        plain = triangulate_tracks(clean, off, CAM, reference=0, config=cfg)
        widened = triangulate_tracks(clean, off, CAM, reference=0, config=with_factor)
        assert widened.pixel_sigma > 1.0 and np.median(widened.sigma / plain.sigma) > 1.5
        same = triangulate_tracks(clean, poses, CAM, reference=0, config=with_factor)
        np.testing.assert_allclose(same.sigma, b.sigma, rtol=1e-9)

    def test_held_pose_kernels_match_the_dense_normal_equations(self):
        """The compiled held-pose path (refinement, variance, checks) agrees with `_Problem`'s numpy algebra."""
        from gpdepth3d.mapping.points.multiview import (
            _held_pose_depths,
            _held_pose_variance,
            _linear_inverse_depth,
            _point_checks,
            _Problem,
        )

        rng = np.random.default_rng(14)
        X = _scene(120, seed=14)
        poses = _views()
        tracks = _tracks(X, poses) + rng.normal(0, 0.4, (120, 4, 2))
        tracks[:, 0] = _tracks(X, poses)[:, 0]
        tracks[:10, 2] += 25.0  # outliers the refinement drops
        tracks[10:30, 3] = np.nan
        Ts = np.stack(poses)
        T_jr = np.linalg.inv(Ts[1:]) @ Ts[0]
        xbar = np.column_stack([(tracks[:, 0, 0] - CAM.cx) / CAM.fx, (tracks[:, 0, 1] - CAM.cy) / CAM.fy, np.ones(120)])
        mask = np.all(np.isfinite(tracks[:, 1:]), axis=-1)
        obs = np.where(mask[..., None], tracks[:, 1:], 0.0)
        prob = _Problem(xbar, obs, mask, T_jr[:, :3, :3], T_jr[:, :3, 3], CAM, 0.5, np.radians(0.1), 0.005)
        rho0 = _linear_inverse_depth(xbar, obs, mask, prob.R, prob.t, prob.f, prob.c)
        np.testing.assert_allclose(1 / rho0[30:], X[30:, 2], rtol=0.05)  # the linear start is close
        rho, r, valid = _held_pose_depths(xbar, obs, mask, prob.R, prob.t, prob.f, prob.c, 0.5, rho0, 2.0, 3.0)
        assert not valid[:10, 1].any() and valid[10:, 1].all() and not valid[10:30, 2].any()

        # the same robust Gauss-Newton with _Problem's Jacobians: 3 steps, outliers > 3 px dropped, 1 step
        def steps(x, k):
            for _ in range(k):
                res, ok, J_rho, _ = prob.derivatives(x)
                w = 1.0 / (1.0 + np.sum(res**2, -1) / 4.0) * ok
                h = np.sum(w[..., None] * J_rho**2, axis=(1, 2))
                b = np.sum(w[..., None] * J_rho * res, axis=(1, 2))
                x_new = x - np.where(h > 0, b / np.where(h > 0, h, 1.0), 0.0)
                x = np.where(x_new > 0.1 * x, x_new, 0.5 * x)
            return x

        x = steps(rho0, 3)
        _, _, res, ok = prob.residuals(x)
        prob.mask = mask & ok & (np.linalg.norm(res, axis=-1) * 0.5 <= 3.0)
        x = steps(x, 1)
        np.testing.assert_allclose(rho, x, rtol=1e-10)
        _, _, r_np, valid_np = prob.residuals(rho)
        np.testing.assert_array_equal(valid, valid_np)
        np.testing.assert_allclose(r, r_np, rtol=1e-10, atol=1e-10)
        # variance: 1 / h + the poses' prior through d rho / d xi = -h^-1 H_rho_xi (unit weights)
        prob.pixel_sigma = 0.8
        _, _, J_rho, J_xi = prob.derivatives(rho)
        h = np.sum(J_rho**2, axis=(1, 2))
        H_xr = np.sum(J_rho[..., None] * J_xi, axis=2)
        expected = 1 / h + np.sum((H_xr / h[:, None, None]) ** 2 / prob.prior, axis=(1, 2))
        var = _held_pose_variance(xbar, rho, valid, prob.R, prob.t, prob.f / 0.8, 1.0 / prob.prior)
        np.testing.assert_allclose(var, expected, rtol=1e-10)
        # checks: views, parallax against each neighbour centre, in front, RMS residual
        Xr = xbar / rho[:, None]
        n_views, parallax, front, rms = _point_checks(Xr, r, valid, prob.R, prob.t, 0.05)
        np.testing.assert_array_equal(n_views, 1 + valid.sum(1))
        centres = Ts[1:, :3, 3]  # the reference is the world frame here
        rays = Xr[:, None] - centres[None]
        cos = np.einsum("na,nja->nj", Xr, rays) / (np.linalg.norm(Xr, axis=1)[:, None] * np.linalg.norm(rays, axis=-1))
        np.testing.assert_allclose(parallax, np.degrees(np.arccos(np.where(valid, cos, 1.0))).max(1), rtol=1e-9)
        assert front.all()
        np.testing.assert_allclose(rms, np.sqrt(np.sum(r**2, axis=(1, 2)) / valid.sum(1)), rtol=1e-12)

    def test_refined_poses_are_closer_to_the_truth(self):
        X = _scene(300, seed=13)
        poses = _views()
        tracks = _tracks(X, poses)
        off = [poses[0]] + [T @ _posed([0.0, 0.0, 0.0], (0.3, -0.3, 0.2)) for T in poses[1:]]
        cfg = TriangulationConfig(
            refine_below=1.0, refine_rotation_sigma_deg=1.0, refine_translation_sigma=0.01, max_relative_sigma=1.0
        )
        mv = triangulate_tracks(tracks, off, CAM, reference=0, config=cfg)
        held = TriangulationConfig(refine_poses=False, max_relative_sigma=1.0)
        fixed = triangulate_tracks(tracks, off, CAM, reference=0, config=held)

        def angle(A, B):
            c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
            return np.degrees(np.arccos(np.clip(c, -1, 1)))

        for k in (1, 2, 3):
            assert angle(mv.poses[k], poses[k]) < 0.2 * angle(off[k], poses[k])
        assert np.median(np.abs(mv.depth / X[mv.index, 2] - 1)) < 0.5 * np.median(
            np.abs(fixed.depth / X[fixed.index, 2] - 1)
        )

    def test_refinement_beats_held_poses_and_sigma_covers_its_error(self):
        """Neighbour poses off by their prior: the bundle adjustment's depths are closer and its sigma honest."""
        rng = np.random.default_rng(22)
        X = _scene(200, seed=22)
        poses = _views()
        clean = _tracks(X, poses)
        cfg = TriangulationConfig(
            pixel_sigma=0.5,
            rotation_sigma_deg=0.2,
            translation_sigma=0.005,
            refine_poses=True,
            refine_below=1.0,  # refined always: the tracks agree with these poses within the gate
            refine_rotation_sigma_deg=0.2,
            refine_translation_sigma=0.005,
            variance_factor=False,
            depth_sigma_floor=0.0,
            max_relative_sigma=1.0,
        )
        err_refined, err_held, inside, z_scores = [], [], [], []
        for _ in range(20):
            noisy = [poses[0]] + [
                T @ _posed(rng.normal(0, 0.005, 3), np.degrees(rng.normal(0, np.radians(0.2), 3))) for T in poses[1:]
            ]
            tracks = clean + rng.normal(0, 0.5, clean.shape)
            tracks[:, 0] = clean[:, 0]  # the reference keypoint is the ray: exact
            refined = triangulate_tracks(tracks, noisy, CAM, config=cfg)
            held = triangulate_tracks(tracks, noisy, CAM, config=replace(cfg, refine_poses=False))
            e = refined.depth - X[refined.index, 2]
            err_refined.append(np.abs(e) / X[refined.index, 2])
            err_held.append(np.abs(held.depth / X[held.index, 2] - 1))
            inside.append(np.abs(e) <= 2 * refined.sigma)
            z_scores.append(e / refined.sigma)
            assert len(refined) >= 190
        # the pose errors shared by all points are what the refinement removes
        assert np.median(np.concatenate(err_refined)) < 0.65 * np.median(np.concatenate(err_held))
        # +-2 sigma (pixel noise and the poses' posterior through the Schur complement) covers ~95 %
        assert 0.9 <= np.mean(np.concatenate(inside)) <= 0.995
        assert 0.75 < np.std(np.concatenate(z_scores)) < 1.3

    def test_bundle_adjustment_jacobian_and_variance(self):
        """`_Problem.jacobian` is the derivative of its residuals; the variance is the inverse of J^T J's depth block."""
        from scipy.optimize._numdiff import approx_derivative

        from gpdepth3d.mapping.points.multiview import _joint_inverse_depth_variance, _Problem

        rng = np.random.default_rng(22)
        X = _scene(40, seed=22)
        poses = _views()
        tracks = _tracks(X, poses) + rng.normal(0, 0.5, (40, 4, 2))
        T_jr = np.linalg.inv(np.stack(poses[1:])) @ poses[0]
        xbar = np.column_stack([(tracks[:, 0, 0] - CAM.cx) / CAM.fx, (tracks[:, 0, 1] - CAM.cy) / CAM.fy, np.ones(40)])
        mask = np.ones((40, 3), bool)
        mask[:10, 1] = False  # not seen there: no rows
        prob = _Problem(xbar, tracks[:, 1:], mask, T_jr[:, :3, :3], T_jr[:, :3, 3], CAM, 0.5, np.radians(0.2), 0.005)
        x = np.r_[1 / X[:, 2] * (1 + 0.05 * rng.normal(size=40)), rng.normal(0, 0.02, 18)]
        J = prob.jacobian(x)
        assert J.shape == (2 * 110 + 18, 40 + 18)
        np.testing.assert_allclose(J.toarray(), approx_derivative(prob.stacked_residuals, x), atol=1e-4 * abs(J).max())
        # the prior rows: xi / sigma
        np.testing.assert_allclose(prob.stacked_residuals(x)[-18:], x[40:] * np.tile(np.sqrt(prob.prior), 3))
        # marginal variance of each inverse depth = diagonal of (J^T J)^-1 (with the pixel sigma given)
        rho = prob.unpack(x)
        valid = prob.residuals(rho)[3]
        var = _joint_inverse_depth_variance(prob, rho, valid, 0.8)
        prob.pixel_sigma = 0.8
        J = prob.jacobian(x).toarray()
        np.testing.assert_allclose(var, np.diag(np.linalg.inv(J.T @ J))[:40], rtol=1e-6)
        # the bundle adjustment lowers the robust cost to a stationary point of its reweighted normal equations
        from gpdepth3d.mapping.points.multiview import _bundle_adjusted, _normal_equations, _robust_cost

        prob.pixel_sigma, prob.mask = 0.5, mask
        start = _robust_cost(prob, rho, 2.0)
        rho2 = _bundle_adjusted(prob, rho.copy(), 2.0)
        assert _robust_cost(prob, rho2, 2.0) < 0.5 * start
        r = prob.residuals(rho2)[2]
        w = np.where(mask, 1.0 / (1.0 + np.sum(r * r, axis=-1) / 4.0), 0.0)
        h, g_r, _, H_xx, g_x, _, _ = _normal_equations(prob, rho2, w)
        assert np.max(np.abs(g_r) / np.sqrt(h)) < 0.2 and np.max(np.abs(g_x) / np.sqrt(np.diag(H_xx))) < 0.2
        # the normal equations are J^T W J and J^T W r of the stacked system
        Js = prob.jacobian(prob.pack(rho2)).toarray()
        rs = prob.stacked_residuals(prob.pack(rho2))
        wrow = np.r_[np.repeat(w[mask], 2), np.ones(18)]
        np.testing.assert_allclose(g_r, (Js.T @ (wrow * rs))[:40], atol=1e-8 * np.abs(g_r).max())
        np.testing.assert_allclose(H_xx, (Js.T @ (wrow[:, None] * Js))[40:, 40:], rtol=1e-8, atol=1e-6)

    def test_checks_and_errors(self):
        X = _scene(50, seed=14)
        poses = _views()
        tracks = _tracks(X, poses)
        # a tiny baseline: the depths are too uncertain to keep
        near = [poses[0], _posed([0.002, 0.0, 0.0])]
        assert len(triangulate_tracks(_tracks(X, near), near, CAM)) == 0
        # min_views: tracks seen in fewer views are dropped
        t2 = tracks.copy()
        t2[:10, 2:] = np.nan
        mv = triangulate_tracks(t2, poses, CAM, config=TriangulationConfig(min_views=3, max_relative_sigma=1.0))
        assert not np.isin(np.arange(10), mv.index).any() and len(mv) == 40
        # no tracks
        assert len(triangulate_tracks(np.zeros((0, 4, 2)), poses, CAM)) == 0
        with pytest.raises(ShapeError):
            triangulate_tracks(tracks[..., 0], poses, CAM)
        with pytest.raises(ShapeError):
            triangulate_tracks(tracks, poses[:3], CAM)
        with pytest.raises(InvalidInputError):
            triangulate_tracks(tracks, poses, CAM, reference=4)
        t3 = tracks.copy()
        t3[0, 0] = np.nan
        with pytest.raises(InvalidInputError):
            triangulate_tracks(t3, poses, CAM, reference=0)
        bad = [p.copy() for p in poses]
        bad[1][:3, :3] *= 1.1
        with pytest.raises(CalibrationError):
            triangulate_tracks(tracks, bad, CAM)


SMALL = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)


def _texture(seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (1024, 1024)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 255
    return tex.astype(np.float32)


def _render_plane(T_world_camera: np.ndarray, tex: np.ndarray, distance: float = 2.0, extent: float = 4.0):
    """RGB image and z-depth of a textured plane z = distance (world) seen by SMALL."""
    import cv2

    u, v = SMALL.pixel_grid()
    rays = np.stack([(u - SMALL.cx) / SMALL.fx, (v - SMALL.cy) / SMALL.fy, np.ones_like(u, dtype=float)], -1)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    rw = rays @ R.T
    s = (distance - t[2]) / rw[..., 2]  # the camera's z-depth (rays have z = 1)
    X = t[0] + s * rw[..., 0]
    Y = t[1] + s * rw[..., 1]
    mx = ((X / extent + 0.5) * tex.shape[1]).astype(np.float32)
    my = ((Y / extent + 0.5) * tex.shape[0]).astype(np.float32)
    grey = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
    rgb = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return rgb, s


class TestTrackTriangulator:
    def test_textured_plane(self):
        tex = _texture()
        poses = [_posed([0.03 * k, 0.005 * k, 0.0], (0.0, 0.3 * k, 0.0)) for k in range(6)]
        tracker = TrackTriangulator(SMALL, TriangulationConfig(max_features=300), window=4)
        counts, errors, inside = [], [], []
        for k, T in enumerate(poses):
            rgb, depth = _render_plane(T, tex)
            sparse = tracker.add(rgb, T)
            counts.append(len(sparse))
            if len(sparse):
                iu = np.rint(sparse.uv).astype(int)
                truth = depth[iu[:, 1], iu[:, 0]]
                errors.append(np.abs(sparse.depth - truth) / truth)
                inside.append(np.abs(sparse.depth - truth) <= 2 * sparse.sigma)
        assert counts[0] == 0  # nothing to triangulate against yet
        assert min(counts[2:]) > 100
        assert tracker.n_tracks > 150
        assert tracker.last is not None and tracker.last.n_views.max() == 5  # tracks span the window
        assert np.median(np.concatenate(errors)) < 0.01
        assert np.mean(np.concatenate(inside)) > 0.95
        tracker.reset()
        assert tracker.n_tracks == 0 and len(tracker.add(rgb, poses[-1])) == 0

    def test_update_poses_after_a_loop_closure(self):
        """Poses replaced through update_poses are the ones the next triangulation uses."""
        tex = _texture(2)
        poses = [_posed([0.03 * k, 0.0, 0.0]) for k in range(4)]
        shifted = [T.copy() for T in poses]
        for T in shifted:
            T[:3, 3] += [0.5, 0.2, 0.0]  # the whole trajectory moved: the depths must not change
        images = [_render_plane(T, tex)[0] for T in poses]
        cfg = TriangulationConfig(max_features=200)
        a = TrackTriangulator(SMALL, cfg, window=3)
        b = TrackTriangulator(SMALL, cfg, window=3)
        for k in range(3):
            a.add(images[k], poses[k], key=k)
            b.add(images[k], poses[k] if k != 1 else np.eye(4), key=k)  # frame 1 with a wrong pose
        assert b.update_poses({1: poses[1], 99: np.eye(4)}) == 1
        sa, sb = a.add(images[3], poses[3], key=3), b.add(images[3], poses[3], key=3)
        np.testing.assert_allclose(sb.depth, sa.depth, rtol=1e-9)
        assert a.update_poses({k: T for k, T in enumerate(shifted)}) == 4
        moved = a.add(images[3], shifted[3])  # the same image again: zero parallax to itself, others moved with it
        assert len(moved) > 50
        # the plane is 2 m ahead of every camera
        assert np.mean(np.abs(moved.depth / 2.0 - 1) < 0.02) > 0.95 and abs(np.median(moved.depth) - 2.0) < 0.005
        with pytest.raises(CalibrationError):
            a.update_poses({3: np.eye(4) * 2})

    def test_batch_reference_first_frame(self):
        tex = _texture(1)
        poses = [_posed([0.04 * k, 0.0, 0.0]) for k in range(5)]
        views = [_render_plane(T, tex) for T in poses]
        sparse = triangulate_frames(
            [v[0] for v in views], poses, SMALL, reference=0, config=TriangulationConfig(max_features=300)
        )
        assert len(sparse) > 100
        iu = np.rint(sparse.uv).astype(int)
        truth = views[0][1][iu[:, 1], iu[:, 0]]
        assert np.median(np.abs(sparse.depth - truth) / truth) < 0.01
        tracks = build_tracks(
            [v[0] for v in views], poses, SMALL, reference=0, config=TriangulationConfig(max_features=300)
        )
        assert tracks.shape[1:] == (5, 2) and np.isfinite(tracks[:, 4, 0]).sum() > 100
        with pytest.raises(InvalidInputError):
            build_tracks([v[0] for v in views], poses, SMALL, reference=5)
        with pytest.raises(InvalidInputError):
            build_tracks([views[0][0]], poses[:1], SMALL)
        with pytest.raises(ShapeError):
            build_tracks([views[0][0], np.zeros((10, 10, 3), np.uint8)], poses[:2], SMALL)

    def test_lag_triangulates_each_frame_from_views_on_both_sides(self):
        tex = _texture(3)
        poses = [_posed([0.03 * k, 0.004 * k, 0.0], (0.0, 0.2 * k, 0.0)) for k in range(7)]
        views = [_render_plane(T, tex) for T in poses]
        tracker = TrackTriangulator(SMALL, TriangulationConfig(max_features=300), window=3, lag=2)
        got = {}
        for k, (T, (rgb, _)) in enumerate(zip(poses, views)):
            sparse = tracker.add(rgb, T, key=f"f{k}")
            if k < 2:  # the frame's later views have not come yet
                assert len(sparse) == 0 and tracker.last_key is None and tracker.pending == k + 1
            else:
                assert tracker.last_key == f"f{k - 2}" and tracker.pending == 2
                got[tracker.last_key] = (sparse, tracker.last)
        rest = tracker.flush()
        assert [k for k, _ in rest] == ["f5", "f6"] and tracker.pending == 0 and tracker.flush() == []
        got.update({k: (s, None) for k, s in rest})
        assert sorted(got) == [f"f{k}" for k in range(7)]
        for k in range(7):
            sparse = got[f"f{k}"][0]
            assert len(sparse) > 100, k  # the first frame too: it has later views
            iu = np.rint(sparse.uv).astype(int)
            truth = views[k][1][iu[:, 1], iu[:, 0]]
            assert np.median(np.abs(sparse.depth - truth) / truth) < 0.01
        # frame 3 is seen from up to 3 earlier and 2 later views (6 with itself)
        assert got["f3"][1].n_views.max() == 6
        # lag 0 is the frame just added
        plain = TrackTriangulator(SMALL, TriangulationConfig(max_features=300), window=3)
        for k in range(3):
            s0 = plain.add(views[k][0], poses[k], key=k)
        assert plain.last_key == 2 and len(s0) > 100 and plain.flush() == []

    def test_errors(self):
        tracker = TrackTriangulator(SMALL)
        with pytest.raises(ShapeError):
            tracker.add(np.zeros((480, 640, 3), np.uint8), np.eye(4))
        with pytest.raises(CalibrationError):
            tracker.add(np.zeros((240, 320, 3), np.uint8), np.eye(4) * 2)
        with pytest.raises(InvalidInputError):
            TrackTriangulator(SMALL, window=0)
        with pytest.raises(InvalidInputError):
            TrackTriangulator(SMALL, lag=-1)
        with pytest.raises(InvalidInputError):
            TrackTriangulator(SMALL, lag=1.5)  # type: ignore[arg-type]
        with pytest.raises(InvalidInputError):
            TrackTriangulator("camera")  # type: ignore[arg-type]


class TestRealFrames:
    @pytest.mark.parametrize("detector", ["orb", "sift"])
    def test_depths_agree_with_kinect(self, shared_data, detector):
        """Frames 250 and 230 of 7-Scenes: triangulated RGB features vs the Kinect depth.

        The comparison lifts each triangulated point into the *depth* camera (the dataset's K,
        f = 585) and reads the Kinect depth there; the RGB frames use f = 525 (the colour
        camera; see gpdepth3d.mapping.SEVEN_SCENES_RGB_K).
        """
        from gpdepth3d.datasets.sevenscenes import SevenScenes
        from gpdepth3d.mapping import SEVEN_SCENES_RGB_K

        reader = SevenScenes(shared_data / "7scenes")
        a, b = reader.load("frame-000250"), reader.load("frame-000230")
        rgb_cam = PinholeCamera.from_K(SEVEN_SCENES_RGB_K, 640, 480)
        tp = triangulate_pair(a.rgb, b.rgb, rgb_cam, a.pose, b.pose, config=TriangulationConfig(detector=detector))
        assert len(tp) > 50
        Tcw = np.linalg.inv(a.pose)
        uv, z = a.camera.project(tp.points_world @ Tcw[:3, :3].T + Tcw[:3, 3])
        inside = a.camera.in_image(uv)
        iu = np.rint(uv[inside]).astype(int)
        kinect = a.depth[iu[:, 1], iu[:, 0]]
        ok = kinect > 0
        assert ok.sum() > 40
        rel = np.abs(z[inside][ok] - kinect[ok]) / kinect[ok]
        assert np.median(rel) < 0.06
        # the stated sigma has the size of the actual errors: 1 px noise is conservative for
        # SIFT's sub-pixel keypoints (errors ~0.3 sigma here), about right for ORB
        err = np.abs(z[inside][ok] - kinect[ok])
        assert 0.2 < np.median(err) / np.median(tp.sigma[inside][ok]) < 3


def _seven_scenes(shared_data, indices):
    from gpdepth3d.datasets.sevenscenes import SevenScenes
    from gpdepth3d.mapping import SEVEN_SCENES_RGB_K

    reader = SevenScenes(shared_data / "7scenes")
    names = [f"frame-{5 * i:06d}" for i in indices]
    for name in names:
        if not (shared_data / "7scenes" / f"{name}.color.jpg").exists():
            pytest.skip(f"7-Scenes frame {name} not found")
    return [reader.load(name) for name in names], PinholeCamera.from_K(SEVEN_SCENES_RGB_K, 640, 480)


def _against_kinect(frame, rgb_cam, sparse):
    """(|depth error|, sigma) of the points with a Kinect depth: each point lifted with the colour
    camera (f = 525) and projected into the depth camera (f = 585), as bench/fusion.py does."""
    lifted = rgb_cam.backproject_pixels(sparse.uv, sparse.depth)
    uv, z = frame.camera.project(lifted)
    inside = frame.camera.in_image(uv)
    iu = np.rint(uv[inside]).astype(int)
    kinect = frame.depth[iu[:, 1], iu[:, 0]]
    ok = kinect > 0
    return np.abs(z[inside][ok] - kinect[ok]), np.asarray(sparse.sigma)[inside][ok], kinect[ok]


class TestRealSequence:
    def test_stream_sigma_covers_kinect(self, shared_data):
        """7-Scenes frames 40-70 (every 5th raw frame) through the TrackTriangulator."""
        frames, rgb_cam = _seven_scenes(shared_data, range(8, 15))
        tracker = TrackTriangulator(rgb_cam, window=4)
        errs, sigmas, rel, counts = [], [], [], []
        for f in frames:
            sparse = tracker.add(f.rgb, f.pose)
            counts.append(len(sparse))
            if len(sparse):
                e, s, k = _against_kinect(f, rgb_cam, sparse)
                errs.append(e)
                sigmas.append(s)
                rel.append(e / k)
        e, s = np.concatenate(errs), np.concatenate(sigmas)
        assert counts[0] == 0 and min(counts[2:]) > 20 and np.mean(counts[2:]) > 80
        assert 0.85 <= np.mean(e <= 2 * s) <= 0.99
        assert np.median(np.concatenate(rel)) < 0.08
        # sigma is not a constant: it grows where the errors grow
        assert np.median(e[s > np.median(s)]) > np.median(e[s <= np.median(s)])

    def test_first_frame_gets_points_from_later_frames(self, shared_data):
        frames, rgb_cam = _seven_scenes(shared_data, range(0, 9))
        sparse = triangulate_frames([f.rgb for f in frames], [f.pose for f in frames], rgb_cam, reference=0)
        assert len(sparse) > 100
        e, s, k = _against_kinect(frames[0], rgb_cam, sparse)
        assert np.median(e / k) < 0.08
        assert 0.85 <= np.mean(e <= 2 * s) <= 0.99


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_match_features_is_the_mutual_ratio_test_of_a_brute_force_matcher(detector):
    """The matches are OpenCV's brute-force ones: nearest under the ratio test, and nearest the other way."""
    import cv2

    rng = np.random.default_rng(3)
    if detector == "sift":
        da = rng.integers(0, 120, (300, 128)).astype(np.float32)
        db = np.vstack([da[:150] + rng.normal(0, 6, (150, 128)), rng.integers(0, 120, (200, 128))]).astype(np.float32)
    else:
        da = rng.integers(0, 256, (300, 32), dtype=np.uint8)
        flips = rng.random((150, 32 * 8)) < 0.06
        db = np.vstack([np.packbits(np.unpackbits(da[:150], axis=1) ^ flips, axis=1), rng.integers(0, 256, (200, 32))])
        db = db.astype(np.uint8)
    a = Features(rng.uniform(0, 600, (300, 2)), da, detector)
    b = Features(rng.uniform(0, 600, (350, 2)), db, detector)
    pairs = match_features(a, b, config=TriangulationConfig(ratio=0.8))
    matcher = cv2.BFMatcher(cv2.NORM_L2 if detector == "sift" else cv2.NORM_HAMMING)
    forward = {
        m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(da, db, k=2) if m[0].distance < 0.8 * m[1].distance
    }
    backward = {m.queryIdx: m.trainIdx for m in matcher.match(db, da)}
    expected = sorted((i, j) for i, j in forward.items() if backward[j] == i)
    assert sorted(map(tuple, pairs.tolist())) == expected
    assert 120 <= len(expected) <= 150 and all(i == j for i, j in expected)  # the perturbed copies, found


def test_sift_contrast_threshold_keeps_weaker_keypoints(shared_data):
    """Half OpenCV's contrast threshold keeps the keypoints of a plain indoor image that its default drops."""
    import cv2

    rgb = cv2.cvtColor(cv2.imread(str(shared_data / "hololens" / "images" / "00163.png")), cv2.COLOR_BGR2RGB)
    counts = {
        t: len(detect_features(rgb, config=TriangulationConfig(detector="sift", sift_contrast_threshold=t)))
        for t in (0.04, 0.02, 0.01)
    }
    assert counts[0.04] < counts[0.02] < counts[0.01]
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(InvalidInputError, match="sift_contrast_threshold"):
            TriangulationConfig(sift_contrast_threshold=bad)


def test_pose_displacement_measures_how_far_the_given_poses_move_the_tracks():
    """Exact poses: about 0 (keypoint noise is subtracted); every neighbour turned by 1 degree: about f times that."""
    rng = np.random.default_rng(21)
    X = _scene(300, seed=21)
    poses = _views()
    tracks = _tracks(X, poses) + rng.normal(0, 0.5, (300, 4, 2))
    tracks[:, 0] = _tracks(X, poses)[:, 0]
    cfg = TriangulationConfig(max_relative_sigma=1.0)
    exact = triangulate_tracks(tracks, poses, CAM, reference=0, config=cfg)
    assert 0.0 <= exact.pose_displacement < 0.5
    turned = [poses[0]] + [
        T @ _posed([0.0, 0.0, 0.0], tuple(a)) for T, a in zip(poses[1:], ([1, 0, 0], [0, 0, 1], [0.7, 0.7, 0]))
    ]
    moved = triangulate_tracks(tracks, turned, CAM, reference=0, config=cfg)
    # 1 degree moves a point about 500 px x 0.0175 = 8.7 px; part of it along the epipolar lines the depths absorb
    assert 3.0 < moved.pose_displacement < 12.0
