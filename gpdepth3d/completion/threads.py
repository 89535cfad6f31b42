"""One BLAS thread for the small dense algebra of a frame's points (threads only contend on it)."""

from __future__ import annotations

from ..gp.blas_threads import single_threaded_blas as single_threaded_blas
