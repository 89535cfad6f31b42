"""Two-view triangulation of matched keypoints (``cv2.triangulatePoints``) with sigma propagated through the DLT."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...camera import PinholeCamera, check_pose
from ...errors import ShapeError, describe
from .features import Features, detect_features, fundamental_from_poses, match_features
from .tracks import build_tracks
from .triangulation_config import TriangulationConfig


@dataclass(frozen=True)
class TriangulatedPoints:
    """Points triangulated from two views.

    Attributes:
        points_world: (N, 3) positions in the world frame, metres.
        uv_ref: (N, 2) pixel positions in the reference view.
        uv_other: (N, 2) pixel positions in the other view.
        depth: (N,) z-depth in the reference camera, metres.
        sigma: (N,) standard deviation of that depth from `pixel_sigma` pixel noise, metres.
        reprojection_error: (N,) largest reprojection error of the two views, pixels.
        parallax_deg: (N,) angle between the viewing rays, degrees.
    """

    points_world: np.ndarray
    uv_ref: np.ndarray
    uv_other: np.ndarray
    depth: np.ndarray
    sigma: np.ndarray
    reprojection_error: np.ndarray
    parallax_deg: np.ndarray

    def __len__(self) -> int:
        return int(self.depth.shape[0])


def _triangulate(P_a: np.ndarray, P_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    import cv2

    if uv_a.shape[0] == 0:
        return np.zeros((0, 3))
    X = cv2.triangulatePoints(P_a, P_b, uv_a.T.astype(np.float64), uv_b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


def triangulate_matches(
    uv_ref: np.ndarray,
    uv_other: np.ndarray,
    camera: PinholeCamera,
    T_world_ref: np.ndarray,
    T_world_other: np.ndarray,
    *,
    config: TriangulationConfig | None = None,
) -> TriangulatedPoints:
    """Triangulates pixel correspondences of two posed views and keeps the well-conditioned ones.

    Args:
        uv_ref: (N, 2) pixels in the reference view.
        uv_other: (N, 2) corresponding pixels in the other view.
        camera: Intrinsics shared by both views.
        T_world_ref: 4x4 pose of the reference camera.
        T_world_other: 4x4 pose of the other camera.
        config: Reprojection, parallax, depth and uncertainty options.

    Returns:
        The points that pass the checks of the module docstring, with depth and sigma in the
        reference camera.
    """
    config = config or TriangulationConfig()
    uv_ref = np.asarray(uv_ref, np.float64)
    uv_other = np.asarray(uv_other, np.float64)
    if uv_ref.ndim != 2 or uv_ref.shape[1] != 2:
        raise ShapeError("uv_ref", "an (N, 2) array", describe(uv_ref))
    if uv_other.shape != uv_ref.shape:
        raise ShapeError("uv_other", f"shape {uv_ref.shape} like uv_ref", describe(uv_other))
    T_wr = check_pose(T_world_ref, "T_world_ref")
    T_wo = check_pose(T_world_other, "T_world_other")
    T_rw, T_ow = np.linalg.inv(T_wr), np.linalg.inv(T_wo)
    K = camera.K
    P_r, P_o = K @ T_rw[:3], K @ T_ow[:3]
    empty = TriangulatedPoints(*(np.zeros((0, 3)),) + (np.zeros((0, 2)),) * 2 + (np.zeros(0),) * 4)
    if uv_ref.shape[0] == 0:
        return empty

    X = _triangulate(P_r, P_o, uv_ref, uv_other)
    ok = np.all(np.isfinite(X), axis=1)
    Xr = X @ T_rw[:3, :3].T + T_rw[:3, 3]
    Xo = X @ T_ow[:3, :3].T + T_ow[:3, 3]
    ok &= (Xr[:, 2] > config.min_depth) & (Xr[:, 2] < config.max_depth) & (Xo[:, 2] > config.min_depth)
    with np.errstate(divide="ignore", invalid="ignore"):
        proj_r, _ = camera.project(Xr)
        proj_o, _ = camera.project(Xo)
        err = np.maximum(np.linalg.norm(proj_r - uv_ref, axis=1), np.linalg.norm(proj_o - uv_other, axis=1))
        ray_r = X - T_wr[:3, 3]
        ray_o = X - T_wo[:3, 3]
        cosang = np.einsum("ij,ij->i", ray_r, ray_o) / (np.linalg.norm(ray_r, axis=1) * np.linalg.norm(ray_o, axis=1))
    parallax = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    ok &= np.isfinite(err) & (err <= config.max_reprojection_error)
    ok &= np.isfinite(parallax) & (parallax >= config.min_parallax_deg)

    # Uncertainty: central differences of the triangulation w.r.t. the 4 pixel coordinates.
    idx = np.nonzero(ok)[0]
    h = 0.5
    J = np.zeros((idx.shape[0], 3, 4))
    for k in range(4):
        du = np.zeros((idx.shape[0], 4))
        du[:, k] = h
        plus = _triangulate(P_r, P_o, uv_ref[idx] + du[:, :2], uv_other[idx] + du[:, 2:])
        minus = _triangulate(P_r, P_o, uv_ref[idx] - du[:, :2], uv_other[idx] - du[:, 2:])
        J[:, :, k] = (plus - minus) / (2 * h)
    # z-depth in the reference camera: row 2 of R_rw applied to the world point.
    dz = np.einsum("j,njk->nk", T_rw[2, :3], J)
    sigma = config.pixel_sigma * np.sqrt(np.sum(dz**2, axis=1))
    depth = Xr[idx, 2]
    good = np.isfinite(sigma) & (sigma > 0) & (sigma <= config.max_relative_sigma * depth)
    sel = idx[good]
    return TriangulatedPoints(
        points_world=X[sel],
        uv_ref=uv_ref[sel],
        uv_other=uv_other[sel],
        depth=depth[good],
        sigma=sigma[good],
        reprojection_error=err[sel],
        parallax_deg=parallax[sel],
    )


def triangulate_pair(
    rgb_ref: np.ndarray,
    rgb_other: np.ndarray,
    camera: PinholeCamera,
    T_world_ref: np.ndarray,
    T_world_other: np.ndarray,
    *,
    config: TriangulationConfig | None = None,
    features: tuple[Features, Features] | None = None,
) -> TriangulatedPoints:
    """Detects, matches and triangulates features of two posed RGB frames.

    Args:
        rgb_ref: (H, W, 3) uint8 reference image (the camera's size).
        rgb_other: (H, W, 3) uint8 other image.
        camera: Intrinsics of both images.
        T_world_ref: 4x4 pose of the reference camera.
        T_world_other: 4x4 pose of the other camera.
        config: Options.
        features: Precomputed features of (ref, other), to avoid detecting twice in a sequence.

    Returns:
        `TriangulatedPoints` with depth and sigma in the reference camera.
    """
    config = config or TriangulationConfig()
    camera.check_image(rgb_ref, "rgb_ref")
    camera.check_image(rgb_other, "rgb_other")
    if config.detector == "klt":
        tracks = build_tracks(
            [rgb_ref, rgb_other],
            [T_world_ref, T_world_other],
            camera,
            reference=0,
            config=config,
            features=None if features is None else [features[0], features[1]],
        )
        seen = np.isfinite(tracks[:, 1, 0])
        return triangulate_matches(tracks[seen, 0], tracks[seen, 1], camera, T_world_ref, T_world_other, config=config)
    fa, fb = (
        features
        if features is not None
        else (detect_features(rgb_ref, config=config), detect_features(rgb_other, config=config))
    )
    F = fundamental_from_poses(camera, T_world_ref, T_world_other)
    pairs = match_features(fa, fb, config=config, F=F)
    return triangulate_matches(
        fa.uv[pairs[:, 0]], fb.uv[pairs[:, 1]], camera, T_world_ref, T_world_other, config=config
    )
