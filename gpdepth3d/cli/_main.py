"""The ``gpdepth3d`` entry point: one subcommand per module of `gpdepth3d.cli`, errors as one line.

Every command prints what it wrote. A `GPDepthError` (bad input, missing or corrupt file)
becomes one line on stderr and exit code 1.
"""

from __future__ import annotations

import io
import os
import re
import sys
import warnings
from typing import Optional

import tyro

from ..errors import GPDepthError


def _commands() -> dict:
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
    return {name: _announce_start(f) for name, f in commands.items()}


class _ParseErrors:
    """Holds what the parser writes to stderr until the command starts (tyro's error box becomes one line)."""

    def __init__(self) -> None:
        self.buffer = io.StringIO()
        self.real = sys.stderr
        self.parsing = False

    def write(self, text: str) -> int:
        return (self.buffer if self.parsing else self.real).write(text)

    def flush(self) -> None:
        if not self.parsing:
            self.real.flush()

    def __getattr__(self, name: str):
        return getattr(self.real, name)

    def release(self) -> None:
        """The command starts: what the parser wrote (warnings) goes out, later writes go straight through."""
        self.parsing = False
        if self.buffer.getvalue():
            self.real.write(self.buffer.getvalue())
            self.buffer = io.StringIO()


_PARSE: Optional[_ParseErrors] = None


def _announce_start(f):
    import functools

    @functools.wraps(f)
    def run(*args, **kwargs):
        if _PARSE is not None:
            _PARSE.release()
        return f(*args, **kwargs)

    return run


def one_line_parse_error(box: str) -> str:
    """tyro's error message (framed on a terminal, ruled with dashes otherwise) as one line."""
    title, sections = "", [[]]
    for raw in box.splitlines():
        t = raw.rstrip()
        stripped = t.strip()
        if stripped.startswith("\u256d"):  # top border with the title
            title = stripped.strip("\u256d\u256e\u2500 ")
            continue
        if stripped.startswith("\u2570") or not stripped:
            continue
        if stripped.startswith("\u2502"):
            t = stripped[1:-1] if stripped.endswith("\u2502") else stripped[1:]
        if set(t.strip()) <= {"\u2500", "-"}:
            sections.append([])
            continue
        sections[-1].append(t.rstrip())
    sections = [sec for sec in sections if sec]
    if not title and len(sections) > 1 and len(sections[0]) == 1:
        title = sections.pop(0)[0].strip()
    for i, sec in enumerate(sections):
        indent = min(len(line) - len(line.lstrip()) for line in sec)
        sections[i] = [line[indent:] for line in sec]
    parts, hint = [], ""
    for sec in sections:
        if not sec:
            continue
        head = sec[0].strip()
        if head.startswith("For full helptext"):
            hint = " ".join([head] + [line.strip() for line in sec[1:]])
            hint = re.sub(r"^For full helptext,?\s*(run|see)?:?\s*", "", hint)
            continue
        if head.startswith("Argument helptext"):
            continue
        if head.endswith(":") and len(sec) > 1:
            indent = min(len(line) - len(line.lstrip()) for line in sec[1:])
            items = [line.split()[0] for line in sec[1:] if len(line) - len(line.lstrip()) == indent]
            parts.append(f"{head} {', '.join(items)}")
        else:
            parts.append(" ".join(line.strip() for line in sec))
    text = "; ".join(parts).replace("__tyro-dummy-inner__.", "--")
    text = " ".join(text.split())
    message = f"{title}: {text}" if title else text
    if hint:
        message += f" (see {hint})"
    return message or "invalid command line (see gpdepth3d --help)"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"gpdepth3d: warning: {message}", file=file or sys.stderr)


COMPILE_NOTICE = "compiling kernels (once, ~1 min) ..."
"""Printed before numba first compiles one of the fast engine's kernels (a cold cache), never on warm runs."""


def _compile_notice(argv: list[str]):
    """Prints `COMPILE_NOTICE` once when a command compiles kernels (not for `view` or --help: no numba import)."""
    import contextlib

    if not argv or argv[0] not in ("complete", "demo", "eval", "fuse", "map", "batch") or "--help" in argv or "-h" in argv:
        return contextlib.nullcontext()
    from ..gp.compile_notice import on_first_compile

    return on_first_compile(lambda _name: print(COMPILE_NOTICE, flush=True))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``gpdepth3d`` command.

    Every failure is one line on stderr and exit code 1 (a bad option value included); set
    GPDEPTH3D_DEBUG=1 to see the traceback of an unexpected error instead.
    """
    global _PARSE
    show_warning = warnings.showwarning
    warnings.showwarning = _one_line_warning
    parse = _ParseErrors()
    parse.parsing = True
    _PARSE = parse
    sys.stderr = parse  # type: ignore[assignment]
    try:
        from ._options import normalize_argv

        argv, notes = normalize_argv(list(sys.argv[1:] if argv is None else argv))
        for note in notes:
            print(f"gpdepth3d: note: {note}", file=parse.real)
        with _compile_notice(argv):
            tyro.extras.subcommand_cli_from_dict(
                _commands(), args=argv, prog="gpdepth3d", config=(tyro.conf.CascadeSubcommandArgs,)
            )
    except SystemExit as exc:
        if parse.parsing and exc.code not in (0, None):
            parse.parsing = False
            print(f"gpdepth3d: error: {one_line_parse_error(parse.buffer.getvalue())}", file=parse.real)
            return 1
        parse.release()
        raise
    except GPDepthError as exc:
        parse.release()
        print(f"gpdepth3d: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        parse.release()
        print("gpdepth3d: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` & co.: not an error
        parse.release()
        sys.stdout = open(os.devnull, "w")
        return 0
    except OSError as exc:
        parse.release()
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"gpdepth3d: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except MemoryError:
        parse.release()
        print("gpdepth3d: error: out of memory (try a smaller --output-size or input)", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - the CLI's contract: one line and exit 1
        parse.release()
        if os.environ.get("GPDEPTH3D_DEBUG"):
            raise
        print(
            f"gpdepth3d: error: unexpected {type(exc).__name__}: {exc} (set GPDEPTH3D_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 1
    finally:
        sys.stderr = parse.real
        warnings.showwarning = show_warning
        _PARSE = None
    parse.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
