"""Tests of gpdepth3d.gp.compile_ahead: the kernels it compiles ahead are the ones a real run calls (the same
signatures, so a run loads them from the cache), and the process it starts leaves them in the cache."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp import neumann, readout, sublattice
from gpdepth3d.gp.compile_ahead import GROUPS, compile_ahead, compile_groups
from gpdepth3d.gp.model import DepthGPConfig


def test_the_groups_compile_the_signatures_of_a_real_run(street_frame):
    # a real run first: the default model with enough points for the parallel detail, the paper's model by the
    # Neumann route; the groups must then add no signature of their own (else a run would not find them cached)
    DepthCompleter().complete(street_frame.mde, street_frame.lidar)
    DepthCompleter(DepthGPConfig.paper(), engine=EngineConfig(route="neumann")).complete(
        street_frame.mde, street_frame.lidar
    )
    kernels = [
        readout._read_mean,
        sublattice._krige,
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
    proc = compile_ahead(("neumann",))
    if proc is None:
        pytest.skip("one core: nothing is compiled ahead")
    assert proc.wait(timeout=900) == 0
    assert any(p.suffix == ".nbc" and "neumann" in p.name for p in tmp_path.rglob("*"))


def test_groups_are_checked():
    with pytest.raises(InvalidInputError, match="groups"):
        compile_ahead(("everything",))
    assert compile_ahead(()) is None
    with pytest.raises(KeyError):
        compile_groups(["everything"])
    assert np.all([g in ("detail", "neumann") for g in GROUPS])
