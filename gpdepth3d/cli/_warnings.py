"""How the command line shows warnings: one line each, no colour codes, third-party notices with nothing to do held back."""

from __future__ import annotations

import re
import sys
import warnings

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = " ".join(_ANSI.sub("", str(message)).split())  # third-party colour codes and line breaks out
    print(f"gpdepth3d: warning: {text}", file=file or sys.stderr)


QUIET_WARNINGS: tuple[tuple[str, str], ...] = (
    ("numba", r"(?s).*TBB threading layer"),  # numba falls back to another threading layer by itself
)
"""(module, message regex) of third-party warnings the command line does not show: nothing for a user to do."""


def quiet_third_party() -> None:
    """Adds the `QUIET_WARNINGS` filters (again: a ``simplefilter("always")`` inside a command drops them)."""
    for module, message in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", message=message, module=module)


def report_warnings(caught: list, names: dict | None = None) -> None:
    """Prints each distinct warning once, with how often it came (per-frame warnings would flood the terminal).

    Args:
        caught: Recorded warnings (``warnings.catch_warnings(record=True)``).
        names: Frame number -> image name: "frame 19" in a message becomes "image <name>".
    """
    counts: dict[str, int] = {}
    first: dict[str, str] = {}
    for w in caught:
        if any(re.match(m, str(w.message)) and (w.filename or "").find(mod) >= 0 for mod, m in QUIET_WARNINGS):
            continue
        text = " ".join(_ANSI.sub("", str(w.message)).split())
        key = f"{w.category.__name__}:{re.sub(r'[-+]?[0-9][0-9.,]*', '#', text)}"
        if names:
            text = re.sub(r"\bframe (\d+)\b", lambda m: f"image {names.get(int(m.group(1)), m.group(1))}", text)
        counts[key] = counts.get(key, 0) + 1
        first.setdefault(key, text)
    for key, n in counts.items():
        more = f" (and {n - 1} more like it)" if n > 1 else ""
        print(f"gpdepth3d: warning: {first[key]}{more}", file=sys.stderr)
