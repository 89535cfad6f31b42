"""Monocular depth front-ends and the alignment of relative depth to metric measurements."""

from .align import align_depth as align_depth
from .align import AlignmentResult as AlignmentResult
