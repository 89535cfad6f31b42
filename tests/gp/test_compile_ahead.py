"""Tests of gpdepth3d.gp.compile_ahead and compile_wait: the kernels it compiles ahead are the ones a real run calls (the same
signatures, so a run loads them from the cache), the process it starts leaves them in the cache, and `ready`
waits for the groups that process reports."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp import compile_wait as ahead_module
from gpdepth3d.gp import multifrontal, neumann, readout, sublattice
from gpdepth3d.gp.compile_ahead import GROUPS, compile_ahead, compile_groups
from gpdepth3d.gp.compile_wait import ready
from gpdepth3d.gp.model import DepthGPConfig


def test_the_groups_compile_the_signatures_of_a_real_run(street_frame):
    # a real run first: the default model with enough points for the parallel detail (two frames: the second reuses
    # the prior's factor) and with few (the serial detail), the paper's model by the Neumann route; the groups must
    # then add no signature of their own (else a run would not find them cached)
    completer = DepthCompleter()
    for _ in range(2):  # the second frame of a resolution reuses the prior's factor
        completer.complete(street_frame.mde, street_frame.lidar)
    few = street_frame.lidar.subset(np.arange(0, len(street_frame.lidar), 64))
    DepthCompleter().complete(street_frame.mde, few)
    DepthCompleter(DepthGPConfig.paper(), engine=EngineConfig(route="neumann")).complete(
        street_frame.mde, street_frame.lidar
    )
    kernels = [
        multifrontal._solve,
        multifrontal._touched,
        readout._read_mean,
        sublattice._krige,
        sublattice._krige_serial,
        neumann._coefficients,
        neumann._neumann_mean,
        neumann._diag_series,
    ]
    before = [len(k.signatures) for k in kernels]
    assert all(n >= 1 for n in before), "the real run did not reach every kernel of the groups"
    compile_groups(list(GROUPS))
    assert [len(k.signatures) for k in kernels] == before


@pytest.mark.slow
def test_the_process_fills_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # a cold cache, inherited by the process
    monkeypatch.setattr(ahead_module, "_AHEAD", None)
    proc = compile_ahead(("neumann",))
    if proc is None:
        pytest.skip("one core: nothing is compiled ahead")
    ready("neumann")  # returns once the process has reported the group
    assert any(p.suffix == ".nbc" and "neumann" in p.name for p in tmp_path.rglob("*"))
    assert proc.wait(timeout=900) == 0
    assert ahead_module._AHEAD.pending == set()


def _reporting(*lines: str) -> subprocess.Popen:
    """A process that writes ``lines`` (group names) as the compiling process does, then ends."""
    script = "import sys; [print(x, flush=True) for x in sys.argv[1:]]"
    return subprocess.Popen([sys.executable, "-c", script, *lines], stdout=subprocess.PIPE)


def test_ready_waits_for_the_reported_group(monkeypatch):
    proc = _reporting("solve", "detail")
    monkeypatch.setattr(ahead_module, "_AHEAD", None)
    ahead_module.track(proc, ("solve", "detail", "neumann"))
    ready("other")  # not a group of the process: at once, nothing read
    assert ahead_module._AHEAD.pending == {"solve", "detail", "neumann"}
    ready("detail")  # reads the reports up to the group's
    assert ahead_module._AHEAD.pending == {"neumann"}
    ready("solve")  # already reported
    ready("neumann")  # never reported: the process ends, and nothing is left to wait for
    assert ahead_module._AHEAD.pending == set()
    assert proc.wait(timeout=60) == 0


def test_ready_stops_waiting_for_a_stuck_process(monkeypatch):
    """A process that reports nothing within `MAX_WAIT_S` is not waited for: the run compiles for itself."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], stdout=subprocess.PIPE)
    try:
        monkeypatch.setattr(ahead_module, "MAX_WAIT_S", 0.5)
        monkeypatch.setattr(ahead_module, "_AHEAD", None)
        ahead_module.track(proc, ("solve",))
        ready("solve")
        assert ahead_module._AHEAD.pending == set()
    finally:
        proc.kill()
        proc.wait()


def test_ready_without_a_process_returns_at_once(monkeypatch):
    monkeypatch.setattr(ahead_module, "_AHEAD", None)
    for group in GROUPS:
        ready(group)


def test_groups_are_checked():
    with pytest.raises(InvalidInputError, match="groups"):
        compile_ahead(("everything",))
    assert compile_ahead(()) is None
    with pytest.raises(KeyError):
        compile_groups(["everything"])
    assert GROUPS == ("solve", "detail_serial", "detail", "neumann", "reuse")  # the order a run reaches them


def test_one_process_at_most_and_the_switch_turns_it_off(monkeypatch):
    from gpdepth3d.gp import compile_ahead as module

    started, proc = [], _reporting()
    monkeypatch.setattr(ahead_module, "_AHEAD", None)
    monkeypatch.setattr(module.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(module.subprocess, "Popen", lambda *a, **k: started.append(a) or proc)
    monkeypatch.setenv(module.ENV_SWITCH, "0")
    assert compile_ahead(("solve",)) is None and not started
    monkeypatch.delenv(module.ENV_SWITCH)
    assert compile_ahead(("solve",)) is not None and len(started) == 1
    assert compile_ahead(("detail",)) is None and len(started) == 1  # one per process


def test_the_first_completion_call_starts_it_on_a_cold_cache(monkeypatch):
    from numba import njit

    from gpdepth3d.gp import compile_ahead as module
    from gpdepth3d.gp.compile_ahead import on_cold_cache

    calls = []
    monkeypatch.setattr(module, "_WATCHED", False)
    monkeypatch.setattr(module, "compile_ahead", calls.append)

    def compile_a_package_kernel():  # a new dispatcher of a package function: numba compiles it (a cold cache)
        arrays = (np.zeros(1, np.int64), np.full(1, -1), np.zeros(1, np.int64), np.ones(1, np.int64), np.ones(1))
        njit(multifrontal._touched.py_func)(*arrays)

    with on_cold_cache(("solve",)):
        compile_a_package_kernel()
    assert calls == [("solve",)]
    with on_cold_cache(("solve",)):  # only a process's first call watches
        compile_a_package_kernel()
    assert calls == [("solve",)]
