"""Deprecated: `gpdepth3d.experiments.mapping_run` moved to `gpdepth3d.pipelines.mapping_run` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import mapping_run as _new

warn_moved("gpdepth3d.experiments.mapping_run", "gpdepth3d.pipelines.mapping_run")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
