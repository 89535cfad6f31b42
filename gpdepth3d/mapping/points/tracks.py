"""Feature tracks through posed frames (KLT frame to frame, or descriptor matches) and the streaming `TrackTriangulator`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ...camera import PinholeCamera, check_pose
from ...errors import InvalidInputError, ShapeError, describe
from ...measurements import SparseDepth
from .features import Features, _gray, descriptor_matches, detect_features, epipolar_gate, fundamental_from_poses
from .multiview import MultiViewPoints, triangulate_tracks
from .triangulation_config import TriangulationConfig


def _track_klt(
    grays: Sequence[np.ndarray],
    shape: tuple[int, int],
    start: np.ndarray,
    order: Sequence[int],
    config: TriangulationConfig,
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
    params = dict(
        winSize=(config.klt_window, config.klt_window),
        maxLevel=config.klt_levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03),
    )
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


def _match_tracks(
    feats: Sequence[Features],
    ref: int,
    camera: PinholeCamera,
    poses,
    config: TriangulationConfig,
    matches: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """Star tracks: every reference keypoint with its descriptor match in each other view (`match_features`;
    ``matches[j]``, where given, is view j's `descriptor_matches` computed ahead)."""
    n = len(feats[ref])
    out = np.full((n, len(feats), 2), np.nan)
    out[:, ref] = feats[ref].uv
    for j in range(len(feats)):
        if j == ref:
            continue
        F = fundamental_from_poses(camera, poses[ref], poses[j])
        pairs = matches[j] if matches is not None and matches[j] is not None else None
        if pairs is None:
            pairs = descriptor_matches(feats[ref], feats[j], ratio=config.ratio)
        pairs = epipolar_gate(pairs, feats[ref], feats[j], F, config.max_epipolar_error)
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
    matches: Sequence[np.ndarray | None] | None = None,
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
        matches: Optional, with descriptors: per frame, the reference's `descriptor_matches` with it
            computed ahead (None for the reference and for frames to match here); the epipolar gate
            is applied to them here, with ``poses``.

    Returns:
        (N, V, 2) pixel positions, NaN where a track is not seen; column ``reference`` is
        the reference keypoints.

    Raises:
        InvalidInputError: fewer than two frames, a pose count that differs, a reference out
            of range, or features of another detector than ``config.detector``.
        ShapeError: an image of another size than ``camera``'s.
    """

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
    if matches is not None and len(matches) != V:
        raise InvalidInputError("matches", f"{V} entries, one per frame", len(matches))
    return _match_tracks(feats, ref, camera, poses, config, matches)


def triangulate_frames(
    rgbs: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    *,
    reference: int = -1,
    config: TriangulationConfig | None = None,
    features: Sequence[Features] | None = None,
    matches: Sequence[np.ndarray | None] | None = None,
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
        matches: Optional descriptor matches computed ahead, as in `build_tracks`.

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
    tracks = build_tracks(rgbs, poses, camera, reference=reference, config=config, features=features, matches=matches)
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
    end of a stream. Views on both sides give every frame points (the first one too) and smaller
    per-frame biases than the same number of earlier views alone: a pose error of one view then
    pulls the depth less (see docs/results.md).

    Args:
        camera: Intrinsics of the RGB images given to `add`.
        config: Options (``detector`` is ignored: always KLT).
        window: Earlier frames a track keeps its positions in (views before the reference).
        lag: Later frames a frame waits for before it is triangulated (views after the reference).

    Attributes:
        tracks_seen: frame key -> how many of its tracks were seen in another view when it was
            triangulated (the candidates; ``len`` of its points says how many became points).
            A pose that does not belong to its image leaves almost none of them (see
            `gpdepth3d.mapping.frame_points.POSE_TRACK_SHARE`).
        tracks_agreeing: frame key -> how many of those its pose and its neighbours' agree with
            (`MultiViewPoints.agreeing`: within the reprojection gate, in front), points or not.
        pose_displacement: frame key -> how far, pixels, the given poses carry its tracks' points
            across its neighbours' images from where they are seen (`MultiViewPoints.pose_displacement`).
    """

    def __init__(
        self, camera: PinholeCamera, config: TriangulationConfig | None = None, *, window: int = 4, lag: int = 0
    ):
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
        self.tracks_agreeing: dict = {}
        self.pose_displacement: dict = {}
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
        self.tracks_agreeing = {}  # key -> of those, the ones its pose agrees with
        self.pose_displacement = {}  # key -> MultiViewPoints.pose_displacement of its triangulation

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
        self.tracks_agreeing[self.last_key] = 0
        self.pose_displacement[self.last_key] = 0.0
        for kept in (self.tracks_seen, self.tracks_agreeing, self.pose_displacement):
            if len(kept) > 4 * (self.window + self.lag + 1):  # keys nobody asked for
                kept.pop(next(iter(kept)))
        if tracks.shape[0] == 0 or tracks.shape[1] < 2:
            return SparseDepth.empty(self.camera.shape)
        finite = np.isfinite(tracks[..., 0])
        seen = finite[:, col] & (finite.sum(axis=1) >= 2)
        self.tracks_seen[self.last_key] = int(seen.sum())
        if not seen.any():
            return SparseDepth.empty(self.camera.shape)
        mv = triangulate_tracks(
            tracks[seen], self._poses, self.camera, reference=col, config=self.config, _checked=True
        )
        # point rows refer to the tracks given; map back to all tracks
        self.last = replace(mv, index=np.nonzero(seen)[0][mv.index])
        self.tracks_agreeing[self.last_key] = mv.agreeing
        self.pose_displacement[self.last_key] = mv.pose_displacement
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
                    winSize=(cfg.klt_window, cfg.klt_window),
                    maxLevel=cfg.klt_levels,
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
        tracks = (
            np.concatenate([tracks.reshape(n, c, 2), new_col], axis=1)
            if self._gray is not None
            else np.zeros((0, 1, 2))
        )
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
                small,
                int(cfg.max_features - n_live),
                0.01,
                max(1.0, cfg.min_corner_distance / 2),
                mask=small_mask,
                blockSize=3,
            )
            if corners is not None:
                corners = corners * 2.0 + 0.5
                new = np.full((corners.shape[0], tracks.shape[1], 2), np.nan)
                new[:, -1] = corners.reshape(-1, 2)
                tracks = np.concatenate([tracks, new], axis=0)
        self._tracks = tracks
