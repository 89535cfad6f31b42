"""Deprecated: `gpdepth3d.experiments` split in two (kept for one release).

The product's runners moved to `gpdepth3d.pipelines` (`mapping_run`, `batch`, `previews`, `demo`,
`frames`, `scoring`), the paper's protocols to `gpdepth3d.evaluation` (`evaluation`,
`kitti_protocol`, `baselines`) and the synthetic scenes to `gpdepth3d.datasets.synthetic`. Each old
module path still imports, as the new module itself, with a DeprecationWarning naming the new place
(`gpdepth3d._deprecation.MOVED_MODULES`).
"""

from .._deprecation import warn_moved

warn_moved("gpdepth3d.experiments", "gpdepth3d.pipelines and gpdepth3d.evaluation")
