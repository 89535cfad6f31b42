"""What comes out of a TSDF volume: its surface as a mesh (whole, or chunk by chunk), surface points, voxels.

Open3D's extraction runs over a hash map with threads, so the order of its vertices, faces and
points changes from run to run; `canonical_mesh` and the sorted points of `surface_cloud` give
one order for one surface (files written from them repeat byte for byte).

Extraction keeps voxels whose accumulated weight exceeds ``weight_threshold`` (Open3D's test is
strict) and runs Open3D's marching cubes and surface-point search
(https://www.open3d.org/docs/release/python_api/open3d.t.geometry.VoxelBlockGrid.html). Meshes
are `trimesh.Trimesh` with vertex colours, metres, world frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import EmptyInputError
from ...extras import require
from ..cloud import ColoredCloud
from .blocks import blocks_to_keys, find_blocks, grid_attributes, keys_to_blocks, new_grid, to_torch, torch_device

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

    from .fusion_config import FusionConfig


def observed_voxels(vbg: Any, config: "FusionConfig") -> dict[str, np.ndarray]:
    """The voxels of ``vbg`` with accumulated weight > 0 (`TSDFFusion.voxels` documents the arrays)."""
    buf = vbg.hashmap().active_buf_indices()
    coords, idx = vbg.voxel_coordinates_and_flattened_indices(buf)
    weight = vbg.attribute("weight").reshape((-1,))[idx]
    keep = weight > 0
    out = {
        "coords": coords[keep].cpu().numpy().astype(np.float64),
        "tsdf": vbg.attribute("tsdf").reshape((-1,))[idx][keep].cpu().numpy().astype(np.float64),
        "weight": weight[keep].cpu().numpy().astype(np.float64),
    }
    if config.integrate_color:
        out["color"] = vbg.attribute("color").reshape((-1, 3))[idx][keep].cpu().numpy().astype(np.float64) / 255
    if config.integrate_variance:
        out["variance"] = vbg.attribute("variance").reshape((-1,))[idx][keep].cpu().numpy().astype(np.float64)
    return out


def _no_surface(config: "FusionConfig", what: str) -> EmptyInputError:
    return EmptyInputError("fusion", f"a surface with weight > {config.weight_threshold}", what)


def _empty_mesh() -> "trimesh.Trimesh":
    import trimesh

    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)


def _vertex_colors(attributes: Any) -> np.ndarray:
    """(N, 3) uint8 colours of an Open3D mesh's ``vertex`` or a cloud's ``point`` attributes (stored 0..1)."""
    return np.clip(np.rint(attributes.colors.numpy() * 255.0), 0, 255).astype(np.uint8)


def grid_mesh(vbg: Any, config: "FusionConfig", allow_empty: bool) -> "trimesh.Trimesh":
    """The zero level set of ``vbg`` as a `trimesh.Trimesh` (`TSDFFusion.extract_mesh`)."""
    import trimesh

    mesh = vbg.extract_triangle_mesh(float(config.weight_threshold)).cpu()
    if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0 or mesh.triangle.indices.shape[0] == 0:
        if allow_empty:
            return _empty_mesh()
        raise _no_surface(config, "no triangles")
    vertices = mesh.vertex.positions.numpy().astype(np.float64)
    faces = mesh.triangle.indices.numpy().astype(np.int64)
    colors = _vertex_colors(mesh.vertex) if "colors" in mesh.vertex else None
    return trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)


class MeshChunks:
    """A volume's surface as triangles cached per cubic chunk of blocks, re-meshed only where blocks changed.

    A marching-cubes cell belongs to the block of its lowest voxel and needs the voxels of the
    next block along each axis, so a changed block changes the cells of its own chunk and of the
    chunks of its 7 lower neighbours. Those chunks' blocks and a one-block halo are copied into a
    temporary grid and meshed by Open3D; every other chunk keeps its cached triangles. The first
    `mesh` meshes the whole volume.
    """

    def __init__(self) -> None:
        self.dirty: list[np.ndarray] = []  # block keys changed since the last `mesh`
        self.chunks: dict[int, tuple[np.ndarray, np.ndarray]] | None = None  # chunk key -> (triangles, colours)

    def mark(self, keys: np.ndarray) -> None:
        """Records that the blocks ``keys`` (int64 block keys) changed."""
        self.dirty.append(keys)

    def mesh(
        self, vbg: Any, config: "FusionConfig", device: Any, chunk_blocks: int, allow_empty: bool
    ) -> "trimesh.Trimesh":
        """The surface of ``vbg`` as a triangle soup, re-meshing the chunks (``chunk_blocks`` blocks
        a side) changed since the last call; the triangles are those of `grid_mesh`."""
        res, C = int(config.block_resolution), int(chunk_blocks)
        if self.chunks is None:
            chunks, grid = None, vbg  # everything
        else:
            dirty = np.unique(np.concatenate(self.dirty)) if self.dirty else np.zeros(0, np.int64)
            if dirty.size == 0:
                return self._assemble(config, allow_empty)
            chunks, grid = _chunk_grid(vbg, config, device, dirty, C)
        mesh = grid.extract_triangle_mesh(float(config.weight_threshold)).cpu()
        tri, col, owner = _triangles_by_chunk(mesh, float(config.voxel_size), res, C)
        if chunks is None:
            self.chunks = {}
        else:
            for key in chunks:
                self.chunks.pop(int(key), None)
            keep = np.isin(owner, chunks)
            tri, col, owner = tri[keep], col[keep], owner[keep]
        order = np.argsort(owner, kind="stable")
        tri, col, owner = tri[order], col[order], owner[order]
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if owner.size else np.zeros(0, np.int64)
        for a, b_ in zip(starts, np.r_[starts[1:], owner.size].astype(np.int64)):
            self.chunks[int(owner[a])] = (tri[a:b_], col[a:b_])
        self.dirty = []
        return self._assemble(config, allow_empty)

    def _assemble(self, config: "FusionConfig", allow_empty: bool) -> "trimesh.Trimesh":
        import trimesh

        parts = list(self.chunks.values()) if self.chunks else []
        if not parts:
            if allow_empty:
                return _empty_mesh()
            raise _no_surface(config, "no triangles")
        tri = np.concatenate([p[0] for p in parts]).reshape(-1, 3)
        col = np.concatenate([p[1] for p in parts]).reshape(-1, 3)
        faces = np.arange(tri.shape[0], dtype=np.int64).reshape(-1, 3)
        return trimesh.Trimesh(tri, faces, vertex_colors=col, process=False)


def _chunk_grid(vbg: Any, config: "FusionConfig", device: Any, dirty: np.ndarray, C: int) -> tuple[np.ndarray, Any]:
    """Keys of the chunks (``C`` blocks a side) the changed blocks ``dirty`` affect, and a new grid
    holding a copy of those chunks' blocks with a one-block halo."""
    import torch

    o3c = require("open3d.core")
    b = keys_to_blocks(dirty).astype(np.int64)
    offsets = np.array([[i, j, k] for i in (0, -1) for j in (0, -1) for k in (0, -1)])
    chunk_coords = np.unique(np.floor_divide((b[:, None, :] + offsets[None]).reshape(-1, 3), C), axis=0)
    span = np.stack(np.meshgrid(*[np.arange(C + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    candidates = np.unique(blocks_to_keys((chunk_coords[:, None, :] * C + span[None]).reshape(-1, 3)))
    buf, found = find_blocks(vbg, candidates, device)
    tdev = torch_device(device)
    src = torch.as_tensor(buf[found], device=tdev)
    grid = new_grid(config, max(1, int(found.sum())), device)
    if found.any():
        dst_buf, _ = grid.hashmap().activate(o3c.Tensor(keys_to_blocks(candidates[found]), device=device))
        dst = torch.as_tensor(dst_buf.cpu().numpy().astype(np.int64).reshape(-1), device=tdev)
        for name in grid_attributes(config):
            to_torch(grid.attribute(name))[dst] = to_torch(vbg.attribute(name))[src]
    return blocks_to_keys(chunk_coords), grid


def _triangles_by_chunk(mesh: Any, voxel_size: float, res: int, C: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An Open3D mesh as (m, 3, 3) triangle corners, (m, 3, 3) uint8 corner colours and (m,) keys of
    the chunks (``C`` blocks of ``res`` voxels a side) that own them."""
    if not ("positions" in mesh.vertex and mesh.vertex.positions.shape[0] and mesh.triangle.indices.shape[0]):
        return np.zeros((0, 3, 3)), np.zeros((0, 3, 3), np.uint8), np.zeros(0, np.int64)
    vertices = mesh.vertex.positions.numpy().astype(np.float64)
    faces = mesh.triangle.indices.numpy().astype(np.int64)
    tri = vertices[faces]  # (m, 3, 3)
    col = _vertex_colors(mesh.vertex)[faces] if "colors" in mesh.vertex else np.full(tri.shape, 128, np.uint8)
    owner_voxel = np.floor(tri.mean(axis=1) / voxel_size).astype(np.int64)
    return tri, col, blocks_to_keys(np.floor_divide(np.floor_divide(owner_voxel, res), C))


def canonical_mesh(mesh: "trimesh.Trimesh") -> "trimesh.Trimesh":
    """The same surface in one canonical form, whatever the order Open3D produced it in.

    Vertices equal in position and colour are merged (a triangle soup shares its vertices), and
    sorted lexicographically by (x, y, z, colour); each face starts at the rotation of its
    vertex indices that is smallest (winding kept), and faces are sorted lexicographically.
    """
    import trimesh

    vertices = np.asarray(mesh.vertices, dtype=np.float64) + 0.0  # -0.0 and 0.0 alike
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    colors = np.asarray(mesh.visual.vertex_colors, np.uint8) if mesh.visual.kind == "vertex" else None
    rows = vertices if colors is None else np.concatenate([vertices, colors.astype(np.float64)], axis=1)
    order = np.lexsort(rows.T[::-1])
    ranked = rows[order]
    new = np.r_[True, np.any(ranked[1:] != ranked[:-1], axis=1)] if len(rows) else np.zeros(0, bool)
    inverse = np.empty(len(rows), np.int64)
    inverse[order] = np.cumsum(new) - 1
    unique = ranked[new]
    faces = inverse[faces]
    best = faces
    for shift in (1, 2):
        rolled = np.roll(faces, -shift, axis=1)
        best = np.where(_lex_less(rolled, best)[:, None], rolled, best)
    best = best[np.lexsort(best.T[::-1])]
    out_colors = None if colors is None else unique[:, 3:].astype(np.uint8)
    return trimesh.Trimesh(unique[:, :3], best, vertex_colors=out_colors, process=False)


def _lex_less(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m,) whether each row of the (m, 3) ``a`` comes lexicographically before that of ``b``."""
    a0, a1, a2 = a.T
    b0, b1, b2 = b.T
    return (a0 < b0) | ((a0 == b0) & ((a1 < b1) | ((a1 == b1) & (a2 < b2))))


def surface_cloud(vbg: Any, config: "FusionConfig", device: Any, allow_empty: bool) -> ColoredCloud:
    """Surface points of ``vbg`` with their nearest voxel's values (`TSDFFusion.extract_point_cloud`),
    sorted lexicographically by position (then colour)."""
    pcd = vbg.extract_point_cloud(float(config.weight_threshold)).cpu()
    if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
        if allow_empty:
            return ColoredCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0), np.zeros(0))
        raise _no_surface(config, "no points")
    pts = pcd.point.positions.numpy().astype(np.float64) + 0.0
    n = pts.shape[0]
    colors = _vertex_colors(pcd.point) if "colors" in pcd.point else np.full((n, 3), 128, np.uint8)
    order = np.lexsort(np.concatenate([pts, colors], axis=1).T[::-1])  # one order for one surface
    pts, colors = pts[order], colors[order]
    flat = nearest_voxels(vbg, pts, config, device)
    weight = vbg.attribute("weight").cpu().numpy().reshape(-1)[flat].astype(np.float64)
    conf = np.clip(weight / config.weight_cap, 0.0, 1.0)
    if config.integrate_variance:
        var = vbg.attribute("variance").cpu().numpy().reshape(-1)[flat].astype(np.float64)
    else:
        var = np.full(n, np.nan)
    return ColoredCloud(pts, colors, var, conf, np.full(n, np.nan))


def nearest_voxels(vbg: Any, points: np.ndarray, config: "FusionConfig", device: Any) -> np.ndarray:
    """(N,) flat buffer indices of the voxels nearest to (N, 3) world points (on extracted surfaces).

    A voxel's sample point is at ``voxel_size * index``; Open3D stores a block's voxels at
    ``buffer_index * res^3 + (z * res + y) * res + x``. Points whose nearest voxel's block
    does not exist fall back to a nearest-neighbour search over the observed voxels.
    """
    res = int(config.block_resolution)
    vi = np.rint(points / float(config.voxel_size)).astype(np.int64)
    blocks = np.floor_divide(vi, res)
    local = vi - blocks * res
    uniq, inverse = np.unique(blocks_to_keys(blocks), return_inverse=True)
    buf, found = find_blocks(vbg, uniq, device)
    buf, found = buf[inverse], found[inverse]
    flat = buf * res**3 + (local[:, 2] * res + local[:, 1]) * res + local[:, 0]
    if not found.all():
        from scipy.spatial import cKDTree

        coords, idx = vbg.voxel_coordinates_and_flattened_indices(vbg.hashmap().active_buf_indices())
        _, near = cKDTree(coords.cpu().numpy()).query(points[~found])
        flat[~found] = idx.cpu().numpy().astype(np.int64)[near]
    return flat
