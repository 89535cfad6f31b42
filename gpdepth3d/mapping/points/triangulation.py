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
  (a robust bundle adjustment with a Gaussian pose prior, solved by `scipy.optimize.least_squares`). With the
  poses held (the default) the tracks are independent 1-D problems, solved by compiled loops
  (numba; ~2 ms for the ~350 tracks of a 7-Scenes frame with 12 views, 12 ms as numpy arrays).
* **Sigma**: pixel noise (the larger of ``pixel_sigma`` and the noise the residuals show) and
  the poses' uncertainty (``rotation_sigma_deg``, ``translation_sigma`` per axis, relative to
  the reference) propagated to the inverse depth through the Gauss-Newton information; with
  ``variance_factor`` the whole variance is scaled by (residual noise / ``pixel_sigma``)^2 when
  the residuals are larger than the assumed pixel noise (inconsistent poses in a frame then
  widen every sigma of that frame); a relative floor ``depth_sigma_floor`` is added in quadrature.

Accuracy on the shared sequences (points per frame, +-2 sigma coverage against the sensor depth):
see docs/results.md; what limits it is the given poses (the residuals show them
a few pixels off), so the pose uncertainty goes into sigma rather than into a per-frame pose
refinement (``refine_poses``, off by default: it made the depth worse).

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
