"""Thin commands: `complete` and `map` parse, call the library (`read_frame_inputs` + `run_complete`,
`open_map_inputs` + `map_files`, themselves or through the module's private helpers) and print; their code after
the docstring is at most 60 lines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

CLI = Path(__file__).resolve().parents[2] / "gpdepth3d" / "cli"


@pytest.mark.parametrize(
    "module, command, calls",
    [
        ("complete.py", "complete_command", {"read_frame_inputs", "run_complete", "plan_outputs"}),
        ("map.py", "map_command", {"open_map_inputs", "map_files"}),
    ],
)
def test_command_is_thin_and_calls_the_library(module, command, calls):
    tree = ast.parse((CLI / module).read_text(encoding="utf-8"))
    function = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == command)
    body = function.body[1:] if isinstance(function.body[0], ast.Expr) else function.body  # after the docstring
    assert function.end_lineno - body[0].lineno + 1 <= 60
    helpers = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("_")}
    called = _called(function)
    for name in called & set(helpers):
        called |= _called(helpers[name])
    assert calls <= called


def _called(function: ast.FunctionDef) -> set[str]:
    """The names a function calls directly."""
    return {n.func.id for n in ast.walk(function) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
