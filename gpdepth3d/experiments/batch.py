"""Deprecated: `gpdepth3d.experiments.batch` moved to `gpdepth3d.pipelines.batch` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import batch as _new

warn_moved("gpdepth3d.experiments.batch", "gpdepth3d.pipelines.batch")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
