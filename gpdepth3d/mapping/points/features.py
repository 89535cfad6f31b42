"""Keypoints and their matches: Shi-Tomasi corners, ORB / SIFT descriptors (OpenCV), the epipolar gate of given poses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...camera import PinholeCamera, check_pose
from ...errors import InvalidInputError, ShapeError, describe
from .triangulation_config import TriangulationConfig


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
        det = cv2.SIFT_create(
            nfeatures=int(config.max_features), contrastThreshold=float(config.sift_contrast_threshold)
        )
    kps, desc = det.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        dim, dtype = (32, np.uint8) if config.detector == "orb" else (128, np.float32)
        return Features(np.zeros((0, 2)), np.zeros((0, dim), dtype), config.detector)
    uv = np.array([kp.pt for kp in kps], dtype=np.float64)
    # OpenCV keypoint coordinates put pixel centres at integers, as gpdepth3d does.
    return Features(uv, desc, config.detector)


def fundamental_from_poses(camera: PinholeCamera, T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
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
    a: Features, b: Features, *, config: TriangulationConfig | None = None, F: np.ndarray | None = None
) -> np.ndarray:
    """Matches descriptors of two images with Lowe's ratio test and mutual consistency.

    A match is the nearest descriptor of the other image, closer than ``ratio`` times the second
    nearest, and nearest the other way too (https://docs.opencv.org/4.x/dc/dc3/tutorial_py_matcher.html).

    Args:
        a: Features of the first image.
        b: Features of the second image.
        config: Ratio threshold and epipolar tolerance.
        F: Optional fundamental matrix (x_b^T F x_a = 0); matches farther than
            ``max_epipolar_error`` pixels (Sampson distance) are dropped.

    Returns:
        (M, 2) int64 index pairs (index into a, index into b).
    """

    config = config or TriangulationConfig()
    return epipolar_gate(descriptor_matches(a, b, ratio=config.ratio), a, b, F, config.max_epipolar_error)


def descriptor_matches(a: Features, b: Features, *, ratio: float = 0.8) -> np.ndarray:
    """`match_features` before the epipolar gate: the mutual ratio-test matches of the descriptors alone.

    They do not depend on the poses, so they can be computed ahead and gated later (`epipolar_gate`).

    Args:
        a: Features of the first image.
        b: Features of the second image (same detector).
        ratio: Lowe's ratio threshold, in (0, 1].

    Returns:
        (M, 2) int64 index pairs (index into a, index into b), by increasing index into a.

    Raises:
        InvalidInputError: features of two detectors, or KLT corners (no descriptors).
    """
    if a.detector != b.detector:
        raise InvalidInputError("b", f"features of the same detector as a ({a.detector})", b.detector)
    if a.detector == "klt":
        raise InvalidInputError("a", "features with descriptors (detector 'orb' or 'sift')", "klt corners")
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    if a.detector == "orb":
        return _orb_matches(a, b, ratio)
    return _mutual_ratio_matches(_squared_descriptor_distances(a, b), ratio)


def epipolar_gate(pairs: np.ndarray, a: Features, b: Features, F: np.ndarray | None, max_error: float) -> np.ndarray:
    """The index pairs whose keypoints lie within ``max_error`` pixels (Sampson distance) of F's epipolar
    geometry (x_b^T F x_a = 0); all of them without F."""
    if F is None or not len(pairs):
        return pairs
    err = sampson_distance(np.asarray(F, np.float64), a.uv[pairs[:, 0]], b.uv[pairs[:, 1]])
    return pairs[np.isfinite(err) & (err <= max_error)]


EXACT_NORM2 = float(2**20)
"""Largest squared descriptor norm for which float32 holds every term of a squared distance exactly (as integers)."""


def _squared_descriptor_distances(a: Features, b: Features) -> np.ndarray:
    """(Na, Nb) squared Euclidean distances of SIFT descriptors (float32; may be slightly < 0 from rounding).

    ``|a|^2 + |b|^2 - 2 a.b`` from one matrix product. OpenCV's SIFT descriptors are integers of small
    norm: then every product and partial sum is an integer below 2^24 that float32 holds exactly, whatever
    the order of the sums, and one product of augmented matrices ``[a, |a|^2, 1] [-2b, 1, |b|^2]^T`` gives
    the same values bit for bit in one pass (`_integer_squared_distances`).
    """
    da, db = a.descriptors.astype(np.float32), b.descriptors.astype(np.float32)
    na, nb = np.einsum("ij,ij->i", da, da), np.einsum("ij,ij->i", db, db)
    if _exactly_held(da, na) and _exactly_held(db, nb):
        return _integer_squared_distances(da, na, db, nb)
    sq = na[:, None] + nb[None, :]
    dot = da @ db.T
    dot *= 2.0  # exact in floating point: the same sum as ``|a|^2 + |b|^2 - 2.0 * (a @ b.T)``
    sq -= dot
    return sq


def _exactly_held(d: np.ndarray, norm2: np.ndarray) -> bool:
    """Descriptors of integer values whose squared norms are at most `EXACT_NORM2` (Cauchy-Schwarz bounds every
    partial dot product by it)."""
    return bool(d.size and norm2.max() <= EXACT_NORM2 and np.array_equal(d, np.rint(d)))


def _integer_squared_distances(da: np.ndarray, na: np.ndarray, db: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """Squared distances of integer descriptors (`_exactly_held`) from one augmented matrix product, float32."""
    one_a, one_b = np.ones((len(da), 1), np.float32), np.ones((len(db), 1), np.float32)
    left = np.hstack([da, na[:, None], one_a])
    right = np.hstack([-2.0 * db, one_b, nb[:, None]])
    return left @ right.T


def _distance(sq: np.ndarray) -> np.ndarray:
    """Euclidean distances from squared ones that rounding may have made slightly negative."""
    return np.sqrt(np.maximum(sq, 0.0))


def _orb_matches(a: Features, b: Features, ratio: float) -> np.ndarray:
    """`_mutual_ratio_matches` for ORB's binary descriptors, by OpenCV's brute-force Hamming matcher."""
    import cv2

    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    best_back = np.full(len(b), -1, np.int64)
    for m in matcher.match(b.descriptors, a.descriptors):
        best_back[m.queryIdx] = m.trainIdx
    return pairs[best_back[pairs[:, 1]] == pairs[:, 0]]


def _mutual_ratio_matches(sq: np.ndarray, ratio: float) -> np.ndarray:
    """Index pairs (i, j): j nearest to i, closer than ``ratio`` times i's second nearest, and i nearest to j.

    ``sq`` holds squared distances (`_squared_descriptor_distances`); the distances compared are
    ``sqrt(max(sq, 0))``. That map never decreases, so the nearest and second-nearest distances are
    the map of the squared ones' and only the few compared values are taken to distances: the
    result is the one on the full distance matrix, without it. ``sq`` is left as it was.
    """
    rows = np.arange(sq.shape[0])
    j = np.argmin(sq, axis=1)
    best_sq = sq[rows, j]
    column_min = _distance(sq.min(axis=0))
    sq[rows, j] = np.inf  # the second nearest: the smallest once the nearest is set aside
    second = _distance(sq.min(axis=1))
    sq[rows, j] = best_sq
    best = _distance(best_sq)
    # a tie at the nearest gives best == second, which the ratio test (ratio <= 1) drops whichever j it named
    i = rows[(best < ratio * second) & (best == column_min[j])]
    j = j[i]
    if i.size:  # i nearest to j: the first row of column j at its minimum (argmin's tie rule)
        mutual = np.argmin(_distance(sq[:, j]), axis=0) == i
        i, j = i[mutual], j[mutual]
    return np.column_stack([i, j]).astype(np.int64)
