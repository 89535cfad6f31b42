"""Deprecated: `gpdepth3d.experiments.frames` moved to `gpdepth3d.pipelines.frames` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import frames as _new

warn_moved("gpdepth3d.experiments.frames", "gpdepth3d.pipelines.frames")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
