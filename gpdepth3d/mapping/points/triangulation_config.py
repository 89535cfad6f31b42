"""Options of feature tracking, matching and triangulation (`TriangulationConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


from ...checks import Bool, Int, Real, check_choice, check_fields, non_negative, positive
from ...errors import InvalidInputError


@dataclass(frozen=True)
class TriangulationConfig:
    """Options of feature tracking and triangulation.

    Attributes:
        detector: "klt" (Shi-Tomasi corners followed by pyramidal Lucas-Kanade: sub-pixel
            tracks, the default), "orb" or "sift" (descriptor matching, OpenCV).
        max_features: Most keypoints detected per image (tracks kept alive for "klt");
            None: 800 for "klt", 3000 for "orb" / "sift".
        sift_contrast_threshold: "sift" keypoints' contrast threshold (OpenCV's ``contrastThreshold``,
            https://docs.opencv.org/4.x/d7/d60/classcv_1_1SIFT.html); lower keeps more keypoints on
            low-contrast surfaces (plain walls and floors).
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
            the reference (per axis), degrees, for poses held: poses that agree with their tracks.
        translation_sigma: The same for the translation, metres.
        refine_poses: Where the tracks contradict the given poses (fewer than ``refine_below`` of the
            observations within ``max_reprojection_error`` with the poses held), refine the neighbours'
            poses relative to the reference jointly with the depths: a robust (Cauchy) bundle adjustment
            under the prior ``refine_rotation_sigma_deg`` / ``refine_translation_sigma``, an iteratively
            reweighted Levenberg-Marquardt on the Schur complement of the depths, sigma from its
            Gauss-Newton information. False: poses always held, their prior carried into sigma.
        refine_below: The share of the observations agreeing with the held poses below which they are refined.
        refine_rotation_sigma_deg: Prior standard deviation of each neighbour's rotation relative to the
            reference when refined, degrees: loose, as the tracks fix the rotations well and a SLAM or VIO
            back-end's poses are off by a fraction of a degree to a few degrees.
        refine_translation_sigma: The same for the translation, metres: what holds the metric scale.
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
    sift_contrast_threshold: float = 0.02
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
    refine_poses: bool = True
    refine_below: float = 0.3
    refine_rotation_sigma_deg: float = 1.0
    refine_translation_sigma: float = 0.02
    variance_factor: bool = True
    min_views: int = 2
    depth_sigma_floor: float = 0.04
    min_depth: float = 0.1
    max_depth: float = 20.0
    max_relative_sigma: float = 0.3

    def __post_init__(self) -> None:
        object.__setattr__(self, "detector", check_choice("detector", self.detector, ("klt", "orb", "sift")))
        if self.max_features is None:
            object.__setattr__(self, "max_features", 800 if self.detector == "klt" else 3000)
        rules = {"max_features": Int(8), "klt_window": Int(5), "klt_levels": Int(0), "min_views": Int(2)}
        rules.update(ratio=Real(0.0, 1.0, low_open=True), min_parallax_deg=Real(0.0, 90.0, high_open=True, unit="deg"))
        positives = ("max_epipolar_error", "max_reprojection_error", "pixel_sigma", "max_depth", "max_relative_sigma")
        positives += ("rotation_sigma_deg", "translation_sigma", "min_corner_distance", "sift_contrast_threshold")
        positives += ("refine_rotation_sigma_deg", "refine_translation_sigma")
        rules.update({name: positive() for name in positives})
        rules.update(klt_fb_error=non_negative(), depth_sigma_floor=non_negative(), min_depth=non_negative("m"))
        rules.update(refine_below=Real(0.0, 1.0, unit="a share"), refine_poses=Bool(), variance_factor=Bool())
        check_fields(self, rules)
        if not 0 <= self.min_depth < self.max_depth:
            raise InvalidInputError("min_depth", f"0 <= min_depth < max_depth ({self.max_depth})", self.min_depth)
