"""Deprecated: `gpdepth3d.experiments.scoring` moved to `gpdepth3d.pipelines.scoring` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import scoring as _new

warn_moved("gpdepth3d.experiments.scoring", "gpdepth3d.pipelines.scoring")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
