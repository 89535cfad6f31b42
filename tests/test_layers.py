"""The package layout: each folder one layer, imports point down only, no import cycle.

Every module under gpdepth3d/ is parsed with `ast` (nothing is imported): every import
statement counts, at module level, inside functions and under ``if TYPE_CHECKING``, relative or
absolute. Layer ranks (docs/architecture.md, "Layers"): errors 0; camera, measurements, sampling, metrics,
io, depthmap 1; mde, datasets 2; gp 3 (and gp may import only errors); completion 4; mapping 5;
experiments 6; cli, viewer 7; the package's own ``__init__`` (the public re-exports) 8.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "gpdepth3d"
PACKAGE = "gpdepth3d"

RANKS: dict[str, int] = {
    "errors": 0,
    "camera": 1,
    "measurements": 1,
    "sampling": 1,
    "metrics": 1,
    "io": 1,
    "limits": 1,
    "depthmap": 1,
    "extras": 1,
    "mde": 2,
    "datasets": 2,
    "gp": 3,
    "completion": 4,
    "mapping": 5,
    "experiments": 6,
    "pipelines": 6,
    "cli": 7,
    "viewer": 7,
}
ROOT_RANK = 8
GP_MAY_IMPORT = {"errors", "gp"}


def module_names(package_dir: Path) -> dict[str, Path]:
    """Dotted name of every module of the package (``pkg.sub`` for ``pkg/sub/__init__.py``) -> file."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = [package_dir.name, *path.relative_to(package_dir).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def _resolve(name: str, known: set[str]) -> str | None:
    """The module an imported dotted name lives in: the longest known prefix (None: outside the package)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        candidate = ".".join(parts[:i])
        if candidate in known:
            return candidate
    return None


def imports_of(module: str, path: Path, known: set[str]) -> list[tuple[str, int]]:
    """(imported module of the package, line) for every import statement of one module file."""
    is_package = path.name == "__init__.py"
    package = module.split(".") if is_package else module.split(".")[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _resolve(alias.name, known)
                if target is not None:
                    found.append((target, node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if node.level - 1 > len(package) - 1:
                    raise ValueError(f"{path}:{node.lineno}: relative import beyond the package")
                base = package[: len(package) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:  # `from pkg import submodule` imports the submodule
                target = _resolve(f"{source}.{alias.name}", known) if alias.name != "*" else None
                if target is None or target == _resolve(source, known):
                    target = _resolve(source, known)
                if target is not None:
                    found.append((target, node.lineno))
    return found


def import_graph(package_dir: Path) -> dict[str, list[tuple[str, int]]]:
    """Module -> the package's modules it imports (with the line), self-imports left out."""
    names = module_names(package_dir)
    known = set(names)
    return {m: [(t, line) for t, line in imports_of(m, p, known) if t != m] for m, p in names.items()}


def layer(module: str) -> tuple[str, int]:
    """(layer name, rank) of a dotted module name of the package."""
    parts = module.split(".")
    if len(parts) == 1:
        return PACKAGE, ROOT_RANK
    if parts[1] not in RANKS:
        raise KeyError(f"{module} belongs to no layer: add it to a layer folder or to RANKS (docs/architecture.md)")
    return parts[1], RANKS[parts[1]]


def layer_violations(graph: dict[str, list[tuple[str, int]]]) -> list[str]:
    """Every import from a lower layer to a higher one (and from gp to anything but errors)."""
    bad = []
    for module, targets in graph.items():
        name, rank = layer(module)
        for target, line in targets:
            tname, trank = layer(target)
            if trank > rank:
                bad.append(f"{module}:{line} imports {target} (layer {tname}, rank {trank} > {name}'s {rank})")
            elif name == "gp" and tname not in GP_MAY_IMPORT:
                bad.append(f"{module}:{line} imports {target}: gp may import only errors")
    return bad


def find_cycle(graph: dict[str, list[tuple[str, int]]]) -> list[str] | None:
    """One import cycle as [m0, m1, ..., m0], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    stack: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        stack.append(module)
        for target, _ in graph.get(module, ()):
            if state.get(target) == 1:
                return stack[stack.index(target) :] + [target]
            if target not in state:
                cycle = visit(target)
                if cycle:
                    return cycle
        stack.pop()
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state:
            cycle = visit(module)
            if cycle:
                return cycle
    return None


# ------------------------------------------------------------------------------------ the real package
def test_every_module_is_in_a_layer():
    for module in module_names(PACKAGE_DIR):
        layer(module)  # raises for a module outside the layers


def test_no_import_points_up():
    assert layer_violations(import_graph(PACKAGE_DIR)) == []


def test_no_import_cycle():
    assert find_cycle(import_graph(PACKAGE_DIR)) is None


def test_the_graph_sees_known_edges():
    """The parser finds module-level, function-level, relative and `from . import` edges of the real tree."""
    graph = {m: {t for t, _ in ts} for m, ts in import_graph(PACKAGE_DIR).items()}
    assert "gpdepth3d.gp.model" in graph["gpdepth3d.completion.complete"]  # module level, relative
    assert "gpdepth3d.completion.fit" in graph["gpdepth3d.completion.complete"]  # inside a method
    assert "gpdepth3d.mde" in graph["gpdepth3d.cli.fuse"]  # inside a function (load_frontend)
    assert {"gpdepth3d.datasets", "gpdepth3d.completion.complete"} <= graph["gpdepth3d.experiments.batch"]
    assert (
        "gpdepth3d.errors" in graph["gpdepth3d.gp.fit"]
        and "gpdepth3d.completion.problem" not in graph["gpdepth3d.gp.fit"]
    )


# ------------------------------------------------------------------------------------ a fake tree
def _tree(root: Path, files: dict[str, str]) -> Path:
    pkg = root / PACKAGE
    for rel, text in files.items():
        path = pkg / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text), encoding="utf-8")
    return pkg


CLEAN = {
    "__init__.py": "from .completion.complete import complete as complete\n",
    "errors.py": "class GPDepthError(Exception):\n    pass\n",
    "camera.py": "from .errors import GPDepthError\n",
    "measurements.py": "from .camera import GPDepthError\n",
    "gp/__init__.py": "",
    "gp/model.py": "from ..errors import GPDepthError\n",
    "completion/__init__.py": "",
    "completion/complete.py": "from ..gp.model import GPDepthError\nfrom ..measurements import GPDepthError as E\n",
    "mapping/__init__.py": "",
    "mapping/cloud.py": "import gpdepth3d.completion.complete\n",
}


def test_fake_tree_clean(tmp_path):
    graph = import_graph(_tree(tmp_path, CLEAN))
    assert layer_violations(graph) == [] and find_cycle(graph) is None
    assert {t for t, _ in graph["gpdepth3d.mapping.cloud"]} == {"gpdepth3d.completion.complete"}


@pytest.mark.parametrize(
    "rel, code, expected",
    [
        # a function-level relative import from gp up to completion
        (
            "gp/model.py",
            "def f():\n    from ..completion.complete import complete\n",
            "gp.model:3 imports gpdepth3d.completion.complete",
        ),
        # an absolute import from completion up to mapping
        (
            "completion/complete.py",
            "import gpdepth3d.mapping.cloud\n",
            "completion.complete:3 imports gpdepth3d.mapping.cloud",
        ),
        # `from .. import x` of a higher package
        ("camera.py", "def f():\n    from . import mapping\n", "camera:3 imports gpdepth3d.mapping"),
        # gp may import nothing but errors, even from a lower layer
        ("gp/model.py", "from ..measurements import GPDepthError\n", "gp may import only errors"),
        # nothing may import the package's public re-exports
        ("mapping/cloud.py", "from gpdepth3d import complete\n", "mapping.cloud:2 imports gpdepth3d (layer"),
    ],
)
def test_fake_tree_upward_import_is_found(tmp_path, rel, code, expected):
    files = dict(CLEAN)
    files[rel] = files.get(rel, "") + code
    bad = layer_violations(import_graph(_tree(tmp_path, files)))
    assert len(bad) == 1 and expected in bad[0], bad


def test_fake_tree_cycle_is_found(tmp_path):
    files = dict(CLEAN)
    files["camera.py"] += "def f():\n    from .measurements import GPDepthError\n"  # same layer: rank allows it
    graph = import_graph(_tree(tmp_path, files))
    assert layer_violations(graph) == []
    cycle = find_cycle(graph)
    assert cycle is not None and set(cycle) == {"gpdepth3d.camera", "gpdepth3d.measurements"} and cycle[0] == cycle[-1]


def test_fake_tree_module_outside_the_layers(tmp_path):
    files = dict(CLEAN)
    files["helpers.py"] = "from .errors import GPDepthError\n"
    with pytest.raises(KeyError, match="helpers belongs to no layer"):
        for module in module_names(_tree(tmp_path, files)):
            layer(module)
