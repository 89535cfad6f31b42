"""The elimination tree of the ``fast`` engine's grid route: equal tiles sharing one template, then separators.

The grid, padded by unobserved pixels (the real pixels' posterior is unchanged), is cut into equal
tiles split by one-pixel rows and columns; all tiles share one nested-dissection subtree (so their
work runs batched) and the separators form a nested dissection of the tile lattice. See docs/engines.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .multifrontal import FrontTree


STENCIL_OFFSETS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
"""The 9-point stencil of the prior precision: (row, column) offsets of a pixel's neighbours and itself."""


def _ring(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """(m, 2) pixels around the region [r0, r1) x [c0, c1) (unclipped), in a fixed order."""
    top = np.stack([np.full(c1 - c0 + 2, r0 - 1), np.arange(c0 - 1, c1 + 1)], 1)
    bottom = np.stack([np.full(c1 - c0 + 2, r1), np.arange(c0 - 1, c1 + 1)], 1)
    left = np.stack([np.arange(r0, r1), np.full(r1 - r0, c0 - 1)], 1)
    right = np.stack([np.arange(r0, r1), np.full(r1 - r0, c1)], 1)
    return np.concatenate([top, bottom, left, right]).astype(np.int64)


@dataclass
class Template:
    """Nested-dissection subtree of one th x tw tile (relative pixel coordinates)."""

    th: int
    tw: int
    own: list  # per node (k, 2) own pixels
    ring: list  # per node (m, 2) ring pixels (may lie outside the tile)
    children: list
    parent: list
    posmap: list  # per node (th + 2, tw + 2): front pixel position of pixel (r + 1, c + 1), -1 = absent


def build_template(th: int, tw: int, leaf_pixels: int) -> Template:
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
    return Template(th, tw, own, ring, children, parent, posmap)


def _tiling(n: int, target: int) -> tuple[int, int]:
    """(tiles, tile size) along an axis of n pixels: tiles * (size + 1) - 1 >= n, size ~ target."""
    tiles = max(1, int(round((n + 1) / (target + 1))))
    size = -(-(n + 1) // tiles) - 1
    return tiles, size


@dataclass
class EliminationTree:
    """Elimination structure of the padded pixel grid: template nodes batched over tiles, then top separators."""

    shape: tuple[int, int]  # the problem's grid
    padded: tuple[int, int]
    ds: int
    tpl: Template
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


def _template_variables(tpl: Template, origins: np.ndarray, wp: int, ds: int, pix_var: np.ndarray):
    """Numbers the tiles' own variables template node by node (all tiles of a node contiguous).

    Returns (t_base, t_no, vnode chunks); fills ``pix_var`` for the tiles' pixels.
    """
    T = origins.shape[0]
    vnode_chunks, t_base, t_no = [], [0], []
    for tau, o in enumerate(tpl.own):
        k = o.shape[0]
        glob = origins[:, None, :] + o[None, :, :]  # (T, k, 2)
        pix = glob[..., 0] * wp + glob[..., 1]
        pix_var[pix.ravel()] = t_base[-1] + np.arange(T * k) * ds
        vnode_chunks.append(np.repeat(tau * T + np.arange(T), k * ds))
        t_no.append(k * ds)
        t_base.append(t_base[-1] + T * k * ds)
    return t_base, t_no, vnode_chunks


def _top_dissection(nr: int, nc: int, th: int, tw: int, hp: int, wp: int) -> dict:
    """Nested dissection of the nr x nc tile lattice: per top node its own pixels, ring, children and tiles."""
    top = {"own": [], "ring": [], "children": [], "tiles": [], "parent": []}

    def visit(i0, i1, j0, j1) -> tuple[str, int]:
        if (i1 - i0) * (j1 - j0) == 1:
            return ("tile", i0 * nc + j0)
        r0, r1 = i0 * (th + 1), i1 * (th + 1) - 1
        c0, c1 = j0 * (tw + 1), j1 * (tw + 1) - 1
        if (c1 - c0 >= r1 - r0 and j1 - j0 > 1) or i1 - i0 == 1:
            m = (j0 + j1) // 2
            kids = [visit(i0, i1, j0, m), visit(i0, i1, m, j1)]
            o = np.arange(r0, r1) * wp + m * (tw + 1) - 1
        else:
            m = (i0 + i1) // 2
            kids = [visit(i0, m, j0, j1), visit(m, i1, j0, j1)]
            o = (m * (th + 1) - 1) * wp + np.arange(c0, c1)
        g = _ring(r0, r1, c0, c1)
        g = g[(g[:, 0] >= 0) & (g[:, 0] < hp) & (g[:, 1] >= 0) & (g[:, 1] < wp)]
        node = len(top["own"])
        top["own"].append(o.astype(np.int64))
        top["ring"].append(g[:, 0] * wp + g[:, 1])
        top["children"].append([k for kind, k in kids if kind == "top"])
        top["tiles"].append([k for kind, k in kids if kind == "tile"])
        top["parent"].append(-1)
        for kind, k in kids:
            if kind == "top":
                top["parent"][k] = node
        return ("top", node)

    visit(0, nr, 0, nc)
    return top


def _template_fronts(
    tpl: Template, origins: np.ndarray, hp: int, wp: int, ds: int, pix_var: np.ndarray, nvar: int, t_no: list
):
    """Per template node: its rings' global variables (T, nb), front sizes, and positions in the parent's front."""
    states = np.arange(ds)
    T = origins.shape[0]
    t_bnd, t_nf = [], []
    for tau, g in enumerate(tpl.ring):
        glob = origins[:, None, :] + g[None, :, :]
        inside = (glob[..., 0] >= 0) & (glob[..., 0] < hp) & (glob[..., 1] >= 0) & (glob[..., 1] < wp)
        pix = np.where(inside, glob[..., 0] * wp + glob[..., 1], 0)
        var = np.where(inside[..., None], pix_var[pix][..., None] + states, nvar)
        t_bnd.append(var.reshape(T, -1))
        t_nf.append(t_no[tau] + g.shape[0] * ds)
    t_nf = np.array(t_nf, dtype=np.int64)
    ntpl = len(tpl.own)
    t_loc, t_ea = [None] * ntpl, [None] * ntpl
    for tau in range(ntpl):
        p = tpl.parent[tau]
        if p >= 0:
            g = tpl.ring[tau]
            pos = tpl.posmap[p][g[:, 0] + 1, g[:, 1] + 1]
            if np.any(pos < 0):
                raise RuntimeError("internal error: ring pixel not in the parent's front")
            loc = (pos[:, None] * ds + states).ravel()
            t_loc[tau] = loc
            t_ea[tau] = (loc[:, None] * t_nf[p] + loc[None, :]).ravel()
    return t_bnd, t_nf, t_loc, t_ea


def _link_fronts(tree: EliminationTree) -> None:
    """Fills the positions of each top node's and each tile root's ring in its top parent's front."""
    for x in range(tree.ntop):
        p = tree.top_parent[x]
        if p >= 0:
            loc = tree.top_positions(p, tree.top_bnd[x])
            tree.top_loc[x] = loc
            tree.top_ea[x] = (loc[:, None] * tree.top_nf[p] + loc[None, :]).ravel()
    root_bnd = tree.t_bnd[tree.ntpl - 1]
    T, nb_root = root_bnd.shape
    tree.tile_loc = np.zeros((T, nb_root), dtype=np.int64)
    tree.tile_ea = np.zeros((T, nb_root * nb_root), dtype=np.int64)
    for x in range(tree.ntop):
        nf = tree.top_nf[x]
        for t in tree.top_tiles[x]:
            tree.tile_parent[t] = x
            v = root_bnd[t]
            real = v < tree.nvar
            loc = np.full(nb_root, nf, dtype=np.int64)
            loc[real] = tree.top_positions(x, v[real])
            tree.tile_loc[t] = loc
            ea = loc[:, None] * nf + loc[None, :]
            ea[~real, :] = nf * nf
            ea[:, ~real] = nf * nf
            tree.tile_ea[t] = ea.ravel()


def build_tree(h: int, w: int, ds: int, tile: int, leaf_pixels: int) -> EliminationTree:
    """The elimination tree of an h x w grid with ds states per pixel, tiles of ~``tile`` pixels a side."""
    nr, th = _tiling(h, tile)
    nc, tw = _tiling(w, tile)
    hp, wp = nr * (th + 1) - 1, nc * (tw + 1) - 1
    tpl = build_template(th, tw, leaf_pixels)
    T = nr * nc
    ti, tj = np.divmod(np.arange(T), nc)
    origins = np.stack([ti * (th + 1), tj * (tw + 1)], 1).astype(np.int64)
    pix_var = np.full(hp * wp, -1, dtype=np.int64)
    t_base, t_no, vnode_chunks = _template_variables(tpl, origins, wp, ds, pix_var)
    top = _top_dissection(nr, nc, th, tw, hp, wp)
    top_starts = [t_base[-1]]
    for x, o in enumerate(top["own"]):
        pix_var[o] = top_starts[-1] + np.arange(o.size) * ds
        vnode_chunks.append(np.full(o.size * ds, len(tpl.own) * T + x))
        top_starts.append(top_starts[-1] + o.size * ds)
    nvar = top_starts[-1]
    if np.any(pix_var < 0):
        raise RuntimeError("internal error: a padded pixel has no variable")
    top_bnd = [np.sort((pix_var[g][:, None] + np.arange(ds)).ravel()) for g in top["ring"]]
    top_starts = np.array(top_starts)
    top_nf = np.array(
        [top_starts[x + 1] - top_starts[x] + top_bnd[x].size for x in range(len(top_bnd))], dtype=np.int64
    )
    t_bnd, t_nf, t_loc, t_ea = _template_fronts(tpl, origins, hp, wp, ds, pix_var, nvar, t_no)
    ntop = len(top_bnd)
    tree = EliminationTree(
        shape=(h, w),
        padded=(hp, wp),
        ds=ds,
        tpl=tpl,
        origins=origins,
        nvar=int(nvar),
        pix_var=pix_var,
        vnode=np.concatenate(vnode_chunks),
        t_base=np.array(t_base),
        t_no=np.array(t_no),
        t_nf=t_nf,
        t_bnd=t_bnd,
        t_loc=t_loc,
        t_ea=t_ea,
        top_starts=top_starts,
        top_bnd=top_bnd,
        top_nf=top_nf,
        top_parent=np.array(top["parent"], dtype=np.int64),
        top_children=top["children"],
        top_tiles=top["tiles"],
        top_loc=[None] * ntop,
        top_ea=[None] * ntop,
        tile_loc=None,
        tile_ea=None,
        tile_parent=np.full(T, -1, dtype=np.int64),
    )
    _link_fronts(tree)
    return tree


def front_tree(tree: EliminationTree) -> FrontTree:
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
