"""Tests of `DepthCompleter.map` (gpdepth3d.completion.parallel): a sequence completed frame after frame or
several frames at a time gives each frame the posterior of `DepthCompleter.complete`."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.completion.parallel import check_workers
from gpdepth3d.errors import InvalidDepthError, InvalidInputError
from gpdepth3d.datasets.synthetic import make_scene
from gpdepth3d.gp.model import DepthGPConfig


@pytest.fixture(scope="module")
def frames():
    """Five simulated street frames (different seeds: different scenes, points and MDE errors)."""
    scenes = [make_scene(seed, kind="street", width=160, height=48) for seed in range(5)]
    return [(s.mde, s.lidar.subset(np.arange(0, len(s.lidar), 3))) for s in scenes]


def _assert_same(a, b):
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(a.variance, b.variance, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("workers", [2, 3])
def test_workers_give_the_serial_posteriors_in_order(frames, workers):
    alone = [DepthCompleter().complete(mde, sparse) for mde, sparse in frames]
    together = list(DepthCompleter().map(iter(frames), workers=workers))
    assert len(together) == len(frames)
    for a, b in zip(together, alone):
        _assert_same(a, b)


def test_one_worker_and_fit_run_in_order(frames):
    completer = DepthCompleter(DepthGPConfig(fit=True))
    chained = list(completer.map(frames[:3], workers=4))  # fit: each frame starts from the previous fit
    serial = DepthCompleter(DepthGPConfig(fit=True))
    for post, (mde, sparse) in zip(chained, frames[:3]):
        _assert_same(post, serial.complete(mde, sparse))
    first = list(DepthCompleter().map(frames[:2]))
    _assert_same(first[1], DepthCompleter().complete(*frames[1]))


def test_output_shape_and_mean_only_reach_every_frame(frames):
    out = list(DepthCompleter().map(frames[:3], workers=2, output_shape=(96, 320), variance=False))
    assert all(p.mean.shape == (96, 320) and np.isnan(p.variance).all() for p in out)


def test_a_frame_error_is_raised_in_its_turn(frames):
    bad = [frames[0], (np.full((48, 160), -1.0), frames[1][1]), frames[2]]
    posteriors = DepthCompleter().map(bad, workers=2)
    assert next(posteriors).mean.shape == (48, 160)
    with pytest.raises(InvalidDepthError):
        next(posteriors)


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_workers_are_checked_up_front(workers):
    with pytest.raises(InvalidInputError, match="workers"):
        DepthCompleter().map([], workers=workers)
    assert check_workers(None) >= 1 and check_workers(3) == 3
