"""The install: the core carries what `complete` needs, the rest sits behind extras, missing parts are one line."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.errors import GPDepthError
from gpdepth3d.extras import EXTRAS, MissingDependencyError, missing_dependency, require

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
HEAVY = (
    "torch",
    "open3d",
    "viser",
    "gpytorch",
    "linear_operator",
    "trimesh",
    "pycolmap",
    "evo",
    "distributed",
    "ai_edge_litert",
)


def _name(requirement: str) -> str:
    for sep in "<>=!~[; ":
        requirement = requirement.split(sep)[0]
    return requirement.strip().lower()


class TestPackageMetadata:
    def test_no_exact_pin_anywhere(self):
        project = PYPROJECT["project"]
        requirements = list(project["dependencies"])
        for extra in project["optional-dependencies"].values():
            requirements += extra
        assert not [r for r in requirements if "==" in r or "===" in r]

    def test_core_has_no_heavy_package(self):
        core = {_name(r) for r in PYPROJECT["project"]["dependencies"]}
        assert core >= {"numpy", "scipy", "numba", "opencv-python-headless", "pillow", "tyro", "onnxruntime"}
        assert not core & {
            "torch",
            "open3d",
            "viser",
            "gpytorch",
            "linear_operator",
            "trimesh",
            "pycolmap",
            "evo",
            "distributed",
            "ai-edge-litert",
        }

    def test_every_optional_module_is_in_the_extra_it_names(self):
        extras = PYPROJECT["project"]["optional-dependencies"]
        pip_name = {"ai_edge_litert": "ai-edge-litert", "dask": "distributed"}
        for module, names in EXTRAS.items():
            for extra in names:
                assert pip_name.get(module, module) in {_name(r) for r in extras[extra]}, (module, extra)
        (everything,) = extras["all"]
        assert set(everything.split("[")[1].rstrip("]").split(",")) == set(extras) - {"all", "dev"}
        assert "gpdepth3d[all]" in extras["dev"] and "ruff" in {_name(r) for r in extras["dev"]}

    def test_ci_pins_torch_through_a_constraints_file(self):
        constraints = (ROOT / ".ci" / "constraints.txt").read_text(encoding="utf-8")
        assert "torch==" in constraints
        assert "-c .ci/constraints.txt" in (ROOT / "scripts" / "install.sh").read_text(encoding="utf-8")
        assert 'install.sh" dev' in (ROOT / "scripts" / "setup-dev.sh").read_text(encoding="utf-8")


class TestMissingDependency:
    def test_missing_package_names_its_extra(self):
        error = missing_dependency(ModuleNotFoundError("No module named 'open3d'", name="open3d"))
        assert isinstance(error, MissingDependencyError) and isinstance(error, GPDepthError)
        assert "[mapping]" in str(error) and 'pip install "gpdepth3d[mapping]"' in str(error)
        assert "\n" not in str(error)

    def test_open3d_without_libusb_names_the_system_package(self, monkeypatch):
        import importlib

        def no_libusb(name, *args):
            raise OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")

        monkeypatch.setattr(importlib, "import_module", no_libusb)
        with pytest.raises(MissingDependencyError) as info:
            require("open3d")
        assert str(info.value) == (
            "open3d could not be imported: the system library libusb-1.0 is missing (sudo apt-get install libusb-1.0-0)"
        )

    def test_other_errors_are_left_alone(self):
        assert missing_dependency(ModuleNotFoundError("No module named 'nope'", name="nope")) is None
        assert missing_dependency(OSError("disk full")) is None
        assert require("numpy") is np

    def test_the_command_line_says_it_in_one_line(self, monkeypatch, capsys, tmp_path):
        import functools

        import gpdepth3d.cli.fuse as fuse
        from gpdepth3d.cli import main

        @functools.wraps(fuse.fuse_command)  # the parser reads the signature
        def fails(**kwargs):
            raise OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")

        monkeypatch.setattr(fuse, "fuse_command", fails)
        assert main(["fuse", "--data", str(tmp_path)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "libusb-1.0-0" in err[0]


BLOCKER = textwrap.dedent(
    """
    import importlib.abc, sys
    HEAVY = {heavy!r}

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.split(".")[0] in HEAVY:
                raise ModuleNotFoundError(f"No module named {{name!r}} (blocked: not a core dependency)", name=name)
            return None

    sys.meta_path.insert(0, Block())
    from gpdepth3d.cli import main
    code = main(sys.argv[1:])
    loaded = sorted({{m.split(".")[0] for m in sys.modules}} & set(HEAVY))
    print("LOADED", loaded)
    sys.exit(code)
    """
)


@pytest.mark.slow
def test_complete_runs_without_any_extra(tmp_path):
    """`complete` with every optional package made unimportable: exits 0 and loads none of them."""
    rng = np.random.default_rng(0)
    np.save(tmp_path / "mde.npy", 2.0 + 0.1 * rng.random((48, 64)))
    pts = np.stack([rng.integers(0, 64, 40), rng.integers(0, 48, 40), 2.0 + 0.1 * rng.random(40)], 1)
    np.savetxt(tmp_path / "points.txt", pts)
    script = tmp_path / "blocked.py"
    script.write_text(BLOCKER.format(heavy=HEAVY), encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    run = subprocess.run(
        [
            sys.executable,
            str(script),
            "complete",
            "--mde",
            str(tmp_path / "mde.npy"),
            "--sparse",
            str(tmp_path / "points.txt"),
            "--output",
            str(tmp_path / "out" / "f"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr
    assert "LOADED []" in run.stdout and "wrote" in run.stdout
    assert (tmp_path / "out" / "f.npz").is_file() and (tmp_path / "out" / "f_depth_preview.png").is_file()
