"""Deprecated: `gpdepth3d.experiments.baselines` moved to `gpdepth3d.evaluation.baselines` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..evaluation import baselines as _new

warn_moved("gpdepth3d.experiments.baselines", "gpdepth3d.evaluation.baselines")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
