"""One BLAS thread inside a block: the small dense algebra of a frame's points and of one numba thread's fronts.

BLAS threads only contend on these small products (and, inside numba's parallel regions, oversubscribe the
cores). threadpoolctl finds the loaded BLAS libraries once per process (a scan of the process's libraries takes
ms); the stages and the engine share that one controller. Setting and restoring the counts costs a call into every
library, so a block inside another of the same thread (a stage's solver inside the stage) leaves them as they are.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

_CONTROLLER = None
_LOCK = threading.Lock()
_DEPTH = threading.local()  # .n: this thread's open blocks


@contextmanager
def single_threaded_blas():
    """A context in which every loaded BLAS library runs on one thread; the counts before it are restored after
    (by the outermost block of the thread)."""
    depth = getattr(_DEPTH, "n", 0)
    _DEPTH.n = depth + 1
    try:
        if depth:
            yield
        else:
            with _controller().limit(limits=1, user_api="blas"):
                yield
    finally:
        _DEPTH.n = depth


def _controller():
    """The process's one `threadpoolctl.ThreadpoolController`."""
    global _CONTROLLER
    if _CONTROLLER is None:
        with _LOCK:
            if _CONTROLLER is None:
                from threadpoolctl import ThreadpoolController

                _CONTROLLER = ThreadpoolController()
    return _CONTROLLER
