"""Optional dependencies: which extra installs a module, and one-line errors when one is missing.

The core install (``pip install gpdepth3d``) carries what `complete`, `demo` and `eval` need. The
rest sits behind extras (``pip install "gpdepth3d[mapping]"``) and is imported when used, through
`require`, so that a missing package or system library is reported as one line naming its fix.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import GPDepthError

EXTRAS: dict[str, tuple[str, ...]] = {
    "open3d": ("mapping",),
    "trimesh": ("mapping", "viewer"),
    "pycolmap": ("mapping",),
    "evo": ("mapping",),
    "viser": ("viewer",),
    "torch": ("mapping", "kissgp"),
    "gpytorch": ("kissgp",),
    "linear_operator": ("kissgp",),
    "ai_edge_litert": ("tflite",),
    "distributed": ("batch",),
    "dask": ("batch",),
}
"""Top-level module name -> the extras of gpdepth3d that install it (``pip install "gpdepth3d[EXTRA]"``)."""

SYSTEM_LIBRARIES: dict[str, str] = {"libusb-1.0": "libusb-1.0-0"}
"""Shared-library name (as the loader reports it missing) -> the Debian/Ubuntu package that provides it."""


class MissingDependencyError(GPDepthError, ImportError):
    """An optional Python package, or a system library it loads, is not installed.

    Attributes:
        module: The module that could not be imported.
        fix: What to install, in words (a pip or apt-get command).
    """

    def __init__(self, module: str, fix: str):
        self.module = module
        self.fix = fix
        super().__init__(f"{module} could not be imported: {fix}")

    def __reduce__(self):  # picklable across Dask workers
        return (type(self), (self.module, self.fix))


def missing_dependency(exc: BaseException, module: str | None = None) -> MissingDependencyError | None:
    """The one-line error for an import failure of an optional dependency, or None for any other error.

    Args:
        exc: The ImportError (or OSError from a shared library) raised while importing.
        module: The module being imported, when known (else read from ``exc.name``).
    """
    text = str(exc)
    for library, package in SYSTEM_LIBRARIES.items():
        if library in text:
            name = module or getattr(exc, "name", None) or "a module"
            return MissingDependencyError(
                name, f"the system library {library} is missing (sudo apt-get install {package})"
            )
    name = (getattr(exc, "name", None) or module or "").split(".")[0]
    if isinstance(exc, ModuleNotFoundError) and name in EXTRAS:
        extras = _needed_first(EXTRAS[name], exc)
        return MissingDependencyError(
            name,
            f"not installed; it comes with the {' or '.join(f'[{e}]' for e in extras)} extra "
            f'(pip install "gpdepth3d[{extras[0]}]")',
        )
    return None


PACKAGE_EXTRAS: dict[str, str] = {"gp": "kissgp", "mapping": "mapping", "viewer": "viewer", "experiments": "batch"}
"""Sub-package of gpdepth3d -> the extra its optional imports come with (a module of several extras is
named by the one the failing code needs: torch for the ``kissgp`` engine is ``[kissgp]``, not ``[mapping]``)."""


def _needed_first(extras: tuple[str, ...], exc: BaseException) -> tuple[str, ...]:
    """``extras`` with the one of the sub-package whose import failed first (from the traceback), if any."""
    import os

    tb = exc.__traceback__
    while tb is not None:
        parts = os.path.normpath(tb.tb_frame.f_code.co_filename).split(os.sep)
        if "gpdepth3d" in parts[:-1]:
            sub = parts[len(parts) - 1 - parts[::-1].index("gpdepth3d") + 1]
            extra = PACKAGE_EXTRAS.get(sub)
            if extra in extras:
                return (extra,) + tuple(e for e in extras if e != extra)
        tb = tb.tb_next
    return extras


def require(module: str) -> ModuleType:
    """Imports an optional dependency, or raises `MissingDependencyError` naming the extra or system package.

    Args:
        module: Dotted module name, e.g. ``"open3d"`` or ``"open3d.core"``.

    Raises:
        MissingDependencyError: the package (or a system library it loads, e.g. libusb for Open3D) is missing.
    """
    try:
        return importlib.import_module(module)
    except (ImportError, OSError) as exc:
        error = missing_dependency(exc, module)
        if error is None:
            raise
        raise error from exc
