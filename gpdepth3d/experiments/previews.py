"""Deprecated: `gpdepth3d.experiments.previews` moved to `gpdepth3d.pipelines.previews` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import previews as _new

warn_moved("gpdepth3d.experiments.previews", "gpdepth3d.pipelines.previews")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
