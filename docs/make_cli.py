"""Writes docs/cli.md from the commands' signatures and docstrings: ``python docs/make_cli.py``.

The page is what ``gpdepth3d COMMAND --help`` prints, in one place: each command's description, every option
with its type, default and meaning, the GP fields of ``--gp.FIELD``, the engine options of ``--engine.FIELD``, and
the exit codes. tests/cli/test_cli_docs.py
regenerates it and fails when it differs.
"""

from __future__ import annotations

import dataclasses
import inspect
import sys
import typing
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUTPUT = REPO / "docs" / "cli.md"

EXIT_CODES = """| code | meaning |
|---|---|
| 0 | done; the command listed every file it wrote |
| 1 | an error, printed as one line `gpdepth3d: error: ...` naming the option or file: a bad command line, bad input, a missing file or optional dependency (with the extra or system package that provides it), a failed frame in `batch`; nothing half-written is left behind |
| 130 | interrupted (Ctrl-C) |"""


def _type_name(annotation) -> str:
    """A short, readable spelling of a parameter's type."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " | ".join(str(a) for a in args)
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        names = [_type_name(a) for a in args if a is not type(None)]
        return " | ".join(names) + (" (optional)" if type(None) in args else "")
    if origin in (tuple, typing.Tuple):
        if len(args) == 2 and args[1] is Ellipsis:
            return f"{_type_name(args[0])} ..."
        return " ".join(_type_name(a) for a in args)
    if origin is typing.Annotated:
        return _type_name(args[0])
    return {Path: "PATH", str: "TEXT", int: "INT", float: "FLOAT", bool: "flag"}.get(
        annotation, getattr(annotation, "__name__", str(annotation))
    )


def _default(value) -> str:
    if value is inspect.Parameter.empty:
        return "required"
    if isinstance(value, tuple) and not value:
        return "none"
    if dataclasses.is_dataclass(value):
        return "`default`"
    return f"`{value}`"


def _doc(obj) -> tuple[str, dict[str, str]]:
    """The description (before ``Args:``) and the per-argument help of a Google docstring."""
    from docstring_parser import parse

    doc = parse(inspect.getdoc(obj) or "")
    text = "\n\n".join(p for p in (doc.short_description, doc.long_description) if p)
    return text, {p.arg_name: " ".join((p.description or "").split()) for p in doc.params}


def _option(name: str, annotation, default) -> str:
    flag = "--" + name.replace("_", "-")
    if annotation is bool or default is True or default is False:
        return f"`{flag}`, `--no-{name.replace('_', '-')}`"
    return f"`{flag} {_type_name(annotation)}`"


def command_section(name: str, function) -> str:
    """One command: its description, then a table of its options."""
    from gpdepth3d.cli._options import WITH_PRESET

    description, helps = _doc(function)
    hints = typing.get_type_hints(function, include_extras=True)
    rows = []
    for pname, param in inspect.signature(function).parameters.items():
        annotation = hints.get(pname, str)
        if pname == "gp":
            rows.append(["`--preset default|paper|residual`", "`default`", helps.get(pname, "")])
            continue
        if pname == "engine":
            rows.append(["`--engine.FIELD VALUE`", "`EngineConfig()`", helps.get(pname, "") + " See *Engine options*."])
            continue
        rows.append([_option(pname, annotation, param.default), _default(param.default), helps.get(pname, "")])
    lines = [f"## `gpdepth3d {name}`", "", description, "", "| option | default | meaning |", "|---|---|---|"]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in r) + " |" for r in rows]
    if name in WITH_PRESET:
        lines += ["", "The GP: `--preset default|paper|residual`, then `--gp.FIELD VALUE` (see *GP fields* below)."]
    return "\n".join(lines)


def gp_section() -> str:
    """The fields of `DepthGPConfig`, spelled ``--gp.FIELD``, with the default preset's values."""
    from gpdepth3d.cli._options import PRESETS

    _, helps = _doc(type(PRESETS["default"]))
    lines = [
        "## GP fields (`--gp.FIELD`)",
        "",
        "For `complete`, `fuse` and `batch`. Defaults of each preset: `default` is `DepthGPConfig()`, `paper` "
        "`DepthGPConfig.paper()`, `residual` `DepthGPConfig.residual()`.",
        "",
        "| option | default | paper | residual | meaning |",
        "|---|---|---|---|---|",
    ]
    for field in dataclasses.fields(PRESETS["default"]):
        value = getattr(PRESETS["default"], field.name)
        if not dataclasses.is_dataclass(value):
            values = [f"`{getattr(PRESETS[p], field.name)}`" for p in ("default", "paper", "residual")]
            lines.append(_row(f"--gp.{field.name}", values, helps.get(field.name, "")))
            continue
        _, nested_helps = _doc(type(value))  # a nested config: one row per field, --gp.SECTION.FIELD
        for inner in dataclasses.fields(value):
            values = [
                f"`{getattr(getattr(PRESETS[p], field.name), inner.name)}`" for p in ("default", "paper", "residual")
            ]
            lines.append(_row(f"--gp.{field.name}.{inner.name}", values, nested_helps.get(inner.name, "")))
    return "\n".join(lines)


def engine_section() -> str:
    """The fields of `EngineConfig`, spelled ``--engine.FIELD``, with their defaults."""
    from gpdepth3d.gp.engine import EngineConfig

    _, helps = _doc(EngineConfig)
    lines = [
        "## Engine options (`--engine.FIELD`)",
        "",
        "For `complete` and `batch`: how the posterior is computed (`gpdepth3d.gp.EngineConfig`), not the model.",
        "",
        "| option | default | meaning |",
        "|---|---|---|",
    ]
    for field in dataclasses.fields(EngineConfig()):
        lines.append(
            _row(f"--engine.{field.name}", [f"`{getattr(EngineConfig(), field.name)}`"], helps.get(field.name, ""))
        )
    return "\n".join(lines)


def _row(flag: str, values: list[str], meaning: str) -> str:
    """One table row: the option, its value(s), its meaning (``|`` escaped)."""
    cells = [f"`{flag.replace('_', '-')}`", *values, meaning]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def render() -> str:
    """The whole of docs/cli.md."""
    from gpdepth3d.cli._main import _commands

    functions = _commands()
    parts = [
        "# Command line",
        "Generated by `python docs/make_cli.py` from the commands' signatures and docstrings (what "
        "`gpdepth3d COMMAND --help` prints). One vocabulary in every command: `--output` is what it writes (a base "
        "name for `complete`, a folder for the others), `--mde NAME|FILE` the monocular front-end, `--preset` and "
        "`--gp.FIELD` the GP, `--frames` a cap on the frames. Every command ends by listing what it wrote.",
        "## Exit codes\n\n" + EXIT_CODES,
    ]
    parts += [command_section(name, function) for name, function in functions.items()]
    parts.append(gp_section())
    parts.append(engine_section())
    return "\n\n".join(parts) + "\n"


def main() -> int:
    text = render()
    if "--check" in sys.argv[1:]:
        same = OUTPUT.is_file() and OUTPUT.read_text(encoding="utf-8") == text
        print("docs/cli.md is up to date" if same else "docs/cli.md differs: run python docs/make_cli.py")
        return 0 if same else 1
    OUTPUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUTPUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
