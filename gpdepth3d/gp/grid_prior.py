"""The prior precision of the separable Matern field, Qv (x) Qu with unit outputscale, assembled into the fronts.

A 9-point stencil of d x d state blocks (d = nu + 1/2) from the 1-D chain precisions
(`gpdepth3d.gp.markov.chain_precision`), per front of an `EliminationTree`. See docs/engines.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidInputError
from .elimination_tree import STENCIL_OFFSETS, EliminationTree, front_tree
from .markov import chain_precision, state_dim


@dataclass
class BatchedPrior:
    """Front assembly of the unit-variance prior precision Qv (x) Qu, and its log-determinant."""

    t_qpos: list  # per template node (nq,) flat positions
    t_qval: list  # per template node (T, nq) values
    top_qpos: list
    top_qval: list
    logdet: float  # log det(Qv (x) Qu) over the padded grid (unit outputscale)


def _prior_pattern(tree: EliminationTree) -> dict:
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
        for dr, dc in STENCIL_OFFSETS:
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
            np.clip(ga[..., 0], 0, hp - 1).ravel(),
            np.clip(ga[..., 1], 0, wp - 1).ravel(),
            np.clip(gb[..., 0], 0, hp - 1).ravel(),
            np.clip(gb[..., 1], 0, wp - 1).ravel(),
        )
        pos = ((pa * ds)[:, None, None] + np.arange(ds)[None, :, None]) * nf + (pb * ds)[:, None, None] + np.arange(ds)
        template.append((pos.ravel(), coords, inside))
    is_top = np.zeros(hp * wp, dtype=bool)
    is_top[tree.vnode[tree.pix_var] >= tree.ntpl * T] = True
    all_top = np.nonzero(is_top)[0]
    pr, pc = np.divmod(all_top, wp)
    rows_p, rows_q = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for dr, dc in STENCIL_OFFSETS:
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


def _chains(tree: EliminationTree, nu: float, lengthscale: float):
    """The 1-D chain precisions along rows and columns of the padded grid and log det(Qv (x) Qu)."""
    hp, wp = tree.padded
    d = state_dim(nu)
    if d * d != tree.ds:
        raise InvalidInputError("nu", f"a smoothness with {tree.ds} states per pixel", nu)
    Qv, ldv = chain_precision(np.arange(hp, dtype=np.float64), nu, lengthscale)
    Qu, ldu = chain_precision(np.arange(wp, dtype=np.float64), nu, lengthscale)
    return Qv, Qu, wp * d * ldv + hp * d * ldu


def build_batched_prior(tree: EliminationTree, nu: float, lengthscale: float) -> BatchedPrior:
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
    return BatchedPrior(t_qpos, t_qval, top_qpos, top_qval, logdet)


@dataclass
class FrontalPrior:
    """Prior precision entries (lower triangle, unit outputscale) and their front assembly map."""

    asm: tuple  # (ptr, flat positions, source entry) per front
    qvals: np.ndarray  # value of each entry
    logdet: float


def build_frontal_prior(tree: EliminationTree, nu: float, lengthscale: float) -> FrontalPrior:
    hp, wp = tree.padded
    d = state_dim(nu)
    ds = tree.ds
    Qv, Qu, logdet = _chains(tree, nu, lengthscale)
    fronts = front_tree(tree)
    if "_frontal_pattern" not in tree.__dict__:
        pr, pc = np.divmod(np.arange(hp * wp), wp)
        ents = []
        for dr, dc in STENCIL_OFFSETS:
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
    return FrontalPrior(asm, qv * qu, logdet)


def _bands(Q: sp.spmatrix, d: int) -> np.ndarray:
    """(n, 3, d, d) blocks Q[i, i + o - 1] of a block-tridiagonal chain precision (n d x n d)."""
    n = Q.shape[0] // d
    coo = Q.tocoo()
    i, j = np.divmod(coo.row, d), np.divmod(coo.col, d)
    out = np.zeros((n, 3, d, d))
    out[i[0], j[0] - i[0] + 1, i[1], j[1]] = coo.data
    return out
