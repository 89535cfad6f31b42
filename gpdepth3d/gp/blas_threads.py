"""One BLAS thread inside a block: the small dense algebra of a frame's points and of one numba thread's fronts.

BLAS threads only contend on these small products (and, inside numba's parallel regions, oversubscribe the
cores). threadpoolctl finds the loaded BLAS libraries once (a scan of the process's libraries takes ms); each
block then reads and sets their thread counts directly, and a block inside another one, where BLAS already
runs on one thread, costs two reads.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Iterator

_LIBRARIES: list | None = None
_LOCK = threading.Lock()


def _blas_libraries() -> list:
    """threadpoolctl's controllers of the BLAS libraries loaded now (found once per process)."""
    global _LIBRARIES
    if _LIBRARIES is None:
        with _LOCK:
            if _LIBRARIES is None:
                from threadpoolctl import ThreadpoolController

                _LIBRARIES = [lib for lib in ThreadpoolController().lib_controllers if lib.user_api == "blas"]
    return _LIBRARIES


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """A block in which every loaded BLAS library runs on one thread; the counts before it are restored after."""
    changed = []
    for lib in _blas_libraries():
        threads = lib.get_num_threads()
        if threads != 1:
            lib.set_num_threads(1)
            changed.append((lib, threads))
    try:
        yield
    finally:
        for lib, threads in changed:
            lib.set_num_threads(threads)
