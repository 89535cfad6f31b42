"""`single_threaded_blas`: one BLAS thread inside, the counts restored by the thread's outermost block."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from gpdepth3d.gp.blas_threads import single_threaded_blas


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():
    np.ones(2) @ np.ones(2)  # the BLAS library loaded
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl controls")
    with threadpool_limits(limits=2, user_api="blas"):
        yield


def test_one_thread_inside_and_the_counts_restored_after(two_blas_threads):
    before = _blas_threads()
    with single_threaded_blas():
        assert set(_blas_threads()) == {1}
        with single_threaded_blas():  # nested: nothing to set, nothing restored on leaving
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before


def test_a_block_inside_another_thread_sets_and_restores_its_own(two_blas_threads):
    seen = []

    def work():
        with single_threaded_blas():
            seen.append(set(_blas_threads()))
        seen.append(set(_blas_threads()))

    before = _blas_threads()
    with single_threaded_blas():
        t = threading.Thread(target=work)
        t.start()
        t.join()
        assert seen == [{1}, {1}]  # that thread's block restored the counts it found: this block's
    assert _blas_threads() == before


def test_the_counts_are_restored_after_an_error(two_blas_threads):
    before = _blas_threads()
    with pytest.raises(RuntimeError):
        with single_threaded_blas():
            with single_threaded_blas():
                raise RuntimeError("inside")
    assert _blas_threads() == before
    with single_threaded_blas():  # the thread's depth went back to 0: this block sets the count again
        assert set(_blas_threads()) == {1}
