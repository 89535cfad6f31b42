"""Moved modules and names: the old dotted paths keep importing for one release, with a DeprecationWarning.

`MOVED_MODULES` is the one table of old module path -> new module path. `install` (called by the
package's ``__init__``) puts a finder at the end of ``sys.meta_path`` that answers only those old
paths: ``import gpdepth3d.mapping.fusion`` gives the module ``gpdepth3d.mapping.tsdf.fusion`` itself
(every name, and a test's patches, reach one object) and warns once, naming the new place. No file
stays at an old path, so history and merges follow the moved files.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

MOVED_MODULES: dict[str, str] = {
    "gpdepth3d.experiments.mapping_run": "gpdepth3d.pipelines.mapping_run",
    "gpdepth3d.experiments.batch": "gpdepth3d.pipelines.batch",
    "gpdepth3d.experiments.previews": "gpdepth3d.pipelines.previews",
    "gpdepth3d.experiments.demo": "gpdepth3d.pipelines.demo",
    "gpdepth3d.experiments.frames": "gpdepth3d.pipelines.frames",
    "gpdepth3d.experiments.scoring": "gpdepth3d.pipelines.scoring",
    "gpdepth3d.experiments.evaluation": "gpdepth3d.evaluation.evaluation",
    "gpdepth3d.experiments.kitti_protocol": "gpdepth3d.evaluation.kitti_protocol",
    "gpdepth3d.experiments.baselines": "gpdepth3d.evaluation.baselines",
    "gpdepth3d.experiments.synthetic": "gpdepth3d.datasets.synthetic",
    "gpdepth3d.mapping.trajectories": "gpdepth3d.io.poses",
    "gpdepth3d.mapping.fusion": "gpdepth3d.mapping.tsdf.fusion",
    "gpdepth3d.mapping.fusion_config": "gpdepth3d.mapping.tsdf.fusion_config",
    "gpdepth3d.mapping.fusion_weights": "gpdepth3d.mapping.tsdf.fusion_weights",
    "gpdepth3d.mapping.triangulation": "gpdepth3d.mapping.points.triangulation",
    "gpdepth3d.mapping.triangulation_config": "gpdepth3d.mapping.points.triangulation_config",
    "gpdepth3d.mapping.refinding": "gpdepth3d.mapping.points.refinding",
    "gpdepth3d.mapping.local_map": "gpdepth3d.mapping.points.local_map",
    "gpdepth3d.mapping.colmap_points": "gpdepth3d.mapping.points.colmap_points",
    "gpdepth3d.mapping.map_points": "gpdepth3d.mapping.points.map_points",
}
"""Old module path -> new module path of every module moved in this release (removed in the next)."""


def warn_moved(old: str, new: str, *, stacklevel: int = 3) -> None:
    """Warn that ``old`` moved to ``new`` and will go in the next release.

    Args:
        old: the deprecated dotted name, as the user wrote it.
        new: where it lives now (dotted name, or a short phrase naming the new places).
        stacklevel: the frame the warning points at (3: the caller of the function that warns).
    """
    warnings.warn(
        f"{old} is deprecated and will be removed in the next release; use {new}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


class _MovedModuleLoader(importlib.abc.Loader):
    """Loads an old module path as the new module itself (the import system then files it under the old name)."""

    def __init__(self, old: str, new: str) -> None:
        self.old, self.new = old, new
        self._spec = None

    def create_module(self, spec):
        warn_moved(self.old, self.new, stacklevel=3)  # 3: past this method, to the importing line
        module = importlib.import_module(self.new)
        self._spec = module.__spec__
        return module

    def exec_module(self, module) -> None:
        module.__spec__ = self._spec  # the import system set the alias's spec on the real module: undo it


class _MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds only the old paths of `MOVED_MODULES`; every other name is left to the normal finders."""

    def find_spec(self, fullname, path=None, target=None):
        new = MOVED_MODULES.get(fullname)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _MovedModuleLoader(fullname, new))


def install() -> None:
    """Put the finder of moved modules at the end of ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedModuleFinder())
