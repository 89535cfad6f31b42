"""Formulations as strategies (`gpdepth3d.completion.formulations`) and engines from their registry."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.completion.formulations import (
    FORMULATIONS,
    Balanced,
    Formulation,
    LogResidual,
    Residual,
    formulation_of,
    mde_on_output,
)
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import EngineConfig, make_engine
from gpdepth3d.gp.engine import ENGINE_NAMES, ENGINES
from gpdepth3d.gp.model import DepthGPConfig


def _scene(n=80, seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:h, 0:w]
    truth = 2.0 + 2.0 * rr / h + 0.3 * np.sin(cc / 6.0)
    mde = truth * np.exp(0.05 * rng.standard_normal((h, w)))
    return truth, mde, g.sample_uniform(truth, n=n, rng=seed)


class TestFormulations:
    def test_every_config_name_has_one_strategy(self):
        assert set(FORMULATIONS) == {"log_residual", "balanced", "residual"}
        for name, cls in (("log_residual", LogResidual), ("balanced", Balanced), ("residual", Residual)):
            strategy = formulation_of(DepthGPConfig(formulation=name))
            assert isinstance(strategy, cls) and isinstance(strategy, Formulation) and strategy.name == name
        assert isinstance(formulation_of(DepthGPConfig.paper()), Balanced)
        assert isinstance(formulation_of(DepthGPConfig.residual()), Residual)

    @pytest.mark.parametrize("config", [DepthGPConfig(), DepthGPConfig.paper(), DepthGPConfig.residual()])
    def test_the_strategy_gives_what_complete_returns(self, config):
        truth, mde, sp = _scene()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", g.PosteriorWarning)
            post = g.complete(mde, sp, config=config)
            completer = DepthCompleter(config)
            fields = formulation_of(config).posterior(completer, mde, sp, None, True, None)
        np.testing.assert_array_equal(fields["mean"], post.mean)
        np.testing.assert_array_equal(fields["variance"], post.variance)
        assert fields["config"] == post.config
        assert np.all(post.variance >= 0) and np.median(np.abs(post.mean - truth)) < 0.2

    def test_warnings_point_at_the_caller(self):
        _, mde, sp = _scene(n=3)
        with pytest.warns(g.PosteriorWarning) as record:
            g.DepthCompleter(DepthGPConfig()).complete(mde, sp)
        assert record[0].filename == __file__

    def test_mde_on_output(self):
        mde = np.array([[1.0, 2.0], [3.0, 0.0]])
        valid = mde > 0
        np.testing.assert_array_equal(mde_on_output(mde, valid, (2, 2)), mde)
        up = mde_on_output(mde, valid, (4, 4))
        assert up.shape == (4, 4) and up[3, 3] == 0.0 and up[0, 0] == 1.0


class TestEngineRegistry:
    def test_each_name_builds_its_engine(self):
        assert ENGINE_NAMES == tuple(ENGINES) == ("exact", "kissgp", "fast")
        for name in ("exact", "fast"):
            engine = make_engine(EngineConfig(name=name))
            assert type(engine).__name__ == ENGINES[name].class_name
        assert make_engine(EngineConfig(name="exact", max_exact_points=5)).max_points == 5

    def test_options_are_checked_against_the_engine(self):
        with pytest.raises(InvalidInputError, match="options"):
            make_engine(EngineConfig(name="exact", options={"max_points": 3}))  # a field sets it
        with pytest.raises(InvalidInputError, match="options"):
            make_engine(EngineConfig(name="fast", options={"no_such_option": 1}))
        with pytest.raises(InvalidInputError, match="name"):
            EngineConfig(name="dense")
