"""Exact read-out of the field at output pixels off the factorised grid from the 2 x 2 grid states around each.

Conditioned on all grid states, f at an off-grid point depends only on the surrounding 2 x 2
pixels' states, with Kronecker weights from the 1-D chains (`gpdepth3d.gp.markov.readout_weights`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp

from .elimination_tree import EliminationTree
from .markov import readout_weights, state_dim
from .multifrontal import FrontTree


@dataclass
class Readout:
    """Exact read-out of the field at an output tensor grid from the 2 x 2 neighbouring grid states."""

    wv: sp.csr_matrix  # (Ho, H d) row weights
    wu: sp.csr_matrix  # (Wo, W d) column weights
    resid: np.ndarray  # (Ho, Wo) conditional prior variance (unit outputscale)
    t_groups: list  # per template node: (outputs (m,), tiles (m,), front positions (m, 4 ds), weights (m, 4 ds))
    top_groups: list  # per top node: (outputs (m,), front positions (m, 4 ds), weights (m, 4 ds))
    corner_vars: np.ndarray  # (Ho Wo, 4 ds) grid state variables each output reads
    corner_wgt: np.ndarray  # (Ho Wo, 4 ds) their weights


def build_readout(
    tree: EliminationTree, out_rows: np.ndarray, out_cols: np.ndarray, nu: float, lengthscale: float
) -> Readout:
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
        pos = tree.tile_positions(tau, np.repeat(tiles, 4 * ds), pix, np.tile(states, sel.size)).reshape(
            sel.size, 4 * ds
        )
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
    return Readout(wmat(fr, wr, h), wmat(fc, wc, w), resid, t_groups, top_groups, corner_vars, wgt)


def frontal_readout(fronts: FrontTree, readout: Readout) -> tuple:
    """The read-out split for the compiled selected inverse (cached on the read-out):
    ``((ptr, output index, front positions, weights, n_out), (outputs, variable, weight^2))``.

    An output that reads a single grid state (a non-zero weight on one variable: every output on
    a grid pixel, and the rows outside the factorised lattice, which read its edge state) has the
    variance weight^2 diag(P^-1)[variable]; only the others (between grid pixels) need covariance
    fronts. Leaf fronts without them take the selected inverse's diagonal-only path (an output
    on the input grid reads single states only).
    """
    cached = readout.__dict__.get("_frontal")
    if cached is None or cached[0] is not fronts:
        nz = readout.corner_wgt != 0.0
        single = np.count_nonzero(nz, axis=1) == 1
        out_single = np.nonzero(single)[0]
        k = np.argmax(nz[out_single], axis=1)
        simple = (
            out_single.astype(np.int64),
            readout.corner_vars[out_single, k],
            readout.corner_wgt[out_single, k] ** 2,
        )
        rest = np.nonzero(~single)[0]
        v = readout.corner_vars[rest]
        f = fronts.front_of[v.min(axis=1)]
        pos = fronts.positions(np.repeat(f, v.shape[1]), v.ravel()).reshape(v.shape)
        srt = np.argsort(f, kind="stable")
        ptr = np.searchsorted(f[srt], np.arange(fronts.st.size + 1)).astype(np.int64)
        cached = (
            fronts,
            (
                (
                    ptr,
                    rest[srt].astype(np.int64),
                    np.ascontiguousarray(pos[srt]),
                    np.ascontiguousarray(readout.corner_wgt[rest[srt]]),
                    readout.corner_vars.shape[0],
                ),
                simple,
            ),
        )
        readout.__dict__["_frontal"] = cached
    return cached[1]


def read_mean(readout: Readout, x: np.ndarray, real_vars: np.ndarray, d: int, out_prior: np.ndarray) -> np.ndarray:
    """Posterior mean at the output grid (Ho, Wo), metres: ``out_prior + Wv M Wu^T`` for the state means ``x``.

    ``M`` (H d, W d) holds state (k, l) of grid pixel (r, c) at (r d + k, c d + l), read from ``x``
    (nvar,) at ``real_vars[r, c] + k d + l``. The two sparse products in compiled loops, without
    their transposed copies and temporaries (the same sums in the same order).

    Args:
        readout: The read-out (its row and column weights ``wv``, ``wu``).
        x: (nvar,) posterior state means of the factorised grid.
        real_vars: (H, W) variable of state 0 of each grid pixel.
        d: States per axis (`gpdepth3d.gp.markov.state_dim`).
        out_prior: (Ho, Wo) prior mean at the outputs (metres).
    """
    wv, wu = readout.wv, readout.wu
    h, w = real_vars.shape
    out = np.empty(out_prior.shape)
    prior = np.ascontiguousarray(out_prior, dtype=np.float64).view()
    prior.flags.writeable = False  # one compiled signature, whether the caller's array is writeable or not
    _read_mean(
        np.ascontiguousarray(x, dtype=np.float64),
        np.ascontiguousarray(real_vars, dtype=np.int64),
        int(d),
        wv.indptr.astype(np.int64),
        wv.indices.astype(np.int64),
        wv.data.astype(np.float64),
        wu.indptr.astype(np.int64),
        wu.indices.astype(np.int64),
        wu.data.astype(np.float64),
        prior,
        np.empty((h * d, out.shape[1])),
        out,
    )
    return out


@nb.njit(nogil=True, cache=True, boundscheck=False)
def _read_mean(x, real_vars, d, wv_ptr, wv_idx, wv_dat, wu_ptr, wu_idx, wu_dat, out_prior, T, out):
    """out = out_prior + Wv (Wu M^T)^T (CSR weights, in the order of the sparse products), M (H d, W d)
    read from ``x``; ``T`` (H d, Wo) is scratch for M Wu^T.

    The column weights' gathers run once per grid row (H d of them, fewer than the Ho output
    rows), the row weights' combination of T's rows is contiguous (vectorised). Flat unsigned
    offsets (all >= 0 by construction): no checks for negative indices in the loops.
    """
    h, w = real_vars.shape
    ud = np.uint64(d)
    ho, wo = out.shape
    uwo = np.uint64(wo)
    tf, of, pf = T.ravel(), out.ravel(), out_prior.ravel()
    rv = real_vars.ravel()
    mrow = np.empty(w * d)
    for r in range(np.uint64(h)):
        for k in range(ud):
            for c in range(np.uint64(w)):  # row r d + k of M
                v = np.uint64(rv[r * np.uint64(w) + c]) + k * ud
                for l in range(ud):
                    mrow[c * ud + l] = x[v + l]
            t0 = (r * ud + k) * uwo
            for j in range(uwo):
                acc = 0.0
                for b in range(np.uint64(wu_ptr[j]), np.uint64(wu_ptr[j + np.uint64(1)])):
                    acc += wu_dat[b] * mrow[np.uint64(wu_idx[b])]
                tf[t0 + j] = acc
    buf = np.empty(wo)
    for i in range(np.uint64(ho)):
        for j in range(uwo):
            buf[j] = 0.0
        for a in range(np.uint64(wv_ptr[i]), np.uint64(wv_ptr[i + np.uint64(1)])):
            wt = wv_dat[a]
            r0 = np.uint64(wv_idx[a]) * uwo
            for j in range(uwo):
                buf[j] += wt * tf[r0 + j]
        o0 = i * uwo
        for j in range(uwo):
            of[o0 + j] = pf[o0 + j] + buf[j]
