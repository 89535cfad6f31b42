"""The default model's fast paths on a real KITTI frame give the posterior of the reference paths.

kitti_tiny frame 0, RT-MonoDepth-S, the KITTI protocol's 1/3 grid (`prepare_kitti_frame`). The
fast paths: the compiled leave-one-out kriging (`gpdepth3d.gp._loo`), the scale term's second
right-hand side sharing the factorisation (``extra_obs``), the grid route on the lattice spanning
the points (``lattice="observed"``). The references: NumPy's batched solves, the dense exact
engine, the grid route on the whole grid (the paths before these).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gpdepth3d.completion.complete import DepthCompleter
from gpdepth3d.completion.log_frame import edge_range_at
from gpdepth3d.gp import EngineConfig
from gpdepth3d.gp.model import DepthGPConfig, separable_correlation
from gpdepth3d.gp.points import PointFit, loo_zscores


@pytest.fixture(scope="module")
def kitti(shared_data):
    """(KittiFrameSetup, {density: SparseDepth}) of kitti_tiny frame 0."""
    pytest.importorskip("onnxruntime")
    from gpdepth3d.datasets import open_dataset
    from gpdepth3d.evaluation.kitti_protocol import draw_input, lidar_frames, prepare_kitti_frame
    from gpdepth3d.mde import RTMonoDepthONNX

    models = shared_data.parent / "models"
    if not (models / "rtmonodepth_s_ms_640_192.onnx").is_file():
        pytest.skip(f"RT-MonoDepth-S not found in {models}")
    name, rgb, lidar = next(iter(lidar_frames(open_dataset(shared_data / "kitti_tiny"))))
    setup = prepare_kitti_frame(name, rgb, lidar, RTMonoDepthONNX(models_dir=models), factor=3, holdout=0.2, rng=0)
    inputs = {d: draw_input("uniform", d, setup.lidar.available, rng=1) for d in (1 / 64, 1.0)}
    return setup, inputs


def _complete(config, setup, sparse, out_shape, engine=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return DepthCompleter(config, engine=engine)(setup.mde_grid, sparse, output_shape=out_shape)


def _close(a, b, rtol):
    np.testing.assert_array_equal(a.rejected, b.rejected)
    np.testing.assert_allclose(a.mean, b.mean, rtol=rtol)
    np.testing.assert_allclose(a.variance, b.variance, rtol=rtol)


@pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
@pytest.mark.parametrize("full", [False, True])
def test_sparse_points_fast_engine_equals_exact(kitti, full):
    """1/64 of the LiDAR (~200 points): Woodbury with the scale term's second right-hand side vs dense algebra."""
    setup, inputs = kitti
    out = setup.full_shape if full else None
    fast = _complete(DepthGPConfig(), setup, inputs[1 / 64], out)
    exact = _complete(
        DepthGPConfig(), setup, inputs[1 / 64], out, EngineConfig(name="exact", options={"max_cross_entries": 10**9})
    )
    _close(fast, exact, 1e-6)


@pytest.mark.parametrize("full", [False, True])
def test_full_lidar_lattice_equals_whole_grid(kitti, full):
    """All of the LiDAR (~12.6k points, none in the top third): the grid route on their lattice vs the whole grid."""
    setup, inputs = kitti
    out = setup.full_shape if full else None
    lattice = _complete(DepthGPConfig(), setup, inputs[1.0], out)
    whole = _complete(DepthGPConfig(), setup, inputs[1.0], out, EngineConfig(lattice="full"))
    _close(lattice, whole, 1e-6)


def _loo_reference(rows, cols, resid, noise, fit, nn):
    """Leave-one-out z-scores from given neighbours by NumPy's batched solves (the path before the kernel)."""
    r = resid - fit.log_scale
    s2, tau2 = fit.outputscale**2, fit.nugget**2
    R, C = rows[nn], cols[nn]
    K = s2 * separable_correlation(R[:, :, None] - R[:, None, :], C[:, :, None] - C[:, None, :], fit.lengthscale, 0.5)
    d = np.arange(nn.shape[1])
    K[:, d, d] += tau2 + noise[nn]
    kx = s2 * separable_correlation(rows[:, None] - R, cols[:, None] - C, fit.lengthscale, 0.5)
    w = np.linalg.solve(K, kx[:, :, None])[:, :, 0]
    var = s2 + tau2 + noise - np.sum(w * kx, axis=1)
    return (r - np.sum(w * r[nn], axis=1)) / np.sqrt(var)


def test_leave_one_out_kernel_equals_numpy(kitti):
    """All of the LiDAR (12.6k points): the ring search finds the 12 nearest (their distances are the brute-force
    ones, checked on every 50th point; the tie rule is tests/gp/test_loo.py's) and the compiled kriging equals
    NumPy's batched solves on them."""
    from gpdepth3d.gp.points import neighbours_of

    setup, inputs = kitti
    sp = inputs[1.0]
    rows, cols = sp.v.astype(np.float64), sp.u.astype(np.float64)
    resid = np.log(sp.depth) - np.log(setup.mde_grid[rows.astype(int), cols.astype(int)])
    noise = 1e-4 + edge_range_at(np.log(setup.mde_grid), rows.astype(int), cols.astype(int)) ** 2
    fit = PointFit(32.0, 0.2, 0.02, float(np.median(resid)), 1e-5, len(sp))
    z = loo_zscores(rows, cols, resid, noise, fit)
    n = len(sp)
    nn, dist = neighbours_of(rows, cols, np.ones(n, dtype=bool), np.arange(n), 12)
    for i in range(0, n, 50):
        others = np.flatnonzero(np.arange(n) != i)
        d = np.abs(rows[others] - rows[i]) + np.abs(cols[others] - cols[i])
        np.testing.assert_array_equal(dist[i], np.sort(d)[:12])
        np.testing.assert_array_equal(dist[i], np.abs(rows[nn[i]] - rows[i]) + np.abs(cols[nn[i]] - cols[i]))
        assert len(set(nn[i])) == 12 and i not in nn[i]
    np.testing.assert_allclose(z, _loo_reference(rows, cols, resid, noise, fit, nn), rtol=1e-9, atol=1e-9)
