"""One DeprecationWarning for a public name or module that moved, naming where it went."""

from __future__ import annotations

import warnings


def warn_moved(old: str, new: str, *, stacklevel: int = 3) -> None:
    """Warn once per import that ``old`` moved to ``new`` and will go in the next release.

    Args:
        old: the deprecated dotted name, as the user wrote it.
        new: where it lives now (dotted name, or a short phrase naming the new places).
        stacklevel: the frame the warning points at (3: the importer of a shim module).
    """
    warnings.warn(
        f"{old} is deprecated and will be removed in the next release; use {new}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )
