"""One BLAS thread for the small dense algebra of a frame's points (threads only contend on it)."""

from __future__ import annotations

_CONTROLLER = None


def single_threaded_blas():
    """A context limiting BLAS to one thread (the controller is found once: finding the libraries takes ms)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
