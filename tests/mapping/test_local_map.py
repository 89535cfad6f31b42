"""The local map: earlier frames' points fill the grid cells a frame's own points leave empty."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import InvalidInputError
from gpdepth3d.mapping.points.local_map import LocalMap, fill_cells
from gpdepth3d.mapping.mapper import MapperConfig
from gpdepth3d.measurements import SparseDepth

CAM = PinholeCamera(100.0, 100.0, 79.5, 59.5, 160, 120)
ROOT = Path(__file__).resolve().parents[2]


def _pose(tx: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = tx
    return T


def _sparse(u, v, depth, sigma) -> SparseDepth:
    return SparseDepth(np.asarray(u, float), np.asarray(v, float), np.asarray(depth, float), CAM.shape, sigma)


def test_fill_cells_keeps_the_most_certain_point_of_each_empty_cell():
    own = _sparse([5.0], [5.0], [2.0], 0.02)
    others = _sparse(
        [6.0, 25.0, 28.0, 45.0], [6.0, 5.0, 8.0, 45.0], [2.0, 2.0, 4.0, 3.0], np.array([0.01, 0.1, 0.1, 0.3])
    )
    kept = fill_cells(own, others, 20.0)
    # (6, 6) shares the own point's cell; of (25, 5) and (28, 8) in one cell the one with sigma/depth 0.025 stays
    assert sorted(zip(kept.u.tolist(), kept.v.tolist())) == [(28.0, 8.0), (45.0, 45.0)]
    assert len(fill_cells(SparseDepth.empty(CAM.shape), others, 20.0)) == 3
    with pytest.raises(InvalidInputError, match="cell"):
        fill_cells(own, others, 0.0)


def test_local_map_projects_earlier_points_into_a_moved_camera():
    lm = LocalMap(frames=2, cell=0.1)
    assert len(lm.fill(SparseDepth.empty(CAM.shape), _pose(), CAM)) == 0
    pts = _sparse([79.5, 100.0], [59.5, 59.5], [2.0, 4.0], np.array([0.02, 0.04]))
    lm.add("a", pts, _pose(0.0), CAM)
    seen = lm.fill(SparseDepth.empty(CAM.shape), _pose(0.5), CAM)
    # a camera moved 0.5 m along +x sees a point at x = 0, z = 2 at u = cx - fx * 0.5 / 2 (to the pixel centre)
    order = np.argsort(seen.depth)
    np.testing.assert_allclose(seen.u[order], [79.5 - 25.0, 79.5 + 100.0 * (0.82 - 0.5) / 4.0], atol=0.51)
    np.testing.assert_allclose(seen.depth[order], [2.0, 4.0])
    np.testing.assert_allclose(seen.sigma[order], [0.02, 0.04])
    # after a loop closure the points move with their frame's pose
    lm.update_poses({"a": _pose(0.5)})
    np.testing.assert_allclose(
        np.sort(lm.fill(SparseDepth.empty(CAM.shape), _pose(0.5), CAM).u), [79.5, 100.0], atol=0.5
    )
    # frames beyond ``frames`` are forgotten, oldest first
    lm.add("b", pts, _pose(), CAM)
    lm.add("c", pts, _pose(), CAM)
    assert len(lm) == 4


@pytest.mark.parametrize(("frames", "cell"), [(0, 0.1), (1.5, 0.1), (True, 0.1), (2, 0.0), (2, 1.5), (2, float("nan"))])
def test_local_map_refuses_bad_options(frames, cell):
    with pytest.raises(InvalidInputError):
        LocalMap(frames, cell)


@pytest.mark.parametrize("field", [{"local_map_frames": -1}, {"local_map_frames": 0.5}, {"local_map_cell": 0.0}])
def test_mapper_config_checks_the_local_map_options(field):
    with pytest.raises(InvalidInputError, match=next(iter(field))):
        MapperConfig(**field)


@pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
def test_the_mapper_fills_frames_from_the_local_map_on_a_real_walk(shared_data):
    """HoloLens walk, frames 16-29 (the tracks break): with the local map every frame from the second on
    has at least as many measurements as without it, some many more; the added ones are within +-2 sigma
    of the sensor depth about as often as the frames' own."""
    from scipy.ndimage import distance_transform_edt

    import importlib.util

    from gpdepth3d.mapping.mapper import Mapper

    if not (shared_data / "hololens").is_dir():
        pytest.skip(f"HoloLens sequence not found in {shared_data}")
    spec = importlib.util.spec_from_file_location("mapping_sequences", ROOT / "bench" / "mapping_sequences.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    frames = bench.load_hololens(shared_data / "hololens", 30)[16:]
    rgbs, poses, depths, cam = (
        [f.rgb for f in frames],
        [f.pose for f in frames],
        [f.depth for f in frames],
        frames[0].camera,
    )

    def standin(depth):  # the sensor depth, hole-filled and 12 % too far, as the MDE
        _, (ri, ci) = distance_transform_edt(depth <= 0, return_indices=True)
        return 1.12 * depth[ri, ci]

    def run(frames: int) -> list:
        mapper = Mapper(cam, MapperConfig(working_scale=0.5, local_map_frames=frames))
        results = [mapper.add_frame(rgb, T, mde_depth=standin(d)) for rgb, T, d in zip(rgbs, poses, depths)]
        return [r for r in results if r is not None] + mapper.flush()

    with_map, without = run(8), run(0)
    n_with = np.array([len(r.sparse) for r in with_map])
    n_without = np.array([len(r.sparse) for r in without])
    assert np.all(n_with[1:] >= n_without[1:]) and np.sum(n_with - n_without) > 300
    inside = []
    for r, d in zip(with_map, depths):
        iu, iv = np.rint(r.sparse.u).astype(int), np.rint(r.sparse.v).astype(int)
        gt = d[iv, iu]
        ok = gt > 0
        inside.append(np.abs(r.sparse.depth[ok] - gt[ok]) <= 2 * r.sparse.sigma[ok])
    assert 0.85 <= np.mean(np.concatenate(inside)) <= 0.98
