"""Deprecated: `gpdepth3d.experiments.kitti_protocol` moved to `gpdepth3d.evaluation.kitti_protocol` (kept for one release)."""

import sys

from .._deprecation import warn_moved
from ..evaluation import kitti_protocol as _new

warn_moved("gpdepth3d.experiments.kitti_protocol", "gpdepth3d.evaluation.kitti_protocol")
sys.modules[__name__] = _new  # the new module itself: every name, and patches, reach one object
