"""Sizes refused before memory is spent: what a call will need, estimated and checked at the boundary.

A request too large for the machine (an output of 11000 x 12000 pixels, a frame resized 100 times,
a file whose header claims 200000 x 200000 values) is refused with a `ProblemTooLargeError` naming
the size and the limit, before the arrays are allocated, instead of exhausting the memory.

The limit of one call (`memory_limit`) is the smallest of `DEFAULT_MAX_MEMORY_MB` (or the
environment variable ``GPDEPTH3D_MAX_MEMORY_MB``), three quarters of the memory available now, and
the room left under the process's address-space limit (``ulimit -v``, ``RLIMIT_AS``). The
per-pixel costs of a completion are measured (see docs/results.md).
"""

from __future__ import annotations

import math
import os

import numpy as np

from .errors import InvalidInputError, ProblemTooLargeError

DEFAULT_MAX_MEMORY_MB = 4096
"""Memory one call may plan to use (MiB) unless ``GPDEPTH3D_MAX_MEMORY_MB`` says otherwise."""

COMPLETION_BYTES_PER_OUTPUT_PIXEL = 400
"""Peak bytes of a completion per output pixel: the output arrays (mean, variance, std, prior, the
interpolation of the field to the output grid) and their temporaries."""

COMPLETION_BYTES_PER_INPUT_PIXEL = 200
"""Peak bytes of a completion per MDE pixel outside the engine (the engine checks its own solve)."""

ENV_VAR = "GPDEPTH3D_MAX_MEMORY_MB"


def _gib(n: float) -> str:
    try:
        n = float(n)
    except OverflowError:  # an integer beyond any float: a size no machine has
        return "more than 1e308 bytes"
    return f"{n / 2**30:.2f} GiB" if n >= 2**28 else f"{n / 2**20:.0f} MiB"


def _available_bytes() -> int | None:
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001 - psutil missing or unsupported: no reading
        return None


def _address_space_room() -> int | None:
    """Bytes of address space left under RLIMIT_AS (None: no limit or not knowable)."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return None
    try:
        with open("/proc/self/statm") as f:
            used = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        used = 0
    return max(0, soft - used)


def memory_limit() -> int:
    """Bytes one call may plan to use: the configured limit, 3/4 of the available memory, the RLIMIT_AS room.

    Raises:
        InvalidInputError: ``GPDEPTH3D_MAX_MEMORY_MB`` is set but not a number > 0.
    """
    text = os.environ.get(ENV_VAR, "").strip()
    if text:
        try:
            configured = float(text)
        except ValueError:
            configured = float("nan")
        if not math.isfinite(configured) or configured <= 0:
            raise InvalidInputError(ENV_VAR, "a memory limit in MiB, a number > 0", text)
    else:
        configured = DEFAULT_MAX_MEMORY_MB
    limits = [int(configured * 2**20)]
    available = _available_bytes()
    if available is not None:
        limits.append(available * 3 // 4)
    room = _address_space_room()
    if room is not None:
        limits.append(room * 3 // 4)
    return max(0, min(limits))


def check_memory(what: str, needed: float, limit: int | None = None) -> None:
    """Refuses a request whose estimated memory ``needed`` (bytes) exceeds ``limit`` (default `memory_limit`).

    Raises:
        ProblemTooLargeError: naming ``what`` (the size asked for), the estimate and the limit.
    """
    limit = memory_limit() if limit is None else int(limit)
    if needed > limit:
        raise ProblemTooLargeError(
            f"{what}: needs about {_gib(needed)}, above the memory limit of {_gib(limit)} "
            f"(the smallest of {ENV_VAR} (default {DEFAULT_MAX_MEMORY_MB}), 3/4 of the free memory and ulimit -v)"
        )


def completion_bytes(input_shape: tuple[int, int], output_shape: tuple[int, int]) -> int:
    """Estimated peak bytes of completing an (H, W) MDE map to an (Ho, Wo) output, outside the engine's solve."""
    h, w = (int(x) for x in input_shape)
    ho, wo = (int(x) for x in output_shape)
    return COMPLETION_BYTES_PER_OUTPUT_PIXEL * ho * wo + COMPLETION_BYTES_PER_INPUT_PIXEL * h * w


def check_completion_size(input_shape: tuple[int, int], output_shape: tuple[int, int]) -> None:
    """Refuses a completion whose estimated memory exceeds `memory_limit`, before anything is allocated.

    Raises:
        ProblemTooLargeError: naming the output size, the MDE size, the estimate and the limit.
    """
    check_memory(
        f"output_shape {tuple(int(s) for s in output_shape)} from an MDE map of shape {tuple(int(s) for s in input_shape)}",
        completion_bytes(input_shape, output_shape),
    )


def check_array_size(what: str, shape: tuple[int, ...], dtype=np.float64, copies: float = 1.0) -> None:
    """Refuses to allocate ``copies`` arrays of ``shape`` and ``dtype`` beyond `memory_limit`.

    Raises:
        ProblemTooLargeError: naming ``what``, the shape and the limit.
    """
    n = 1
    for s in shape:
        n *= int(s)
    check_memory(f"{what} of shape {tuple(int(s) for s in shape)}", copies * n * np.dtype(dtype).itemsize)
