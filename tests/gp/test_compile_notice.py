"""`gpdepth3d.gp.compile_notice.on_first_compile`: called once before numba compiles, never on a cache hit."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.compile_notice import on_first_compile

ROOT = Path(__file__).resolve().parents[2]

KERNELS = textwrap.dedent("""
    import numba as nb

    @nb.njit(cache=True)
    def twice(x):
        return 2 * x

    @nb.njit(cache=True)
    def thrice(x):
        return 3 * x
""")

RUN = textwrap.dedent("""
    import sys
    sys.path.insert(0, sys.argv[1])
    from gpdepth3d.gp.compile_notice import on_first_compile
    import notice_kernels as k
    calls = []
    with on_first_compile(calls.append, prefix="notice_kernels"):
        assert k.twice(2) == 4 and k.thrice(2) == 6
    assert k.twice(2.5) == 5.0  # compiled outside the block: not reported
    print(calls)
""")


def _run(folder: Path) -> str:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("NUMBA_CACHE_DIR", None)  # the cache beside the module, in the test's folder
    proc = subprocess.run(
        [sys.executable, "-c", RUN, str(folder)], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


@pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
def test_once_on_a_cold_cache_never_on_a_warm_one(tmp_path):
    (tmp_path / "notice_kernels.py").write_text(KERNELS)
    assert _run(tmp_path) == "['notice_kernels.twice']"  # two kernels compiled, one call, the first one's name
    assert _run(tmp_path) == "[]"  # both from the cache now


def test_other_modules_and_errors():
    import numba as nb

    calls = []

    @nb.njit
    def local(x):
        return x + 1

    with on_first_compile(calls.append):  # this test module is not the package: not reported
        assert local(1) == 2
    assert calls == []
    with pytest.raises(InvalidInputError, match="callback"):
        with on_first_compile("print"):
            pass
