"""The ``gpdepth3d`` entry point: one subcommand per module of `gpdepth3d.cli`, errors as one line.

Every command prints what it wrote. A `GPDepthError` (bad input, missing or corrupt file)
becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings

import tyro

from ..errors import GPDepthError, did_you_mean
from ..extras import missing_dependency
from ._warnings import _one_line_warning, quiet_third_party


def _commands() -> dict:
    """Each subcommand's name -> its function, in the order `gpdepth3d --help` lists them."""
    from .batch import batch_command
    from .complete import complete_command
    from .demo import demo_command
    from .eval import eval_command
    from .fuse import fuse_command
    from .map import map_command
    from .view import view_command

    commands = {
        "demo": demo_command,
        "complete": complete_command,
        "eval": eval_command,
        "fuse": fuse_command,
        "map": map_command,
        "view": view_command,
        "batch": batch_command,
    }
    return commands


class CommandLineError(GPDepthError):
    """The command line does not parse: an unknown option, a missing one or a bad value."""


def _flags(argument) -> str:
    """The spelling of a tyro argument on the command line (``--mde``, or its metavar when positional)."""
    lowered = getattr(argument, "lowered", None)
    names = getattr(lowered, "name_or_flags", None) or ()
    return "/".join(names) if names else str(getattr(lowered, "metavar", None) or "an argument")


def known_flags(command: str | None) -> list[str]:
    """Every option of a subcommand as spelt on the command line (``--output``, ``--gp.fit``), for suggestions."""
    import dataclasses
    import inspect

    from ..gp.engine import EngineConfig
    from ._options import PRESETS

    function = _commands().get(command or "")
    if function is None:
        return [f"{name}" for name in _commands()]
    flags = []
    for name in inspect.signature(function).parameters:
        if name == "gp":
            flags.append("--preset")
            for f in dataclasses.fields(PRESETS["default"]):
                value = getattr(PRESETS["default"], f.name)
                inner = (
                    [f"{f.name}.{g.name}" for g in dataclasses.fields(value)] if dataclasses.is_dataclass(value) else []
                )
                flags += [f"--gp.{n.replace('_', '-')}" for n in [f.name, *inner]]
        elif name == "engine":
            flags += [f"--engine.{f.name.replace('_', '-')}" for f in dataclasses.fields(EngineConfig)]
        else:
            flags.append("--" + name.replace("_", "-"))
    return flags


def describe_parse_error(event, command: str | None = None) -> str:
    """One line for a tyro parse-failure event (its structured fields, no rendered text), naming the option.

    Args:
        event: The event tyro passes to its parse-error hook.
        command: The subcommand being parsed (for the help hint), if known.
    """
    from ._options import PRESETS

    kind = type(event).__name__
    prog = f"gpdepth3d {command}" if command else "gpdepth3d"
    if kind == "MissingArgs":
        text = f"{prog}: missing {', '.join(_flags(a.arg) for a in event.missing_arguments)}"
        if event.unrecognized_tokens:
            text += f"; unrecognised {' '.join(event.unrecognized_tokens)}"
            text += did_you_mean(event.unrecognized_tokens[0].split("=")[0], known_flags(command))
    elif kind == "UnrecognizedArgs":
        text = f"{prog}: unrecognised {' '.join(event.tokens)}"
        text += did_you_mean(event.tokens[0].split("=")[0], known_flags(command)) if event.tokens else ""
    elif kind == "InvalidChoice":
        text = f"{_flags(event.argument)}: expected one of {', '.join(event.choices)}, got {event.value}"
    elif kind == "BadValue":
        got = event.offending_value if event.offending_value is not None else "too few values"
        text = f"{_flags(event.argument)}: {got}"
    elif kind == "InstantiationFailure":
        message = str(event.message)
        if event.argument is not None:
            text = f"{_flags(event.argument)}: {message}"
        elif message.split(":")[0] in vars(PRESETS["default"]):  # a GP config field refused its value
            text = f"--gp.{message}"
        else:
            text = message
    elif kind == "MissingSubcommand":
        found = event.found_token
        text = f"{prog}: expected a command{'' if found is None else f', got {found}'}"
    else:
        text = f"{prog}: invalid command line"
    return " ".join(f"{text} (see {prog} --help)".split())


def _parse_error_hook(command: str | None):
    """Routes tyro's parse failures to `CommandLineError` (one line); None where tyro has no parse-error hook."""
    try:
        from tyro._errors import on_parse_error
    except ImportError:
        return None

    def raise_one_line(event) -> None:
        try:
            line = describe_parse_error(event, command)
        except Exception:  # noqa: BLE001 - an event of another tyro version: still one line
            line = _generic_parse_error(command)
        raise CommandLineError(line)

    return on_parse_error(raise_one_line)


def _generic_parse_error(command: str | None) -> str:
    where = f"gpdepth3d {command}" if command else "gpdepth3d"
    return f"{where}: invalid command line (see {where} --help)"


COMPILE_NOTICE = "compiling kernels (once, ~1 min) ..."
"""Printed before numba first compiles one of the fast engine's kernels (a cold cache), never on warm runs."""


DEMO_GROUPS = ("solve", "detail", "neumann")
"""The kernel groups the demo reaches (`gpdepth3d.gp.compile_ahead.GROUPS`): the default model on frames with many
points, then the paper's model by the Neumann route."""


def _compile_notice(argv: list[str]):
    """Prints `COMPILE_NOTICE` once when a command compiles kernels (not for `view` or --help: no numba import)."""
    import contextlib

    if (
        not argv
        or argv[0] not in ("complete", "demo", "eval", "fuse", "map", "batch")
        or "--help" in argv
        or "-h" in argv
    ):
        return contextlib.nullcontext()
    from ..gp.compile_notice import on_first_compile

    def cold(_name: str) -> None:  # a cold cache: the kernels this command reaches later, compiled on another core
        from ..gp.compile_ahead import DEFAULT_MODEL_GROUPS, compile_ahead

        print(COMPILE_NOTICE, flush=True)
        compile_ahead(DEMO_GROUPS if argv[0] == "demo" else DEFAULT_MODEL_GROUPS)

    return on_first_compile(cold)


def _idle_threads_sleep() -> None:
    """The compiled kernels' OpenMP threads sleep between parallel regions instead of spinning, unless the user set
    ``OMP_WAIT_POLICY``: on cores shared with other busy processes (a robot's SLAM, a second run) spinning threads
    make a frame several times slower; alone on its cores it costs a few per cent (docs/engines.md, "Threads").
    Read when the OpenMP runtime loads, so it is set before the first parallel kernel runs."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gpdepth3d`` command.

    Every failure is one line on stderr and exit code 1 (a bad option value included); set
    GPDEPTH3D_DEBUG=1 to see the traceback of an unexpected error instead.
    """
    _idle_threads_sleep()
    command = None
    show_warning = warnings.showwarning
    warnings.showwarning = _one_line_warning
    filters = list(warnings.filters)
    quiet_third_party()
    try:
        from ._options import normalize_argv

        argv = normalize_argv(list(sys.argv[1:] if argv is None else argv))
        commands = _commands()
        command = argv[0] if argv and argv[0] in commands else None
        hook = _parse_error_hook(command)
        # without the hook tyro's own (multi-line) message is held back and replaced by one line; help still prints
        quiet = hook is None and not ({"-h", "--help"} & set(argv))
        with _compile_notice(argv), hook or contextlib.nullcontext():
            tyro.extras.subcommand_cli_from_dict(
                commands,
                args=argv,
                prog="gpdepth3d",
                config=(tyro.conf.CascadeSubcommandArgs,),
                console_outputs=not quiet,
            )
    except SystemExit as exc:
        if exc.code not in (0, None):  # a parse failure tyro reported itself (a tyro without the hook)
            print(f"gpdepth3d: error: {_generic_parse_error(command)}", file=sys.stderr)
            return 1
        raise
    except GPDepthError as exc:
        print(f"gpdepth3d: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("gpdepth3d: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` & co.: not an error
        sys.stdout = open(os.devnull, "w")
        return 0
    except (ImportError, OSError) as exc:
        missing = missing_dependency(exc)
        if missing is not None:
            print(f"gpdepth3d: error: {missing}", file=sys.stderr)
        elif isinstance(exc, ImportError):
            print(f"gpdepth3d: error: {exc}", file=sys.stderr)
        else:
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            print(f"gpdepth3d: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print("gpdepth3d: error: out of memory (try a smaller --output-size or input)", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - the CLI's contract: one line and exit 1
        if os.environ.get("GPDEPTH3D_DEBUG"):
            raise
        print(
            f"gpdepth3d: error: unexpected {type(exc).__name__}: {exc} (set GPDEPTH3D_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 1
    finally:
        warnings.showwarning = show_warning
        warnings.filters[:] = filters
    return 0


if __name__ == "__main__":
    sys.exit(main())
