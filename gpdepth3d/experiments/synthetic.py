"""Deprecated: `gpdepth3d.experiments.synthetic` moved to `gpdepth3d.datasets.synthetic` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..datasets import synthetic as _new

warn_moved("gpdepth3d.experiments.synthetic", "gpdepth3d.datasets.synthetic")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
