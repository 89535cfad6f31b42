"""Waiting for the kernels that a second process compiles ahead (`gpdepth3d.gp.compile_ahead`).

On a cold numba cache the command line, or a program's first completion, starts a process compiling the kernel
groups a run reaches later (`gpdepth3d.gp.compile_ahead`); it writes each group's name on its standard output once
the group is in the cache. A module calls `ready` with a group's name before its first kernel call: it returns at
once on warm runs (no such process) and otherwise once the group is reported, so that this process loads the
group's kernels from the cache instead of compiling them a second time alongside the other process. Kept apart from `gpdepth3d.gp.compile_ahead`, which imports the kernels'
modules, so that those can import this one.
"""

from __future__ import annotations

import selectors
import subprocess
import threading
import time
from dataclasses import dataclass, field

MAX_WAIT_S = 300.0
"""The longest `ready` waits for a group (seconds): a process that reports nothing for that long is not waited for
again, and this process compiles what it needs itself. Far above a cold compile on a slow core, so it only ends a
wait on a process that is stuck."""


@dataclass
class _Ahead:
    """The process compiling ahead, and the groups it has not reported yet."""

    proc: subprocess.Popen
    pending: set = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)


_AHEAD: _Ahead | None = None
"""The process compiling ahead for this one, while it has groups pending; None otherwise (warm runs)."""


def track(proc: subprocess.Popen, groups) -> None:
    """Makes `ready` wait for ``groups`` (names) until ``proc`` (its standard output a pipe) reports them."""
    global _AHEAD
    _AHEAD = _Ahead(proc, set(groups))


def started() -> bool:
    """Whether this process has started a process compiling ahead (`track`), running or ended."""
    return _AHEAD is not None


def ready(group: str) -> None:
    """Returns once the process compiling ahead has compiled ``group`` (or has ended); at once when no
    such process runs or ``group`` is not among its groups.

    Called before a group's first kernel call, so that this process loads the kernels from the cache instead of
    compiling them a second time alongside the other process.
    """
    ahead = _AHEAD
    if ahead is None or group not in ahead.pending:
        return
    with ahead.lock:
        deadline = time.monotonic() + MAX_WAIT_S
        while group in ahead.pending:
            line = _report(ahead.proc, deadline - time.monotonic())
            if not line:  # ended, failed or stuck: whatever it did not compile, this process compiles
                ahead.pending.clear()
                break
            ahead.pending.discard(line.decode(errors="replace").strip())


def _report(proc: subprocess.Popen, timeout: float) -> bytes:
    """The next line ``proc`` writes, or b"" when it ends or writes none within ``timeout`` seconds."""
    if timeout <= 0:
        return b""
    with selectors.DefaultSelector() as sel:
        try:
            sel.register(proc.stdout, selectors.EVENT_READ)
        except (ValueError, OSError):  # a pipe the platform cannot select on (Windows): wait without a bound
            return proc.stdout.readline()
        return proc.stdout.readline() if sel.select(timeout) else b""
