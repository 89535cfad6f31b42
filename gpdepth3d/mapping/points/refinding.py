"""Points across large camera motion: views chosen by parallax, features re-found by their descriptors.

Frame-to-frame KLT tracks (`gpdepth3d.mapping.points.triangulation.TrackTriangulator`) break when the
camera moves far between frames (a walk sampled every few frames). `Refinder` keeps the recent
posed frames; for a frame whose tracks gave few points it picks the views whose baseline over the
frame's depth lies in a useful range (`select_views`), matches ORB or SIFT descriptors
(OpenCV) under the epipolar geometry of the given poses, and triangulates the matches from all
their views (`triangulate_frames`, same sigma model as the tracks). See
https://docs.opencv.org/4.x/dc/dc3/tutorial_py_matcher.html for the matching.
"""

from __future__ import annotations

from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from ...camera import PinholeCamera
from ...checks import Choice, Int, Real, check_fields
from ...errors import InvalidInputError
from ...measurements import SparseDepth
from .features import Features, _gray, descriptor_matches, detect_features
from .tracks import triangulate_frames
from .triangulation_config import TriangulationConfig


@dataclass(frozen=True)
class RefindConfig:
    """When and how features are re-found by descriptor.

    Attributes:
        detector: "orb" or "sift" (OpenCV), or "none" to turn re-finding off.
        max_features: Keypoints detected per image.
        below: A frame whose tracks gave fewer points than this gets descriptor points too.
        views: Most other views a frame is matched with.
        min_parallax: Smallest baseline / depth of a view (below it depth is ill-determined); the
            baseline is its part across the frame's optical axis (moving forward gives no parallax
            where the frame looks).
        max_parallax: Largest baseline / depth (beyond it the views see too different images).
        target_parallax: Views closest to this baseline / depth (in log) are chosen first.
        max_angle_deg: Largest angle between the optical axes of the frame and a view, degrees.
        pool: Frames remembered as candidate views (earlier ones and the Mapper's later ones).
    """

    detector: str = "sift"
    max_features: int = 2000
    below: int = 200
    views: int = 5
    min_parallax: float = 0.02
    max_parallax: float = 0.6
    target_parallax: float = 0.15
    max_angle_deg: float = 40.0
    pool: int = 20

    def __post_init__(self) -> None:
        rules = {"detector": Choice(("orb", "sift", "none")), "max_features": Int(8), "below": Int(0)}
        rules.update(views=Int(1), pool=Int(2), min_parallax=Real(), target_parallax=Real(), max_parallax=Real())
        rules.update(max_angle_deg=Real(0.0, 180.0, low_open=True, high_open=True, unit="degrees"))
        check_fields(self, rules)
        if not 0 < self.min_parallax <= self.target_parallax <= self.max_parallax:
            raise InvalidInputError(
                "min_parallax, target_parallax, max_parallax",
                "0 < min <= target <= max",
                (self.min_parallax, self.target_parallax, self.max_parallax),
            )


def select_views(
    T_world_camera: np.ndarray, depth: float, candidates: dict, config: RefindConfig | None = None
) -> list:
    """Keys of the candidate views to triangulate a frame from, best parallax first.

    Args:
        T_world_camera: 4x4 pose of the frame.
        depth: Typical depth of the frame (e.g. the MDE's median), metres.
        candidates: key -> 4x4 ``T_world_camera`` of the other views.
        config: Parallax range, target, axis angle and number of views.

    Returns:
        Up to ``config.views`` keys with baseline / depth in [min_parallax, max_parallax] and
        optical axes within ``max_angle_deg``, closest to ``target_parallax`` (in log) first.
    """
    config = config or RefindConfig()
    if not np.isfinite(depth) or depth <= 0:
        raise InvalidInputError("depth", "a typical depth > 0 (metres)", depth)
    centre, axis = T_world_camera[:3, 3], T_world_camera[:3, 2]
    cos_max = np.cos(np.radians(config.max_angle_deg))
    scored = []
    for key, T in candidates.items():
        baseline = T[:3, 3] - centre  # its part along the optical axis gives no parallax at the image centre
        parallax = float(np.linalg.norm(baseline - (baseline @ axis) * axis)) / depth
        if config.min_parallax <= parallax <= config.max_parallax and float(axis @ T[:3, 2]) >= cos_max:
            scored.append((abs(np.log(parallax / config.target_parallax)), key))
    scored.sort(key=lambda item: item[0])
    return [key for _, key in scored[: int(config.views)]]


class Refinder:
    """Recent posed frames and their descriptors, for triangulating a frame from parallax-chosen views.

    Args:
        camera: Intrinsics of the images given to `add`.
        config: Re-finding options.
        triangulation: Triangulation options (sigma model, gates); its detector is replaced and its
            ``variance_factor`` turned off (see the comment in the code).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        config: RefindConfig | None = None,
        triangulation: TriangulationConfig | None = None,
    ):
        self.camera = camera
        self.config = config or RefindConfig()
        base = triangulation or TriangulationConfig()
        detector = "orb" if self.config.detector == "none" else self.config.detector
        # the residuals' pixel noise already enters sigma; the a-posteriori factor would scale the poses'
        # share by it too, while descriptor keypoints' larger residuals are their localisation, not pose error
        self.triangulation = replace(
            base, detector=detector, max_features=int(self.config.max_features), variance_factor=False
        )
        self._frames: OrderedDict = OrderedDict()  # key -> [gray, pose, Features | Future | None]
        self._detector: ThreadPoolExecutor | None = None
        self._ahead: dict[tuple, Future] = {}  # (frame, view) -> its `descriptor_matches`, started by `prepare`

    def add(self, rgb: np.ndarray, T_world_camera: np.ndarray, key: object, *, prefetch: bool = False) -> None:
        """Remembers a posed frame (its grey image; descriptors are computed when first needed).

        With ``prefetch`` its descriptors are computed at once on a background thread (OpenCV
        releases the GIL), so that a later `points` call finds them ready while the caller goes on
        (e.g. with its GP and fusion): the same `Features` as computing them when first needed.
        """
        gray = _gray(rgb, "rgb")
        features = None
        if prefetch and self.config.detector != "none":
            features = self._background().submit(detect_features, gray, config=self.triangulation)
        self._frames[key] = [gray, np.asarray(T_world_camera, dtype=np.float64), features]
        while len(self._frames) > self.config.pool:
            gone, _ = self._frames.popitem(last=False)
            for pair in [p for p in self._ahead if gone in p]:
                del self._ahead[pair]

    def prepare(self, key: object, depth: float) -> None:
        """Starts matching frame ``key`` with the views `select_views` picks now, on the background thread.

        For a frame whose `points` call comes later (the next frame a fixed-lag caller refines): its
        descriptors' matches with each view (`descriptor_matches`, which do not depend on the poses) are
        computed while the caller goes on, and `points` takes those of the views it picks then (a view
        added since is matched there). The points are the ones `points` gives without it.

        Args:
            key: A frame given to `add`.
            depth: Its typical depth (metres), as for `points`.
        """
        if self.config.detector == "none" or key not in self._frames or not np.isfinite(depth) or depth <= 0:
            return
        others = {k: v[1] for k, v in self._frames.items() if k != key}
        views = [
            v for v in select_views(self._frames[key][1], depth, others, self.config) if (key, v) not in self._ahead
        ]
        if not views:
            return
        pool = self._background()
        for k in (key, *views):  # descriptors not asked for yet: found on the same thread, before the matches
            if self._frames[k][2] is None:
                self._frames[k][2] = pool.submit(detect_features, self._frames[k][0], config=self.triangulation)
        ratio = float(self.triangulation.ratio)
        for v in views:
            self._ahead[(key, v)] = pool.submit(_matches_of, self._frames[key][2], self._frames[v][2], ratio)

    def _background(self) -> ThreadPoolExecutor:
        """The one background thread (first in, first out: a task finds the descriptors it needs done)."""
        if self._detector is None:
            self._detector = ThreadPoolExecutor(1, thread_name_prefix="gpdepth3d-refind")
        return self._detector

    def update_poses(self, poses: dict) -> None:
        """New poses of remembered frames (after a loop closure); unknown keys are ignored."""
        for key, T in poses.items():
            if key in self._frames:
                self._frames[key][1] = np.asarray(T, dtype=np.float64)

    def _features(self, key: object) -> Features:
        entry = self._frames[key]
        if entry[2] is None:
            entry[2] = detect_features(entry[0], config=self.triangulation)
        elif isinstance(entry[2], Future):  # prefetched: wait for it
            future, entry[2] = entry[2], None
            entry[2] = future.result()  # its error is raised here, and the next call detects again
        return entry[2]

    def points(self, key: object, depth: float) -> SparseDepth:
        """Descriptor points of remembered frame ``key`` from the views `select_views` picks.

        Args:
            key: A frame given to `add`.
            depth: Its typical depth (metres), for the parallax of the candidate views.

        Returns:
            `SparseDepth` of the frame with per-point sigma (empty without a suitable view).
        """
        if self.config.detector == "none" or key not in self._frames:
            return SparseDepth.empty(self.camera.shape)
        T = self._frames[key][1]
        others = {k: v[1] for k, v in self._frames.items() if k != key}
        views = select_views(T, depth, others, self.config)
        if not views:
            return SparseDepth.empty(self.camera.shape)
        keys = [*views, key]
        features = [self._features(k) for k in keys]
        ahead = {pair: self._ahead.pop(pair) for pair in [p for p in self._ahead if p[0] == key]}
        matches = [ahead[(key, v)].result() if (key, v) in ahead else None for v in views] + [None]
        return triangulate_frames(
            [self._frames[k][0] for k in keys],
            [self._frames[k][1] for k in keys],
            self.camera,
            reference=-1,
            config=self.triangulation,
            features=features,
            matches=matches,
        )


def _matches_of(a: Features | Future, b: Features | Future, ratio: float) -> np.ndarray:
    """`descriptor_matches` of two frames' features, either given or still being found (`Refinder.prepare`)."""
    a, b = (f.result() if isinstance(f, Future) else f for f in (a, b))
    return descriptor_matches(a, b, ratio=ratio)
