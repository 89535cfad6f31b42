"""The one validation vocabulary (`gpdepth3d.checks`) and every config that uses it, table-driven."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpdepth3d.checks import (
    Bool,
    Choice,
    Instance,
    Int,
    Real,
    Reals,
    check_bool,
    check_choice,
    check_fields,
    check_int,
    check_real,
    is_integer,
    is_real,
)
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.evaluation.kitti_protocol import KittiProtocolConfig
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp.model import (
    AssemblyConfig,
    CalibrationConfig,
    DepthGPConfig,
    LatticeConfig,
    ScreenConfig,
    SlopeConfig,
)
from gpdepth3d.mapping.tsdf.fusion_config import FusionConfig
from gpdepth3d.mapping.mapper_config import MapperConfig
from gpdepth3d.mapping.points.refinding import RefindConfig
from gpdepth3d.mapping.points.triangulation_config import TriangulationConfig
from gpdepth3d.viewer.app import ViewerConfig

CONFIGS = [
    DepthGPConfig,
    ScreenConfig,
    SlopeConfig,
    LatticeConfig,
    AssemblyConfig,
    CalibrationConfig,
    EngineConfig,
    FusionConfig,
    MapperConfig,
    TriangulationConfig,
    RefindConfig,
    ViewerConfig,
    KittiProtocolConfig,
]

# (config, field, a value that must be refused); every kind of mistake on every config
REFUSED = [
    (DepthGPConfig, "formulation", "gaussian"),
    (DepthGPConfig, "nu", 1.0),
    (DepthGPConfig, "nu", True),
    (DepthGPConfig, "lengthscale", 0.0),
    (DepthGPConfig, "outputscale", math.nan),
    (DepthGPConfig, "outputscale", 5.0),  # beyond the log-depth bound of log_residual
    (DepthGPConfig, "units", "mm"),
    (DepthGPConfig, "fit", 1),
    (DepthGPConfig, "screen", 3),
    (ScreenConfig, "neighbours", 12.0),
    (ScreenConfig, "neighbours", True),
    (ScreenConfig, "fit_nuggets", ()),
    (ScreenConfig, "fit_lengthscales", (2.0, -1.0)),
    (ScreenConfig, "outlier_threshold", math.inf),
    (ScreenConfig, "raise_outputscale", "yes"),
    (SlopeConfig, "prior_sigma", 0.0),
    (SlopeConfig, "min_points", 2),
    (SlopeConfig, "huber", False),
    (LatticeConfig, "dense_stride", 17),
    (LatticeConfig, "sparse_share", 1.5),
    (AssemblyConfig, "edge_sigma", -0.1),
    (AssemblyConfig, "depth_lengthscale", "0.7"),
    (CalibrationConfig, "min_points", 10.0),
    (CalibrationConfig, "reach", 1e300),
    (EngineConfig, "name", "dense"),
    (EngineConfig, "threads", 2.0),
    (EngineConfig, "threads", True),
    (EngineConfig, "max_memory_mb", 0.0),
    (EngineConfig, "lattice_stride", 0),
    (EngineConfig, "route", None),
    (FusionConfig, "voxel_size", 0.0),
    (FusionConfig, "truncation", 0.01),  # below the voxel size
    (FusionConfig, "block_count", True),
    (FusionConfig, "block_resolution", 8.0),
    (FusionConfig, "cpu_threads", -1),
    (FusionConfig, "fallback_weight", 1.5),
    (FusionConfig, "weighting", "linear"),
    (FusionConfig, "integrate_color", 1),
    (FusionConfig, "relative_sigma_ref", False),
    (FusionConfig, "depth_min", 10.0),  # above depth_max
    (MapperConfig, "window", 8.0),
    (MapperConfig, "lag", True),
    (MapperConfig, "local_map_cell", 0.0),
    (MapperConfig, "refine", "no"),
    (MapperConfig, "gp", {}),
    (MapperConfig, "fuse_depth", "max"),
    (TriangulationConfig, "detector", "surf"),
    (TriangulationConfig, "max_features", 100.0),
    (TriangulationConfig, "min_views", 1),
    (TriangulationConfig, "ratio", 0.0),
    (TriangulationConfig, "refine_poses", 0),
    (TriangulationConfig, "min_depth", 30.0),  # beyond max_depth
    (RefindConfig, "pool", 20.0),
    (RefindConfig, "views", False),
    (RefindConfig, "max_angle_deg", 180.0),
    (RefindConfig, "detector", "klt"),
    (ViewerConfig, "max_points", 1e5),
    (ViewerConfig, "layout", "grid"),
    (ViewerConfig, "point_size", 0.0),
    (KittiProtocolConfig, "factor", 3.0),
    (KittiProtocolConfig, "holdout", 1.0),
    (KittiProtocolConfig, "densities", (0.5, 0.0)),
    (KittiProtocolConfig, "full_resolution", 1),
]


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: c.__name__)
def test_defaults_are_valid_and_canonical(config):
    c = config()
    for name, value in vars(c).items():
        assert not isinstance(value, np.generic), f"{config.__name__}.{name} keeps a numpy scalar"


@pytest.mark.parametrize(("config", "name", "value"), REFUSED, ids=lambda x: getattr(x, "__name__", repr(x)))
def test_every_config_refuses_by_one_vocabulary(config, name, value):
    with pytest.raises(InvalidInputError) as info:
        config(**{name: value})
    err = info.value
    assert name in err.argument  # the message names the argument...
    assert err.expected and str(err.got)  # ...what was expected and what came


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: c.__name__)
def test_no_post_init_is_longer_than_15_lines(config):
    import inspect

    lines = inspect.getsource(config.__post_init__).strip().splitlines()
    assert len(lines) - 1 <= 15, f"{config.__name__}.__post_init__ has {len(lines) - 1} lines"


def test_numpy_numbers_are_stored_as_python_numbers():
    c = EngineConfig(threads=np.int64(2), max_memory_mb=np.float32(100.0))
    assert type(c.threads) is int and type(c.max_memory_mb) is float
    assert type(ScreenConfig(neighbours=np.int32(5)).neighbours) is int
    assert type(FusionConfig(voxel_size=np.float64(0.01)).voxel_size) is float


class TestVocabulary:
    def test_is_real_and_is_integer(self):
        assert is_real(1) and is_real(1.5) and is_real(np.float32(1)) and is_real(np.int8(1))
        assert not is_real(True) and not is_real("1") and not is_real(None) and not is_real(np.bool_(True))
        assert is_integer(3) and is_integer(np.int64(3))
        assert not is_integer(3.0) and not is_integer(False)

    def test_check_int(self):
        assert check_int("n", 3, 1, 5) == 3 and check_int("n", None, optional=True) is None
        for bad in (0, 6, 3.0, True, "3", None):
            with pytest.raises(InvalidInputError, match=r"n: expected an integer in \[1, 5\]"):
                check_int("n", bad, 1, 5)

    def test_check_real(self):
        assert check_real("x", 1, 0, 1) == 1.0 and type(check_real("x", np.float32(0.5))) is float
        with pytest.raises(InvalidInputError, match=r"x: expected a number in \(0, 1\] \(m\), got int 0"):
            check_real("x", 0, 0, 1, low_open=True, unit="m")
        for bad in (math.nan, math.inf, True, "1"):
            with pytest.raises(InvalidInputError, match="x: expected a finite number"):
                check_real("x", bad)
        assert check_real("x", None, optional=True) is None

    def test_check_bool_and_choice(self):
        assert check_bool("b", np.bool_(True)) is True
        with pytest.raises(InvalidInputError, match="b: expected True or False, got int 1"):
            check_bool("b", 1)
        assert check_choice("c", "a", ("a", "b")) == "a"
        with pytest.raises(InvalidInputError, match="c: expected 'a' or 'b'"):
            check_choice("c", 0, ("a", "b"))

    def test_rules_and_check_fields(self):
        class Holder:
            pass

        h = Holder()
        h.n, h.x, h.b, h.c, h.t, h.i = np.int16(4), 2, True, "a", [1, 2], 5
        check_fields(
            h, {"n": Int(1), "x": Real(0, 3), "b": Bool(), "c": Choice(("a",)), "t": Reals(Real(0)), "i": Instance(int)}
        )
        assert (type(h.n), type(h.x), h.t) == (int, float, (1.0, 2.0))
        with pytest.raises(InvalidInputError, match="t: expected a non-empty tuple"):
            Reals(Real())("t", "12")
        with pytest.raises(InvalidInputError, match="i: expected a int"):
            Instance(int)("i", "5")
