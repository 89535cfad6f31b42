"""The posterior obeys the laws of its output: variance >= 0 and finite, mean finite (> 0 for the log-normal
default), or a typed error; hyperparameters outside the ranges that keep it so are refused by name.

The real-data cases are the inputs that once gave negative variances (disparity passed as depth on KITTI,
points an order of magnitude apart on 7-Scenes); the property test draws such inputs at random.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import gpdepth3d as g
from gpdepth3d.gp.engine import EngineConfig
from gpdepth3d.gp.model import ScreenConfig
from gpdepth3d.completion.complete import PosteriorWarning
from gpdepth3d.errors import GPDepthError, InvalidInputError
from gpdepth3d.mapping.mapper_config import MAPPER_GP

EXACT = EngineConfig(name="exact")


def _quiet(mde, sparse, config, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PosteriorWarning)
        return g.complete(mde, sparse, config=config, **kwargs)


def _assert_valid(post, *, positive: bool = True) -> None:
    assert np.all(np.isfinite(post.variance)) and np.all(post.variance >= 0), float(np.nanmin(post.variance))
    assert np.all(np.isfinite(post.mean))
    if positive:
        assert np.all(post.mean > 0)


# ----------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def kitti_disparity(shared_data):
    """kitti_tiny frame 0 at 1/3: RT-MonoDepth-S's disparity (1 / depth) passed as depth, and its LiDAR."""
    pytest.importorskip("onnxruntime")
    from gpdepth3d.pipelines.frames import mde_to_grid
    from gpdepth3d.mde import load_frontend

    models = shared_data.parent / "models"
    if not (models / "rtmonodepth_s_ms_640_192.onnx").is_file() or not (shared_data / "kitti_tiny").is_dir():
        pytest.skip("RT-MonoDepth-S or kitti_tiny not found")
    frame = g.open_dataset(shared_data / "kitti_tiny")[0]
    mde = mde_to_grid(np.asarray(load_frontend("rtmonodepth", models_dir=models)(frame.rgb), dtype=np.float64), 3)
    return 1.0 / mde, frame.sparse


@pytest.fixture(scope="module")
def seven_scenes_two_depths(shared_data):
    """7-Scenes frame 0, FastDepth at 320 x 240, 200 points: those on the left half at 1 m, on the right at 10 m."""
    pytest.importorskip("ai_edge_litert")
    from gpdepth3d.mde import load_frontend

    models = shared_data.parent / "models"
    if not (models / "fast_depth_224.tflite").is_file() or not (shared_data / "7scenes").is_dir():
        pytest.skip("FastDepth or 7scenes not found")
    small = g.open_dataset(shared_data / "7scenes")[0].resized(0.5)
    mde = np.asarray(load_frontend("fastdepth", models_dir=models)(small.rgb), dtype=np.float64)
    sp = g.sample_uniform(small.depth, n=200, rng=0)
    return mde, g.SparseDepth(sp.u, sp.v, np.where(sp.u < sp.image_size[1] / 2, 1.0, 10.0), sp.image_size)


@pytest.mark.shared_data
@pytest.mark.slow
class TestRealCases:
    @pytest.mark.parametrize("config", [g.DepthGPConfig(), MAPPER_GP], ids=["default", "mapper"])
    def test_kitti_disparity_with_all_of_the_lidar(self, kitti_disparity, config):
        disparity, lidar = kitti_disparity
        _assert_valid(_quiet(disparity, lidar, config))

    @pytest.mark.parametrize(
        "config, engine",
        [(g.DepthGPConfig(), None), (MAPPER_GP, None), (g.DepthGPConfig(), EXACT)],
        ids=["default", "mapper", "exact"],
    )
    def test_kitti_disparity_with_200_points(self, kitti_disparity, config, engine):
        disparity, lidar = kitti_disparity
        post = _quiet(disparity, g.sample_uniform(lidar, n=200, rng=0), config, engine=engine)
        _assert_valid(post)
        assert post.mde_slope < 0  # the points say the MDE runs backwards; the variance is still a variance

    @pytest.mark.parametrize(
        "config, engine",
        [(g.DepthGPConfig(), None), (MAPPER_GP, None), (g.DepthGPConfig(), EXACT)],
        ids=["default", "mapper", "exact"],
    )
    def test_seven_scenes_points_at_1_and_10_m(self, seven_scenes_two_depths, config, engine):
        _assert_valid(_quiet(*seven_scenes_two_depths, config, engine=engine))

    def test_without_variance_the_mean_is_bit_identical(self, kitti_disparity):
        disparity, lidar = kitti_disparity
        sp = g.sample_uniform(lidar, n=500, rng=1)
        with_var = _quiet(1.0 / disparity, sp, g.DepthGPConfig())
        without = _quiet(1.0 / disparity, sp, g.DepthGPConfig(), variance=False)
        np.testing.assert_array_equal(without.mean, with_var.mean)
        assert np.all(np.isnan(without.variance))


# ----------------------------------------------------------------------------- hyperparameter ranges
def _small_inputs(seed: int = 0):
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:20, 0:28]
    mde = 2.0 + np.sin(rr / 5.0) + 0.5 * cc / 28
    u, v = rng.integers(0, 28, 40).astype(float), rng.integers(0, 20, 40).astype(float)
    depth = 1.2 * mde[v.astype(int), u.astype(int)] * np.exp(0.1 * rng.standard_normal(40))
    return mde, g.SparseDepth(u, v, depth, (20, 28))


def _config(**changes) -> g.DepthGPConfig:
    """The default config with ``changes``; a key "section.field" changes a field of a nested config."""
    top, nested = {}, {}
    for key, value in changes.items():
        if "." in key:
            section, name = key.split(".")
            nested.setdefault(section, {})[name] = value
        else:
            top[key] = value
    return g.DepthGPConfig().replace(**top, **nested)


@pytest.mark.parametrize(
    "field, value",
    [
        ("nugget", 100.0),
        ("outputscale", 50.0),
        ("nugget", 3.01),
        ("slope.prior_sigma", 1e-300),
        ("slope.prior_sigma", 1e300),
        ("calibration.reach", 1e-300),
        ("calibration.reach", 1e300),
        ("assembly.depth_lengthscale", 1e-320),
        ("assembly.edge_sigma", 1e100),
        ("lengthscale", 1e-300),
    ],
)
def test_hyperparameters_outside_their_range_are_refused_by_name(field, value):
    with pytest.raises(InvalidInputError, match=rf"{field.split('.')[-1]}: expected a number in \["):
        _config(**{field: value})


def test_a_large_relative_outputscale_stays_allowed_for_the_gaussian_formulations():
    assert g.DepthGPConfig.paper(outputscale=50.0).outputscale == 50.0


@pytest.mark.parametrize(
    "changes",
    [
        {
            "nugget": 3.0,
            "outputscale": 3.0,
            "slope.prior_sigma": 3.0,
            "assembly.edge_sigma": 10.0,
            "calibration.reach": 100.0,
            "assembly.depth_lengthscale": 1e3,
            "lengthscale": 1e5,
        },
        {
            "nugget": 0.0,
            "outputscale": 1e-9,
            "slope.prior_sigma": 1e-3,
            "assembly.edge_sigma": 0.0,
            "calibration.reach": 0.1,
            "assembly.depth_lengthscale": 1e-3,
            "lengthscale": 1e-3,
        },
    ],
)
def test_the_ends_of_the_ranges_give_a_valid_posterior(changes):
    mde, sp = _small_inputs()
    for engine in ("fast", "exact"):
        try:
            post = _quiet(mde, sp, _config(**changes), engine=EngineConfig(name=engine))
        except GPDepthError:
            continue  # a typed refusal is allowed; a silent inf or negative variance is not
        _assert_valid(post)


def test_a_fitted_scale_stays_inside_the_range():
    """Points whose log ratio to the MDE spreads over a factor of 1000: the raised s is capped at the bound."""
    rng = np.random.default_rng(3)
    mde, sp = _small_inputs(3)
    wild = g.SparseDepth(sp.u, sp.v, sp.depth * np.exp(rng.uniform(-7, 7, len(sp))), sp.image_size)
    for config in (g.DepthGPConfig(), g.DepthGPConfig(fit=True)):
        post = _quiet(mde, wild, config)
        assert post.config.outputscale <= 3.0 and post.config.nugget <= 3.0
        _assert_valid(post)


@pytest.mark.parametrize(
    "config, engine",
    [
        (g.DepthGPConfig(), None),
        (MAPPER_GP, None),
        (g.DepthGPConfig(), EXACT),
        (g.DepthGPConfig(screen=ScreenConfig(outlier_threshold=None)), None),
        (g.DepthGPConfig(fit=True), None),
    ],
    ids=["default", "mapper", "exact", "no-screen", "fit"],
)
def test_without_variance_the_mean_is_bit_identical_on_small_frames(config, engine):
    mde, sp = _small_inputs(1)
    for shape in (None, (40, 56), (10, 14)):
        a = _quiet(mde, sp, config, engine=engine, output_shape=shape)
        b = _quiet(mde, sp, config, engine=engine, output_shape=shape, variance=False)
        np.testing.assert_array_equal(a.mean, b.mean)
        assert np.all(np.isnan(b.variance))


# ----------------------------------------------------------------------------- property test
def _mde(kind: str, h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:h, 0:w]
    depth = 1.5 + 8.0 * rr / h * (0.5 + rng.random()) + np.sin(cc / (2 + 5 * rng.random()))
    if kind == "disparity":
        return 1.0 / depth
    if kind == "flipped":
        return depth.max() + depth.min() - depth
    if kind == "constant":
        return np.full((h, w), 0.5 + 5 * rng.random())
    return depth


def _points(kind: str, mde: np.ndarray, n: int, seed: int) -> g.SparseDepth:
    rng = np.random.default_rng(seed)
    h, w = mde.shape
    u, v = rng.integers(0, w, n).astype(float), rng.integers(0, h, n).astype(float)
    if kind == "two_clusters":  # an order of magnitude apart, whatever the MDE says
        near = 0.3 + rng.random()
        depth = np.where(u < w / 2, near, 10 * near) * np.exp(0.02 * rng.standard_normal(n))
    else:
        depth = np.abs(mde[v.astype(int), u.astype(int)] * rng.uniform(0.3, 3.0) * np.exp(0.2 * rng.standard_normal(n)))
    sigma = np.full(n, np.nan) if rng.random() < 0.5 else 0.01 * depth
    return g.SparseDepth(u, v, np.maximum(depth, 1e-3), (h, w), sigma)


FORMULATIONS = {
    "log_residual": g.DepthGPConfig(),
    "log_residual_fit": g.DepthGPConfig(fit=True),
    "balanced": g.DepthGPConfig.paper(),
    "residual": g.DepthGPConfig.residual(),
}


@pytest.mark.parametrize("formulation", sorted(FORMULATIONS))
@pytest.mark.parametrize("engine, examples", [("fast", 25), ("exact", 25), ("kissgp", 3)])
def test_posterior_is_valid_for_random_inputs(formulation, engine, examples):
    if engine == "kissgp":
        pytest.importorskip("gpytorch")

    @settings(max_examples=examples, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
    @given(
        mde_kind=st.sampled_from(["depth", "disparity", "flipped", "constant"]),
        point_kind=st.sampled_from(["uniform", "two_clusters"]),
        h=st.integers(6, 20),
        w=st.integers(6, 24),
        n=st.integers(0, 60),
        seed=st.integers(0, 2**16),
        upsample=st.booleans(),
    )
    def check(mde_kind, point_kind, h, w, n, seed, upsample):
        mde = _mde(mde_kind, h, w, seed)
        sparse = _points(point_kind, mde, n, seed + 1)
        config = FORMULATIONS[formulation]
        shape = (2 * h, 2 * w) if upsample else None
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PosteriorWarning)
            try:
                post = g.complete(mde, sparse, config=config, engine=EngineConfig(name=engine), output_shape=shape)
            except GPDepthError:
                return  # a typed error is an allowed answer
        gaussian = not formulation.startswith("log_residual")
        _assert_valid(post, positive=not gaussian)
        if gaussian and not np.all(post.mean > 0):  # a Gaussian model in metres: said, not hidden
            assert any("posterior mean <= 0" in str(c.message) for c in caught)

    check()


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    a=st.floats(-5, 5),
    lz=st.floats(1e-3, 1e3),
    s=st.floats(1e-3, 3.0),
    tau=st.floats(0.0, 3.0),
    var_b=st.floats(0.0, 9.0),
    var_a=st.floats(0.0, 9.0),
    seed=st.integers(0, 2**16),
)
def test_assemble_gives_a_variance_for_any_slope_and_weights(a, lz, s, tau, var_b, var_a, seed):
    """The read-out alone: any slope sign, any kriging weights and an engine variance in [0, s^2] give var >= 0
    (an overflow to inf is refused by `assemble_depth` with a typed error; NaN or a negative value never comes)."""
    from gpdepth3d.completion.assemble import assemble

    rng = np.random.default_rng(seed)
    shape = (4, 5)
    log_out, x_out = rng.normal(1.0, 1.0, shape), rng.normal(0.0, 2.0, shape)
    g_mean, g_var = rng.normal(0.0, s, shape), rng.uniform(0.0, s * s, shape)
    w1, wx = rng.normal(0.5, 1.0, shape), rng.normal(0.0, 3.0, shape)
    mean, var = assemble(
        log_out,
        g_mean,
        g_var,
        w1,
        wx,
        x_out,
        b=0.1,
        s2=s * s,
        tau2=tau * tau,
        var_b=var_b,
        var_a=var_a,
        a=a,
        lz=lz,
        floor=1e-3,
        scale_term=True,
        slope_term=True,
        variance=True,
    )
    assert np.all(mean > 0) and np.all(var >= 0)  # NaN fails both


def test_read_out_centres_in_the_pass_and_counts_the_pixels_that_overflow():
    """`_read_out` with ``centre`` gives `assemble` of the centred map bit for bit (serial and parallel sizes), and
    counts the pixels whose mean is not finite and > 0 or whose variance is not finite (`assemble_depth` refuses
    those)."""
    from gpdepth3d.completion.assemble import CHUNK, _read_out, assemble

    rng = np.random.default_rng(5)
    terms = dict(b=0.1, s2=0.04, tau2=4e-4, var_b=1e-4, var_a=3e-3, a=0.9, lz=0.7, floor=1e-3, scale_term=True)
    for shape in ((4, 5), (3, CHUNK // 2 + 7)):
        log_out, x_raw = rng.normal(1.0, 1.0, shape), rng.normal(2.0, 2.0, shape)
        g_mean, g_var = rng.normal(0.0, 0.2, shape), rng.uniform(0.0, 0.04, shape)
        w1, wx = rng.normal(0.5, 1.0, shape), rng.normal(0.0, 3.0, shape)
        fields = (log_out, g_mean, g_var, w1, wx)
        mean, var = assemble(*fields, x_raw - 2.5, **terms, slope_term=True, variance=True)
        mean2, var2, bad = _read_out(*fields, x_raw, **terms, slope_term=True, variance=True, centre=2.5)
        np.testing.assert_array_equal(mean2, mean)
        np.testing.assert_array_equal(var2, var)
        assert bad == 0
        log_out[0, :2] = 800.0  # exp overflows: inf
        g_var[1, 0] = np.nan
        assert _read_out(*fields, x_raw, **terms, slope_term=True, variance=True, centre=2.5)[2] == 3


@pytest.mark.parametrize("lz", [None, 0.7])
@pytest.mark.parametrize("scale_term", [False, True])
@pytest.mark.parametrize("slope_term", [False, True])
@pytest.mark.parametrize("variance", [False, True])
def test_assemble_is_the_formula_of_its_module(lz, scale_term, slope_term, variance):
    """The compiled read-out against the module docstring's formula in numpy, every switch on and off (pixels with
    |w1| under the floor included: rho = 1 there)."""
    from gpdepth3d.completion.assemble import assemble

    rng = np.random.default_rng(7)
    shape = (6, 9)
    log_out, x_out = rng.normal(1.0, 1.0, shape), rng.normal(0.0, 2.0, shape)
    g_mean, g_var = rng.normal(0.0, 0.2, shape), rng.uniform(-1e-9, 0.04, shape)
    w1, wx = rng.normal(0.5, 1.0, shape), rng.normal(0.0, 3.0, shape)
    w1[0, :3] = [0.0, 5e-4, -5e-4]
    b, s2, tau2, var_b, var_a, a, floor = 0.1, 0.04, 4e-4, 1e-3, 3e-3, -0.9, 1e-3
    mean, var = assemble(
        log_out, g_mean, g_var, w1, wx, x_out, b=b, s2=s2, tau2=tau2, var_b=var_b, var_a=var_a, a=a, lz=lz,
        floor=floor, scale_term=scale_term, slope_term=slope_term, variance=variance,
    )  # fmt: skip
    rho = np.ones(shape)
    if lz is not None:
        ok = np.abs(w1) >= floor
        rho[ok] = np.exp(-abs(a) * np.abs(x_out - wx / np.where(ok, w1, 1.0)) / lz)[ok]
    v = np.zeros(shape)
    if variance:
        gv = np.maximum(g_var, 0.0)
        if lz is not None:
            gv = (1 - rho**2) * s2 + rho**2 * gv
        v = gv + tau2 + var_b * ((1 - rho * w1) ** 2 if scale_term else 1.0)
        v += var_a * (x_out - rho * wx) ** 2 if slope_term else 0.0
    expected = np.exp(log_out + b + rho * g_mean + v / 2)
    np.testing.assert_allclose(mean, expected, rtol=1e-12)
    if variance:
        np.testing.assert_allclose(var, np.expm1(v) * expected**2, rtol=1e-12)
    else:
        assert np.all(np.isnan(var))
