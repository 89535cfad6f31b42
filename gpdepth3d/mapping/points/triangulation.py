"""Sparse depth from posed RGB frames: feature tracks over several views, triangulated with honest sigmas.

Given posed RGB frames (``T_world_camera``, e.g. from a SLAM system) and intrinsics:

* **Tracks** (`build_tracks`, `TrackTriangulator`): by default Shi-Tomasi corners followed with
  pyramidal Lucas-Kanade (OpenCV, forward-backward checked; sub-pixel), one tracking step per
  frame in a stream (`TrackTriangulator`) or outward from a reference frame through a batch of
  frames (`triangulate_frames`); or ORB / SIFT descriptors matched from the reference to every
  other frame (ratio test, mutual best, loose epipolar gate around the given poses).
* **Multi-view triangulation** (`triangulate_tracks`): each track's inverse depth along its
  reference ray from all its views: a linear multi-view DLT in inverse-depth form (iteratively
  reweighted), then a robust (Cauchy) bundle adjustment of the depths jointly with every
  neighbour's pose relative to the reference, around the given poses with a Gaussian prior
  (``refine_poses``, the default: a Levenberg-Marquardt with the depths eliminated by their Schur
  complement); observations off by more than ``max_reprojection_error`` pixels are dropped and the
  problem solved again. The tracks fix the relative rotations well and the prior (``rotation_sigma_deg``,
  ``translation_sigma``: loose enough for a SLAM or VIO back-end's poses) holds the metric scale.
  With ``refine_poses=False`` the poses are held and the tracks are independent 1-D problems
  (compiled loops, numba), which suits exact poses only.
* **Sigma**: pixel noise (the larger of ``pixel_sigma`` and the noise the residuals show) and
  the poses' uncertainty propagated to the inverse depth through the Gauss-Newton information
  (refined poses: the Schur complement, so the uncertainty all points share reaches each depth;
  held poses: the prior); with ``variance_factor`` the whole variance is scaled by
  (residual noise / ``pixel_sigma``)^2 when the residuals are larger than the assumed pixel noise;
  a relative floor ``depth_sigma_floor`` is added in quadrature. ``MultiViewPoints.pose_displacement``
  says how far the given poses move the tracks' points across the neighbours' images beyond keypoint
  noise: the `Mapper` widens the points it carries between frames by it, and calibrates the sigma of
  its points against the local map's (`gpdepth3d.mapping.point_calibration`).

Accuracy on the shared sequences, with exact and perturbed poses (points per frame, +-2 sigma
coverage against the sensor depth): see docs/results.md.

Modules: `triangulation_config` (options), `features` (detection, matching), `tracks` (KLT and
descriptor tracks, the streaming `TrackTriangulator`), `multiview` (`triangulate_tracks`),
`two_view` (`triangulate_matches`, `triangulate_pair`); this module re-exports their public names.

The two-view functions triangulate one pair with ``cv2.triangulatePoints`` and propagate
``pixel_sigma`` through the DLT (central differences), checking cheirality, reprojection error
and parallax.
"""

from .features import Features as Features
from .features import detect_features as detect_features
from .features import fundamental_from_poses as fundamental_from_poses
from .features import match_features as match_features
from .features import sampson_distance as sampson_distance
from .multiview import MultiViewPoints as MultiViewPoints
from .multiview import triangulate_tracks as triangulate_tracks
from .tracks import TrackTriangulator as TrackTriangulator
from .tracks import build_tracks as build_tracks
from .tracks import triangulate_frames as triangulate_frames
from .triangulation_config import TriangulationConfig as TriangulationConfig
from .two_view import TriangulatedPoints as TriangulatedPoints
from .two_view import triangulate_matches as triangulate_matches
from .two_view import triangulate_pair as triangulate_pair
