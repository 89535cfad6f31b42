"""Deprecated: `gpdepth3d.mapping.trajectories` moved to `gpdepth3d.io.poses` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..io import poses as _new

warn_moved("gpdepth3d.mapping.trajectories", "gpdepth3d.io.poses")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
