"""docs/cli.md is what `python docs/make_cli.py` writes: every command, every option, the exit codes."""

from __future__ import annotations

import importlib.util
import inspect
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _make_cli():
    spec = importlib.util.spec_from_file_location("make_cli", ROOT / "docs" / "make_cli.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_page_regenerates_identically():
    assert (ROOT / "docs" / "cli.md").read_text(encoding="utf-8") == _make_cli().render(), (
        "docs/cli.md is out of date: run python docs/make_cli.py"
    )


def test_every_command_and_option_is_on_the_page():
    import dataclasses

    from gpdepth3d.cli._main import _commands
    from gpdepth3d.gp.engine import EngineConfig
    from gpdepth3d.gp.model import DepthGPConfig

    text = _make_cli().render()
    for name, function in _commands().items():
        assert f"## `gpdepth3d {name}`" in text
        for param in inspect.signature(function).parameters:
            flag = "--preset" if param == "gp" else "--" + param.replace("_", "-")
            assert f"`{flag}" in text, (name, flag)
    for field in dataclasses.fields(DepthGPConfig):
        value = getattr(DepthGPConfig(), field.name)
        names = (
            [f"{field.name}.{f.name}" for f in dataclasses.fields(value)]
            if dataclasses.is_dataclass(value)
            else [field.name]
        )
        for n in names:
            assert f"`--gp.{n.replace('_', '-')}`" in text, n
    for field in dataclasses.fields(EngineConfig):
        assert f"`--engine.{field.name.replace('_', '-')}`" in text, field.name
    assert "## Exit codes" in text and "| 1 |" in text
