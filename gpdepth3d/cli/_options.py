"""The CLI's shared vocabulary: the GP preset choice and the old flag spellings that still work.

Every subcommand spells its options the same way: ``--output`` for what it writes, ``--mde NAME|FILE``
for the monocular front-end, ``--preset default|paper|residual`` (then ``--gp.FIELD VALUE``) for the GP,
``--frames`` for a frame cap. Older spellings (``--out``, ``--output-dir``, ``--limit``, ``--model`` as
the GP preset or the front-end's model file, ``--model.FIELD``, ``--engine``) are rewritten to these
before parsing, with a one-line deprecation note on stderr; they are not listed in ``--help``.
"""

from __future__ import annotations

from typing import Annotated, Union

import tyro

from ..errors import InvalidInputError
from ..gp.model import DepthGPConfig

PRESETS: dict[str, DepthGPConfig] = {
    "default": DepthGPConfig(),
    "paper": DepthGPConfig.paper(),
    "residual": DepthGPConfig.residual(),
}
"""The GP presets by name (``--preset``); "default" is the library's default, `DepthGPConfig()`."""

# The GP of a command: a preset, then any of its fields (`--preset residual --gp.fit`).
GPPreset = Union[
    Annotated[DepthGPConfig, tyro.conf.subcommand("default", default=PRESETS["default"], prefix_name=False)],
    Annotated[DepthGPConfig, tyro.conf.subcommand("paper", default=PRESETS["paper"], prefix_name=False)],
    Annotated[DepthGPConfig, tyro.conf.subcommand("residual", default=PRESETS["residual"], prefix_name=False)],
]

# old spelling -> new spelling, per subcommand (a prefix ending in "." renames every flag under it)
RENAMED: dict[str, dict[str, str]] = {
    "complete": {"--out": "--output", "--output-dir": "--output", "--model": "--preset", "--model.": "--gp."},
    "demo": {"--out": "--output", "--output-dir": "--output"},
    "eval": {"--out": "--output", "--output-dir": "--output", "--limit": "--frames", "--model": "--mde"},
    "fuse": {"--out": "--output", "--output-dir": "--output", "--limit": "--frames", "--model": "--mde",
             "--engine": "--gp.engine"},
    "batch": {"--out": "--output", "--output-dir": "--output", "--limit": "--frames", "--engine": "--gp.engine"},
}
"""Deprecated flags that still work, per subcommand, and what they are now."""

WITH_PRESET = ("complete", "fuse", "batch")
"""Subcommands whose GP is chosen with ``--preset`` (and tuned with ``--gp.FIELD``)."""


def normalize_argv(argv: list[str]) -> tuple[list[str], list[str]]:
    """Rewrites old flag spellings and ``--preset NAME`` into what the parser takes.

    ``--preset NAME`` (or ``--preset=NAME``) becomes the preset's subcommand right after the
    command's name, so that ``--gp.FIELD`` options may follow anywhere.

    Args:
        argv: The arguments after ``gpdepth3d``.

    Returns:
        The rewritten arguments and one deprecation note per old spelling used.

    Raises:
        InvalidInputError: an unknown preset, or two presets.
    """
    if not argv or argv[0] not in RENAMED:
        return list(argv), []
    command, rest = argv[0], list(argv[1:])
    renamed, notes, out = RENAMED[command], [], []
    for token in rest:
        if token.startswith("--") and not token.startswith("--preset"):
            flag, eq, value = token.partition("=")
            new = renamed.get(flag)
            if new is None:
                prefix = next((p for p in renamed if p.endswith(".") and flag.startswith(p)), None)
                if prefix is not None:
                    new = renamed[prefix] + flag[len(prefix):]
            if new is not None:
                old = flag if not flag.startswith("--model.") else "--model.FIELD"
                note = f"{old} is deprecated; use {new if old != '--model.FIELD' else '--gp.FIELD'}"
                if note not in notes:
                    notes.append(note)
                token = new + eq + value
        out.append(token)
    if command not in WITH_PRESET:
        return [command] + out, notes
    presets, kept, i = [], [], 0
    while i < len(out):
        token = out[i]
        if token == "--preset":
            if i + 1 >= len(out):
                raise InvalidInputError("--preset", f"one of {', '.join(PRESETS)}", "nothing")
            presets.append(out[i + 1])
            i += 2
            continue
        if token.startswith("--preset="):
            presets.append(token.split("=", 1)[1])
        else:
            kept.append(token)
        i += 1
    if len(presets) > 1:
        raise InvalidInputError("--preset", "one GP preset", " and ".join(presets))
    for name in presets:
        if name not in PRESETS:
            raise InvalidInputError("--preset", f"one of {', '.join(PRESETS)}", name)
    return [command] + presets + kept, notes
