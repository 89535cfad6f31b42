"""A callback run once, just before numba first compiles one of the package's kernels.

The fast engine's kernels are numba functions cached on disk (``cache=True``): the first run after
an install, or after their source changed, compiles them (about a minute); later runs load them
from the cache in well under a second. numba announces a compilation (a cache miss) with its
``"numba:compile"`` event and never for a cache hit, so listening to that event tells a cold cache
from a warm one exactly, at no cost: the CLI prints "compiling kernels (once, ~1 min)" from it.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Callable, Iterator

PACKAGE_PREFIX = "gpdepth3d."
"""Only kernels defined in modules of this package trigger the callback."""


def _kernel_module(data: object) -> str:
    dispatcher = data.get("dispatcher") if isinstance(data, dict) else None
    py_func = getattr(dispatcher, "py_func", None)
    return str(getattr(py_func, "__module__", "") or "")


@contextlib.contextmanager
def on_first_compile(callback: Callable[[str], None], *, prefix: str = PACKAGE_PREFIX) -> Iterator[None]:
    """Calls ``callback(kernel_name)`` once, before the first numba compilation of a package kernel.

    Nothing is called when every kernel used inside the block comes from numba's cache (a warm
    run), and nothing when numba is not installed. The callback runs in the compiling thread,
    before the compilation starts; it is called at most once per block.

    Args:
        callback: Receives the qualified name of the first kernel compiled, e.g.
            ``"gpdepth3d.gp.multifrontal._factor_run"``.
        prefix: Only kernels of modules whose name starts with this count (default: this package).

    Yields:
        None; the listener is removed on leaving the block.
    """
    if not callable(callback):
        from ..errors import InvalidInputError

        raise InvalidInputError("callback", "a callable taking the kernel's name", type(callback).__name__)
    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba is a dependency; without it nothing compiles
        yield
        return

    lock = threading.Lock()
    fired = [False]

    class _Listener(event.Listener):
        def on_start(self, ev: "event.Event") -> None:
            module = _kernel_module(ev.data)
            if not module.startswith(prefix):
                return
            with lock:
                if fired[0]:
                    return
                fired[0] = True
            name = getattr(getattr(ev.data["dispatcher"], "py_func", None), "__name__", "?")
            callback(f"{module}.{name}")

        def on_end(self, ev: "event.Event") -> None:
            pass

    listener = _Listener()
    event.register("numba:compile", listener)
    try:
        yield
    finally:
        event.unregister("numba:compile", listener)
