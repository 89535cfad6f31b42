"""One BLAS thread inside a block: the small dense algebra of a frame's points and of one numba thread's fronts.

BLAS threads only contend on these small products (and, inside numba's parallel regions, oversubscribe the
cores). threadpoolctl finds the loaded BLAS libraries once per process (a scan of the process's libraries takes
ms); the stages and the engine share that one controller.
"""

from __future__ import annotations

import threading

_CONTROLLER = None
_LOCK = threading.Lock()


def single_threaded_blas():
    """A context in which every loaded BLAS library runs on one thread; the counts before it are restored after."""
    global _CONTROLLER
    if _CONTROLLER is None:
        with _LOCK:
            if _CONTROLLER is None:
                from threadpoolctl import ThreadpoolController

                _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
