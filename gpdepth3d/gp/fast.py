"""The ``fast`` engine: exact GP posterior through the sparse precision of the separable Matern field.

Maths. A Matern-nu process on a line (nu = 0.5, 1.5, 2.5) is the first state of a linear SDE
with d = nu + 1/2 states, whose states at any sorted coordinates form a Gauss-Markov chain with
a block-tridiagonal precision (`gpdepth3d.gp.markov`). The separable kernel
s^2 M(du / l) M(dv / l) of the model (`gpdepth3d.gp.model`) is therefore the first component of
a 2-D field with d^2 states per pixel whose prior precision is exactly

    Q = (Qv (x) Qu) / s^2          (a 9-point stencil of d^2 x d^2 blocks),

and with observations y = f + e at pixels (precision w >= 0 per pixel, 0 = unobserved; the
balanced and the residual formulation only differ in w) the posterior precision and mean are

    P = Q + S^T W S,     mu = P^-1 S^T W (y - m),

with S selecting the f state. P is sparse SPD: it is factorised with a multifrontal Cholesky
over a nested-dissection ordering of the pixel grid. The grid is padded with unobserved pixels (which leaves the
posterior of the real pixels unchanged) to a lattice of equal tiles separated by one-pixel rows
and columns; every tile has the same elimination subtree, so the tile work runs batched over all
tiles (one batched dense Cholesky / triangular solve / product per subtree node), and the
separators between tiles are eliminated by a nested dissection of the tile lattice. The
structure, index maps and prior precision are cached per resolution and kernel. Marginal
variances diag(P^-1) come from the selected inverse computed top-down over the same fronts
(Takahashi / Erisman-Tinney recursions): exact, no sampling.
On this (grid) route no approximation is made anywhere; results equal the dense `exact` engine to rounding.

Output grids other than the input grid (finer, coarser or shifted) are exact too: conditioned
on all grid states, f at an off-grid point depends only on the states of the 2 x 2 surrounding
grid pixels, with Kronecker weights from the 1-D chains (`markov.readout_weights`). The mean is
the weighted sum of the posterior state means, the variance the weighted quadratic form of the
posterior covariance of those states (a clique of the 9-point stencil, so present in one front
of the selected inverse) plus the conditional prior variance.

Cost with n pixels: O(n^1.5) flops and O(n log n) memory (nested dissection on a 2-D grid),
the same for the selected inverse; about d^6 times more for nu > 0.5 (nu = 2.5 is heavy beyond
~100 x 100 pixels). Limits of the grid route: the precision's entries grow like
(l / pixel)^(2 nu + 1) per axis while the covariance stays O(s^2), so in float64 the route is
exact only while the conditioning allows (`grid_error_estimate` <= 1e-7: e.g. nu = 1.5 up to
l ~ 7 px, nu = 2.5 up to l ~ 3 px with sparse points, l ~ 60 / 9 px with every pixel observed). Beyond
that, and beyond the memory budget (`grid_bytes`, ``max_memory_mb``), the route is refused
with a typed error (`IllConditionedError`, `ProblemTooLargeError`) instead of a wrong answer. Numerics, float64 everywhere, in one of two back-ends (``backend=``):

* ``compiled`` (the default on the CPU): every (template node, tile) pair and every top node is
  one front of `gpdepth3d.gp.multifrontal`, which runs the factorisation, the solves and the
  selected inverse in numba-compiled loops calling LAPACK/BLAS, independent subtrees on
  separate threads, with buffers reused from frame to frame. From the second frame of a
  resolution and kernel on, the fronts that no observation reaches (most of them with sparse
  points in the residual formulation) are copied from a cached factor of the prior alone
  (``prior_cache_mb``) instead of being recomputed.
* ``torch`` (any torch device, ``FastEngine(device="cuda")``): the tiles' fronts batched into
  one cholesky_ex / solve_triangular / matmul / index_add_ call per template node, the top
  nodes one by one.

The set-up (tree, index maps, prior precision, read-out) runs once per resolution and kernel
with NumPy and is cached.

With few observed pixels (up to ``max_dense_points``) and any nu, the ``dense`` route computes the
same posterior by dense algebra over those pixels (`gpdepth3d.gp.exact.dense_posterior`,
O(m^3 + n m^2)): the residual formulation with nu = 1.5 / 2.5 and hundreds of points takes ~1 s
at 320 x 240 instead of minutes on the grid route, and long length scales stay exact there.
With nu = 0.5 two other routes compute the same posterior when the cost model says they are
cheaper (``route=`` forces any): few observed pixels (the residual formulation with sparse
points) take Woodbury over those pixels with the exponential kernel's recursive filtering
(`gpdepth3d.gp.woodbury`, exact, O(m^3 + m^2 + n) for m points and n output pixels), and a
precision that the observations make diagonally dominant (the paper's balanced set-up: the
stencil's couplings are ~2 % of the diagonal) takes a Neumann series with a certified bound
(`gpdepth3d.gp.neumann`, O(n) with a few terms; the omitted terms are bounded by 1e-13 of the
scaled mean and 2e-9 of each variance).

The grid route factorises only the lattice spanning the observed pixels (``lattice="observed"``,
`observed_lattice`: LiDAR leaves the top third of a KITTI frame empty, so 93 of its 125 rows at
1/3 resolution): the field is Markov along each axis, so the posterior there is the whole grid's,
and the pixels outside are read out exactly from the lattice's edge states like any off-grid
output. Several observation vectors with one precision (``extra_obs``) share every route's
factorisation (on the grid route, one pass of forward and backward substitution for all of them).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import ConvergenceError, InvalidInputError, ShapeError
from .engine import Solution, SolveInfo, check_extra_obs
from .exact import check_problem, dense_log_marginal_likelihood, dense_solve
from .markov import chain_precision, readout_weights, state_dim
from .multifrontal import FrontalFactor, FrontTree, PriorFactor
from .model import GridProblem
from .cost_model import grid_bytes as grid_bytes
from .cost_model import grid_error_estimate as grid_error_estimate
from .cost_model import memory_budget as memory_budget
from .neumann import NEUMANN_MEAN_TOL, NEUMANN_VAR_TOL
from .routes import IllConditionedError as IllConditionedError
from .routes import RouteQuery, choose_route
from .woodbury import WoodburyPosterior


# ----------------------------------------------------------------------------- symbolic phase
#
# The grid (padded by unobserved pixels, which leaves the posterior of the real pixels unchanged)
# is cut into nr x nc equal tiles of th x tw pixels separated by one-pixel rows and columns.
# Inside a tile, nested dissection gives the same elimination subtree (a "template") for every
# tile, so the numeric work on the tiles runs batched over all tiles, one template node at a
# time. The separator rows and columns between tiles are eliminated afterwards by a nested
# dissection over the tile lattice ("top" nodes, one by one). Front positions of pixels outside
# the padded grid (rings of border tiles) point at a dummy variable / trash slot that is zero.

_OFFSETS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]


def _ring(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """(m, 2) pixels around the region [r0, r1) x [c0, c1) (unclipped), in a fixed order."""
    top = np.stack([np.full(c1 - c0 + 2, r0 - 1), np.arange(c0 - 1, c1 + 1)], 1)
    bottom = np.stack([np.full(c1 - c0 + 2, r1), np.arange(c0 - 1, c1 + 1)], 1)
    left = np.stack([np.arange(r0, r1), np.full(r1 - r0, c0 - 1)], 1)
    right = np.stack([np.arange(r0, r1), np.full(r1 - r0, c1)], 1)
    return np.concatenate([top, bottom, left, right]).astype(np.int64)


@dataclass
class _Template:
    """Nested-dissection subtree of one th x tw tile (relative pixel coordinates)."""

    th: int
    tw: int
    own: list  # per node (k, 2) own pixels
    ring: list  # per node (m, 2) ring pixels (may lie outside the tile)
    children: list
    parent: list
    posmap: list  # per node (th + 2, tw + 2): front pixel position of pixel (r + 1, c + 1), -1 = absent


def _build_template(th: int, tw: int, leaf_pixels: int) -> _Template:
    own, ring, children, parent = [], [], [], []

    def visit(r0, r1, c0, c1) -> int:
        hh, ww = r1 - r0, c1 - c0
        kids = []
        if hh * ww <= leaf_pixels or (hh < 3 and ww < 3):
            rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
            o = np.stack([rr.ravel(), cc.ravel()], 1)
        elif ww >= hh:
            m = c0 + ww // 2
            kids = [visit(r0, r1, c0, m)] + ([visit(r0, r1, m + 1, c1)] if m + 1 < c1 else [])
            o = np.stack([np.arange(r0, r1), np.full(hh, m)], 1)
        else:
            m = r0 + hh // 2
            kids = [visit(r0, m, c0, c1)] + ([visit(m + 1, r1, c0, c1)] if m + 1 < r1 else [])
            o = np.stack([np.full(ww, m), np.arange(c0, c1)], 1)
        node = len(own)
        own.append(o.astype(np.int64))
        ring.append(_ring(r0, r1, c0, c1))
        children.append(kids)
        parent.append(-1)
        for k in kids:
            parent[k] = node
        return node

    visit(0, th, 0, tw)
    posmap = []
    for o, g in zip(own, ring):
        pm = np.full((th + 2, tw + 2), -1, dtype=np.int64)
        front = np.concatenate([o, g])
        pm[front[:, 0] + 1, front[:, 1] + 1] = np.arange(front.shape[0])
        posmap.append(pm)
    return _Template(th, tw, own, ring, children, parent, posmap)


def _tiling(n: int, target: int) -> tuple[int, int]:
    """(tiles, tile size) along an axis of n pixels: tiles * (size + 1) - 1 >= n, size ~ target."""
    tiles = max(1, int(round((n + 1) / (target + 1))))
    size = -(-(n + 1) // tiles) - 1
    return tiles, size


@dataclass
class _Tree:
    """Elimination structure of the padded pixel grid (see the comment above)."""

    shape: tuple[int, int]  # the problem's grid
    padded: tuple[int, int]
    ds: int
    tpl: _Template
    origins: np.ndarray  # (T, 2) tile origins
    nvar: int  # real variables; index nvar is the dummy
    pix_var: np.ndarray  # (hp * wp,) variable of state 0 of each padded pixel
    vnode: np.ndarray  # (nvar,) virtual node owning each variable (template: tau * T + t; top: offset + x)
    # template nodes (batched over tiles)
    t_base: np.ndarray  # (ntpl + 1,) first variable of each template node's block (T * no variables)
    t_no: np.ndarray  # own variables per tile
    t_nf: np.ndarray  # front size (variables)
    t_bnd: list  # per node (T, nb): global variables of the ring (dummy = nvar)
    t_loc: list  # per non-root node (nb,): positions of the ring in the parent's front
    t_ea: list  # per non-root node: flat positions of the update matrix in the parent's front
    # top nodes (one by one)
    top_starts: np.ndarray  # (ntop + 1,) own variable ranges
    top_bnd: list  # sorted global variables
    top_nf: np.ndarray
    top_parent: np.ndarray
    top_children: list  # top children
    top_tiles: list  # per top node: tiles whose template root hangs below it
    top_loc: list
    top_ea: list
    tile_loc: np.ndarray  # (T, nb_root) positions of a tile root's ring in its top parent's front (trash = nf)
    tile_ea: np.ndarray  # (T, nb_root^2) flat positions (trash = nf^2)
    tile_parent: np.ndarray  # (T,) top node (-1: a single tile, no top nodes)

    @property
    def ntiles(self) -> int:
        return self.origins.shape[0]

    @property
    def ntpl(self) -> int:
        return len(self.tpl.own)

    @property
    def ntop(self) -> int:
        return len(self.top_bnd)

    def top_positions(self, x: int, variables: np.ndarray) -> np.ndarray:
        """Positions of variables (all in top node x's front) within that front."""
        st, en = self.top_starts[x], self.top_starts[x + 1]
        v = np.asarray(variables)
        out = np.empty(v.shape, dtype=np.int64)
        own = (v >= st) & (v < en)
        out[own] = v[own] - st
        b = self.top_bnd[x]
        idx = np.searchsorted(b, v[~own])
        if np.any(idx >= b.size) or np.any(b[np.minimum(idx, max(b.size - 1, 0))] != v[~own]):
            raise RuntimeError("internal error: variable not in front")
        out[~own] = en - st + idx
        return out

    def tile_positions(self, tau: int, tiles: np.ndarray, pixels: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Front positions in template node tau of tile-relative pixels of the given tiles."""
        rel = pixels - self.origins[tiles]
        pos = self.tpl.posmap[tau][rel[:, 0] + 1, rel[:, 1] + 1]
        if np.any(pos < 0):
            raise RuntimeError("internal error: pixel not in template front")
        return pos * self.ds + states


def _build_tree(h: int, w: int, ds: int, tile: int, leaf_pixels: int) -> _Tree:
    nr, th = _tiling(h, tile)
    nc, tw = _tiling(w, tile)
    hp, wp = nr * (th + 1) - 1, nc * (tw + 1) - 1
    tpl = _build_template(th, tw, leaf_pixels)
    T = nr * nc
    ti, tj = np.divmod(np.arange(T), nc)
    origins = np.stack([ti * (th + 1), tj * (tw + 1)], 1).astype(np.int64)
    states = np.arange(ds)
    pix_var = np.full(hp * wp, -1, dtype=np.int64)
    vnode_chunks = []
    t_base = [0]
    t_no = []
    for tau, o in enumerate(tpl.own):
        k = o.shape[0]
        glob = (origins[:, None, :] + o[None, :, :])  # (T, k, 2)
        pix = glob[..., 0] * wp + glob[..., 1]
        pix_var[pix.ravel()] = t_base[-1] + np.arange(T * k) * ds
        vnode_chunks.append(np.repeat(tau * T + np.arange(T), k * ds))
        t_no.append(k * ds)
        t_base.append(t_base[-1] + T * k * ds)
    ntpl = len(tpl.own)
    # top nodes: nested dissection of the tile lattice
    top_own, top_ring, top_children, top_tiles, top_parent = [], [], [], [], []

    def visit(i0, i1, j0, j1) -> tuple[str, int]:
        if (i1 - i0) * (j1 - j0) == 1:
            return ("tile", i0 * nc + j0)
        r0, r1 = i0 * (th + 1), i1 * (th + 1) - 1
        c0, c1 = j0 * (tw + 1), j1 * (tw + 1) - 1
        if (c1 - c0 >= r1 - r0 and j1 - j0 > 1) or i1 - i0 == 1:
            m = (j0 + j1) // 2
            kids = [visit(i0, i1, j0, m), visit(i0, i1, m, j1)]
            col = m * (tw + 1) - 1
            o = np.arange(r0, r1) * wp + col
        else:
            m = (i0 + i1) // 2
            kids = [visit(i0, m, j0, j1), visit(m, i1, j0, j1)]
            row = m * (th + 1) - 1
            o = row * wp + np.arange(c0, c1)
        g = _ring(r0, r1, c0, c1)
        g = g[(g[:, 0] >= 0) & (g[:, 0] < hp) & (g[:, 1] >= 0) & (g[:, 1] < wp)]
        node = len(top_own)
        top_own.append(o.astype(np.int64))
        top_ring.append(g[:, 0] * wp + g[:, 1])
        top_children.append([k for kind, k in kids if kind == "top"])
        top_tiles.append([k for kind, k in kids if kind == "tile"])
        top_parent.append(-1)
        for kind, k in kids:
            if kind == "top":
                top_parent[k] = node
        return ("top", node)

    visit(0, nr, 0, nc)
    off = t_base[-1]
    top_starts = [off]
    for x, o in enumerate(top_own):
        pix_var[o] = top_starts[-1] + np.arange(o.size) * ds
        vnode_chunks.append(np.full(o.size * ds, ntpl * T + x))
        top_starts.append(top_starts[-1] + o.size * ds)
    nvar = top_starts[-1]
    assert np.all(pix_var >= 0)
    top_bnd = [np.sort((pix_var[g][:, None] + states).ravel()) for g in top_ring]
    top_starts = np.array(top_starts)
    top_nf = np.array([top_starts[x + 1] - top_starts[x] + top_bnd[x].size for x in range(len(top_own))], dtype=np.int64)
    # template rings as global variables (dummy outside the padded grid)
    t_bnd, t_nf = [], []
    for tau, g in enumerate(tpl.ring):
        glob = origins[:, None, :] + g[None, :, :]
        inside = (glob[..., 0] >= 0) & (glob[..., 0] < hp) & (glob[..., 1] >= 0) & (glob[..., 1] < wp)
        pix = np.where(inside, glob[..., 0] * wp + glob[..., 1], 0)
        var = np.where(inside[..., None], pix_var[pix][..., None] + states, nvar)
        t_bnd.append(var.reshape(T, -1))
        t_nf.append(t_no[tau] + g.shape[0] * ds)
    t_nf = np.array(t_nf, dtype=np.int64)
    t_loc, t_ea = [None] * ntpl, [None] * ntpl
    for tau in range(ntpl):
        p = tpl.parent[tau]
        if p >= 0:
            g = tpl.ring[tau]
            pos = tpl.posmap[p][g[:, 0] + 1, g[:, 1] + 1]
            assert np.all(pos >= 0)
            loc = (pos[:, None] * ds + states).ravel()
            t_loc[tau] = loc
            t_ea[tau] = (loc[:, None] * t_nf[p] + loc[None, :]).ravel()
    tree = _Tree(
        shape=(h, w), padded=(hp, wp), ds=ds, tpl=tpl, origins=origins, nvar=int(nvar), pix_var=pix_var,
        vnode=np.concatenate(vnode_chunks), t_base=np.array(t_base), t_no=np.array(t_no), t_nf=t_nf,
        t_bnd=t_bnd, t_loc=t_loc, t_ea=t_ea, top_starts=top_starts, top_bnd=top_bnd, top_nf=top_nf,
        top_parent=np.array(top_parent, dtype=np.int64), top_children=top_children, top_tiles=top_tiles,
        top_loc=[None] * len(top_own), top_ea=[None] * len(top_own), tile_loc=None, tile_ea=None,
        tile_parent=np.full(T, -1, dtype=np.int64),
    )
    for x in range(tree.ntop):
        p = tree.top_parent[x]
        if p >= 0:
            loc = tree.top_positions(p, top_bnd[x])
            tree.top_loc[x] = loc
            tree.top_ea[x] = (loc[:, None] * top_nf[p] + loc[None, :]).ravel()
    root = ntpl - 1
    nb_root = t_bnd[root].shape[1]
    tile_loc = np.zeros((T, nb_root), dtype=np.int64)
    tile_ea = np.zeros((T, nb_root * nb_root), dtype=np.int64)
    for x in range(tree.ntop):
        nf = top_nf[x]
        for t in top_tiles[x]:
            tree.tile_parent[t] = x
            v = t_bnd[root][t]
            real = v < nvar
            loc = np.full(nb_root, nf, dtype=np.int64)
            loc[real] = tree.top_positions(x, v[real])
            tile_loc[t] = loc
            ea = loc[:, None] * nf + loc[None, :]
            ea[~real, :] = nf * nf
            ea[:, ~real] = nf * nf
            tile_ea[t] = ea.ravel()
    tree.tile_loc, tree.tile_ea = tile_loc, tile_ea
    return tree


@dataclass
class _Prior:
    """Front assembly of the unit-variance prior precision Qv (x) Qu, and its log-determinant."""

    t_qpos: list  # per template node (nq,) flat positions
    t_qval: list  # per template node (T, nq) values
    top_qpos: list
    top_qval: list
    logdet: float  # log det(Qv (x) Qu) over the padded grid (unit outputscale)


def _prior_pattern(tree: _Tree) -> dict:
    """Front positions and pixel pairs of every prior precision entry (per tree, cached on it)."""
    if "_pattern" in tree.__dict__:
        return tree.__dict__["_pattern"]
    hp, wp = tree.padded
    ds = tree.ds
    tpl = tree.tpl
    T = tree.ntiles
    template = []
    for tau in range(tree.ntpl):
        pm = tpl.posmap[tau]
        nf = tree.t_nf[tau]
        pa, pb, pp, qq = [], [], [], []
        for dr, dc in _OFFSETS:
            p = tpl.own[tau]
            q = p + np.array([dr, dc])
            bpos = pm[q[:, 0] + 1, q[:, 1] + 1]
            keep = bpos >= 0
            apos = pm[p[keep, 0] + 1, p[keep, 1] + 1]
            bpos = bpos[keep]
            is_own = bpos < tpl.own[tau].shape[0]
            # (p, q) always; (q, p) when q is a ring pixel (own pairs come twice by symmetry)
            pa += [apos, bpos[~is_own]]
            pb += [bpos, apos[~is_own]]
            pp += [p[keep], q[keep][~is_own]]
            qq += [q[keep], p[keep][~is_own]]
        pa, pb = np.concatenate(pa), np.concatenate(pb)
        pp, qq = np.concatenate(pp), np.concatenate(qq)
        ga = tree.origins[:, None, :] + pp[None]  # (T, m, 2)
        gb = tree.origins[:, None, :] + qq[None]
        inside = (gb[..., 0] >= 0) & (gb[..., 0] < hp) & (gb[..., 1] >= 0) & (gb[..., 1] < wp)
        inside &= (ga[..., 0] >= 0) & (ga[..., 0] < hp) & (ga[..., 1] >= 0) & (ga[..., 1] < wp)
        coords = (
            np.clip(ga[..., 0], 0, hp - 1).ravel(), np.clip(ga[..., 1], 0, wp - 1).ravel(),
            np.clip(gb[..., 0], 0, hp - 1).ravel(), np.clip(gb[..., 1], 0, wp - 1).ravel(),
        )
        pos = ((pa * ds)[:, None, None] + np.arange(ds)[None, :, None]) * nf + (pb * ds)[:, None, None] + np.arange(ds)
        template.append((pos.ravel(), coords, inside))
    is_top = np.zeros(hp * wp, dtype=bool)
    is_top[tree.vnode[tree.pix_var] >= tree.ntpl * T] = True
    all_top = np.nonzero(is_top)[0]
    pr, pc = np.divmod(all_top, wp)
    rows_p, rows_q = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for dr, dc in _OFFSETS:
        qr, qc = pr + dr, pc + dc
        ok = (qr >= 0) & (qr < hp) & (qc >= 0) & (qc < wp)
        qpix = np.where(ok, qr * wp + qc, 0)
        ok &= is_top[qpix]
        rows_p.append(all_top[ok])
        rows_q.append(qpix[ok])
    p_all, q_all = np.concatenate(rows_p), np.concatenate(rows_q)
    owner = tree.vnode[np.minimum(tree.pix_var[p_all], tree.pix_var[q_all])] - tree.ntpl * T
    sort = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[sort], np.arange(tree.ntop + 1))
    st = np.arange(ds)
    top = []
    for x in range(tree.ntop):
        sel = sort[bounds[x] : bounds[x + 1]]
        va = (tree.pix_var[p_all[sel]][:, None] + st).ravel()
        vb = (tree.pix_var[q_all[sel]][:, None] + st).ravel()
        a = tree.top_positions(x, va).reshape(-1, ds)
        b = tree.top_positions(x, vb).reshape(-1, ds)
        pos = (a[:, :, None] * tree.top_nf[x] + b[:, None, :]).ravel()
        top.append((pos, (*np.divmod(p_all[sel], wp), *np.divmod(q_all[sel], wp))))
    pattern = {"template": template, "top": top}
    tree.__dict__["_pattern"] = pattern
    return pattern


def _chains(tree: _Tree, nu: float, lengthscale: float):
    """The 1-D chain precisions along rows and columns of the padded grid and log det(Qv (x) Qu)."""
    hp, wp = tree.padded
    d = state_dim(nu)
    if d * d != tree.ds:
        raise InvalidInputError("nu", f"a smoothness with {tree.ds} states per pixel", nu)
    Qv, ldv = chain_precision(np.arange(hp, dtype=np.float64), nu, lengthscale)
    Qu, ldu = chain_precision(np.arange(wp, dtype=np.float64), nu, lengthscale)
    return Qv, Qu, wp * d * ldv + hp * d * ldu


def _build_prior(tree: _Tree, nu: float, lengthscale: float) -> _Prior:
    d = state_dim(nu)
    ds = tree.ds
    Qv, Qu, logdet = _chains(tree, nu, lengthscale)
    pattern = _prior_pattern(tree)
    Qv, Qu = Qv.toarray(), Qu.toarray()
    kk, ll = np.divmod(np.arange(ds), d)

    def values(rp, cp, rq, cq):
        """(m, ds, ds) Q blocks between pixels p and q (m,) in padded-grid coordinates."""
        a = Qv[(rp * d)[:, None, None] + kk[None, :, None], (rq * d)[:, None, None] + kk[None, None, :]]
        b = Qu[(cp * d)[:, None, None] + ll[None, :, None], (cq * d)[:, None, None] + ll[None, None, :]]
        return a * b

    T = tree.ntiles
    t_qpos, t_qval = [], []
    for pos, coords, inside in pattern["template"]:
        m = inside.shape[1]
        vals = values(*coords).reshape(T, m, ds, ds) * inside[..., None, None]
        t_qpos.append(pos)
        t_qval.append(vals.reshape(T, -1))
    top_qpos, top_qval = [], []
    for pos, coords in pattern["top"]:
        top_qpos.append(pos)
        top_qval.append(values(*coords).ravel())
    return _Prior(t_qpos, t_qval, top_qpos, top_qval, logdet)


@dataclass
class _Readout:
    """Exact read-out of the field at an output tensor grid from the 2 x 2 neighbouring grid states."""

    wv: sp.csr_matrix  # (Ho, H d) row weights
    wu: sp.csr_matrix  # (Wo, W d) column weights
    resid: np.ndarray  # (Ho, Wo) conditional prior variance (unit outputscale)
    t_groups: list  # per template node: (outputs (m,), tiles (m,), front positions (m, 4 ds), weights (m, 4 ds))
    top_groups: list  # per top node: (outputs (m,), front positions (m, 4 ds), weights (m, 4 ds))
    corner_vars: np.ndarray  # (Ho Wo, 4 ds) grid state variables each output reads
    corner_wgt: np.ndarray  # (Ho Wo, 4 ds) their weights


def _build_readout(tree: _Tree, out_rows: np.ndarray, out_cols: np.ndarray, nu: float, lengthscale: float) -> _Readout:
    h, w = tree.shape
    hp, wp = tree.padded
    d = state_dim(nu)
    ds = tree.ds
    fr, wr, rr = readout_weights(np.arange(h, dtype=np.float64), out_rows, nu, lengthscale)
    fc, wc, rc = readout_weights(np.arange(w, dtype=np.float64), out_cols, nu, lengthscale)
    ho, wo = out_rows.shape[0], out_cols.shape[0]

    def wmat(first, wts, n):
        m = first.shape[0]
        rows = np.repeat(np.arange(m), 2 * d)
        cols = ((first[:, None, None] + np.arange(2)[None, :, None]) * d + np.arange(d)[None, None, :]).ravel()
        return sp.csr_matrix((wts.ravel(), (rows, cols)), shape=(m, n * d))

    resid = 1.0 - np.outer(1.0 - rr, 1.0 - rc)
    orr, occ = np.meshgrid(np.arange(ho), np.arange(wo), indexing="ij")
    orr, occ = orr.ravel(), occ.ravel()
    m = orr.size
    corner_r = fr[orr][:, None] + np.array([0, 0, 1, 1])
    corner_c = fc[occ][:, None] + np.array([0, 1, 0, 1])
    cpix = np.stack([corner_r, corner_c], -1)  # (m, 4, 2) padded-grid pixels (inside the real grid)
    pvar = tree.pix_var[corner_r * wp + corner_c]  # (m, 4)
    wgt = np.einsum("mak,mbl->mabkl", wr[orr], wc[occ]).reshape(m, 4 * ds)
    first = np.argmin(pvar, axis=1)
    owner = tree.vnode[pvar[np.arange(m), first]]
    sort = np.argsort(owner, kind="stable")
    T = tree.ntiles
    bounds = np.searchsorted(owner[sort], np.arange((tree.ntpl + tree.ntop) * 0 + tree.ntpl * T + tree.ntop + 1))
    states = np.tile(np.arange(ds), 4)
    t_groups = []
    for tau in range(tree.ntpl):
        sel = sort[bounds[tau * T] : bounds[(tau + 1) * T]]
        if sel.size == 0:
            t_groups.append(None)
            continue
        tiles = owner[sel] - tau * T
        pix = np.repeat(cpix[sel], ds, axis=1).reshape(-1, 2)
        pos = tree.tile_positions(tau, np.repeat(tiles, 4 * ds), pix, np.tile(states, sel.size)).reshape(sel.size, 4 * ds)
        t_groups.append((sel, tiles, pos, wgt[sel]))
    top_groups = []
    for x in range(tree.ntop):
        v = tree.ntpl * T + x
        sel = sort[bounds[v] : bounds[v + 1]]
        if sel.size == 0:
            top_groups.append(None)
            continue
        var = (pvar[sel][:, :, None] + np.arange(ds)).reshape(sel.size, 4 * ds)
        pos = tree.top_positions(x, var.ravel()).reshape(sel.size, 4 * ds)
        top_groups.append((sel, pos, wgt[sel]))
    corner_vars = (pvar[:, :, None] + np.arange(ds)).reshape(m, 4 * ds)
    return _Readout(wmat(fr, wr, h), wmat(fc, wc, w), resid, t_groups, top_groups, corner_vars, wgt)


# ----------------------------------------------------------------------------- compiled CPU phase
#
# On the CPU the numeric work runs in `gpdepth3d.gp.multifrontal` (numba + LAPACK): every
# (template node, tile) pair and every top node becomes one front of a `FrontTree`; the prior
# precision is assembled entry by entry from the 9-point stencil of d x d state blocks.


def _front_tree(tree: _Tree) -> FrontTree:
    """The tree's fronts for the compiled phase (cached on the tree)."""
    if "_fronts" in tree.__dict__:
        return tree.__dict__["_fronts"]
    T, ntpl, nvar = tree.ntiles, tree.ntpl, tree.nvar
    st, no, parent, bnds = [], [], [], []
    for tau in range(ntpl):
        p = tree.tpl.parent[tau]
        for t in range(T):
            st.append(tree.t_base[tau] + t * tree.t_no[tau])
            no.append(tree.t_no[tau])
            b = tree.t_bnd[tau][t]
            bnds.append(b[b < nvar])
            if p >= 0:
                parent.append(p * T + t)
            else:
                parent.append(ntpl * T + tree.tile_parent[t] if tree.tile_parent[t] >= 0 else -1)
    for x in range(tree.ntop):
        st.append(tree.top_starts[x])
        no.append(tree.top_starts[x + 1] - tree.top_starts[x])
        bnds.append(tree.top_bnd[x])
        parent.append(ntpl * T + tree.top_parent[x] if tree.top_parent[x] >= 0 else -1)
    fronts = FrontTree.build(st, no, parent, bnds, nvar)
    tree.__dict__["_fronts"] = fronts
    return fronts


@dataclass
class _FrontalPrior:
    """Prior precision entries (lower triangle, unit outputscale) and their front assembly map."""

    asm: tuple  # (ptr, flat positions, source entry) per front
    qvals: np.ndarray  # value of each entry
    logdet: float


def _build_frontal_prior(tree: _Tree, nu: float, lengthscale: float) -> _FrontalPrior:
    hp, wp = tree.padded
    d = state_dim(nu)
    ds = tree.ds
    Qv, Qu, logdet = _chains(tree, nu, lengthscale)
    fronts = _front_tree(tree)
    if "_frontal_pattern" not in tree.__dict__:
        pr, pc = np.divmod(np.arange(hp * wp), wp)
        ents = []
        for dr, dc in _OFFSETS:
            qr, qc = pr + dr, pc + dc
            ok = (qr >= 0) & (qr < hp) & (qc >= 0) & (qc < wp)
            a, b = pr[ok] * wp + pc[ok], qr[ok] * wp + qc[ok]
            ents.append(np.stack([a, b], 1))
        pairs = np.concatenate(ents)
        s1, s2 = np.divmod(np.arange(ds * ds), ds)
        va = (tree.pix_var[pairs[:, 0]][:, None] + s1).ravel()
        vb = (tree.pix_var[pairs[:, 1]][:, None] + s2).ravel()
        keep = va >= vb  # each symmetric pair once (lower triangle in elimination order)
        pix = np.repeat(pairs, ds * ds, axis=0)[keep]
        st1, st2 = np.tile(s1, pairs.shape[0])[keep], np.tile(s2, pairs.shape[0])[keep]
        tree.__dict__["_frontal_pattern"] = (pix, st1, st2, fronts.assembly(va[keep], vb[keep]))
    pix, st1, st2, asm = tree.__dict__["_frontal_pattern"]
    (ra, ca), (rb, cb) = np.divmod(pix[:, 0], wp), np.divmod(pix[:, 1], wp)
    (k1, l1), (k2, l2) = np.divmod(st1, d), np.divmod(st2, d)
    qv = _bands(Qv, d)[ra, rb - ra + 1, k1, k2]
    qu = _bands(Qu, d)[ca, cb - ca + 1, l1, l2]
    return _FrontalPrior(asm, qv * qu, logdet)


def _bands(Q: sp.spmatrix, d: int) -> np.ndarray:
    """(n, 3, d, d) blocks Q[i, i + o - 1] of a block-tridiagonal chain precision (n d x n d)."""
    n = Q.shape[0] // d
    coo = Q.tocoo()
    i, j = np.divmod(coo.row, d), np.divmod(coo.col, d)
    out = np.zeros((n, 3, d, d))
    out[i[0], j[0] - i[0] + 1, i[1], j[1]] = coo.data
    return out


def _frontal_readout(fronts: FrontTree, readout: _Readout) -> tuple:
    """The read-out split for the compiled selected inverse (cached on the read-out):
    ``((ptr, output index, front positions, weights, n_out), (outputs, variable, weight^2))``.

    An output that reads a single grid state (a non-zero weight on one variable: every output on
    a grid pixel, and the rows outside the factorised lattice, which read its edge state) has the
    variance weight^2 diag(P^-1)[variable]; only the others (between grid pixels) need covariance
    fronts. Leaf fronts without them take the selected inverse's diagonal-only path (KITTI 1/3:
    every output is a single state).
    """
    cached = readout.__dict__.get("_frontal")
    if cached is None or cached[0] is not fronts:
        nz = readout.corner_wgt != 0.0
        single = np.count_nonzero(nz, axis=1) == 1
        out_single = np.nonzero(single)[0]
        k = np.argmax(nz[out_single], axis=1)
        simple = (out_single.astype(np.int64), readout.corner_vars[out_single, k],
                  readout.corner_wgt[out_single, k] ** 2)
        rest = np.nonzero(~single)[0]
        v = readout.corner_vars[rest]
        f = fronts.front_of[v.min(axis=1)]
        pos = fronts.positions(np.repeat(f, v.shape[1]), v.ravel()).reshape(v.shape)
        srt = np.argsort(f, kind="stable")
        ptr = np.searchsorted(f[srt], np.arange(fronts.st.size + 1)).astype(np.int64)
        cached = (fronts, ((ptr, rest[srt].astype(np.int64), np.ascontiguousarray(pos[srt]),
                            np.ascontiguousarray(readout.corner_wgt[rest[srt]]), readout.corner_vars.shape[0]), simple))
        readout.__dict__["_frontal"] = cached
    return cached[1]


# ----------------------------------------------------------------------------- numeric phase (torch)


def _device_arrays(tree: _Tree, prior: _Prior, readout: "_Readout | None", device):
    """Index arrays and prior values of the tree as torch tensors on ``device`` (cached on the objects)."""
    import torch

    key = str(device)
    cache = tree.__dict__.setdefault("_dev", {})
    if key not in cache:
        t = lambda a: None if a is None else torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
        cache[key] = {
            "t_bnd": [t(b) for b in tree.t_bnd], "t_loc": [t(x) for x in tree.t_loc],
            "t_ea": [t(x) for x in tree.t_ea], "top_bnd": [t(b) for b in tree.top_bnd],
            "top_loc": [t(x) for x in tree.top_loc], "top_ea": [t(x) for x in tree.top_ea],
            "tile_loc": t(tree.tile_loc), "tile_ea": t(tree.tile_ea),
            "top_tiles": [t(np.array(x, dtype=np.int64)) for x in tree.top_tiles],
            "t_diag": [t(np.arange(no) * (nf + 1)) for no, nf in zip(tree.t_no, tree.t_nf)],
            "top_diag": [t(np.arange(tree.top_starts[x + 1] - tree.top_starts[x]) * (tree.top_nf[x] + 1)) for x in range(tree.ntop)],
        }
    pcache = prior.__dict__.setdefault("_dev", {})
    if key not in pcache:
        t = lambda a: torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
        pcache[key] = {
            "t_qpos": [t(x) for x in prior.t_qpos], "t_qval": [t(x) for x in prior.t_qval],
            "top_qpos": [t(x) for x in prior.top_qpos], "top_qval": [t(x) for x in prior.top_qval],
        }
    rdev = None
    if readout is not None:
        rcache = readout.__dict__.setdefault("_dev", {})
        if key not in rcache:
            t = lambda a: torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
            rcache[key] = {
                "t": [None if g is None else tuple(t(a) for a in g) for g in readout.t_groups],
                "top": [None if g is None else tuple(t(a) for a in g) for g in readout.top_groups],
            }
        rdev = rcache[key]
    return cache[key], pcache[key], rdev


class _Factor:
    """Cholesky factor of the posterior precision over the tree's fronts (torch, float64, any device)."""

    def __init__(self, tree: _Tree, prior: _Prior, inv_s2: float, prec_var: np.ndarray, device=None):
        import torch

        self.torch = torch
        self.device = torch.device("cpu" if device is None else device)
        self.tree, self.prior = tree, prior
        ix, pq, _ = _device_arrays(tree, prior, None, self.device)
        self.ix = ix
        opts = {"dtype": torch.float64, "device": self.device}
        prec = torch.as_tensor(prec_var, **opts)
        T = tree.ntiles
        tpl = tree.tpl
        solve_tri = torch.linalg.solve_triangular
        logdet = torch.zeros((), **opts)
        info = torch.zeros((), dtype=torch.int32, device=self.device)
        upd: list = [None] * tree.ntpl
        self.tL11, self.tL21T = [], []
        for tau in range(tree.ntpl):
            nf, no = int(tree.t_nf[tau]), int(tree.t_no[tau])
            F = torch.zeros((T, nf * nf), **opts)
            F.index_copy_(1, pq["t_qpos"][tau], pq["t_qval"][tau] * inv_s2)
            F.index_add_(1, ix["t_diag"][tau], prec[tree.t_base[tau] : tree.t_base[tau + 1]].view(T, no))
            for c in tpl.children[tau]:
                F.index_add_(1, ix["t_ea"][c], upd[c].reshape(T, -1))
                upd[c] = None
            F = F.view(T, nf, nf)
            L11, inf = torch.linalg.cholesky_ex(F[:, :no, :no])
            info = info + inf.abs().sum()
            logdet = logdet + 2.0 * torch.log(torch.diagonal(L11, dim1=1, dim2=2)).sum()
            L21T = solve_tri(L11, F[:, :no, no:], upper=False)
            upd[tau] = F[:, no:, no:] - L21T.mT @ L21T
            self.tL11.append(L11)
            self.tL21T.append(L21T)
        root_update = upd[tree.ntpl - 1].reshape(T, -1)
        self.L11, self.L21T = [], []
        updates: list = [None] * tree.ntop
        for x in range(tree.ntop):
            nf = int(tree.top_nf[x])
            st, en = int(tree.top_starts[x]), int(tree.top_starts[x + 1])
            no = en - st
            Ff = torch.zeros(nf * nf + 1, **opts)
            Ff.index_copy_(0, pq["top_qpos"][x], pq["top_qval"][x] * inv_s2)
            Ff.index_add_(0, ix["top_diag"][x], prec[st:en])
            for c in tree.top_children[x]:
                Ff.index_add_(0, ix["top_ea"][c], updates[c].reshape(-1))
                updates[c] = None
            if tree.top_tiles[x]:
                tiles = ix["top_tiles"][x]
                Ff.index_add_(0, ix["tile_ea"][tiles].reshape(-1), root_update[tiles].reshape(-1))
            F = Ff[:-1].view(nf, nf)
            L11, inf = torch.linalg.cholesky_ex(F[:no, :no])
            info = info + inf.abs()
            logdet = logdet + 2.0 * torch.log(torch.diagonal(L11)).sum()
            L21T = solve_tri(L11, F[:no, no:], upper=False)
            if nf > no:
                updates[x] = F[no:, no:] - L21T.T @ L21T
            self.L11.append(L11)
            self.L21T.append(L21T)
        if int(info) != 0:
            raise np.linalg.LinAlgError("posterior precision not positive definite (check precisions and scales)")
        self.logdet = float(logdet)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solves P x = b for b (nvar,) (variables in elimination numbering)."""
        torch = self.torch
        tree, ix = self.tree, self.ix
        T = tree.ntiles
        n = tree.nvar
        solve_tri = torch.linalg.solve_triangular
        y = torch.zeros(n + 1, dtype=torch.float64, device=self.device)
        y[:n] = torch.as_tensor(b, dtype=torch.float64, device=self.device)
        for tau in range(tree.ntpl):
            s = slice(int(tree.t_base[tau]), int(tree.t_base[tau + 1]))
            z = solve_tri(self.tL11[tau], y[s].view(T, -1, 1), upper=False)
            y[s] = z.reshape(-1)
            y.index_add_(0, ix["t_bnd"][tau].reshape(-1), -(self.tL21T[tau].mT @ z).reshape(-1))
        for x in range(tree.ntop):
            st, en = int(tree.top_starts[x]), int(tree.top_starts[x + 1])
            z = solve_tri(self.L11[x], y[st:en].view(-1, 1), upper=False)
            y[st:en] = z.view(-1)
            if self.L21T[x].shape[1]:
                y.index_add_(0, ix["top_bnd"][x], -(self.L21T[x].T @ z).view(-1))
        y[n] = 0.0
        for x in range(tree.ntop - 1, -1, -1):
            st, en = int(tree.top_starts[x]), int(tree.top_starts[x + 1])
            rhs = y[st:en].view(-1, 1)
            if self.L21T[x].shape[1]:
                rhs = rhs - self.L21T[x] @ y[ix["top_bnd"][x]].view(-1, 1)
            y[st:en] = solve_tri(self.L11[x].T, rhs, upper=True).view(-1)
        for tau in range(tree.ntpl - 1, -1, -1):
            s = slice(int(tree.t_base[tau]), int(tree.t_base[tau + 1]))
            rhs = y[s].view(T, -1, 1) - self.tL21T[tau] @ y[ix["t_bnd"][tau]].unsqueeze(-1)
            y[s] = solve_tri(self.tL11[tau].mT, rhs, upper=True).reshape(-1)
        return y[:n].cpu().numpy()

    def selected_inverse(self, readout: _Readout | None) -> tuple[np.ndarray, np.ndarray | None]:
        """diag(P^-1) (nvar,) and, with a read-out, the output variances w^T Sigma_block w (Ho Wo,)."""
        torch = self.torch
        tree, ix = self.tree, self.ix
        _, _, rd = _device_arrays(tree, self.prior, readout, self.device)
        opts = {"dtype": torch.float64, "device": self.device}
        T = tree.ntiles
        solve_tri = torch.linalg.solve_triangular
        diag = torch.empty(tree.nvar, **opts)
        out = torch.empty(readout.resid.size, **opts) if readout is not None else None
        sig: list = [None] * tree.ntop
        nb_root = int(tree.t_nf[-1] - tree.t_no[-1])
        root_sbb = torch.zeros((T, nb_root, nb_root), **opts)  # Sigma of each tile root's ring
        last_child = [min(c) if c else -1 for c in tree.top_children]
        for x in range(tree.ntop - 1, -1, -1):
            st, en = int(tree.top_starts[x]), int(tree.top_starts[x + 1])
            no = en - st
            nf = int(tree.top_nf[x])
            L11 = self.L11[x]
            Linv = solve_tri(L11, torch.eye(no, **opts), upper=False)
            S = torch.zeros((nf + 1, nf + 1), **opts)  # last row / column: the zero trash slot
            SJJ = Linv.T @ Linv
            if nf > no:
                loc = ix["top_loc"][x]
                SBB = sig[tree.top_parent[x]][loc[:, None], loc[None, :]]
                TT = Linv.T @ self.L21T[x]
                SBJ = -(SBB @ TT.T)
                SJJ = SJJ - TT @ SBJ
                S[:no, no:nf] = SBJ.T
                S[no:nf, :no] = SBJ
                S[no:nf, no:nf] = SBB
            S[:no, :no] = SJJ
            diag[st:en] = torch.diagonal(SJJ)
            if rd is not None and rd["top"][x] is not None:
                sel, pos, wgt = rd["top"][x]
                out[sel] = torch.einsum("mi,mij,mj->m", wgt, S[pos[:, :, None], pos[:, None, :]], wgt)
            if tree.top_tiles[x]:
                tiles = ix["top_tiles"][x]
                loc = ix["tile_loc"][tiles]
                root_sbb[tiles] = S[loc[:, :, None], loc[:, None, :]]
            if tree.top_children[x]:
                sig[x] = S
            p = tree.top_parent[x]
            if p >= 0 and last_child[p] == x:
                sig[p] = None  # all its children are done
        tsig: list = [None] * tree.ntpl
        tpl = tree.tpl
        for tau in range(tree.ntpl - 1, -1, -1):
            no, nf = int(tree.t_no[tau]), int(tree.t_nf[tau])
            L11, L21T = self.tL11[tau], self.tL21T[tau]
            Linv = solve_tri(L11, torch.eye(no, **opts).expand(T, no, no), upper=False)
            LinvT = Linv.mT
            p = tpl.parent[tau]
            if p >= 0:
                loc = ix["t_loc"][tau]
                SBB = tsig[p][:, loc[:, None], loc[None, :]]
            else:
                SBB = root_sbb
            TT = LinvT @ L21T  # (T, no, nb)
            SBJ = -(SBB @ TT.mT)  # (T, nb, no)
            S = torch.empty((T, nf, nf), **opts)
            SJJ = LinvT @ Linv - TT @ SBJ
            S[:, :no, :no] = SJJ
            S[:, :no, no:] = SBJ.mT
            S[:, no:, :no] = SBJ
            S[:, no:, no:] = SBB
            diag[int(tree.t_base[tau]) : int(tree.t_base[tau + 1])] = torch.diagonal(SJJ, dim1=1, dim2=2).reshape(-1)
            if rd is not None and rd["t"][tau] is not None:
                sel, tiles, pos, wgt = rd["t"][tau]
                block = S[tiles[:, None, None], pos[:, :, None], pos[:, None, :]]
                out[sel] = torch.einsum("mi,mij,mj->m", wgt, block, wgt)
            tsig[tau] = S
            if p >= 0 and min(tpl.children[p]) == tau:
                tsig[p] = None
        return diag.cpu().numpy(), (out.cpu().numpy() if out is not None else None)



LATTICE_QUANTUM = 8
"""The observed lattice's bounds are rounded outwards to multiples of this many pixels (clipped to
the grid), so that the frames of a sequence share its elimination structure."""


def observed_lattice(precision: np.ndarray, quantum: int = LATTICE_QUANTUM) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1): the sub-grid [r0, r1) x [c0, c1) spanning the observed pixels, or None for the whole grid.

    The separable Matern field is Markov along each axis, so the posterior on this sub-grid
    given the observations (all inside it) is the posterior of the whole grid there, and every
    other pixel is read out exactly from the sub-grid's states next to it (as an output grid
    other than the input grid is, `markov.readout_weights`). The bounds are rounded outwards
    to multiples of ``quantum`` and the sub-grid has at least 2 x 2 pixels.

    Args:
        precision: (H, W) observation precisions (0 = unobserved).
        quantum: Rounding of the bounds (pixels, >= 1).

    Returns:
        The bounds, or None when there is no observation or the sub-grid is the whole grid.
    """
    obs = np.asarray(precision) > 0
    h, w = obs.shape
    rows = np.flatnonzero(obs.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(obs.any(axis=0))
    q = max(int(quantum), 1)

    def bounds(lo: int, hi: int, n: int) -> tuple[int, int]:
        lo, hi = (lo // q) * q, min(n, -(-hi // q) * q)
        if hi - lo < 2:  # the grid route needs two nodes per axis (n >= 2 is checked)
            lo = min(lo, n - 2)
            hi = lo + 2
        return lo, hi

    r0, r1 = bounds(int(rows[0]), int(rows[-1]) + 1, h)
    c0, c1 = bounds(int(cols[0]), int(cols[-1]) + 1, w)
    if (r0, r1, c0, c1) == (0, h, 0, w):
        return None
    return r0, r1, c0, c1


# ----------------------------------------------------------------------------- engine


class FastEngine:
    """Exact GP posterior on the pixel grid via the sparse precision (see the module docstring).

    The engine caches, per resolution and kernel, the elimination structure, the prior
    precision assembly and the output read-out, so a `DepthCompleter` (which keeps one engine)
    only pays the numeric factorisation from the second frame of a resolution on. A direct
    factorisation has nothing to warm-start.

    Args:
        device: torch device of the numeric work (None = "cpu"); float64 everywhere.
        tile: Target tile size (pixels per side) of the batched part of the elimination.
        leaf_pixels: Largest sub-grid (pixels) eliminated as one dense front inside a tile (default:
            20 for nu = 0.5 on the compiled back-end, 40 / (nu + 1/2)^2 otherwise).
        cache_size: Number of (resolution, kernel) set-ups kept.
        threads: torch back-end: CPU threads of torch during the numeric work (restored
            afterwards); None keeps torch's setting. The default 1 is as fast on 2 cores for these
            many small batched kernels. The compiled back-end runs one subtree group per numba
            thread (``numba.set_num_threads`` / NUMBA_NUM_THREADS, read when a resolution is
            first seen) with single-threaded BLAS.
        backend: "compiled" (numba + LAPACK, `gpdepth3d.gp.multifrontal`; CPU only), "torch"
            (batched torch kernels; any device) or "auto" (compiled on the CPU, torch elsewhere).
        route: "auto" (compiled back-end: the cheapest that applies, by a cost model; torch
            back-end: the grid), "grid" (the sparse precision over the pixel grid, any nu),
            "woodbury" (nu = 0.5: dense algebra over the observed pixels on the CPU,
            `gpdepth3d.gp.woodbury`; for a few thousand points at most) or "neumann" (nu = 0.5,
            every pixel observed strongly enough that the precision is diagonally dominant, as
            in the paper's balanced set-up, output on the input grid: a series with a certified
            error bound, `gpdepth3d.gp.neumann`) or "dense" (any nu, few observed pixels: dense
            algebra over them, `gpdepth3d.gp.exact.dense_posterior`). Each call's
            ``Solution.info.route`` tells which one it took (`plan` tells beforehand); the engine
            keeps no per-call state. The log marginal likelihood uses the grid, Woodbury or dense
            ("neumann" forced: the grid). A forced route that cannot compute the exact posterior
            raises (see Raises of `solve`); "auto" picks among those that can.
        max_dense_points: The dense route takes at most this many observed pixels.
        max_memory_mb: Memory budget of one solve (MiB); None: three quarters of the memory
            available at the call (`memory_budget`; buffers the engine already holds for the
            resolution are not counted). Routes whose estimated memory exceeds it are not taken.
        prior_cache_mb: Compiled back-end: memory allowed for the factor of the prior alone
            (`PriorFactor`, one per engine), which the frames of a sequence reuse for every
            front their observations do not reach. It is built from the second frame with the
            same resolution and kernel on, when at least a quarter of the fronts are unreached
            (the residual formulation with sparse points); 0 disables it.
        lattice: Grid route: "observed" (the default) factorises only the sub-grid spanning the
            observed pixels (`observed_lattice`; the pixels around it are read out exactly, as
            an output grid other than the input grid is), "full" the whole GP grid.

    ``solve(problem, variance=True, extra_obs=())`` returns a `gpdepth3d.gp.engine.Solution`;
    the means of ``extra_obs`` (further observation vectors with the same precision) reuse the
    call's factorisation (the default model's scale term needs one).
    """

    name = "fast"

    def __init__(
        self,
        device=None,
        *,
        tile: int | None = None,
        leaf_pixels: int | None = None,
        cache_size: int = 4,
        threads: int | None = 1,
        backend: str = "auto",
        prior_cache_mb: float = 256.0,
        route: str = "auto",
        max_dense_points: int = 6000,
        max_memory_mb: float | None = None,
        lattice: str = "observed",
    ):
        if threads is not None and (not isinstance(threads, (int, np.integer)) or threads < 1):
            raise InvalidInputError("threads", "None or an integer >= 1", threads)
        self.threads = threads
        for name, value in (("tile", tile), ("leaf_pixels", leaf_pixels)):
            if value is not None and (not isinstance(value, (int, np.integer)) or value < 1):
                raise InvalidInputError(name, "an integer >= 1", value)
        if not isinstance(cache_size, (int, np.integer)) or cache_size < 1:
            raise InvalidInputError("cache_size", "an integer >= 1", cache_size)
        if backend not in ("auto", "compiled", "torch"):
            raise InvalidInputError("backend", "'auto', 'compiled' or 'torch'", backend)
        on_cpu = device is None or str(device) == "cpu"
        if backend == "compiled" and not on_cpu:
            raise InvalidInputError("backend", "'torch' or 'auto' on a non-CPU device", backend)
        self.backend = "compiled" if backend == "auto" and on_cpu else ("torch" if backend == "auto" else backend)
        if not isinstance(prior_cache_mb, (int, float, np.integer, np.floating)) or not prior_cache_mb >= 0:
            raise InvalidInputError("prior_cache_mb", "a number >= 0", prior_cache_mb)
        self.prior_cache_mb = float(prior_cache_mb)
        if route not in ("auto", "grid", "woodbury", "neumann", "dense"):
            raise InvalidInputError("route", "'auto', 'grid', 'woodbury', 'neumann' or 'dense'", route)
        self.route = route
        if isinstance(max_dense_points, (bool, np.bool_)) or not isinstance(max_dense_points, (int, np.integer)) \
                or max_dense_points < 0:
            raise InvalidInputError("max_dense_points", "an integer >= 0", max_dense_points)
        self.max_dense_points = int(max_dense_points)
        if max_memory_mb is not None and (isinstance(max_memory_mb, (bool, np.bool_))
                                          or not isinstance(max_memory_mb, (int, float, np.integer, np.floating))
                                          or not max_memory_mb > 0 or not np.isfinite(max_memory_mb)):
            raise InvalidInputError("max_memory_mb", "None or a finite number > 0", max_memory_mb)
        self.max_memory_mb = None if max_memory_mb is None else float(max_memory_mb)
        if lattice not in ("observed", "full"):
            raise InvalidInputError("lattice", "'observed' or 'full'", lattice)
        self.lattice = lattice
        self._prior_factor: tuple | None = None  # (key, PriorFactor)
        self._kernel_uses: dict = {}
        self._woodbury_buffers: dict = {}  # image buffers of the Woodbury route, per output shape
        self._neumann_buffers: dict = {}  # coefficient buffer of the Neumann route
        self.device = device
        self.tile = tile
        self.leaf_pixels = leaf_pixels
        self.cache_size = int(cache_size)
        self._trees: OrderedDict = OrderedDict()
        self._priors: OrderedDict = OrderedDict()
        self._readouts: OrderedDict = OrderedDict()

    # -- caches
    def _cached(self, store: OrderedDict, key, build):
        if key in store:
            store.move_to_end(key)
            return store[key]
        value = build()
        store[key] = value
        while len(store) > self.cache_size:
            store.popitem(last=False)
        return value

    def _tree_key(self, h: int, w: int, ds: int) -> tuple:
        tile = self.tile or (24 if ds == 1 else 12 if ds == 4 else 8)
        # nu = 0.5 on the compiled back-end: 20-pixel leaves (KITTI 1/3 lattice, 1/4 of the LiDAR: 119 instead
        # of 143 MFLOP, grid route 102 -> 90 ms single-thread CPU; all of it 99 -> 94 ms)
        leaf = self.leaf_pixels or (20 if ds == 1 and self.backend == "compiled" else max(1, 40 // ds))
        return (h, w, ds, tile, leaf)

    def _tree(self, h: int, w: int, ds: int) -> _Tree:
        key = self._tree_key(h, w, ds)
        tile, leaf = key[3], key[4]

        def build():
            tree = _build_tree(h, w, ds, tile, leaf)
            tree.__dict__["_key"] = key  # what the prior and read-out caches refer to (ids can be reused)
            return tree

        return self._cached(self._trees, key, build)

    def _prior(self, tree: _Tree, nu: float, lengthscale: float):
        key = (tree.__dict__["_key"], float(nu), float(lengthscale), self.backend)
        build = _build_frontal_prior if self.backend == "compiled" else _build_prior
        return self._cached(self._priors, key, lambda: build(tree, nu, lengthscale))

    def _readout(self, tree: _Tree, problem: GridProblem) -> _Readout:
        k = problem.kernel
        key = (tree.__dict__["_key"], problem.out_rows.tobytes(), problem.out_cols.tobytes(), float(k.nu), float(k.lengthscale))
        return self._cached(
            self._readouts, key, lambda: _build_readout(tree, problem.out_rows, problem.out_cols, k.nu, k.lengthscale)
        )

    def _reusable_prior(self, tree: _Tree, fronts: FrontTree, prior, kernel, prec_var: np.ndarray):
        """The cached `PriorFactor` for this tree and kernel when worth it (see ``prior_cache_mb``)."""
        key = (tree.__dict__["_key"], float(kernel.nu), float(kernel.lengthscale))
        uses = self._kernel_uses[key] = self._kernel_uses.get(key, 0) + 1
        if len(self._kernel_uses) > 64:  # forget kernels of past fits
            self._kernel_uses = {key: uses}
        if self._prior_factor is not None and self._prior_factor[0] == key and self._prior_factor[1].tree is fronts:
            cached = self._prior_factor[1]
        elif uses >= 2 and fronts.prior_bytes <= self.prior_cache_mb * 2**20:
            cached = None
        else:
            return None
        if fronts.touched_share(prec_var) > 0.75:
            return None
        if cached is None:
            self._prior_factor = None  # free the old one first
            cached = PriorFactor(fronts, prior.asm, prior.qvals)
            self._prior_factor = (key, cached)
        return cached

    def _threads(self):
        """torch's thread setting for the torch back-end (the compiled one sets its own)."""
        return _torch_threads(self.threads) if self.backend == "torch" else nullcontext()

    def _route(self, problem: GridProblem, variance: bool, *, lml: bool = False, extra: int = 0):
        """(route, its Neumann series or None, the grid route's problem) for ``problem`` (see ``route``).

        The routes judge themselves (`gpdepth3d.gp.routes`); the grid route's problem is the
        sub-grid spanning the observed pixels with ``lattice="observed"``.

        Raises:
            The errors of `gpdepth3d.gp.routes.choose_route`.
        """
        route = self.route
        if route == "neumann" and lml and problem.kernel.nu == 0.5:
            route = "grid"  # the series gives no log-determinant
        sub = self._lattice_problem(problem) if route in ("auto", "grid") or lml else problem
        query = RouteQuery(
            problem, sub, bool(variance), int(extra), bool(lml), route != "auto", self.backend, self._budget(),
            self.max_dense_points, self._grid_buffers_held(*sub.shape, problem.kernel.nu), self._neumann_buffers,
        )
        choice = choose_route(query, route)
        return choice.name, choice.payload, sub

    def _grid_buffers_held(self, h: int, w: int, nu: float) -> bool:
        """True when this engine already holds the grid route's buffers for this resolution (an earlier
        frame's, kept for reuse): the route then allocates nothing large, whatever memory is free now."""
        tree = self._trees.get(self._tree_key(h, w, state_dim(nu) ** 2))
        fronts = None if tree is None else tree.__dict__.get("_fronts")
        return bool(fronts is not None and fronts.__dict__.get("_pool"))

    @staticmethod
    def _woodbury(problem: GridProblem, buffers) -> WoodburyPosterior:
        """`WoodburyPosterior` with a failed factorisation mapped to a typed error."""
        try:
            return WoodburyPosterior(problem, buffers)
        except np.linalg.LinAlgError as err:
            k = problem.kernel
            raise ConvergenceError(
                f"fast engine, woodbury route: the observed-pixel covariance of the Matern kernel nu={k.nu}, "
                f"lengthscale={k.lengthscale:g} px, outputscale={k.outputscale:g} m is not numerically positive "
                f"definite (largest observation precision {float(np.max(problem.precision)):.3g} 1/m^2): {err}"
            ) from None

    def _budget(self) -> int:
        return int(self.max_memory_mb * 2**20) if self.max_memory_mb is not None else memory_budget()

    # -- public
    def factorize(self, problem: GridProblem):
        """Factorises the posterior precision of ``problem``.

        Returns:
            (factor, tree, prior, real_vars): the factor, the cached elimination structure and
            prior assembly, and the (H, W) variable index of state 0 of each grid pixel.
        """
        _check_problem(problem)
        return self._factorize(problem)

    def _factorize(self, problem: GridProblem):
        """`factorize` of a checked problem (`solve` checks it once, at full resolution ~2 ms)."""
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        tree = self._tree(h, w, d * d)
        prior = self._prior(tree, k.nu, k.lengthscale)
        real_vars = tree.pix_var.reshape(tree.padded)[:h, :w]
        prec_var = np.zeros(tree.nvar)
        prec_var[real_vars.ravel()] = np.asarray(problem.precision, dtype=np.float64).ravel()
        inv_s2 = 1.0 / float(k.outputscale) ** 2
        try:
            if self.backend == "compiled":
                fronts = _front_tree(tree)
                pf = self._reusable_prior(tree, fronts, prior, k, prec_var)
                factor = FrontalFactor(fronts, prior.asm, prior.qvals, prec_var, scale2=1.0 / inv_s2, prior=pf)
            else:
                with _torch_threads(self.threads):
                    factor = _Factor(tree, prior, inv_s2, prec_var, self.device)
        except np.linalg.LinAlgError as err:
            raise IllConditionedError(
                f"fast engine, grid route: the posterior precision of the Matern kernel nu={k.nu}, "
                f"lengthscale={k.lengthscale:g} px, outputscale={k.outputscale:g} m on a {h} x {w} grid is not "
                f"numerically positive definite (estimated error {grid_error_estimate(problem):.2g} x outputscale; "
                f"largest observation precision {float(np.max(problem.precision)):.3g} 1/m^2): {err}"
            ) from None
        return factor, tree, prior, real_vars

    def _posterior_states(self, problem: GridProblem, extra: tuple = ()):
        """Factor and posterior state means of ``problem`` and of each further observation array in ``extra``
        (the compiled back-end solves them all in one pass over the factor)."""
        factor, tree, prior, real_vars = self._factorize(problem)
        prec = np.asarray(problem.precision, dtype=np.float64)
        prior_mean = np.asarray(problem.prior_mean, np.float64)
        observed = prec > 0
        resid = np.where(observed, np.asarray(problem.obs, np.float64) - prior_mean, 0.0)
        b = np.zeros((tree.nvar, 1 + len(extra)))
        b[real_vars.ravel(), 0] = (prec * resid).ravel()
        for j, e in enumerate(extra):
            b[real_vars.ravel(), 1 + j] = np.where(observed, prec * (e - prior_mean), 0.0).ravel()
        with self._threads():
            if self.backend == "compiled":
                x = factor.solve(b)
                mus = [x[:, j] for j in range(x.shape[1])]
            else:
                mus = [factor.solve(b[:, j]) for j in range(b.shape[1])]
        return factor, tree, prior, real_vars, mus, prec, resid

    def plan(self, problem: GridProblem, *, variance: bool = True, extra: int = 0, lml: bool = False) -> str:
        """The route that `solve` (or, with ``lml``, `log_marginal_likelihood`) takes for ``problem``.

        Args:
            problem: The grid problem.
            variance: Whether the call computes variances.
            extra: Number of further observation vectors (``extra_obs``) of the call.
            lml: The route of `log_marginal_likelihood` instead.

        Raises:
            The errors of `solve` that concern the route (no route, a forced route that does not apply).
        """
        _check_problem(problem)
        route, payload, _ = self._route(problem, variance, lml=lml, extra=int(extra))
        if payload is not None:
            payload.release()
        return route

    def _lattice_problem(self, problem: GridProblem) -> GridProblem:
        """``problem`` on the sub-grid spanning its observed pixels (``lattice="observed"``), else itself."""
        if self.lattice == "full":
            return problem
        box = observed_lattice(problem.precision)
        if box is None:
            return problem
        r0, r1, c0, c1 = box
        win = (slice(r0, r1), slice(c0, c1))
        return GridProblem(
            np.asarray(problem.prior_mean)[win], np.asarray(problem.obs)[win], np.asarray(problem.precision)[win],
            np.asarray(problem.out_rows, np.float64) - r0, np.asarray(problem.out_cols, np.float64) - c0,
            problem.out_prior_mean, problem.kernel,
        )

    def solve(self, problem: GridProblem, *, variance: bool = True, extra_obs=()) -> Solution:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None).

        Args:
            problem: The grid problem (either formulation).
            variance: Also compute the marginal variances (selected inversion).
            extra_obs: Further (H, W) observation arrays (the same prior mean, precision and
                kernel); their posterior means reuse this call's factorisation
                (`Solution.extra_means`).

        Returns:
            A `Solution` (unpacks as ``mean, variance``); ``info.route`` says which route
            computed it, ``info.seconds`` the time of its stages ("plan", "factor", "mean",
            "variance", "total"), ``info.details`` the observed pixels and, on the grid route,
            the lattice it factorised ((r0, r1, c0, c1) of the GP grid).

        Raises:
            IllConditionedError: (a `ConvergenceError`) the grid route cannot represent this kernel
                accurately in float64 and no other route applies (or "grid" is forced).
            ProblemTooLargeError: every applicable route exceeds the memory budget (before allocating).
            InvalidInputError: a malformed problem (`gpdepth3d.gp.exact.check_problem`) or a forced
                route that does not apply to it.
            ShapeError: an ``extra_obs`` array of another shape than the grid.
        """
        t0 = time.perf_counter()
        _check_problem(problem)
        extra = check_extra_obs(problem, extra_obs)
        route, post, sub = self._route(problem, variance, extra=len(extra))
        m = int(np.count_nonzero(np.asarray(problem.precision) > 0))
        seconds = {"plan": time.perf_counter() - t0}
        details: dict = {"observed": m}
        if route == "dense":
            mean, var, extras = dense_solve(problem, variance=variance, extra_obs=extra)
        elif route == "woodbury":
            t = time.perf_counter()
            post = self._woodbury(problem, self._woodbury_buffers)
            seconds["factor"] = time.perf_counter() - t
            t = time.perf_counter()
            mean = post.mean()
            extras = tuple(post.mean(e) for e in extra)
            seconds["mean"] = time.perf_counter() - t
            t = time.perf_counter()
            var = post.variance() if variance else None
            seconds["variance"] = time.perf_counter() - t
        elif route == "neumann":
            try:
                t = time.perf_counter()
                km = post.terms(NEUMANN_MEAN_TOL)
                mean = post.mean(km)
                extras = tuple(post.mean(km, e) for e in extra)
                seconds["mean"] = time.perf_counter() - t
                t = time.perf_counter()
                var = post.variance(post.terms(NEUMANN_VAR_TOL)) if variance else None
                seconds["variance"] = time.perf_counter() - t
            finally:
                post.release()
        else:
            mean, var, extras = self._grid_solve(sub, variance, extra, problem, seconds)
            details["lattice"] = self._lattice_box(problem, sub)
        seconds["total"] = time.perf_counter() - t0
        return Solution(mean, var, SolveInfo("fast", route, seconds, details), extras)

    @staticmethod
    def _lattice_box(problem: GridProblem, sub: GridProblem) -> tuple[int, int, int, int]:
        """(r0, r1, c0, c1) of the GP grid that ``sub`` (the grid route's problem) covers."""
        if sub is problem:
            return (0, problem.shape[0], 0, problem.shape[1])
        r0 = int(round(float(problem.out_rows[0]) - float(sub.out_rows[0])))
        c0 = int(round(float(problem.out_cols[0]) - float(sub.out_cols[0])))
        return (r0, r0 + sub.shape[0], c0, c0 + sub.shape[1])

    def _grid_solve(self, problem: GridProblem, variance: bool, extra: tuple, original: GridProblem, seconds: dict):
        """The grid route on ``problem`` (the lattice of ``original``): (mean, variance, extra means)."""
        t = time.perf_counter()
        if problem is not original:  # the extra observations on the lattice too
            r0, r1, c0, c1 = self._lattice_box(original, problem)
            extra = tuple(e[r0:r1, c0:c1] for e in extra)
        factor, tree, prior, real_vars, mus, prec, _ = self._posterior_states(problem, extra)
        seconds["factor"] = time.perf_counter() - t
        t = time.perf_counter()
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        ds = tree.ds
        s2 = float(k.outputscale) ** 2
        same_grid = problem.output_is_input
        readout = None if same_grid else self._readout(tree, problem)
        out_prior = np.asarray(problem.out_prior_mean, np.float64)
        means = []
        for x in mus:
            states = x[real_vars[..., None] + np.arange(ds)].reshape(h, w, d, d)  # (r, c, k, l)
            if same_grid:
                means.append(out_prior + states[:, :, 0, 0])
            else:
                M = states.transpose(0, 2, 1, 3).reshape(h * d, w * d)
                means.append(out_prior + readout.wv @ (readout.wu @ M.T).T)
        seconds["mean"] = time.perf_counter() - t
        if not variance:
            return means[0], None, tuple(means[1:])
        t = time.perf_counter()
        if same_grid:
            with self._threads():
                diag, _ = factor.selected_inverse(None)
            var = diag[real_vars]
        else:
            if self.backend == "compiled":
                ro, (single, var_of, w2) = _frontal_readout(factor.tree, readout)
                diag, out = factor.selected_inverse(ro)
                out[single] = w2 * diag[var_of]
            else:
                with self._threads():
                    _, out = factor.selected_inverse(readout)
            var = out.reshape(problem.out_shape) + s2 * readout.resid
        seconds["variance"] = time.perf_counter() - t
        return means[0], np.maximum(var, 0.0), tuple(means[1:])

    def log_marginal_likelihood(self, problem: GridProblem) -> float:
        """Log marginal likelihood log p(y) of the observed pixels of ``problem`` (nats).

        Uses log p(y) = log N(y; f*, W^-1) + log N(f*; m, Q^-1) - log N(f*; f*, P^-1) at the
        posterior mean f* (the latent field on the padded grid, all states), with log det P
        from the Cholesky factor and log det Q from the 1-D chains.
        """
        _check_problem(problem)
        route, _, sub = self._route(problem, False, lml=True)
        if route == "woodbury":
            return self._woodbury(problem, None).log_marginal_likelihood()
        if route == "dense":
            return dense_log_marginal_likelihood(problem)
        problem = sub  # the observed pixels' likelihood on the lattice that spans them
        factor, tree, prior, real_vars, (mu,), prec, resid = self._posterior_states(problem)
        k = problem.kernel
        d = state_dim(k.nu)
        s2 = float(k.outputscale) ** 2
        obs = prec > 0
        f = mu[real_vars]
        data = -0.5 * float(np.sum(prec[obs] * (resid[obs] - f[obs]) ** 2))
        data += 0.5 * float(np.sum(np.log(prec[obs]))) - 0.5 * obs.sum() * np.log(2 * np.pi)
        hp, wp = tree.padded
        Qv, _ = chain_precision(np.arange(hp, dtype=np.float64), k.nu, k.lengthscale)
        Qu, _ = chain_precision(np.arange(wp, dtype=np.float64), k.nu, k.lengthscale)
        X = mu[tree.pix_var[:, None] + np.arange(tree.ds)].reshape(hp, wp, d, d).transpose(0, 2, 1, 3).reshape(hp * d, wp * d)
        quad = float(np.sum(X * (Qv @ (Qu @ X.T).T))) / s2
        logdet_q = prior.logdet - tree.nvar * np.log(s2)
        return data - 0.5 * quad + 0.5 * logdet_q - 0.5 * factor.logdet


@contextmanager
def _torch_threads(threads: int | None):
    """Temporarily sets torch's intra-op CPU threads."""
    import torch

    old = torch.get_num_threads()
    if threads is not None and threads != old:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if threads is not None and threads != old:
            torch.set_num_threads(old)


def _check_problem(problem: GridProblem) -> None:
    check_problem(problem)
    h, w = problem.shape
    if h < 2 or w < 2:
        raise ShapeError("problem", "a GP grid of at least 2 x 2 pixels", f"{h} x {w}")
