"""Deprecated: `gpdepth3d.experiments.evaluation` moved to `gpdepth3d.evaluation.evaluation` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..evaluation import evaluation as _new

warn_moved("gpdepth3d.experiments.evaluation", "gpdepth3d.evaluation.evaluation")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
