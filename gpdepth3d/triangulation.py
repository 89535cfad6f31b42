"""Sparse depth from posed RGB frames: feature matching and two-view triangulation.

Given two or more RGB frames with known poses (``T_world_camera``, e.g. from a SLAM system)
and intrinsics, the library detects features (OpenCV ORB or SIFT), matches them with Lowe's
ratio test and an epipolar check (the poses give the fundamental matrix), triangulates each
match with ``cv2.triangulatePoints`` and keeps the points that pass:

* cheirality: in front of both cameras, depth inside [min_depth, max_depth];
* reprojection error <= ``max_reprojection_error`` pixels in both views;
* parallax (angle between the two viewing rays at the point) >= ``min_parallax_deg``.

Per-point depth uncertainty comes from the geometry: the pixel positions are assumed to carry
independent Gaussian noise of ``pixel_sigma`` pixels in u and v of both views; the Jacobian
of the triangulated point with respect to these four coordinates (central finite differences
of the same DLT triangulation) propagates it to a 3x3 covariance, whose z-z entry in the
reference camera gives the z-depth sigma (metres). Small parallax or long range give large
sigmas, as they should.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

from .camera import PinholeCamera, check_pose
from .errors import InvalidInputError, ShapeError, describe
from .measurements import SparseDepth


@dataclass(frozen=True)
class TriangulationConfig:
    """Options of feature triangulation.

    Attributes:
        detector: "orb" or "sift" (OpenCV).
        max_features: Most keypoints detected per image.
        ratio: Lowe ratio test threshold (best / second-best descriptor distance).
        max_epipolar_error: Largest Sampson distance to the epipolar geometry given by the
            poses, pixels.
        max_reprojection_error: Largest reprojection error in either view, pixels.
        min_parallax_deg: Smallest angle between the two viewing rays at the point, degrees.
        pixel_sigma: Standard deviation of a keypoint position (u and v), pixels.
        min_depth: Points nearer than this to the reference camera are dropped, metres.
        max_depth: Points farther than this are dropped, metres.
        max_relative_sigma: Points whose depth sigma exceeds this fraction of their depth are dropped.
    """

    detector: Literal["orb", "sift"] = "sift"
    max_features: int = 3000
    ratio: float = 0.8
    max_epipolar_error: float = 2.0
    max_reprojection_error: float = 2.0
    min_parallax_deg: float = 1.0
    pixel_sigma: float = 1.0
    min_depth: float = 0.1
    max_depth: float = 20.0
    max_relative_sigma: float = 0.1

    def __post_init__(self) -> None:
        if self.detector not in ("orb", "sift"):
            raise InvalidInputError("detector", "'orb' or 'sift'", self.detector)
        if int(self.max_features) != self.max_features or self.max_features < 8:
            raise InvalidInputError("max_features", "an integer >= 8", self.max_features)
        if not 0 < self.ratio <= 1:
            raise InvalidInputError("ratio", "a value in (0, 1]", self.ratio)
        for name in ("max_epipolar_error", "max_reprojection_error", "pixel_sigma", "max_depth", "max_relative_sigma"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise InvalidInputError(name, "a finite value > 0", value)
        if not 0 <= self.min_parallax_deg < 90:
            raise InvalidInputError("min_parallax_deg", "an angle in [0, 90) degrees", self.min_parallax_deg)
        if not 0 <= self.min_depth < self.max_depth:
            raise InvalidInputError("min_depth", f"0 <= min_depth < max_depth ({self.max_depth})", self.min_depth)


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image.

    Attributes:
        uv: (N, 2) keypoint positions (u, v), pixels (pixel-centre convention).
        descriptors: (N, D) descriptors (uint8 for ORB, float32 for SIFT).
        detector: Which detector made them.
    """

    uv: np.ndarray
    descriptors: np.ndarray
    detector: str

    def __len__(self) -> int:
        return int(self.uv.shape[0])


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


def _gray(rgb: np.ndarray, argument: str) -> np.ndarray:
    import cv2

    a = np.asarray(rgb)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.dtype != np.uint8:
            raise ShapeError(argument, "a uint8 RGB image", describe(a))
        return cv2.cvtColor(a[..., :3], cv2.COLOR_RGB2GRAY)
    if a.ndim == 2 and a.dtype == np.uint8:
        return a
    raise ShapeError(argument, "an (H, W, 3) uint8 RGB or (H, W) uint8 grey image", describe(a))


def detect_features(rgb: np.ndarray, *, config: TriangulationConfig | None = None) -> Features:
    """Detects keypoints and computes descriptors (ORB or SIFT) in an RGB image.

    Args:
        rgb: (H, W, 3) uint8 RGB image (or (H, W) uint8 grey).
        config: Detector options.

    Returns:
        `Features` (possibly empty).
    """
    import cv2

    config = config or TriangulationConfig()
    gray = _gray(rgb, "rgb")
    if config.detector == "orb":
        det = cv2.ORB_create(nfeatures=int(config.max_features))
    else:
        det = cv2.SIFT_create(nfeatures=int(config.max_features))
    kps, desc = det.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        dim, dtype = (32, np.uint8) if config.detector == "orb" else (128, np.float32)
        return Features(np.zeros((0, 2)), np.zeros((0, dim), dtype), config.detector)
    uv = np.array([kp.pt for kp in kps], dtype=np.float64)
    # OpenCV keypoint coordinates put pixel centres at integers, as gpdepth3d does.
    return Features(uv, desc, config.detector)


def fundamental_from_poses(
    camera: PinholeCamera, T_world_a: np.ndarray, T_world_b: np.ndarray
) -> np.ndarray:
    """Fundamental matrix F with x_b^T F x_a = 0 for pixels x_a of view a and x_b of view b."""
    T_ba = np.linalg.inv(check_pose(T_world_b, "T_world_b")) @ check_pose(T_world_a, "T_world_a")
    R, t = T_ba[:3, :3], T_ba[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(camera.K)
    return Kinv.T @ tx @ R @ Kinv


def sampson_distance(F: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance (pixels) of correspondences uv_a (N, 2) <-> uv_b (N, 2) to F."""
    xa = np.hstack([uv_a, np.ones((uv_a.shape[0], 1))])
    xb = np.hstack([uv_b, np.ones((uv_b.shape[0], 1))])
    Fxa = xa @ F.T
    Ftxb = xb @ F
    num = np.einsum("ij,ij->i", xb, Fxa) ** 2
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(num / den)


def match_features(
    a: Features,
    b: Features,
    *,
    config: TriangulationConfig | None = None,
    F: np.ndarray | None = None,
) -> np.ndarray:
    """Matches descriptors of two images with Lowe's ratio test and mutual consistency.

    Args:
        a: Features of the first image.
        b: Features of the second image.
        config: Ratio threshold and epipolar tolerance.
        F: Optional fundamental matrix (x_b^T F x_a = 0); matches farther than
            ``max_epipolar_error`` pixels (Sampson distance) are dropped.

    Returns:
        (M, 2) int64 index pairs (index into a, index into b).
    """
    import cv2

    config = config or TriangulationConfig()
    if a.detector != b.detector:
        raise InvalidInputError("b", f"features of the same detector as a ({a.detector})", b.detector)
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    norm = cv2.NORM_HAMMING if a.detector == "orb" else cv2.NORM_L2
    matcher = cv2.BFMatcher(norm)
    knn = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    pairs = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in knn
        if len(m) == 2 and m[0].distance < config.ratio * m[1].distance
    ]
    if not pairs:
        return np.zeros((0, 2), np.int64)
    pairs = np.array(pairs, dtype=np.int64)
    # Mutual best: keep a match only if a's keypoint is b's best match too.
    back = matcher.match(b.descriptors, a.descriptors)
    best_back = np.full(len(b), -1, np.int64)
    for m in back:
        best_back[m.queryIdx] = m.trainIdx
    pairs = pairs[best_back[pairs[:, 1]] == pairs[:, 0]]
    if F is not None and len(pairs):
        err = sampson_distance(np.asarray(F, np.float64), a.uv[pairs[:, 0]], b.uv[pairs[:, 1]])
        pairs = pairs[np.isfinite(err) & (err <= config.max_epipolar_error)]
    return pairs


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
        cosang = np.einsum("ij,ij->i", ray_r, ray_o) / (
            np.linalg.norm(ray_r, axis=1) * np.linalg.norm(ray_o, axis=1)
        )
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
    fa, fb = features if features is not None else (
        detect_features(rgb_ref, config=config),
        detect_features(rgb_other, config=config),
    )
    F = fundamental_from_poses(camera, T_world_ref, T_world_other)
    pairs = match_features(fa, fb, config=config, F=F)
    return triangulate_matches(
        fa.uv[pairs[:, 0]], fb.uv[pairs[:, 1]], camera, T_world_ref, T_world_other, config=config
    )


def triangulate_frames(
    rgbs: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    *,
    reference: int = -1,
    config: TriangulationConfig | None = None,
    features: Sequence[Features] | None = None,
) -> SparseDepth:
    """Sparse depth for one frame, triangulated against every other posed frame given.

    Each reference keypoint matched in several frames yields several depth estimates; they
    are combined by inverse-variance weighting (sigma of the result = 1 / sqrt(sum 1/sigma^2))
    after dropping estimates more than 3 sigma from the most certain one.

    Args:
        rgbs: Two or more (H, W, 3) uint8 RGB images.
        poses: Their 4x4 ``T_world_camera`` poses.
        camera: Intrinsics shared by all frames.
        reference: Index of the frame whose depth is returned.
        config: Options.
        features: Optional precomputed features, one per frame.

    Returns:
        `SparseDepth` in the reference image with per-point sigma (metres).
    """
    config = config or TriangulationConfig()
    n = len(rgbs)
    if n < 2 or len(poses) != n:
        raise InvalidInputError("rgbs, poses", "two or more frames with one pose each", (n, len(poses)))
    if features is not None and len(features) != n:
        raise InvalidInputError("features", f"{n} Features, one per frame", len(features))
    if not -n <= reference < n:
        raise InvalidInputError("reference", f"an index into {n} frames", reference)
    ref = reference % n
    feats = list(features) if features is not None else [detect_features(im, config=config) for im in rgbs]
    uv_all, d_all, s_all, key_all = [], [], [], []
    key_of = {tuple(p): i for i, p in enumerate(np.round(feats[ref].uv, 3))}
    for j in range(n):
        if j == ref:
            continue
        tp = triangulate_pair(
            rgbs[ref], rgbs[j], camera, poses[ref], poses[j], config=config, features=(feats[ref], feats[j])
        )
        if len(tp) == 0:
            continue
        uv_all.append(tp.uv_ref)
        d_all.append(tp.depth)
        s_all.append(tp.sigma)
        key_all.append(np.array([key_of[tuple(p)] for p in np.round(tp.uv_ref, 3)], np.int64))
    if not d_all:
        return SparseDepth.empty(camera.shape)
    uv, d, s, key = (np.concatenate(x) for x in (uv_all, d_all, s_all, key_all))
    order = np.lexsort((s, key))
    uv, d, s, key = uv[order], d[order], s[order], key[order]
    starts = np.r_[0, np.nonzero(np.diff(key))[0] + 1]
    best_d = np.repeat(d[starts], np.diff(np.r_[starts, key.shape[0]]))
    best_s = np.repeat(s[starts], np.diff(np.r_[starts, key.shape[0]]))
    agree = np.abs(d - best_d) <= 3.0 * np.hypot(s, best_s)
    w = np.where(agree, 1.0 / s**2, 0.0)
    wsum = np.add.reduceat(w, starts)
    depth = np.add.reduceat(w * d, starts) / wsum
    sigma = 1.0 / np.sqrt(wsum)
    return SparseDepth.from_arrays(uv[starts, 0], uv[starts, 1], depth, camera.shape, sigma)
