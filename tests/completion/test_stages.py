"""The default model's stages (`gpdepth3d.completion.log_residual`) and the nested configs that hold their options."""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict

import numba
import numpy as np
import pytest

import gpdepth3d as g
from gpdepth3d.completion.complete import DepthPosterior, PosteriorWarning
from gpdepth3d.completion.lattice import build_lattice, lattice_stride
from gpdepth3d.completion.log_frame import log_frame
from gpdepth3d.completion.log_residual import log_residual_posterior
from gpdepth3d.completion.problem import _frame_inputs
from gpdepth3d.completion.screen import follow_slope, screen, start_search
from gpdepth3d.completion.mde_slope import fit_slope, refit_slope
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp import make_engine
from gpdepth3d.gp.model import (
    AssemblyConfig,
    CalibrationConfig,
    DepthGPConfig,
    LatticeConfig,
    ScreenConfig,
    SlopeConfig,
)


def _scene(n=120, seed=0, h=30, w=40):
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:h, 0:w]
    truth = 2.0 + 2.0 * rr / h + 0.3 * np.sin(cc / 6.0)
    mde = truth**1.6 * 0.5 * np.exp(0.05 * rng.standard_normal((h, w)))  # over-states depth differences
    sp = g.sample_uniform(truth, n=n, rng=seed)
    return truth, mde, sp


def _frame(mde, sp, config, output_shape=None):
    m, valid, grid_sparse, out_shape = _frame_inputs(mde, sp, output_shape)
    return log_frame(m, valid, grid_sparse, out_shape, config)


class TestStages:
    def test_the_stages_give_what_complete_gives(self):
        _, mde, sp = _scene()
        config = DepthGPConfig()
        result = log_residual_posterior(make_engine(), _frame(mde, sp, config), config)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PosteriorWarning)
            post = g.complete(mde, sp, config=config)
        np.testing.assert_array_equal(result.mean, post.mean)
        np.testing.assert_array_equal(result.variance, post.variance)
        assert result.slope == post.mde_slope and result.config == post.config

    def test_slope_follows_an_mde_that_over_states_depth_differences(self):
        _, mde, sp = _scene()
        config = DepthGPConfig()
        sloped = fit_slope(_frame(mde, sp, config), config)
        assert 0.45 < sloped.a < 0.8  # the points' log depth follows the MDE's with a slope of 1 / 1.6
        fixed = fit_slope(_frame(mde, sp, config), config.replace(slope={"prior_sigma": None}))
        assert fixed.fit is None and fixed.a == 1.0

    def test_refit_without_the_rejected_points_moves_the_slope_and_b(self):
        _, mde, sp = _scene(seed=1)
        depth = sp.depth.copy()
        depth[:6] *= 0.1  # gross outliers, far too close
        bad = g.SparseDepth(sp.u, sp.v, depth, sp.image_size)
        config = DepthGPConfig()
        frame = _frame(mde, bad, config)
        first = fit_slope(frame, config)
        screened = screen(frame, first, config)
        assert screened.rejected[:6].sum() >= 3
        again = refit_slope(frame, first, screened.rejected, config)
        assert again is not first and again.a != first.a and again.fit.n_used == int(screened.keep.sum())
        moved = follow_slope(screened, first, again, config)
        assert moved.fit.log_scale == pytest.approx(float(np.median(again.resid)))
        assert follow_slope(screened, first, first, config) is screened

    def test_screen_with_its_first_search_started_before_is_the_same(self):
        """`start_search` (the screen's first neighbour search on a second thread while the slope is fitted) changes
        nothing in `screen`; None where the screen does not search."""
        _, mde, sp = _scene(n=900, h=60, w=80)
        config = DepthGPConfig()
        frame = _frame(mde, sp, config)
        search = start_search(frame, config)
        if numba.get_num_threads() < 2:
            pytest.skip("numba has one thread: no search is started")
        assert search is not None
        first = fit_slope(frame, config)
        got, ref = screen(frame, first, config, search=search), screen(frame, first, config)
        assert got.fit == ref.fit
        for name in ("rejected", "zscores", "shares", "noise"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
        assert start_search(frame, config.replace(screen={"outlier_threshold": None})) is None
        assert start_search(_frame(*_scene()[1:], config), config) is None  # too few points to split

    def test_log_mde_at_is_the_log_mde_at_each_point(self):
        _, mde, sp = _scene()
        frame = _frame(mde, sp, DepthGPConfig())
        np.testing.assert_array_equal(frame.log_mde_at, np.log(frame.base[frame.rows, frame.cols]))
        assert frame.log_mde_at is frame.log_mde_at  # computed once

    def test_lattice_holds_every_kept_point(self):
        _, mde, sp = _scene(n=200)
        config = DepthGPConfig()
        frame = _frame(mde, sp, config)
        sloped = fit_slope(frame, config)
        screened = screen(frame, sloped, config)
        lattice = build_lattice(frame, sloped, screened, config, stride=2)
        assert lattice.stride == 2 and lattice.problem.shape == (15, 20)
        observed = np.unique((lattice.rows // 2) * 20 + lattice.cols // 2)
        assert np.count_nonzero(lattice.problem.precision) == observed.size
        assert lattice.targets.shape == (int(screened.keep.sum()), 3)  # residuals, ones, centred log MDE
        np.testing.assert_array_equal(lattice.extra[0], lattice.problem.precision > 0)  # 1 at the observed nodes
        again = build_lattice(frame, sloped, screened, config, stride=2)  # the prior means: zeros made once per shape
        for prior in (lattice.problem.prior_mean, lattice.problem.out_prior_mean):
            assert not prior.flags.writeable and not prior.any()
        assert again.problem.out_prior_mean is lattice.problem.out_prior_mean
        assert lattice.problem.out_prior_mean.shape == frame.out_shape


class TestNestedConfigs:
    @pytest.mark.parametrize(
        "make, field",
        [
            (lambda: ScreenConfig(neighbours=0), "neighbours"),
            (lambda: ScreenConfig(fit_nuggets=()), "fit_nuggets"),
            (lambda: ScreenConfig(fit_lengthscales=(2.0, -1.0)), "fit_lengthscales"),
            (lambda: SlopeConfig(huber=0.0), "huber"),
            (lambda: SlopeConfig(min_points=2), "min_points"),
            (lambda: LatticeConfig(detail_share=2.0), "detail_share"),
            (lambda: LatticeConfig(dense_stride=17), "dense_stride"),
            (lambda: AssemblyConfig(weight_floor=0.0), "weight_floor"),
            (lambda: CalibrationConfig(zscore_cap=0.5), "zscore_cap"),
            (lambda: DepthGPConfig(screen={"neighbours": "many"}), "neighbours"),
            (lambda: DepthGPConfig(slope=3), "slope"),
        ],
    )
    def test_bad_values_are_refused_by_name(self, make, field):
        with pytest.raises(InvalidInputError, match=field):
            make()

    def test_json_round_trip(self):
        config = DepthGPConfig(
            screen=ScreenConfig(neighbours=8, fit_nuggets=(0.1, 1.0)), calibration=CalibrationConfig(prior_points=3.0)
        )
        back = DepthGPConfig(**json.loads(json.dumps(asdict(config))))
        assert back == config and isinstance(back.screen.fit_nuggets, tuple)
        assert DepthGPConfig.from_dict(json.loads(json.dumps(asdict(config)))) == config

    def test_replace_with_a_dict_changes_only_those_fields_of_a_nested_config(self):
        base = DepthGPConfig.paper()
        assert base.replace(assembly={"edge_sigma": 0.5}).assembly == AssemblyConfig(
            depth_lengthscale=None, edge_sigma=0.5
        )
        assert DepthGPConfig.paper(calibration={"min_points": 3}).calibration == CalibrationConfig(
            reach=None, min_points=3
        )
        assert base.replace(calibration=CalibrationConfig(min_points=3)).calibration.reach == 1.5  # a config: all of it
        with pytest.raises(InvalidInputError, match="edge_sigma"):
            base.replace(assembly={"edge_sigma": -1.0})
        with pytest.raises(InvalidInputError, match="unknown keys"):
            base.replace(assembly={"no_such_field": 1.0})

    def test_from_dict_reads_what_asdict_writes(self):
        """A stored config (``asdict``, through JSON) reads back as the same model; anything else is refused."""
        config = DepthGPConfig(
            nugget=0.03,
            screen=ScreenConfig(outlier_threshold=2.5, raise_outputscale=False),
            slope=SlopeConfig(prior_sigma=0.25),
            assembly=AssemblyConfig(depth_lengthscale=None, edge_sigma=0.5),
            calibration=CalibrationConfig(reach=3.0),
        )
        assert DepthGPConfig.from_dict(json.loads(json.dumps(asdict(config)))) == config
        partial = DepthGPConfig.from_dict({"calibration": {"min_points": 5}})
        assert partial.calibration == CalibrationConfig(min_points=5)
        for unknown in ({"no_such_field": 1}, {"local_calibration": None}, {"engine": "exact"}):
            with pytest.raises(InvalidInputError, match="unknown keys"):
                DepthGPConfig.from_dict(unknown)
        with pytest.raises(InvalidInputError, match="config"):
            DepthGPConfig.from_dict([("nugget", 0.03)])
        with pytest.raises(InvalidInputError, match="reach"):
            DepthGPConfig.from_dict({"calibration": {"reach": -1.0}})

    def test_a_saved_posterior_loads_with_its_config(self, tmp_path):
        """A file this version writes loads as the same model (its nested config included)."""
        _, mde, sp = _scene()
        config = DepthGPConfig(
            nugget=0.03, screen=ScreenConfig(outlier_threshold=3.0), calibration=CalibrationConfig(reach=2.0)
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PosteriorWarning)
            post = g.complete(mde, sp, config=config)
        path = post.save(tmp_path / "p")[0]
        assert DepthPosterior.load(path).config == post.config == config

    def test_the_options_reach_their_stage(self):
        _, mde, sp = _scene(n=300, seed=2)
        base = DepthGPConfig()
        assert lattice_stride(base.replace(lattice=LatticeConfig(dense_stride=2)), 125, 414, 10**4, 32.0) == 2
        assert lattice_stride(base.replace(lattice=LatticeConfig(min_side=200)), 125, 414, 10, 32.0) == 1
        assert lattice_stride(base, 125, 414, 10**4, 32.0, stride=2) == 2  # `EngineConfig.lattice_stride`
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PosteriorWarning)
            ref = g.complete(mde, sp, config=base)
            for changed in (
                base.replace(screen=ScreenConfig(neighbours=4)),
                base.replace(slope=SlopeConfig(max_points=10)),
                base.replace(calibration=CalibrationConfig(prior_points=50.0)),
            ):
                post = g.complete(mde, sp, config=changed)
                assert not np.array_equal(post.variance, ref.variance)
            few = g.complete(mde, sp, config=base.replace(calibration=CalibrationConfig(min_points=10**4)))
            off = g.complete(mde, sp, config=base.replace(calibration={"reach": None}))
        np.testing.assert_array_equal(few.variance, off.variance)  # too few points: the model's own variance
