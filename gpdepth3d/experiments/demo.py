"""Deprecated: `gpdepth3d.experiments.demo` moved to `gpdepth3d.pipelines.demo` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..pipelines import demo as _new

warn_moved("gpdepth3d.experiments.demo", "gpdepth3d.pipelines.demo")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
