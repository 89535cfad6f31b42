"""Sparse depth from posed RGB frames: feature tracks over several views, triangulated with honest sigmas.

Given posed RGB frames (``T_world_camera``, e.g. from a SLAM system) and intrinsics:

* **Tracks** (`build_tracks`, `TrackTriangulator`): by default Shi-Tomasi corners followed with
  pyramidal Lucas-Kanade (OpenCV, forward-backward checked; sub-pixel), one tracking step per
  frame in a stream (`TrackTriangulator`) or outward from a reference frame through a batch of
  frames (`triangulate_frames`); or ORB / SIFT descriptors matched from the reference to every
  other frame (ratio test, mutual best, loose epipolar gate around the given poses).
* **Multi-view triangulation** (`triangulate_tracks`): each track's inverse depth along its
  reference ray from all its views: a linear multi-view DLT in inverse-depth form (iteratively
  reweighted), then robust (Cauchy) Gauss-Newton; observations off by more than
  ``max_reprojection_error`` pixels are dropped and the depth re-solved. With
  ``refine_poses=True`` the neighbours' poses relative to the reference are refined jointly
  (Levenberg-Marquardt bundle adjustment, Schur complement, Gaussian pose prior). With the
  poses held (the default) the tracks are independent 1-D problems, solved by compiled loops
  (numba; ~2 ms for the ~350 tracks of a 7-Scenes frame with 12 views, 12 ms as numpy arrays).
* **Sigma**: pixel noise (the larger of ``pixel_sigma`` and the noise the residuals show) and
  the poses' uncertainty (``rotation_sigma_deg``, ``translation_sigma`` per axis, relative to
  the reference) propagated to the inverse depth through the Gauss-Newton information; with
  ``variance_factor`` the whole variance is scaled by (residual noise / ``pixel_sigma``)^2 when
  the residuals are larger than the assumed pixel noise (inconsistent poses in a frame then
  widen every sigma of that frame); a relative floor ``depth_sigma_floor`` is added in quadrature.

Measured on the 60 shared 7-Scenes frames (the sequence's own poses, colour camera f = 525;
bench/fusion.py and experiments of issue 14). With 4 earlier frames (`TrackTriangulator`,
``lag=0``): +-2 sigma covers ~93 % of the points' errors against the Kinect depth, ~200 points
a frame, the median point ~6 % off, 4 frames without points. With 8 earlier and 4 later views
(``lag=4``, the Mapper's default): ~250-275 points in every frame, median ~5 % off, median
per-frame |bias| 2.8 % instead of 3.7 %, +-2 sigma 91-92 %. What limits the accuracy is the
poses: with the given poses KLT tracks reproject 2.4 px off (median; the images' relative
poses differ from the given ones by ~0.24 deg and ~0.8 cm between consecutive frames, up to
1.5 deg / 3 cm in the fast, blurred frames 20-40). A bundle adjustment of the whole sequence
with the given poses as priors (0.5 deg, 2 cm) brings that to 1.0 px, but the points it
triangulates are no closer to the Kinect surface (median 5.5 cm off either way) and the fused
mesh was not better; neither a time offset between colour and depth poses, nor a colour-depth
extrinsic, nor self-calibrated intrinsics (f, c, k1, k2 stay at 525, 320, 240, ~0) explain it.
Refining the neighbours' poses per reference (``refine_poses``) made the depth worse (median
per-frame |bias| 3.7 % -> 5-11 %, window 4 or 8), so it is off by default and the pose
uncertainty goes into sigma instead.

The two-view functions (`triangulate_matches`, `triangulate_pair`) remain: they triangulate one
pair with ``cv2.triangulatePoints`` and propagate ``pixel_sigma`` through the DLT (central
differences), checking cheirality, reprojection error and parallax.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, Sequence

import numba as nb
import numpy as np

from ..camera import PinholeCamera, check_pose
from ..errors import InvalidInputError, ShapeError, describe
from ..measurements import SparseDepth


@dataclass(frozen=True)
class TriangulationConfig:
    """Options of feature tracking and triangulation.

    Attributes:
        detector: "klt" (Shi-Tomasi corners followed by pyramidal Lucas-Kanade: sub-pixel
            tracks, the default), "orb" or "sift" (descriptor matching, OpenCV).
        max_features: Most keypoints detected per image (tracks kept alive for "klt");
            None: 800 for "klt", 3000 for "orb" / "sift" (numbers behind 800:
            bench/results/mapping_settings.json).
        min_corner_distance: Smallest distance between two "klt" corners, pixels.
        klt_window: Lucas-Kanade window side, pixels.
        klt_levels: Lucas-Kanade pyramid levels above the image.
        klt_fb_error: Largest forward-backward tracking error of a "klt" step, pixels
            (0 disables the check).
        ratio: Lowe ratio test threshold (best / second-best descriptor distance).
        max_epipolar_error: Largest Sampson distance to the epipolar geometry given by the
            poses for descriptor matches, pixels (loose: the poses are refined afterwards).
        max_reprojection_error: Largest reprojection error of an observation, pixels.
        min_parallax_deg: Smallest angle between two viewing rays at the point, degrees.
        pixel_sigma: Standard deviation of a keypoint position (u and v), pixels; the noise
            the residuals show is used when larger.
        rotation_sigma_deg: Prior standard deviation of each neighbour's rotation relative to
            the reference (per axis), degrees.
        translation_sigma: Prior standard deviation of each neighbour's translation relative
            to the reference (per axis), metres.
        refine_poses: Refine the neighbours' poses relative to the reference jointly with the
            depths (bundle adjustment with the pose prior); off: poses held, their prior
            uncertainty carried into sigma.
        variance_factor: Scale each frame's variances by (residual noise / pixel_sigma)^2 when
            the residuals exceed the assumed pixel noise (a posteriori variance factor).
        min_views: Fewest views (reference included) that must support a multi-view point.
        depth_sigma_floor: Relative depth sigma added in quadrature to the propagated one
            (model errors: keypoints on depth edges, non-rigid or specular surfaces).
        min_depth: Points nearer than this to the reference camera are dropped, metres.
        max_depth: Points farther than this are dropped, metres.
        max_relative_sigma: Points whose depth sigma exceeds this fraction of their depth are dropped.
    """

    detector: Literal["klt", "orb", "sift"] = "klt"
    max_features: int | None = None
    min_corner_distance: float = 8.0
    klt_window: int = 11
    klt_levels: int = 3
    klt_fb_error: float = 1.0
    ratio: float = 0.8
    max_epipolar_error: float = 4.0
    max_reprojection_error: float = 3.0
    min_parallax_deg: float = 0.5
    pixel_sigma: float = 0.5
    rotation_sigma_deg: float = 0.1
    translation_sigma: float = 0.005
    refine_poses: bool = False
    variance_factor: bool = True
    min_views: int = 2
    depth_sigma_floor: float = 0.04
    min_depth: float = 0.1
    max_depth: float = 20.0
    max_relative_sigma: float = 0.3

    def __post_init__(self) -> None:
        if self.detector not in ("klt", "orb", "sift"):
            raise InvalidInputError("detector", "'klt', 'orb' or 'sift'", self.detector)
        if self.max_features is None:
            object.__setattr__(self, "max_features", 800 if self.detector == "klt" else 3000)
        for name, low in (("max_features", 8), ("klt_window", 5), ("klt_levels", 0), ("min_views", 2)):
            value = getattr(self, name)
            if int(value) != value or value < low:
                raise InvalidInputError(name, f"an integer >= {low}", value)
        if not 0 < self.ratio <= 1:
            raise InvalidInputError("ratio", "a value in (0, 1]", self.ratio)
        for name in (
            "max_epipolar_error", "max_reprojection_error", "pixel_sigma", "max_depth", "max_relative_sigma",
            "rotation_sigma_deg", "translation_sigma", "min_corner_distance",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise InvalidInputError(name, "a finite value > 0", value)
        for name in ("klt_fb_error", "depth_sigma_floor"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InvalidInputError(name, "a finite value >= 0", value)
        if not 0 <= self.min_parallax_deg < 90:
            raise InvalidInputError("min_parallax_deg", "an angle in [0, 90) degrees", self.min_parallax_deg)
        if not 0 <= self.min_depth < self.max_depth:
            raise InvalidInputError("min_depth", f"0 <= min_depth < max_depth ({self.max_depth})", self.min_depth)


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image.

    Attributes:
        uv: (N, 2) keypoint positions (u, v), pixels (pixel-centre convention).
        descriptors: (N, D) descriptors (uint8 for ORB, float32 for SIFT; D = 0 for KLT corners).
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
    """Detects keypoints (Shi-Tomasi corners for "klt") and descriptors (ORB or SIFT) in an RGB image.

    Args:
        rgb: (H, W, 3) uint8 RGB image (or (H, W) uint8 grey).
        config: Detector options.

    Returns:
        `Features` (possibly empty).
    """
    import cv2

    config = config or TriangulationConfig()
    gray = _gray(rgb, "rgb")
    if config.detector == "klt":
        corners = cv2.goodFeaturesToTrack(
            gray, int(config.max_features), 0.01, float(config.min_corner_distance), blockSize=5
        )
        uv = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2).astype(np.float64)
        return Features(uv, np.zeros((uv.shape[0], 0), np.float32), "klt")
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
    if a.detector == "klt":
        raise InvalidInputError("a", "features with descriptors (detector 'orb' or 'sift')", "klt corners")
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
    if config.detector == "klt":
        tracks = build_tracks(
            [rgb_ref, rgb_other], [T_world_ref, T_world_other], camera, reference=0, config=config,
            features=None if features is None else [features[0], features[1]],
        )
        seen = np.isfinite(tracks[:, 1, 0])
        return triangulate_matches(
            tracks[seen, 0], tracks[seen, 1], camera, T_world_ref, T_world_other, config=config
        )
    fa, fb = features if features is not None else (
        detect_features(rgb_ref, config=config),
        detect_features(rgb_other, config=config),
    )
    F = fundamental_from_poses(camera, T_world_ref, T_world_other)
    pairs = match_features(fa, fb, config=config, F=F)
    return triangulate_matches(
        fa.uv[pairs[:, 0]], fb.uv[pairs[:, 1]], camera, T_world_ref, T_world_other, config=config
    )


# ---------------------------------------------------------------------- multi-view tracks
@dataclass(frozen=True)
class MultiViewPoints:
    """Points triangulated from tracks over several views by `triangulate_tracks`.

    Attributes:
        index: (N,) int64 row of each point in the tracks given.
        uv: (N, 2) pixel positions in the reference view.
        depth: (N,) z-depth in the reference camera, metres.
        sigma: (N,) standard deviation of that depth, metres: pixel noise (scaled by the
            residuals actually seen) and pose uncertainty propagated through the refinement,
            plus the relative floor ``depth_sigma_floor``.
        points_world: (N, 3) positions in the world frame (the reference pose as given), metres.
        n_views: (N,) views that support the point, the reference included (>= 2).
        reprojection_error: (N,) RMS reprojection error over the supporting views, pixels.
        parallax_deg: (N,) largest angle between the reference ray and another view's ray, degrees.
        poses: (V, 4, 4) ``T_world_camera`` of every view after refinement (the reference is
            kept as given; views without enough tracks keep their given pose).
        pixel_sigma: Reprojection noise estimated from the residuals (pixels, >= the configured
            ``pixel_sigma``); used in ``sigma``.
    """

    index: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    sigma: np.ndarray
    points_world: np.ndarray
    n_views: np.ndarray
    reprojection_error: np.ndarray
    parallax_deg: np.ndarray
    poses: np.ndarray
    pixel_sigma: float

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    def to_sparse(self, image_size: tuple[int, int]) -> SparseDepth:
        """The points as `SparseDepth` of the reference image with their sigma."""
        return SparseDepth.from_arrays(self.uv[:, 0], self.uv[:, 1], self.depth, image_size, self.sigma)


def _skew(a: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(a.shape[:-1])
    return np.stack(
        [
            np.stack([z, -a[..., 2], a[..., 1]], -1),
            np.stack([a[..., 2], z, -a[..., 0]], -1),
            np.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _skew(w)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    return np.eye(3) + a * W + b * (W @ W)


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors (angles below pi)."""
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(c)[..., None]
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(theta)
    return np.where(theta < 1e-8, 0.5 * v, v * theta / (2 * np.where(theta < 1e-8, 1.0, s)))


class _Problem:
    """Inverse-depth bundle adjustment of one reference view against its neighbours.

    Unknowns: the inverse depth rho_i of every track along its reference ray (the reference
    keypoint is taken as exact) and a 6-D correction (rotation vector, translation) of every
    neighbour's pose relative to the reference, with a Gaussian prior around the given pose.
    A point in neighbour j: p = R_j xbar_i + rho_i t_j (homogeneous), pixel = pi(K p).
    """

    def __init__(self, xbar, uv, mask, R0, t0, camera, pixel_sigma, rot_sigma, trans_sigma):
        self.xbar = xbar  # (N, 3) normalised reference rays (z = 1)
        self.uv = uv  # (N, J, 2) observations in the neighbours
        self.mask = mask  # (N, J) observed
        self.R0, self.t0 = R0, t0  # (J, 3, 3), (J, 3): given reference -> neighbour transforms
        self.R, self.t = R0.copy(), t0.copy()
        self.f = np.array([camera.fx, camera.fy])
        self.c = np.array([camera.cx, camera.cy])
        self.pixel_sigma = float(pixel_sigma)
        self.prior = np.r_[np.full(3, 1.0 / rot_sigma**2), np.full(3, 1.0 / trans_sigma**2)]

    def rotated_rays(self, R=None):
        """(N, J, 3) reference rays rotated into every neighbour (cached for the current R)."""
        R = self.R if R is None else R
        cached = getattr(self, "_rx", None)
        if cached is not None and cached[0] is R:
            return cached[1]
        Rx = np.matmul(self.xbar[None], np.swapaxes(R, 1, 2)).transpose(1, 0, 2)  # einsum("jab,nb->nja")
        self._rx = (R, Rx)
        return Rx

    def project(self, rho, R=None, t=None):
        R = self.R if R is None else R
        t = self.t if t is None else t
        p = self.rotated_rays(R) + rho[:, None, None] * t[None]
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p[..., :2] / z[..., None] * self.f + self.c
        return p, z, uv

    def residuals(self, rho, R=None, t=None):
        p, z, uv = self.project(rho, R, t)
        r = (uv - self.uv) / self.pixel_sigma
        valid = self.mask & (z > 1e-9) & np.all(np.isfinite(r), axis=-1)
        return p, z, np.where(valid[..., None], r, 0.0), valid

    def prior_residual(self, R=None, t=None):
        R = self.R if R is None else R
        t = self.t if t is None else t
        dtheta = _log_rotation(R @ np.swapaxes(self.R0, 1, 2))
        return np.concatenate([dtheta, t - self.t0], axis=1)  # (J, 6)

    def cost(self, rho, scale, R=None, t=None):
        _, _, r, valid = self.residuals(rho, R, t)
        s2 = np.sum(r**2, axis=-1)
        data = np.sum(np.where(valid, scale**2 * np.log1p(s2 / scale**2), 0.0))
        e = self.prior_residual(R, t)
        return data + np.sum(e**2 * self.prior)

    def normal_equations(self, rho, weights):
        """Gauss-Newton blocks (depth-depth, pose-depth, pose-pose, right-hand sides) with per-observation weights (N, J)."""
        p, z, r, valid = self.residuals(rho)
        w = np.where(valid, weights, 0.0)
        fz = self.f / self.pixel_sigma
        iz = np.where(valid, 1.0 / np.where(valid, z, 1.0), 0.0)
        # d(residual)/dp: (N, J, 2, 3)
        Jp = np.zeros(p.shape[:2] + (2, 3))
        Jp[..., 0, 0] = fz[0] * iz
        Jp[..., 1, 1] = fz[1] * iz
        Jp[..., 0, 2] = -fz[0] * p[..., 0] * iz**2
        Jp[..., 1, 2] = -fz[1] * p[..., 1] * iz**2
        J_rho = np.matmul(Jp, self.t[None, :, :, None])[..., 0]  # (N, J, 2)
        Rx = self.rotated_rays()
        J_theta = -np.matmul(Jp, _skew(Rx))
        J_t = Jp * rho[:, None, None, None]
        J_xi = np.concatenate([J_theta, J_t], axis=-1)  # (N, J, 2, 6)
        wJ_rho = w[..., None] * J_rho
        h_rr = np.sum(wJ_rho * J_rho, axis=(1, 2))
        H_xr = np.matmul(wJ_rho[..., None, :], J_xi)[..., 0, :]  # (N, J, 6)
        b_r = np.sum(w[..., None] * J_rho * r, axis=(1, 2))
        n, nj = w.shape
        Jx = J_xi.transpose(1, 0, 2, 3).reshape(nj, 2 * n, 6)  # (J, 2N, 6)
        wx = np.repeat(w.T, 2, axis=1)[..., None]  # (J, 2N, 1), a weight per residual row
        H_xx = np.matmul(np.swapaxes(Jx, 1, 2), wx * Jx)  # (J, 6, 6)
        b_x = np.matmul(np.swapaxes(Jx, 1, 2), wx[..., 0, None] * r.transpose(1, 0, 2).reshape(nj, 2 * n, 1))[..., 0]
        e = self.prior_residual()
        H_xx = H_xx + np.eye(6)[None] * self.prior[None, :, None]
        b_x = b_x + e * self.prior[None]
        return r, valid, h_rr, b_r, H_xr, H_xx, b_x

    def schur(self, h_rr, H_xr, H_xx):
        n, nj = H_xr.shape[:2]
        A = H_xr.reshape(n, nj * 6)
        inv = np.where(h_rr > 0, 1.0 / np.where(h_rr > 0, h_rr, 1.0), 0.0)
        S = np.zeros((nj * 6, nj * 6))
        for j in range(nj):
            S[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = H_xx[j]
        S -= (A * inv[:, None]).T @ A
        return S, A, inv


def _cauchy_weights(r: np.ndarray, scale: float) -> np.ndarray:
    return 1.0 / (1.0 + np.sum(r**2, axis=-1) / scale**2)


def triangulate_tracks(
    tracks: np.ndarray,
    poses: Sequence[np.ndarray] | np.ndarray,
    camera: PinholeCamera,
    *,
    reference: int = 0,
    config: TriangulationConfig | None = None,
    _checked: bool = False,
) -> MultiViewPoints:
    """Triangulates feature tracks from all their views, refining the neighbours' poses.

    Every track starts at a keypoint of the reference view. Steps: (1) a linear multi-view
    triangulation of each track's inverse depth along its reference ray (the multi-view DLT
    in inverse-depth form, iteratively reweighted); (2) a robust (Cauchy) Gauss-Newton /
    Levenberg-Marquardt bundle adjustment of all inverse depths jointly with a correction of
    every neighbour's pose relative to the reference, with a Gaussian prior of
    ``rotation_sigma_deg`` / ``translation_sigma`` around the given relative pose (the
    translations' prior fixes the metric scale); (3) observations off by more than
    ``max_reprojection_error`` pixels are dropped and the problem solved again; (4) the
    depth sigma is the marginal standard deviation of the inverse depth from the inverse of
    the Gauss-Newton information (Schur complement: pixel noise *and* the pose uncertainty
    that all points share), with the pixel noise taken as the larger of ``pixel_sigma`` and
    the one the residuals show, plus a relative floor ``depth_sigma_floor * depth`` in
    quadrature (keypoint-on-edge and residual model errors; calibrated on 7-Scenes).

    Args:
        tracks: (N, V, 2) pixel positions (u, v) of N tracks in V views; NaN where a track is
            not seen. Every track must be seen in the reference view.
        poses: V 4x4 ``T_world_camera`` poses.
        camera: Intrinsics shared by all views.
        reference: Index of the reference view.
        config: Options (pixel_sigma, rotation_sigma_deg, translation_sigma, min_views,
            max_reprojection_error, min_parallax_deg, min_depth, max_depth,
            max_relative_sigma, depth_sigma_floor).

    Returns:
        `MultiViewPoints` of the tracks that pass: seen in >= ``min_views`` views after
        outlier removal, in front of every supporting camera, depth in [min_depth,
        max_depth], parallax >= ``min_parallax_deg``, sigma <= ``max_relative_sigma * depth``.

    Raises:
        ShapeError: tracks not (N, V, 2) or poses not V 4x4 matrices.
        InvalidInputError: reference out of range, a track missing in the reference view.
        CalibrationError: a pose that is not rigid.
    """
    config = config or TriangulationConfig()
    tracks = np.asarray(tracks, dtype=np.float64)
    if tracks.ndim != 3 or tracks.shape[2] != 2:
        raise ShapeError("tracks", "an (N, V, 2) array of pixel positions", describe(tracks))
    n, V = tracks.shape[:2]
    poses = list(poses)
    if len(poses) != V or V < 2:
        raise ShapeError("poses", f"{V} 4x4 poses, one per view of tracks (>= 2 views)", len(poses))
    Ts = np.stack([T if _checked else check_pose(T, f"poses[{k}]") for k, T in enumerate(poses)])
    if not -V <= reference < V:
        raise InvalidInputError("reference", f"an index into {V} views", reference)
    ref = reference % V
    if n and not np.all(np.isfinite(tracks[:, ref])):
        raise InvalidInputError("tracks", "every track seen (finite) in the reference view", "NaN in the reference view")
    others = [k for k in range(V) if k != ref]
    empty = MultiViewPoints(
        np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)),
        np.zeros(0, np.int64), np.zeros(0), np.zeros(0), Ts.copy(), float(config.pixel_sigma),
    )
    mask = np.all(np.isfinite(tracks[:, others]), axis=-1)
    keep = np.nonzero(mask.sum(axis=1) >= config.min_views - 1)[0]
    if keep.size == 0:
        return empty
    uv_ref = tracks[keep, ref]
    obs = tracks[keep][:, others]
    mask = mask[keep]
    obs = np.where(mask[..., None], obs, 0.0)
    T_jr = np.linalg.inv(Ts[others]) @ Ts[ref]  # reference camera -> neighbour camera
    xbar = np.column_stack(
        [(uv_ref[:, 0] - camera.cx) / camera.fx, (uv_ref[:, 1] - camera.cy) / camera.fy, np.ones(len(keep))]
    )
    prob = _Problem(
        xbar, obs, mask, T_jr[:, :3, :3], T_jr[:, :3, 3], camera,
        config.pixel_sigma, np.radians(config.rotation_sigma_deg), config.translation_sigma,
    )
    rho = _linear_inverse_depth(xbar, obs, mask, prob.R, prob.t, prob.f, prob.c)
    rho_ok = np.isfinite(rho) & (rho > 0)
    rho = np.where(rho_ok, rho, 1.0 / np.sqrt(config.min_depth * config.max_depth))
    mask &= rho_ok[:, None]
    prob.mask = mask
    # Robust refinement: a wide Cauchy scale first (the given poses can be several pixels
    # off), then the final one; observations beyond max_reprojection_error are then dropped.
    final_scale = 2.0
    if config.refine_poses:
        for scale, iters in ((8.0, 4), (final_scale, 6)):
            rho = _levenberg_marquardt(prob, rho, scale, iters)
        _, _, r, valid = prob.residuals(rho)
        err_px = np.linalg.norm(r, axis=-1) * prob.pixel_sigma
        prob.mask = mask = mask & valid & (err_px <= config.max_reprojection_error)
        rho = _levenberg_marquardt(prob, rho, final_scale, 3)
        _, _, r, valid = prob.residuals(rho)
    else:
        # poses held: independent 1-D problems, one compiled loop over the tracks
        rho, r, valid = _held_pose_depths(
            xbar, obs, mask, prob.R, prob.t, prob.f, prob.c, prob.pixel_sigma, rho, final_scale,
            float(config.max_reprojection_error),
        )

    # Noise level actually seen (Rayleigh median of 2-D residual norms), dof-corrected.
    n_obs = int(valid.sum())
    live = valid.any(axis=1)
    n_par = int(live.sum()) + 6 * len(others)
    if n_obs * 2 > n_par + 2:
        med = np.median(np.linalg.norm(r[valid], axis=-1)) * prob.pixel_sigma / np.sqrt(2 * np.log(2))
        seen = float(med * np.sqrt(2 * n_obs / (2 * n_obs - n_par)))
    else:
        seen = float(config.pixel_sigma)
    sigma_px = max(float(config.pixel_sigma), seen)
    if config.refine_poses:
        prob.pixel_sigma = sigma_px
        _, valid, h_rr, _, H_xr, H_xx, _ = prob.normal_equations(rho, valid.astype(np.float64))
        n_pts, nj = H_xr.shape[:2]
        A = H_xr.reshape(n_pts, nj * 6)
        inv = np.where(h_rr > 0, 1.0 / np.where(h_rr > 0, h_rr, 1.0), 0.0)
        B = A * inv[:, None]
        S, _, _ = prob.schur(h_rr, H_xr, H_xx)
        # joint estimate: the marginal of the inverse depth (Schur complement of the poses)
        try:
            S_inv = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            S_inv = np.linalg.pinv(S)
        var_rho = inv + np.einsum("nk,kl,nl->n", B, S_inv, B)
    else:
        # poses held at their given values: their whole prior uncertainty reaches the depth
        # through d rho / d xi = -H_rho_rho^-1 H_rho_xi
        var_rho = _held_pose_variance(xbar, rho, valid, prob.R, prob.t, prob.f / sigma_px, 1.0 / prob.prior)
    if config.variance_factor:
        # a posteriori variance factor: residuals larger than the pixel noise say the poses
        # (or the tracks) are worse than assumed, in the directions the images cannot see too
        var_rho = var_rho * max(1.0, seen / float(config.pixel_sigma)) ** 2

    depth = np.where(rho > 0, 1.0 / np.where(rho > 0, rho, 1.0), np.nan)
    with np.errstate(invalid="ignore"):
        sigma_geo = np.sqrt(np.maximum(var_rho, 0.0)) * depth**2
    sigma = np.hypot(sigma_geo, config.depth_sigma_floor * depth)
    # geometry checks
    Xr = xbar * depth[:, None]
    n_views, parallax, front, rms = _point_checks(Xr, r, valid, prob.R, prob.t, 0.5 * config.min_depth)
    good = (
        (n_views >= config.min_views)
        & np.isfinite(depth)
        & (depth >= config.min_depth)
        & (depth <= config.max_depth)
        & front
        & (parallax >= config.min_parallax_deg)
        & np.isfinite(sigma)
        & (sigma > 0)
        & (sigma <= config.max_relative_sigma * depth)
    )
    refined = Ts.copy()
    T_new = np.tile(np.eye(4), (len(others), 1, 1))
    T_new[:, :3, :3], T_new[:, :3, 3] = prob.R, prob.t
    refined[others] = Ts[ref] @ np.linalg.inv(T_new)
    sel = np.nonzero(good)[0]
    Xw = Xr[sel] @ Ts[ref][:3, :3].T + Ts[ref][:3, 3]
    return MultiViewPoints(
        index=keep[sel].astype(np.int64),
        uv=uv_ref[sel],
        depth=depth[sel],
        sigma=sigma[sel],
        points_world=Xw,
        n_views=n_views[sel].astype(np.int64),
        reprojection_error=rms[sel] * sigma_px,
        parallax_deg=parallax[sel],
        poses=refined,
        pixel_sigma=sigma_px,
    )


# ---------------------------------------------------------------------- compiled kernels (poses held)
@nb.njit(cache=True, nogil=True, error_model="numpy")
def _residual(Rx0, Rx1, Rx2, rho, t, obs0, obs1, f, c, pixel_sigma):  # pragma: no cover - compiled
    """A point on its reference ray at inverse depth rho in one neighbour: (p, residual / pixel_sigma, valid)."""
    p0 = Rx0 + rho * t[0]
    p1 = Rx1 + rho * t[1]
    p2 = Rx2 + rho * t[2]
    r0 = (p0 / p2 * f[0] + c[0] - obs0) / pixel_sigma
    r1 = (p1 / p2 * f[1] + c[1] - obs1) / pixel_sigma
    ok = p2 > 1e-9 and np.isfinite(r0) and np.isfinite(r1)
    return p0, p1, p2, r0, r1, ok


@nb.njit(cache=True, nogil=True)
def _rotated_rays(xbar, R, Rx):  # pragma: no cover - compiled
    """Rx[j] = R[j] @ xbar for every neighbour j (into ``Rx``, (J, 3))."""
    for j in range(R.shape[0]):
        for a in range(3):
            Rx[j, a] = R[j, a, 0] * xbar[0] + R[j, a, 1] * xbar[1] + R[j, a, 2] * xbar[2]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _linear_inverse_depth(xbar, obs, mask, R, t, f, c):  # pragma: no cover - compiled
    """Multi-view DLT of each track's inverse depth along its reference ray (closed form).

    For an observation (x, y) (normalised) in neighbour j: x (r3.xbar + rho t3) = r1.xbar + rho t1
    and the same in y; each row is linear in rho and scaled by the focal length over the
    point's depth proxy, so that the least-squares residual is in pixels. Two passes, the
    second weighting each observation by a Cauchy weight of its first-pass residual (4 px).
    Returns (N,) inverse depths (NaN or <= 0 where the views do not determine one).
    """
    n, nj = mask.shape
    rho = np.full(n, np.nan)
    Rx = np.empty((nj, 3))
    a = np.empty((nj, 2))
    b = np.empty((nj, 2))
    w = np.empty(nj)
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        for j in range(nj):
            sw = 1.0 / max(Rx[j, 2], 1e-6)
            for q in range(2):
                xy = (obs[i, j, q] - c[q]) / f[q]
                a[j, q] = (xy * t[j, 2] - t[j, q]) * (sw * f[q])
                b[j, q] = (Rx[j, q] - xy * Rx[j, 2]) * (sw * f[q])
            w[j] = 1.0 if mask[i, j] else 0.0
        r = np.nan
        for _ in range(2):
            num = 0.0
            den = 0.0
            for j in range(nj):
                num += w[j] * (a[j, 0] * b[j, 0] + a[j, 1] * b[j, 1])
                den += w[j] * (a[j, 0] * a[j, 0] + a[j, 1] * a[j, 1])
            r = num / den
            for j in range(nj):
                e0 = a[j, 0] * r - b[j, 0]
                e1 = a[j, 1] * r - b[j, 1]
                res = np.sqrt(e0 * e0 + e1 * e1)
                if np.isnan(res):
                    res = 1e6
                elif np.isinf(res):
                    res = 1.7976931348623157e308
                w[j] = (1.0 if mask[i, j] else 0.0) / (1.0 + (res / 4.0) ** 2)
        rho[i] = r
    return rho


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _held_pose_depths(xbar, obs, mask, R, t, f, c, pixel_sigma, rho0, scale, max_error):  # pragma: no cover - compiled
    """Robust (Cauchy) Gauss-Newton of each track's inverse depth with the poses held.

    Per track (independent 1-D problems): 3 Gauss-Newton steps from ``rho0``, observations off
    by more than ``max_error`` pixels dropped, one more step. A step that would bring the
    inverse depth below a tenth of its value halves it instead.

    Returns:
        rho (N,), the residuals (N, J, 2) in units of ``pixel_sigma`` (0 where not valid) and
        valid (N, J): observed, kept, in front of the neighbour, finite.
    """
    n, nj = mask.shape
    rho = rho0.copy()
    r_out = np.zeros((n, nj, 2))
    valid = np.zeros((n, nj), np.bool_)
    Rx = np.empty((nj, 3))
    m = np.empty(nj, np.bool_)
    fs0 = f[0] / pixel_sigma
    fs1 = f[1] / pixel_sigma
    s2 = scale * scale
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        for j in range(nj):
            m[j] = mask[i, j]
        x = rho[i]
        for it in range(5):
            if it == 3:  # drop the outliers of the first 3 steps
                for j in range(nj):
                    if m[j]:
                        _, _, _, r0, r1, ok = _residual(Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma)
                        m[j] = ok and np.sqrt(r0 * r0 + r1 * r1) * pixel_sigma <= max_error
                continue
            h = 0.0
            g = 0.0
            for j in range(nj):
                if not m[j]:
                    continue
                p0, p1, p2, r0, r1, ok = _residual(Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma)
                if not ok:
                    continue
                iz2 = 1.0 / p2**2
                J0 = fs0 * (t[j, 0] * p2 - p0 * t[j, 2]) * iz2
                J1 = fs1 * (t[j, 1] * p2 - p1 * t[j, 2]) * iz2
                wc = 1.0 / (1.0 + (r0 * r0 + r1 * r1) / s2)
                h += wc * (J0 * J0 + J1 * J1)
                g += wc * (J0 * r0 + J1 * r1)
            step = -g / h if h > 0 else 0.0
            x_new = x + step
            x = x_new if x_new > 0.1 * x else 0.5 * x
        rho[i] = x
        for j in range(nj):
            if m[j]:
                _, _, _, r0, r1, ok = _residual(Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma)
                if ok:
                    valid[i, j] = True
                    r_out[i, j, 0] = r0
                    r_out[i, j, 1] = r1
    return rho, r_out, valid


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _held_pose_variance(xbar, rho, valid, R, t, fs, prior_var):  # pragma: no cover - compiled
    """(N,) variance of each inverse depth with the poses held at their given values.

    Pixel noise through the Gauss-Newton information h = sum J_rho^2 (``fs`` = focal length
    over the pixel sigma) plus every neighbour's pose prior (``prior_var``: 6 variances,
    rotation vector then translation) through d rho / d xi = -h^-1 H_rho_xi:
    var = 1/h + sum_j,k (H_rho_xi[j, k] / h)^2 prior_var[k].
    """
    n, nj = valid.shape
    out = np.zeros(n)
    Rx = np.empty((nj, 3))
    H = np.zeros((nj, 6))
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        x = rho[i]
        h = 0.0
        for j in range(nj):
            for k in range(6):
                H[j, k] = 0.0
            if not valid[i, j]:
                continue
            p0 = Rx[j, 0] + x * t[j, 0]
            p1 = Rx[j, 1] + x * t[j, 1]
            p2 = Rx[j, 2] + x * t[j, 2]
            iz = 1.0 / p2
            # d(residual)/dp rows: (a, 0, -a p0 iz) and (0, b, -b p1 iz)
            a0 = fs[0] * iz
            a2 = -fs[0] * p0 * iz * iz
            b1 = fs[1] * iz
            b2 = -fs[1] * p1 * iz * iz
            j_rho0 = a0 * t[j, 0] + a2 * t[j, 2]
            j_rho1 = b1 * t[j, 1] + b2 * t[j, 2]
            h += j_rho0 * j_rho0 + j_rho1 * j_rho1
            # rotation: -Jp @ skew(Rx); translation: Jp * rho
            H[j, 0] = j_rho0 * a2 * Rx[j, 1] + j_rho1 * (b2 * Rx[j, 1] - b1 * Rx[j, 2])
            H[j, 1] = j_rho0 * (a0 * Rx[j, 2] - a2 * Rx[j, 0]) - j_rho1 * b2 * Rx[j, 0]
            H[j, 2] = j_rho1 * b1 * Rx[j, 0] - j_rho0 * a0 * Rx[j, 1]
            H[j, 3] = j_rho0 * a0 * x
            H[j, 4] = j_rho1 * b1 * x
            H[j, 5] = (j_rho0 * a2 + j_rho1 * b2) * x
        inv = 1.0 / h if h > 0 else 0.0
        v = inv
        for j in range(nj):
            for k in range(6):
                e = H[j, k] * inv
                v += e * e * prior_var[k]
        out[i] = v
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _point_checks(Xr, r, valid, R, t, min_front):  # pragma: no cover - compiled
    """Per point (Xr: (N, 3) in the reference camera): views, parallax, in front, RMS residual.

    Returns:
        n_views (N,) (the reference included), the largest angle (degrees) between the
        reference ray and a supporting neighbour's ray (NaN for a NaN point), whether the point
        lies deeper than ``min_front`` in every supporting neighbour, and the RMS of the
        residuals ``r`` over the supporting views.
    """
    n, nj = valid.shape
    n_views = np.ones(n, np.int64)
    parallax = np.zeros(n)
    front = np.ones(n, np.bool_)
    rms = np.zeros(n)
    centre = np.empty((nj, 3))  # neighbour centres in the reference frame: -R^T t
    for j in range(nj):
        for a in range(3):
            centre[j, a] = -(R[j, 0, a] * t[j, 0] + R[j, 1, a] * t[j, 1] + R[j, 2, a] * t[j, 2])
    for i in range(n):
        x0, x1, x2 = Xr[i, 0], Xr[i, 1], Xr[i, 2]
        nx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        best = 0.0
        ss = 0.0
        count = 0
        for j in range(nj):
            if not valid[i, j]:
                continue
            count += 1
            ss += r[i, j, 0] * r[i, j, 0] + r[i, j, 1] * r[i, j, 1]
            zj = R[j, 2, 0] * x0 + R[j, 2, 1] * x1 + R[j, 2, 2] * x2 + t[j, 2]
            if not zj > min_front:
                front[i] = False
            o0, o1, o2 = x0 - centre[j, 0], x1 - centre[j, 1], x2 - centre[j, 2]
            cosang = (x0 * o0 + x1 * o1 + x2 * o2) / (nx * np.sqrt(o0 * o0 + o1 * o1 + o2 * o2))
            ang = np.degrees(np.arccos(min(max(cosang, -1.0), 1.0)))
            if np.isnan(ang) or np.isnan(best):
                best = np.nan
            elif ang > best:
                best = ang
        n_views[i] = 1 + count
        parallax[i] = best
        rms[i] = np.sqrt(ss / max(count, 1))
    return n_views, parallax, front, rms


def _levenberg_marquardt(prob: _Problem, rho: np.ndarray, scale: float, iterations: int) -> np.ndarray:
    lam = 1e-4
    cost = prob.cost(rho, scale)
    nj = prob.R.shape[0]
    for _ in range(iterations):
        _, valid, _, _, _, _, _ = prob.normal_equations(rho, np.ones(prob.mask.shape))
        r = prob.residuals(rho)[2]
        w = _cauchy_weights(r, scale) * valid
        _, _, h_rr, b_r, H_xr, H_xx, b_x = prob.normal_equations(rho, w)
        improved = False
        for _ in range(6):
            hd = h_rr * (1 + lam) + 1e-12
            Hd = H_xx + lam * np.einsum("jkk->jk", H_xx)[..., None] * np.eye(6)[None]
            S, A, inv = prob.schur(hd, H_xr, Hd)
            g = b_x.reshape(-1) - (A * (b_r / hd)[:, None]).sum(axis=0)
            try:
                dx = -np.linalg.solve(S, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            drho = -(b_r + A @ dx) / hd
            dxj = dx.reshape(nj, 6)
            R_new = _rodrigues(dxj[:, :3]) @ prob.R
            t_new = prob.t + dxj[:, 3:]
            rho_new = rho + drho
            new_cost = prob.cost(rho_new, scale, R_new, t_new)
            if np.isfinite(new_cost) and new_cost <= cost:
                prob.R, prob.t, rho, cost = R_new, t_new, rho_new, new_cost
                lam = max(lam / 10, 1e-8)
                improved = True
                break
            lam *= 10
        if not improved:
            break
    return rho


def _track_klt(
    grays: Sequence[np.ndarray], shape: tuple[int, int], start: np.ndarray, order: Sequence[int], config: TriangulationConfig
) -> np.ndarray:
    """Tracks keypoints of view order[0] through the views in ``order`` with pyramidal Lucas-Kanade.

    Returns (N, len(grays), 2) positions (NaN where lost); each step starts from the previous
    view's positions, with a forward-backward check (<= ``klt_fb_error`` pixels).
    """
    import cv2

    n = start.shape[0]
    out = np.full((n, len(grays), 2), np.nan)
    out[:, order[0]] = start
    alive = np.arange(n)
    prev = start.astype(np.float32)
    params = dict(winSize=(config.klt_window, config.klt_window), maxLevel=config.klt_levels,
                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03))
    h, w = shape
    for a, b in zip(order[:-1], order[1:]):
        if alive.size == 0:
            break
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(grays[a], grays[b], prev.reshape(-1, 1, 2), None, **params)
        ok = st.ravel() == 1
        if config.klt_fb_error > 0:
            back, st2, _ = cv2.calcOpticalFlowPyrLK(grays[b], grays[a], nxt, None, **params)
            fb = np.linalg.norm(back.reshape(-1, 2) - prev.reshape(-1, 2), axis=1)
            ok &= (st2.ravel() == 1) & (fb <= config.klt_fb_error)
        nxt = nxt.reshape(-1, 2)
        ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= w - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= h - 1)
        alive, prev = alive[ok], nxt[ok]
        out[alive, b] = prev
    return out


def _match_tracks(feats: Sequence[Features], ref: int, camera: PinholeCamera, poses, config: TriangulationConfig) -> np.ndarray:
    """Star tracks: every reference keypoint with its descriptor match in each other view."""
    n = len(feats[ref])
    out = np.full((n, len(feats), 2), np.nan)
    out[:, ref] = feats[ref].uv
    for j in range(len(feats)):
        if j == ref:
            continue
        F = fundamental_from_poses(camera, poses[ref], poses[j])
        pairs = match_features(feats[ref], feats[j], config=config, F=F)
        out[pairs[:, 0], j] = feats[j].uv[pairs[:, 1]]
    return out


def build_tracks(
    rgbs: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    *,
    reference: int = -1,
    config: TriangulationConfig | None = None,
    features: Sequence[Features] | None = None,
) -> np.ndarray:
    """Feature tracks of the reference frame's keypoints through the other frames.

    With ``detector="klt"`` (the default) the reference's corners are followed with
    pyramidal Lucas-Kanade (OpenCV) outward from the reference through the frames in the
    order given (frames are taken to be in temporal order: reference -> its neighbour -> the
    next ...), with a forward-backward check; with "orb" / "sift" each reference keypoint
    is matched by descriptor in every other frame (ratio test, mutual best, epipolar gate
    ``max_epipolar_error`` around the given poses).

    Args:
        rgbs: V (H, W, 3) uint8 RGB images of ``camera``'s size.
        poses: V 4x4 ``T_world_camera`` poses.
        camera: Intrinsics.
        reference: Index of the reference frame.
        config: Options.
        features: Optional precomputed features (one per frame; only the reference's are
            used with "klt").

    Returns:
        (N, V, 2) pixel positions, NaN where a track is not seen; column ``reference`` is
        the reference keypoints.

    Raises:
        InvalidInputError: fewer than two frames, a pose count that differs, a reference out
            of range, or features of another detector than ``config.detector``.
        ShapeError: an image of another size than ``camera``'s.
    """
    import cv2

    config = config or TriangulationConfig()
    V = len(rgbs)
    if V < 2 or len(poses) != V:
        raise InvalidInputError("rgbs, poses", "two or more frames with one pose each", (V, len(poses)))
    if not -V <= reference < V:
        raise InvalidInputError("reference", f"an index into {V} frames", reference)
    ref = reference % V
    for k, im in enumerate(rgbs):
        camera.check_image(im, f"rgbs[{k}]")
    if features is not None:
        feats = list(features)
        for k, f in enumerate(feats):
            if f.detector != config.detector:
                raise InvalidInputError(f"features[{k}]", f"features of detector {config.detector!r}", f.detector)
    else:
        feats = None
    if config.detector == "klt":
        ref_feat = feats[ref] if feats is not None else detect_features(rgbs[ref], config=config)
        if len(ref_feat) == 0:
            return np.zeros((0, V, 2))
        grays = [_gray(im, f"rgbs[{k}]") for k, im in enumerate(rgbs)]
        before = list(range(ref, -1, -1))
        after = list(range(ref, V))
        out = _track_klt(grays, grays[ref].shape, ref_feat.uv, before, config) if len(before) > 1 else None
        if len(after) > 1:
            out2 = _track_klt(grays, grays[ref].shape, ref_feat.uv, after, config)
            out = out2 if out is None else np.where(np.isnan(out), out2, out)
        return out
    if feats is None:
        feats = [detect_features(im, config=config) for im in rgbs]
    return _match_tracks(feats, ref, camera, poses, config)


def triangulate_frames(
    rgbs: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    *,
    reference: int = -1,
    config: TriangulationConfig | None = None,
    features: Sequence[Features] | None = None,
) -> SparseDepth:
    """Sparse depth for one frame from multi-view feature tracks through the other posed frames.

    `build_tracks` follows the reference frame's keypoints through the other frames (KLT
    outward from the reference in the order given, or descriptor matches), and
    `triangulate_tracks` triangulates every track from all its views while refining the
    other frames' poses relative to the reference (robust bundle adjustment with a pose
    prior), with a per-point sigma that carries pixel noise and pose uncertainty. Any frame
    may be the reference: the first frame of a sequence uses the later frames.

    Args:
        rgbs: Two or more (H, W, 3) uint8 RGB images, in temporal order.
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
    tracks = build_tracks(rgbs, poses, camera, reference=reference, config=config, features=features)
    if tracks.shape[0] == 0:
        return SparseDepth.empty(camera.shape)
    mv = triangulate_tracks(tracks, poses, camera, reference=reference, config=config)
    return mv.to_sparse(camera.shape)


class TrackTriangulator:
    """Sparse depth for a stream of posed frames from feature tracks followed frame to frame.

    Each call of `add` follows the live tracks from the previous frame into the new one with
    pyramidal Lucas-Kanade (OpenCV, forward-backward checked) and starts new Shi-Tomasi corners
    where the image has none: one tracking step per frame, however many views a track spans.
    Every frame is triangulated once, as the reference of `triangulate_tracks`, from all its
    tracks that are seen in at least one other remembered view: up to ``window`` frames before
    it and, with ``lag`` > 0, the ``lag`` frames after it (a fixed-lag smoother).

    With ``lag = 0`` `add` returns the points of the frame just added (the first frame of a
    stream gets none: nothing to triangulate against). With ``lag = L`` it returns the points
    of the frame added L calls earlier (`last_key` names it; nothing while the first L frames
    come in), triangulated from views on both sides; `flush` returns the last L frames at the
    end of a stream. Measured on the shared 7-Scenes sequence (bench/fusion.py), views on both
    sides give every frame points (the first one too) and smaller per-frame biases than the same
    number of earlier views alone: a pose error of one view then pulls the depth less.

    Args:
        camera: Intrinsics of the RGB images given to `add`.
        config: Options (``detector`` is ignored: always KLT).
        window: Earlier frames a track keeps its positions in (views before the reference).
        lag: Later frames a frame waits for before it is triangulated (views after the reference).

    Attributes:
        tracks_seen: frame key -> how many of its tracks were seen in another view when it was
            triangulated (the candidates; ``len`` of its points says how many became points).
            A pose that does not belong to its image leaves almost none of them (see
            `gpdepth3d.mapping.mapper.POSE_TRACK_SHARE`).
    """

    def __init__(self, camera: PinholeCamera, config: TriangulationConfig | None = None, *, window: int = 4, lag: int = 0):
        if not isinstance(camera, PinholeCamera):
            raise InvalidInputError("camera", "a PinholeCamera", type(camera).__name__)
        if isinstance(window, bool) or int(window) != window or window < 1:
            raise InvalidInputError("window", "an integer >= 1", window)
        if isinstance(lag, bool) or int(lag) != lag or lag < 0:
            raise InvalidInputError("lag", "an integer >= 0", lag)
        self.camera = camera
        self.config = config or TriangulationConfig()
        self.window = int(window)
        self.lag = int(lag)
        self.last: MultiViewPoints | None = None
        self.last_key: object = None
        self.tracks_seen: dict = {}
        self.reset()

    def reset(self) -> None:
        """Forgets every track and frame (e.g. after a tracking loss); frames waiting are dropped."""
        self._gray: np.ndarray | None = None
        self._poses: list[np.ndarray] = []
        self._keys: list[object] = []
        self._tracks = np.zeros((0, 0, 2))
        self._pending = 0  # frames at the end of the columns not triangulated yet
        self.last = None
        self.last_key = None
        self.tracks_seen = {}  # key -> tracks of that frame seen in another view, when it was triangulated

    @property
    def n_tracks(self) -> int:
        """Tracks alive in the last frame."""
        if self._tracks.shape[0] == 0 or self._tracks.shape[1] == 0:
            return 0
        return int(np.isfinite(self._tracks[:, -1, 0]).sum())

    @property
    def pending(self) -> int:
        """Frames added but not triangulated yet (at most ``lag``)."""
        return int(self._pending)

    def update_poses(self, poses: dict) -> int:
        """Replaces the poses of remembered frames (e.g. after a loop closure).

        Args:
            poses: key (as given to `add`) -> new 4x4 ``T_world_camera``; keys of frames no
                longer remembered are ignored.

        Returns:
            How many remembered frames got a new pose.

        Raises:
            CalibrationError: a pose that is not rigid.
        """
        changed = 0
        for k, key in enumerate(self._keys):
            if key is not None and key in poses:
                self._poses[k] = check_pose(poses[key], f"poses[{key!r}]")
                changed += 1
        return changed

    def add(self, rgb: np.ndarray, T_world_camera: np.ndarray, *, key: object = None) -> SparseDepth:
        """Tracks into one more posed frame and triangulates the frame whose turn it is.

        Args:
            rgb: (H, W, 3) uint8 RGB image (or (H, W) uint8 grey) of ``camera``'s size.
            T_world_camera: 4x4 rigid pose of the frame.
            key: Optional name of the frame (e.g. a keyframe id) for `update_poses` and `last_key`.

        Returns:
            `SparseDepth` with per-point sigma (metres) of the frame added ``lag`` calls ago
            (this one with ``lag = 0``; `last_key` is its key); empty while the first ``lag``
            frames come in, and for the very first frame of a stream with ``lag = 0``.

        Raises:
            ShapeError: an image of the wrong size or type.
            CalibrationError: a pose that is not rigid.
        """
        T = check_pose(T_world_camera)
        gray = _gray(rgb, "rgb")
        if gray.shape != self.camera.shape:
            raise ShapeError("rgb", f"an image of {self.camera.width}x{self.camera.height}", describe(gray))
        self._step(gray, T, key)
        self._pending += 1
        self.last, self.last_key = None, None
        if self._pending <= self.lag:
            return SparseDepth.empty(self.camera.shape)
        out = self._triangulate_column(len(self._poses) - self._pending)
        self._pending -= 1
        self._prune()
        return out

    def flush(self) -> list[tuple[object, SparseDepth]]:
        """Triangulates the frames still waiting (end of a stream), each from the views there are.

        Returns:
            (key, `SparseDepth`) of every waiting frame, oldest first (empty with ``lag = 0``).
        """
        out = []
        while self._pending > 0:
            sparse = self._triangulate_column(len(self._poses) - self._pending)
            out.append((self.last_key, sparse))
            self._pending -= 1
        self._prune()
        return out

    def _triangulate_column(self, col: int) -> SparseDepth:
        """Points of the frame in column ``col`` from every track seen there and in another column."""
        tracks = self._tracks
        self.last, self.last_key = None, self._keys[col]
        self.tracks_seen[self.last_key] = 0
        if len(self.tracks_seen) > 4 * (self.window + self.lag + 1):  # keys nobody asked for
            self.tracks_seen.pop(next(iter(self.tracks_seen)))
        if tracks.shape[0] == 0 or tracks.shape[1] < 2:
            return SparseDepth.empty(self.camera.shape)
        finite = np.isfinite(tracks[..., 0])
        seen = finite[:, col] & (finite.sum(axis=1) >= 2)
        self.tracks_seen[self.last_key] = int(seen.sum())
        if not seen.any():
            return SparseDepth.empty(self.camera.shape)
        mv = triangulate_tracks(tracks[seen], self._poses, self.camera, reference=col, config=self.config, _checked=True)
        # point rows refer to the tracks given; map back to all tracks
        self.last = replace(mv, index=np.nonzero(seen)[0][mv.index])
        return mv.to_sparse(self.camera.shape)

    def _prune(self) -> None:
        """Drops tracks that can serve no frame still to be triangulated (dead, unseen in those frames)."""
        tracks = self._tracks
        if tracks.shape[0] == 0 or tracks.shape[1] == 0:
            return
        finite = np.isfinite(tracks[..., 0])
        keep = finite[:, -1]
        if self._pending:
            keep = keep | finite[:, tracks.shape[1] - self._pending :].any(axis=1)
        self._tracks = tracks[keep]

    def _step(self, gray: np.ndarray, T: np.ndarray, key: object) -> None:
        """One KLT step of the live tracks into ``gray``, the new column, new corners."""
        import cv2

        cfg = self.config
        h, w = gray.shape
        tracks = self._tracks
        n, c = tracks.shape[:2]
        new_col = np.full((n, 1, 2), np.nan)
        if self._gray is not None and n:
            alive = np.nonzero(np.isfinite(tracks[:, -1, 0]))[0]
            if alive.size:
                prev = tracks[alive, -1].astype(np.float32).reshape(-1, 1, 2)
                params = dict(
                    winSize=(cfg.klt_window, cfg.klt_window), maxLevel=cfg.klt_levels,
                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03),
                )
                nxt, st, _ = cv2.calcOpticalFlowPyrLK(self._gray, gray, prev, None, **params)
                ok = st.ravel() == 1
                if cfg.klt_fb_error > 0:
                    back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self._gray, nxt, None, **params)
                    fb = np.linalg.norm(back.reshape(-1, 2) - prev.reshape(-1, 2), axis=1)
                    ok &= (st2.ravel() == 1) & (fb <= cfg.klt_fb_error)
                nxt = nxt.reshape(-1, 2).astype(np.float64)
                ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= w - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= h - 1)
                new_col[alive[ok], 0] = nxt[ok]
        tracks = np.concatenate([tracks.reshape(n, c, 2), new_col], axis=1) if self._gray is not None else np.zeros((0, 1, 2))
        self._poses.append(T)
        self._keys.append(key)
        keep_cols = self.window + self.lag + 1
        if len(self._poses) > keep_cols:
            self._poses = self._poses[-keep_cols:]
            self._keys = self._keys[-keep_cols:]
            tracks = tracks[:, -keep_cols:]
            tracks = tracks[np.isfinite(tracks[..., 0]).any(axis=1)]
        self._gray = gray

        # new corners where the image has no live track
        live = np.isfinite(tracks[:, -1, 0])
        n_live = int(live.sum())
        if n_live < cfg.max_features:
            # corners on the half-resolution image (4x cheaper); a track starts wherever its
            # corner lies, so sub-pixel corner accuracy is not needed. No new corner within
            # min_corner_distance of a live track (discs drawn by one dilation).
            hs, ws = h // 2, w // 2
            small = cv2.resize(gray, (ws, hs), interpolation=cv2.INTER_AREA)
            small_mask = np.zeros((hs, ws), np.uint8)
            if n_live:
                iu = np.clip(np.rint(tracks[live, -1] / 2).astype(int), 0, [ws - 1, hs - 1])
                small_mask[iu[:, 1], iu[:, 0]] = 255
                r = max(1, int(round(cfg.min_corner_distance / 2)))
                disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
                small_mask = cv2.dilate(small_mask, disc)
            small_mask = 255 - small_mask
            corners = cv2.goodFeaturesToTrack(
                small, int(cfg.max_features - n_live), 0.01, max(1.0, cfg.min_corner_distance / 2),
                mask=small_mask, blockSize=3,
            )
            if corners is not None:
                corners = corners * 2.0 + 0.5
                new = np.full((corners.shape[0], tracks.shape[1], 2), np.nan)
                new[:, -1] = corners.reshape(-1, 2)
                tracks = np.concatenate([tracks, new], axis=0)
        self._tracks = tracks
