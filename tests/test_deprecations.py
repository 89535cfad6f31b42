"""Moved public names keep working for one release, with a DeprecationWarning naming the new place."""

from __future__ import annotations

import importlib
import sys

import pytest

import gpdepth3d

MOVED_MODULES = {
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


def _fresh_import(name: str):
    """Import ``name`` as a first import would (the shim warns when it runs, not when it is cached)."""
    for key in [k for k in sys.modules if k == name or k.startswith("gpdepth3d.experiments") or k in MOVED_MODULES]:
        del sys.modules[key]
    return importlib.import_module(name)


@pytest.mark.filterwarnings("ignore:gpdepth3d.experiments is deprecated")
@pytest.mark.parametrize("old, new", sorted(MOVED_MODULES.items()))
def test_old_module_path_is_the_new_module(old, new):
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")) as record:
        shim = _fresh_import(old)
    module = importlib.import_module(new)
    assert shim is module and sys.modules[old] is module
    assert module.__spec__.name == new, "the moved module keeps its own spec"
    assert any(old in str(w.message) for w in record)


def test_old_from_import_reaches_the_same_objects():
    _fresh_import("gpdepth3d.experiments")
    with pytest.warns(DeprecationWarning) as record:
        from gpdepth3d.experiments.mapping_run import map_sequence
        from gpdepth3d.experiments.synthetic import make_scene
    assert {w.filename for w in record} == {__file__}, "each warning points at the line that imports"
    from gpdepth3d.datasets.synthetic import make_scene as new_make_scene
    from gpdepth3d.pipelines.mapping_run import map_sequence as new_map_sequence

    assert map_sequence is new_map_sequence and make_scene is new_make_scene


def test_old_package_warns():
    with pytest.warns(DeprecationWarning, match=r"gpdepth3d\.pipelines and gpdepth3d\.evaluation"):
        _fresh_import("gpdepth3d.experiments")


def test_root_ip_basic_is_deprecated():
    from gpdepth3d.evaluation.baselines import ip_basic

    with pytest.warns(DeprecationWarning, match=r"gpdepth3d\.evaluation\.baselines\.ip_basic"):
        assert gpdepth3d.ip_basic is ip_basic
    with pytest.raises(AttributeError, match="no_such_name"):
        gpdepth3d.no_such_name  # noqa: B018


def test_importing_the_package_warns_nothing():
    """Only the old paths warn: the package and its new modules import without a DeprecationWarning."""
    import subprocess

    code = (
        "import warnings; warnings.simplefilter('error'); "
        "import gpdepth3d, gpdepth3d.pipelines.batch, gpdepth3d.evaluation.evaluation"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_table_is_the_package_s():
    """The test's table is the package's own, every new path imports, and no file stays at an old path."""
    from pathlib import Path

    from gpdepth3d._deprecation import MOVED_MODULES as TABLE

    assert TABLE == MOVED_MODULES
    root = Path(gpdepth3d.__file__).parent.parent
    for old, new in TABLE.items():
        assert not (root / (old.replace(".", "/") + ".py")).exists(), old
        importlib.import_module(new)


def test_unknown_old_path_still_fails():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("gpdepth3d.mapping.no_such_module")
