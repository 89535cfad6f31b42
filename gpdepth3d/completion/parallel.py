"""Frames of a sequence completed side by side: one thread per core, one frame per thread (`DepthCompleter.map`).

A frame alone keeps two cores busy only in its compiled parallel regions; its Python stages and its small
serial kernels run on one core. Frames of a sequence are independent given the configuration (without
``config.fit``), so a worker thread per core, each completing whole frames with one numba thread and one BLAS
thread, keeps every core busy: the compiled kernels release the GIL, and the engine's numeric phases do not wait
for one another (`gpdepth3d.gp.multifrontal.numeric_section`). Each worker has its own `DepthCompleter` (the
engine's per-shape set-up is per completer); each frame's posterior is the one the serial path computes.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator

from ..errors import InvalidInputError, describe


def check_workers(workers) -> int:
    """``workers`` as an int >= 1; None: the cores this process may use.

    Raises:
        InvalidInputError: anything else (0, negative, a float, a bool).
    """
    if workers is None:
        return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidInputError("workers", "an integer >= 1 (or None: one per core)", describe(workers))
    return workers


def map_frames(make_completer: Callable[[], Callable], frames: Iterable, workers: int, **kwargs) -> Iterator:
    """Posteriors of ``frames`` ((mde_depth, sparse) pairs), in their order, from ``workers`` threads.

    Args:
        make_completer: Builds one worker's completer (called once in each worker thread).
        frames: (mde_depth, sparse) pairs; read as the workers need them (at most 2 x workers ahead).
        workers: Worker threads (>= 2; one frame at a time each).
        kwargs: Keyword arguments of each `DepthCompleter.complete` call.

    Yields:
        One `DepthPosterior` per frame, in the order of ``frames``; a frame's error is raised when its turn
        comes (the frames before it were yielded).
    """
    import numba

    from ..gp.blas_threads import single_threaded_blas

    local = threading.local()

    def run(frame):
        if not hasattr(local, "completer"):
            numba.set_num_threads(1)  # per thread: this worker's parallel regions run on it alone
            local.completer = make_completer()
        mde_depth, sparse = frame
        return local.completer(mde_depth, sparse, **kwargs)

    with single_threaded_blas(), ThreadPoolExecutor(workers, thread_name_prefix="gpdepth3d-frame") as pool:
        pending: deque = deque()
        for frame in frames:
            pending.append(pool.submit(run, frame))
            if len(pending) >= 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
