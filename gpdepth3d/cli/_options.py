"""The CLI's shared vocabulary: the GP preset choice.

Every subcommand spells its options the same way: ``--output`` for what it writes, ``--mde NAME|FILE``
for the monocular front-end, ``--preset default|paper|residual`` (then ``--gp.FIELD VALUE``) for the GP,
``--frames`` for a frame cap.
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

WITH_PRESET = ("complete", "fuse", "batch")
"""Subcommands whose GP is chosen with ``--preset`` (and tuned with ``--gp.FIELD``)."""


def normalize_argv(argv: list[str]) -> list[str]:
    """Moves ``--preset NAME`` (or ``--preset=NAME``) right behind the command's name, where the parser takes it.

    The preset is a subcommand of the parser; placed first, the ``--gp.FIELD`` options may follow anywhere.

    Args:
        argv: The arguments after ``gpdepth3d``.

    Returns:
        The rewritten arguments.

    Raises:
        InvalidInputError: an unknown preset, or two presets.
    """
    if not argv or argv[0] not in WITH_PRESET:
        return list(argv)
    command, rest = argv[0], list(argv[1:])
    presets, kept, i = [], [], 0
    while i < len(rest):
        token = rest[i]
        if token == "--preset":
            if i + 1 >= len(rest):
                raise InvalidInputError("--preset", f"one of {', '.join(PRESETS)}", "nothing")
            presets.append(rest[i + 1])
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
    return [command] + presets + kept
