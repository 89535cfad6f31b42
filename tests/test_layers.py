"""The package layout: each folder one layer, imports point down only, no import cycle.

Every module under gpdepth3d/ is parsed with `ast` (nothing is imported): every import
statement counts, at module level, inside functions and under ``if TYPE_CHECKING``, relative or
absolute. Layer ranks (docs/architecture.md, "Layers"): errors, checks 0; camera, measurements, sampling, metrics,
io, depthmap 1; mde, datasets 2; gp 3 (and gp may import only errors and checks); completion 4; mapping 5;
pipelines 6 (what a user runs); evaluation 7 (the paper's protocols; the deprecated `experiments`
shims beside it); cli, viewer 8; the package's own ``__init__`` (the public re-exports) 9.
Of the top, only ``cli.eval`` imports the protocols.
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
    "_deprecation": 0,
    "checks": 0,
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
    "pipelines": 6,
    "evaluation": 7,
    "experiments": 7,
    "cli": 8,
    "viewer": 8,
}
ROOT_RANK = 9
GP_MAY_IMPORT = {"errors", "checks", "gp"}


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
    """Every import from a lower layer to a higher one (and from gp to anything but errors and checks)."""
    bad = []
    for module, targets in graph.items():
        name, rank = layer(module)
        for target, line in targets:
            tname, trank = layer(target)
            if trank > rank:
                bad.append(f"{module}:{line} imports {target} (layer {tname}, rank {trank} > {name}'s {rank})")
            elif name == "gp" and tname not in GP_MAY_IMPORT:
                bad.append(f"{module}:{line} imports {target}: gp may import only errors and checks")
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


# the one import of the protocols from the package's root: the deprecated `gpdepth3d.ip_basic`
ROOT_DEPRECATED_PROTOCOL_IMPORTS = {"gpdepth3d.evaluation.baselines"}


def test_product_imports_no_protocol():
    """`cli` (but `eval`), `viewer` and `pipelines` import nothing of `evaluation`; the root only its deprecated name."""
    graph = import_graph(PACKAGE_DIR)
    for module, targets in graph.items():
        if module.startswith(("gpdepth3d.evaluation", "gpdepth3d.experiments")) or module == "gpdepth3d.cli.eval":
            continue
        into = {t for t, _ in targets if t == "gpdepth3d.evaluation" or t.startswith("gpdepth3d.evaluation.")}
        allowed = ROOT_DEPRECATED_PROTOCOL_IMPORTS if module == PACKAGE else set()
        assert into <= allowed, f"{module} imports protocol code {sorted(into - allowed)}"
    root_lines = [line for t, line in graph[PACKAGE] if t in ROOT_DEPRECATED_PROTOCOL_IMPORTS]
    root_text = (PACKAGE_DIR / "__init__.py").read_text(encoding="utf-8").splitlines()
    assert all(root_text[line - 1].startswith("        ") for line in root_lines), "only inside __getattr__"


def test_nothing_imports_the_deprecated_experiments():
    for module, targets in import_graph(PACKAGE_DIR).items():
        if not module.startswith("gpdepth3d.experiments"):
            assert not [t for t, _ in targets if t.startswith("gpdepth3d.experiments")], module


def test_the_graph_sees_known_edges():
    """The parser finds module-level, function-level, relative and `from . import` edges of the real tree."""
    graph = {m: {t for t, _ in ts} for m, ts in import_graph(PACKAGE_DIR).items()}
    assert "gpdepth3d.gp.model" in graph["gpdepth3d.completion.complete"]  # module level, relative
    assert "gpdepth3d.completion.marginal_fit" in graph["gpdepth3d.completion.formulations"]  # inside a method
    assert "gpdepth3d.mde" in graph["gpdepth3d.pipelines.fuse_run"]  # inside a function (load_frontend)
    assert {"gpdepth3d.datasets", "gpdepth3d.completion.complete"} <= graph["gpdepth3d.pipelines.batch"]
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


def test_library_names_no_bench_file():
    """A wheel ships no `bench/`: the library points at docs/results.md for measured numbers, never at a script."""
    named = [
        f"{path.relative_to(PACKAGE_DIR)}:{i}"
        for path in sorted(PACKAGE_DIR.rglob("*.py"))
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "bench/" in line
    ]
    assert named == []


# ------------------------------------------------------------------------------------ docs/architecture.md
ARCHITECTURE = PACKAGE_DIR.parent / "docs" / "architecture.md"


def _tree_entries(package_dir: Path) -> dict[str, int]:
    """``gpdepth3d/sub/`` for each package, ``gpdepth3d/sub/mod.py`` for each module -> its layer rank."""
    entries = {}
    for module, path in module_names(package_dir).items():
        rel = path.relative_to(package_dir.parent).as_posix()
        name = rel[: -len("__init__.py")] if path.name == "__init__.py" else rel
        entries[name] = layer(module)[1]
    return entries


def _documented_entries(text: str) -> dict[str, int]:
    """The (path, rank) rows of the layout table between its start and end markers."""
    start, end = text.index("<!-- layout table: start -->"), text.index("<!-- layout table: end -->")
    rows = {}
    for line in text[start:end].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith("`gpdepth3d/"):
            assert cells[0].strip("`") not in rows, f"listed twice: {cells[0]}"
            rows[cells[0].strip("`")] = int(cells[1])
    return rows


def test_architecture_table_is_the_tree():
    """docs/architecture.md lists every package and module with its layer, and nothing that does not exist."""
    tree = _tree_entries(PACKAGE_DIR)
    documented = _documented_entries(ARCHITECTURE.read_text(encoding="utf-8"))
    assert sorted(set(tree) - set(documented)) == [], "modules missing from docs/architecture.md"
    assert sorted(set(documented) - set(tree)) == [], "docs/architecture.md lists what does not exist"
    assert {k: v for k, v in documented.items() if tree[k] != v} == {}, "ranks differ from tests/test_layers.py"


def test_architecture_table_check_sees_a_stale_row(tmp_path):
    """The check fails on a fake tree with a module more, or a row for a module that is gone."""
    pkg = _tree(tmp_path, CLEAN)
    entries = _tree_entries(pkg)
    assert entries["gpdepth3d/"] == ROOT_RANK and entries["gpdepth3d/mapping/cloud.py"] == RANKS["mapping"]
    table = "\n".join(f"| `{k}` | {v} | x |" for k, v in entries.items())
    text = f"<!-- layout table: start -->\n{table}\n<!-- layout table: end -->"
    assert _documented_entries(text) == entries
    stale = text.replace("| `gpdepth3d/camera.py` | 1 | x |", "| `gpdepth3d/kamera.py` | 1 | x |")
    assert set(_documented_entries(stale)) ^ set(entries) == {"gpdepth3d/camera.py", "gpdepth3d/kamera.py"}
