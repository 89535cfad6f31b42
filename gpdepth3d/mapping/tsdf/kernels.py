"""The kernels of a TSDF volume: the per-pixel weighted voxel update and the truncation band's blocks.

For every voxel centre ``x`` (world frame) in the truncation band of a frame (the projective
TSDF update of KinectFusion, https://www.microsoft.com/en-us/research/publication/kinectfusion-real-time-dense-surface-mapping-and-tracking/,
with a weight per pixel as in Open3D's ``examples/python/t_reconstruction_system/integrate_custom.py``)::

    (u, v), z = project(T_camera_world @ x)            nearest pixel, z-depth of the voxel
    d   = depth[v, u],  w = w_p[v, u]                   observed depth and its weight
    sdf = min(d - z, tau) / tau_max                     kept when d - z >= -tau
    tsdf  <- (W * tsdf + w * sdf) / (W + w)
    color <- (W * color + w * rgb[v, u]) / (W + w)
    W     <- min(W + w, weight_cap)

``tau`` is each pixel's truncation, ``tau_max`` `FusionConfig.tsdf_scale`. On the CPU compiled
loops (numba: `update_voxels`, `band_blocks`) visit every voxel and band sample once; the same
computations in torch (`update_torch`, `band_keys_torch`) run on CUDA and serve as the reference.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np

from ...camera import PinholeCamera
from .blocks import KEY_BIAS, KEY_SPAN, blocks_to_keys, to_torch


# ---------------------------------------------------------------------- the frame's pixels
@nb.njit(cache=True, nogil=True)
def masked_frame(
    depth, weights, variance, depth_min, depth_max
):  # pragma: no cover - compiled; tested through integrate
    """The pixels a frame fuses, in one pass (float64 inputs of one shape; ``variance`` may be (0, 0)).

    A pixel is fused when its depth is finite, in (depth_min, depth_max), its weight > 0 and
    (with a variance) its variance finite and >= 0. Returns float32 depth, weight and variance
    (0 where not fused; the variance (0, 0) without one), the number of negative or non-finite
    depths, the number of pixels fused, and whether any weight is negative or not finite.
    """
    h, w = depth.shape
    has_var = variance.shape[0] > 0
    d32 = np.zeros((h, w), np.float32)
    w32 = np.zeros((h, w), np.float32)
    v32 = np.zeros((h, w) if has_var else (0, 0), np.float32)
    n_bad = 0
    pixels = 0
    bad_weights = False
    for i in range(h):
        for j in range(w):
            d = depth[i, j]
            wt = weights[i, j]
            if not (np.isfinite(wt) and wt >= 0):
                bad_weights = True
            if not (np.isfinite(d) and d >= 0):
                n_bad += 1
                continue
            if has_var and not (np.isfinite(variance[i, j]) and variance[i, j] >= 0):
                continue
            if d > depth_min and d < depth_max and wt > 0:
                d32[i, j] = d
                w32[i, j] = wt
                if has_var:
                    v32[i, j] = variance[i, j]
                pixels += 1
    return d32, w32, v32, n_bad, pixels, bad_weights


# ---------------------------------------------------------------------- the voxel update
def update_cpu(
    vbg: Any,
    blocks: np.ndarray,
    buf: np.ndarray,
    camera: PinholeCamera,
    frame: tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray],
    T: np.ndarray,
    voxels: tuple[int, float],
    scale: float,
    cap: float,
) -> int:
    """The voxel update of one frame over the blocks (M, 3) ``blocks`` at buffer indices ``buf`` (M,).

    ``frame`` is (depth, weights, colour or None, variance or None, truncation) of the pixels,
    ``voxels`` (block_resolution, voxel_size); returns the number of voxel updates (`update_voxels`).
    """
    d, w, color, var, trunc = frame
    view = lambda name: to_torch(vbg.attribute(name)).view(-1).numpy()  # flat, zero-copy
    empty = np.zeros(0, np.float32)
    col = view("color") if color is not None else empty
    vvox = view("variance") if var is not None else empty
    T_cw = np.linalg.inv(T)
    pixels = (
        np.ascontiguousarray(d, np.float32),
        np.ascontiguousarray(w, np.float32),
        np.zeros((0, 0, 3), np.float32) if color is None else np.ascontiguousarray(color, np.float32),
        np.zeros((0, 0), np.float32) if var is None else np.ascontiguousarray(var, np.float32),
        np.ascontiguousarray(trunc, np.float32),
    )
    intrinsics = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    res, voxel_size = voxels
    pose = (T_cw[:3, :3].copy(), T_cw[:3, 3].copy())
    grid = (view("tsdf"), view("weight"), col, vvox)
    return int(update_voxels(blocks, buf, res, voxel_size, pose, intrinsics, pixels, float(scale), float(cap), grid))


@nb.njit(cache=True, nogil=True)
def update_voxels(
    blocks, buf, res, voxel_size, pose, intrinsics, pixels, scale, cap, grid
):  # pragma: no cover - compiled; tested against the torch update
    """The projective TSDF update of every voxel of the given blocks (see the module docstring).

    ``blocks`` (M, 3) block coordinates, ``buf`` (M,) their buffer indices; a voxel (x, y, z)
    of block b sits at ``(b * res + (x, y, z)) * voxel_size`` and is stored at
    ``buf * res^3 + (z * res + y) * res + x`` (Open3D's layout). ``pose`` is (R_cw, t_cw),
    ``intrinsics`` (fx, fy, cx, cy), ``pixels`` (depth, weight, colour, variance, truncation) as
    (H, W) float32 maps (colour / variance of size 0 skip those attributes), ``grid`` the flat
    (tsdf, weight, colour, variance) buffers, ``scale`` the distance the stored signed distances
    are divided by. Returns the number of voxel updates.
    """
    R_cw, t_cw = pose
    n = 0
    r3 = res * res * res
    # camera coordinates of voxel (x, y, z) of a block: the voxel (0, y, z) plus x steps along ex
    ex = R_cw[:, 0] * voxel_size
    for m in range(blocks.shape[0]):
        base = buf[m] * r3
        o0 = blocks[m, 0] * res
        o1 = blocks[m, 1] * res
        o2 = blocks[m, 2] * res
        for z in range(res):
            for y in range(res):
                # the block's voxel (0, y, z) in the camera frame
                gx, gy, gz = o0 * voxel_size, (o1 + y) * voxel_size, (o2 + z) * voxel_size
                qx = R_cw[0, 0] * gx + R_cw[0, 1] * gy + R_cw[0, 2] * gz + t_cw[0]
                qy = R_cw[1, 0] * gx + R_cw[1, 1] * gy + R_cw[1, 2] * gz + t_cw[1]
                qz = R_cw[2, 0] * gx + R_cw[2, 1] * gy + R_cw[2, 2] * gz + t_cw[2]
                first = base + (z * res + y) * res
                n += _update_row(first, qx, qy, qz, ex, res, intrinsics, pixels, scale, cap, grid)
    return n


@nb.njit(cache=True, nogil=True, inline="always")
def _update_row(
    first, qx, qy, qz, ex, res, intrinsics, pixels, scale, cap, grid
):  # pragma: no cover - compiled; tested against the torch update
    """`update_voxels` for the ``res`` voxels of one row of a block: voxel x at camera point
    ``(qx, qy, qz) + x * ex``, stored at ``first + x``. Returns the number of voxel updates."""
    fx, fy, cx, cy = intrinsics
    depth, wpix, color, var, trunc = pixels
    tsdf, weight, col, vvox = grid
    h, w = depth.shape
    has_color = color.shape[0] > 0
    has_var = var.shape[0] > 0
    n = 0
    for x in range(res):
        pz = qz + x * ex[2]
        if pz <= 1e-6:
            continue
        inv = 1.0 / pz
        u = np.rint(fx * (qx + x * ex[0]) * inv + cx)
        v = np.rint(fy * (qy + x * ex[1]) * inv + cy)
        if u < 0 or v < 0 or u >= w or v >= h:
            continue
        iu = int(u)
        iv = int(v)
        reading = depth[iv, iu]
        wn = wpix[iv, iu]
        if reading <= 0 or wn <= 0:
            continue
        tau = trunc[iv, iu]
        sdf = reading - pz
        if sdf < -tau:
            continue
        if sdf > tau:
            sdf = tau
        sdf /= scale
        idx = first + x
        wold = weight[idx]
        wsum = wold + wn
        tsdf[idx] = (tsdf[idx] * wold + sdf * wn) / wsum
        if has_color:
            for c in range(3):
                col[3 * idx + c] = (col[3 * idx + c] * wold + color[iv, iu, c] * wn) / wsum
        if has_var:
            vvox[idx] = (vvox[idx] * wold + var[iv, iu] * wn) / wsum
        weight[idx] = min(wsum, cap)
        n += 1
    return n


def update_torch(
    vbg: Any,
    buf_indices: Any,
    camera: PinholeCamera,
    frame: tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray],
    T: np.ndarray,
    scale: float,
    cap: float,
    device: str,
) -> int:
    """`update_voxels` as torch tensor operations on zero-copy views of the grid's buffers.

    ``buf_indices`` is the Open3D tensor of the blocks' buffer indices, ``frame`` (depth, weights,
    colour or None, variance or None, truncation) of the pixels. Returns the number of voxel updates.
    """
    import torch

    d, w, color, var, trunc = frame
    voxel_coords, voxel_indices = vbg.voxel_coordinates_and_flattened_indices(buf_indices)
    sel, u, v, z = _project_torch(to_torch(voxel_coords), T, camera, device)
    reading = torch.as_tensor(d, device=device)[v, u]
    wnew = torch.as_tensor(w, device=device)[v, u]
    tau = torch.as_tensor(np.asarray(trunc, np.float32), device=device)[v, u]
    sdf = reading - z
    keep = torch.nonzero((reading > 0) & (wnew > 0) & (sdf >= -tau)).squeeze(1)
    n = int(keep.shape[0])
    if n == 0:
        return 0
    idx = to_torch(voxel_indices)[sel[keep]]
    sdf = torch.minimum(sdf[keep], tau[keep]) / float(scale)
    wnew = wnew[keep]
    tsdf = to_torch(vbg.attribute("tsdf")).view(-1)
    weight = to_torch(vbg.attribute("weight")).view(-1)
    wold = weight[idx]
    wsum = wold + wnew
    tsdf[idx] = (tsdf[idx] * wold + sdf * wnew) / wsum
    if color is not None:
        col_pix = torch.as_tensor(color, device=device)[v[keep], u[keep]]
        col = to_torch(vbg.attribute("color")).view(-1, 3)
        col[idx] = (col[idx] * wold[:, None] + col_pix * wnew[:, None]) / wsum[:, None]
    if var is not None:
        var_pix = torch.as_tensor(var, device=device)[v[keep], u[keep]]
        vvox = to_torch(vbg.attribute("variance")).view(-1)
        vvox[idx] = (vvox[idx] * wold + var_pix * wnew) / wsum
    weight[idx] = torch.clamp(wsum, max=float(cap))
    return n


def _project_torch(coords: Any, T: np.ndarray, camera: PinholeCamera, device: str) -> tuple[Any, Any, Any, Any]:
    """Nearest pixels of (N, 3) world points: indices of those in view (in front, inside the image),
    their pixel columns u and rows v (int64) and their z-depths."""
    import torch

    Tcw = torch.as_tensor(np.linalg.inv(T), dtype=torch.float32, device=device)
    K = torch.as_tensor(camera.K, dtype=torch.float32, device=device)
    xyz = coords @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = xyz[:, 2]
    front = z > 1e-6
    zs = torch.where(front, z, torch.ones_like(z))
    u = torch.round(K[0, 0] * xyz[:, 0] / zs + K[0, 2]).to(torch.int64)
    v = torch.round(K[1, 1] * xyz[:, 1] / zs + K[1, 2]).to(torch.int64)
    in_view = front & (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
    sel = torch.nonzero(in_view).squeeze(1)
    return sel, u[sel], v[sel], z[sel]


# ---------------------------------------------------------------------- the truncation band's blocks
def band_keys_cpu(
    depth: np.ndarray,
    T: np.ndarray,
    trunc: np.ndarray,
    camera: PinholeCamera,
    sizes: tuple[float, float],
    tile: int,
    conservative: bool,
) -> np.ndarray:
    """(M,) sorted int64 keys of the blocks a frame's truncation band touches (`band_blocks`).

    ``sizes`` is (voxel_size, block_size) in metres; the band is sampled at steps of two voxels.
    """
    voxel_size, block_size = sizes
    blocks = band_blocks(
        np.ascontiguousarray(depth, np.float32),
        (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)),
        np.ascontiguousarray(T[:3, :3], np.float64),
        np.ascontiguousarray(T[:3, 3], np.float64),
        np.ascontiguousarray(trunc, np.float32),
        2.0 * voxel_size,
        float(block_size),
        int(tile),
        bool(conservative),
    )
    return blocks_to_keys(blocks)  # the grid is walked in key order: sorted, unique


@nb.njit(cache=True, nogil=True)
def band_blocks(depth, intrinsics, R, t, trunc, step, block_size, tile, conservative):  # pragma: no cover - compiled
    """(M, 3) int64 coordinates of the blocks the truncation band of a depth frame reaches, in
    key order (x, then y, then z).

    The image is cut into ``tile`` x ``tile`` pixel tiles; the ray through a tile's centre is
    sampled from the smallest (valid depth - trunc) of its pixels to the largest (depth + trunc)
    (``trunc`` (H, W) per pixel), at most ``step`` metres apart; with ``conservative`` each
    sample also marks every block within the distance the tile's other pixel rays can be from it
    at that depth. The samples' blocks are marked in a dense grid over the bounding box of the
    rays' end samples (the samples in between lie between them; one block of margin for
    rounding), read out in order (no sort, no hash).
    """
    fx, fy, cx, cy = intrinsics
    origin = (t[0] / block_size, t[1] / block_size, t[2] / block_size)
    # pixel centres of a tile lie within (tile - 1) / 2 pixels of its centre in u and v: at depth
    # s their rays are within sqrt(2) * s * (tile - 1) / 2 / f metres of the centre ray
    spread = np.sqrt(2.0) * 0.5 * (tile - 1) / min(fx, fy) / block_size if conservative else 0.0
    ray, band, count = _tile_rays(depth, intrinsics, R, trunc, step, block_size, tile)
    lo, hi = _band_bounds(ray, band, count, origin, spread)
    if lo[0] > hi[0]:
        return np.zeros((0, 3), np.int64)
    grid = np.zeros((hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1), np.bool_)
    _mark_band(grid, lo, ray, band, count, origin, spread)
    return _marked_blocks(grid, lo)


@nb.njit(cache=True, nogil=True, inline="always")
def _tile_rays(depth, intrinsics, R, trunc, step, block_size, tile):  # pragma: no cover - compiled
    """Per tile: its centre ray's direction (blocks per metre of depth), its band [a0, a1] (metres
    of depth) and the number of samples along it (0: no depth in the tile)."""
    fx, fy, cx, cy = intrinsics
    h, w = depth.shape
    th, tw = (h + tile - 1) // tile, (w + tile - 1) // tile
    ray = np.empty((th, tw, 3))
    band = np.empty((th, tw, 2))
    count = np.zeros((th, tw), np.int64)
    for ty in range(th):
        v0, v1 = ty * tile, min(h, ty * tile + tile)
        for tx in range(tw):
            u0, u1 = tx * tile, min(w, tx * tile + tile)
            dmin, dmax = np.inf, -1.0
            for v in range(v0, v1):
                for u in range(u0, u1):
                    d = depth[v, u]
                    if d > 0:
                        dmin = min(dmin, d - trunc[v, u])
                        dmax = max(dmax, d + trunc[v, u])
            if dmax < 0:
                continue
            rx = (0.5 * (u0 + u1 - 1) - cx) / fx
            ry = (0.5 * (v0 + v1 - 1) - cy) / fy
            ray[ty, tx, 0] = (R[0, 0] * rx + R[0, 1] * ry + R[0, 2]) / block_size
            ray[ty, tx, 1] = (R[1, 0] * rx + R[1, 1] * ry + R[1, 2]) / block_size
            ray[ty, tx, 2] = (R[2, 0] * rx + R[2, 1] * ry + R[2, 2]) / block_size
            a0 = max(dmin, 1e-3)
            band[ty, tx, 0], band[ty, tx, 1] = a0, dmax
            count[ty, tx] = int(np.ceil((dmax - a0) / step)) + 1
    return ray, band, count


@nb.njit(cache=True, nogil=True, inline="always")
def _band_bounds(ray, band, count, origin, spread):  # pragma: no cover - compiled
    """Lowest and highest block coordinates (3,) of the rays' end samples, one block of margin."""
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    for ty in range(count.shape[0]):
        for tx in range(count.shape[1]):
            n = count[ty, tx]
            if n == 0:
                continue
            a0, a1 = band[ty, tx, 0], band[ty, tx, 1]
            for k in (0, n - 1):
                s = a0 + (a1 - a0) * k / (n - 1)
                r = s * spread
                for axis in range(3):
                    c = origin[axis] + s * ray[ty, tx, axis]
                    lo[axis] = min(lo[axis], int(np.floor(c - r)) - 1)
                    hi[axis] = max(hi[axis], int(np.floor(c + r)) + 1)
    return lo, hi


@nb.njit(cache=True, nogil=True, inline="always")
def _mark_band(grid, lo, ray, band, count, origin, spread):  # pragma: no cover - compiled
    """Marks in ``grid`` (its cell (0, 0, 0) is block ``lo``) the blocks of every tile's band samples."""
    for ty in range(count.shape[0]):
        for tx in range(count.shape[1]):
            n = count[ty, tx]
            if n == 0:
                continue
            d0, d1, d2 = ray[ty, tx, 0], ray[ty, tx, 1], ray[ty, tx, 2]
            a0, a1 = band[ty, tx, 0], band[ty, tx, 1]
            for k in range(n):
                s = a0 + (a1 - a0) * k / (n - 1)
                r = s * spread  # the tile's other rays are within r of this sample (blocks)
                c0, c1, c2 = origin[0] + s * d0, origin[1] + s * d1, origin[2] + s * d2
                for i in range(int(np.floor(c0 - r)), int(np.floor(c0 + r)) + 1):
                    for j in range(int(np.floor(c1 - r)), int(np.floor(c1 + r)) + 1):
                        for q in range(int(np.floor(c2 - r)), int(np.floor(c2 + r)) + 1):
                            grid[i - lo[0], j - lo[1], q - lo[2]] = True


@nb.njit(cache=True, nogil=True, inline="always")
def _marked_blocks(grid, lo):  # pragma: no cover - compiled
    """(M, 3) int64 block coordinates of the marked cells of ``grid`` (cell (0, 0, 0) = block ``lo``), in order."""
    nx, ny, nz = grid.shape
    out = np.zeros((int(grid.sum()), 3), np.int64)
    m = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if grid[i, j, k]:
                    out[m, 0], out[m, 1], out[m, 2] = i + lo[0], j + lo[1], k + lo[2]
                    m += 1
    return out


def band_keys_torch(
    depth: np.ndarray,
    T: np.ndarray,
    trunc: np.ndarray,
    camera: PinholeCamera,
    sizes: tuple[float, float],
    tile: int,
    conservative: bool,
    device: str,
) -> np.ndarray:
    """`band_keys_cpu` with torch (CUDA, and the CPU reference in the tests): the same samples."""
    import torch

    voxel_size, block_size = sizes
    rays, origin, a0, a1 = _tile_rays_torch(depth, T, trunc, camera, block_size, tile, device)
    if rays is None:
        return np.zeros(0, np.int64)
    step = 2.0 * voxel_size
    n = torch.ceil((a1 - a0) / step).long() + 1
    spread = np.sqrt(2.0) * 0.5 * (tile - 1) / min(camera.fx, camera.fy) / block_size if conservative else 0.0
    keys = []
    for k in range(int(n.max())):
        on = n > k
        s = a0[on] + (a1[on] - a0[on]) * k / (n[on] - 1).double()
        c = origin + s[:, None] * rays[on]
        r = (s * spread)[:, None]
        lo, hi = torch.floor(c - r).long(), torch.floor(c + r).long()
        span = int((hi - lo).max()) + 1
        for di in range(span):
            for dj in range(span):
                for dq in range(span):
                    b = lo + torch.tensor([di, dj, dq], device=device)
                    ok = torch.all(b <= hi, dim=1)
                    b = b[ok] + KEY_BIAS
                    keys.append((b[:, 0] * KEY_SPAN + b[:, 1]) * KEY_SPAN + b[:, 2])
    return torch.unique(torch.cat(keys)).cpu().numpy()


def _tile_rays_torch(
    depth: np.ndarray,
    T: np.ndarray,
    trunc: np.ndarray,
    camera: PinholeCamera,
    block_size: float,
    tile: int,
    device: str,
) -> tuple[Any, Any, Any, Any]:
    """`_tile_rays` in torch for the tiles with depth: their centre rays (blocks per metre), the
    camera centre (blocks) and each band's [a0, a1] (metres); all None without depth."""
    import torch

    d = torch.as_tensor(np.asarray(depth, np.float32), device=device)
    h, w = d.shape
    tau = torch.as_tensor(np.asarray(trunc, np.float32), device=device)
    valid = d > 0
    # per tile: the nearest (depth - truncation) and the farthest (depth + truncation)
    big = torch.where(valid, d - tau, torch.full_like(d, float("inf")))[None, None]
    dmin = -torch.nn.functional.max_pool2d(-big, tile, ceil_mode=True)[0, 0]
    dmax = torch.nn.functional.max_pool2d(
        torch.where(valid, d + tau, torch.full_like(d, -1.0))[None, None], tile, ceil_mode=True
    )[0, 0]
    ty, tx = torch.nonzero(dmax > 0, as_tuple=True)
    if ty.numel() == 0:
        return None, None, None, None
    dmin, dmax = dmin[ty, tx].double(), dmax[ty, tx].double()
    u0, v0 = tx * tile, ty * tile
    u1, v1 = torch.clamp(u0 + tile, max=w), torch.clamp(v0 + tile, max=h)
    rx = (0.5 * (u0 + u1 - 1).double() - camera.cx) / camera.fx
    ry = (0.5 * (v0 + v1 - 1).double() - camera.cy) / camera.fy
    Tw = torch.as_tensor(T, dtype=torch.float64, device=device)
    rays = torch.stack([rx, ry, torch.ones_like(rx)], dim=1) @ Tw[:3, :3].T / block_size  # blocks per metre
    return rays, Tw[:3, 3] / block_size, torch.clamp(dmin, min=1e-3), dmax
