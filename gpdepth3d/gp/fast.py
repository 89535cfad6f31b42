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
over a nested-dissection ordering of the pixel grid (the separators are image rows and columns,
so the elimination tree and every frontal index map are known from the grid size alone and are
cached per resolution). Marginal variances diag(P^-1) come from the selected inverse computed
top-down over the same fronts (Takahashi / Erisman-Tinney recursions): exact, no sampling.
No approximation is made anywhere; results equal the dense `exact` engine to rounding.

Output grids other than the input grid (finer, coarser or shifted) are exact too: conditioned
on all grid states, f at an off-grid point depends only on the states of the 2 x 2 surrounding
grid pixels, with Kronecker weights from the 1-D chains (`markov.readout_weights`). The mean is
the weighted sum of the posterior state means, the variance the weighted quadratic form of the
posterior covariance of those states (a clique of the 9-point stencil, so present in one front
of the selected inverse) plus the conditional prior variance.

Cost with n pixels: O(n^1.5) flops and O(n log n) memory for the factor (nested dissection on a
2-D grid), the same for the selected inverse; d^6 times more for nu > 0.5 (nu = 2.5 is heavy
beyond ~100 x 100). Back-ends: NumPy/SciPy LAPACK on the CPU (``device=None``, the default), or
torch on any device (``device="cuda"``, float64), the same algorithm for mean and variance.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import blas, lapack

from ..errors import InvalidInputError, ShapeError
from .markov import chain_precision, readout_weights, state_dim
from .model import GridProblem


# ----------------------------------------------------------------------------- symbolic phase


@dataclass
class _Tree:
    """Elimination tree and frontal index maps of the nested-dissection order of an (H, W) grid.

    Variables are numbered in elimination order: node X owns the contiguous range
    starts[X]:starts[X + 1]; its front is those variables followed by bnd[X] (sorted).
    """

    shape: tuple[int, int]
    ds: int
    pix_order: np.ndarray  # (n,) pixel (r * W + c) at each elimination position
    pix_pos: np.ndarray  # (n,) elimination position of each pixel
    starts: np.ndarray  # (nodes + 1,) own variable ranges
    bnd: list  # per node: sorted variable indices (elimination numbering) of the boundary
    parent: np.ndarray  # (nodes,) -1 for the root
    children: list  # per node: list of child nodes
    loc: list  # per node: positions of bnd within the parent's front
    ea_flat: list  # per node: flat positions of the child's update matrix in the parent's front
    node_of_var: np.ndarray  # (nvar,) owning node
    nf: np.ndarray  # (nodes,) front sizes

    @property
    def nodes(self) -> int:
        return len(self.bnd)

    def front_positions(self, node: int, variables: np.ndarray) -> np.ndarray:
        """Positions of variables (all in the node's front) within the node's front."""
        st, en = self.starts[node], self.starts[node + 1]
        v = np.asarray(variables)
        out = np.empty(v.shape, dtype=np.int64)
        own = (v >= st) & (v < en)
        out[own] = v[own] - st
        b = self.bnd[node]
        idx = np.searchsorted(b, v[~own])
        if np.any(idx >= b.size) or np.any(b[np.minimum(idx, b.size - 1)] != v[~own]):
            raise RuntimeError("internal error: variable not in front")
        out[~own] = en - st + idx
        return out


def _build_tree(h: int, w: int, ds: int, leaf_pixels: int) -> _Tree:
    """Nested dissection of the (h, w) pixel grid by middle rows/columns, leaves <= leaf_pixels."""
    order_chunks: list[np.ndarray] = []
    ring_pix: list[np.ndarray] = []
    parent: list[int] = []
    children: list[list[int]] = []

    def ring(r0, r1, c0, c1):
        rr, cc = [], []
        cl, cr = max(c0 - 1, 0), min(c1 + 1, w)
        if r0 > 0:
            rr.append(np.full(cr - cl, r0 - 1))
            cc.append(np.arange(cl, cr))
        if r1 < h:
            rr.append(np.full(cr - cl, r1))
            cc.append(np.arange(cl, cr))
        if c0 > 0:
            rr.append(np.arange(r0, r1))
            cc.append(np.full(r1 - r0, c0 - 1))
        if c1 < w:
            rr.append(np.arange(r0, r1))
            cc.append(np.full(r1 - r0, c1))
        if not rr:
            return np.zeros(0, dtype=np.int64)
        return (np.concatenate(rr) * w + np.concatenate(cc)).astype(np.int64)

    def visit(r0, r1, c0, c1) -> int:
        hh, ww = r1 - r0, c1 - c0
        kids = []
        if hh * ww <= leaf_pixels or (hh < 3 and ww < 3):
            rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
            own = (rr * w + cc).ravel()
        elif ww >= hh:
            m = c0 + ww // 2
            kids = [visit(r0, r1, c0, m), visit(r0, r1, m + 1, c1)] if m + 1 < c1 else [visit(r0, r1, c0, m)]
            own = np.arange(r0, r1) * w + m
        else:
            m = r0 + hh // 2
            kids = [visit(r0, m, c0, c1), visit(m + 1, r1, c0, c1)] if m + 1 < r1 else [visit(r0, m, c0, c1)]
            own = m * w + np.arange(c0, c1)
        node = len(order_chunks)
        order_chunks.append(own.astype(np.int64))
        ring_pix.append(ring(r0, r1, c0, c1))
        parent.append(-1)
        children.append(kids)
        for k in kids:
            parent[k] = node
        return node

    visit(0, h, 0, w)
    n = h * w
    pix_order = np.concatenate(order_chunks)
    pix_pos = np.empty(n, dtype=np.int64)
    pix_pos[pix_order] = np.arange(n)
    counts = np.array([c.size for c in order_chunks])
    starts = np.concatenate([[0], np.cumsum(counts)]) * ds
    states = np.arange(ds)
    bnd = []
    for rp in ring_pix:
        pos = np.sort(pix_pos[rp])
        bnd.append((pos[:, None] * ds + states).ravel())
    nodes = len(bnd)
    node_of_var = np.repeat(np.arange(nodes), counts * ds)
    nf = np.array([starts[k + 1] - starts[k] + bnd[k].size for k in range(nodes)])
    tree = _Tree(
        shape=(h, w), ds=ds, pix_order=pix_order, pix_pos=pix_pos, starts=starts, bnd=bnd,
        parent=np.array(parent), children=children, loc=[None] * nodes, ea_flat=[None] * nodes,
        node_of_var=node_of_var, nf=nf,
    )
    for k in range(nodes):
        p = parent[k]
        if p >= 0 and bnd[k].size:
            loc = tree.front_positions(p, bnd[k])
            tree.loc[k] = loc
            tree.ea_flat[k] = (loc[:, None] * nf[p] + loc[None, :]).ravel()
    return tree


@dataclass
class _Prior:
    """Per-node assembly of the prior precision (Qv (x) Qu) of unit variance, and its log-det."""

    qpos: list  # per node: flat positions in the front
    qval: list  # per node: values
    dpos: list  # per node: flat positions of the own diagonal
    logdet: float  # log det(Qv (x) Qu) (unit outputscale)


def _build_prior(tree: _Tree, nu: float, lengthscale: float) -> _Prior:
    h, w = tree.shape
    d = state_dim(nu)
    Qv, ldv = chain_precision(np.arange(h, dtype=np.float64), nu, lengthscale)
    Qu, ldu = chain_precision(np.arange(w, dtype=np.float64), nu, lengthscale)
    Q = sp.kron(Qv, Qu, format="coo")  # index (r d + k) (W d) + (c d + l)
    rv, cu = np.divmod(Q.row, w * d)
    r, k = np.divmod(rv, d)
    c, l = np.divmod(cu, d)
    rv2, cu2 = np.divmod(Q.col, w * d)
    r2, k2 = np.divmod(rv2, d)
    c2, l2 = np.divmod(cu2, d)
    ds = d * d
    vi = tree.pix_pos[r * w + c] * ds + k * d + l
    vj = tree.pix_pos[r2 * w + c2] * ds + k2 * d + l2
    owner = np.minimum(tree.node_of_var[vi], tree.node_of_var[vj])
    sort = np.argsort(owner, kind="stable")
    vi, vj, val, owner = vi[sort], vj[sort], Q.data[sort], owner[sort]
    bounds = np.searchsorted(owner, np.arange(tree.nodes + 1))
    qpos, qval, dpos = [], [], []
    for x in range(tree.nodes):
        sl = slice(bounds[x], bounds[x + 1])
        a = tree.front_positions(x, vi[sl])
        b = tree.front_positions(x, vj[sl])
        qpos.append(a * tree.nf[x] + b)
        qval.append(val[sl].copy())
        no = tree.starts[x + 1] - tree.starts[x]
        dpos.append(np.arange(no) * (tree.nf[x] + 1))
    return _Prior(qpos, qval, dpos, w * d * ldv + h * d * ldu)


@dataclass
class _Readout:
    """Exact read-out of the field at an output tensor grid from the 2 x 2 neighbouring grid states."""

    wv: sp.csr_matrix  # (Ho, H d) row weights
    wu: sp.csr_matrix  # (Wo, W d) column weights
    resid: np.ndarray  # (Ho, Wo) conditional prior variance (unit outputscale)
    node_groups: list  # per node: (output flat indices (m,), front positions (m, 4 ds), weights (m, 4 ds))


def _build_readout(tree: _Tree, out_rows: np.ndarray, out_cols: np.ndarray, nu: float, lengthscale: float) -> _Readout:
    h, w = tree.shape
    d = state_dim(nu)
    ds = d * d
    fr, wr, rr = readout_weights(np.arange(h, dtype=np.float64), out_rows, nu, lengthscale)
    fc, wc, rc = readout_weights(np.arange(w, dtype=np.float64), out_cols, nu, lengthscale)
    ho, wo = out_rows.shape[0], out_cols.shape[0]

    def wmat(first, wts, n):
        m = first.shape[0]
        rows = np.repeat(np.arange(m), 2 * d)
        cols = ((first[:, None, None] + np.arange(2)[None, :, None]) * d + np.arange(d)[None, None, :]).ravel()
        return sp.csr_matrix((wts.ravel(), (rows, cols)), shape=(m, n * d))

    resid = 1.0 - np.outer(1.0 - rr, 1.0 - rc)
    # Variance: group output pixels by the node owning the first-eliminated variable of their 2x2 block.
    orr, occ = np.meshgrid(np.arange(ho), np.arange(wo), indexing="ij")
    orr, occ = orr.ravel(), occ.ravel()
    br, bc = fr[orr], fc[occ]
    corner_r = br[:, None] + np.array([0, 0, 1, 1])
    corner_c = bc[:, None] + np.array([0, 1, 0, 1])
    pix = tree.pix_pos[corner_r * w + corner_c]  # (m, 4)
    var = (pix[:, :, None] * ds + np.arange(ds)).reshape(len(orr), 4 * ds)
    # weights: corner (a, b) state (k, l) -> wr[:, a, k] * wc[:, b, l]
    wgt = np.einsum("mak,mbl->mabkl", wr[orr], wc[occ]).reshape(len(orr), 4 * ds)
    owner = tree.node_of_var[var.min(axis=1)]
    sort = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[sort], np.arange(tree.nodes + 1))
    groups = []
    for x in range(tree.nodes):
        sel = sort[bounds[x] : bounds[x + 1]]
        if sel.size == 0:
            groups.append(None)
            continue
        pos = tree.front_positions(x, var[sel].ravel()).reshape(sel.size, 4 * ds)
        groups.append((sel, pos, wgt[sel]))
    return _Readout(wmat(fr, wr, h), wmat(fc, wc, w), resid, groups)


# ----------------------------------------------------------------------------- numeric phase (NumPy / LAPACK)


class _Factor:
    """Multifrontal Cholesky factor of P (NumPy): per node L11 (no, no) and L21^T (no, nb)."""

    def __init__(self, tree: _Tree, prior: _Prior, inv_s2: float, prec_var: np.ndarray):
        self.tree = tree
        starts, nf = tree.starts, tree.nf
        L11s, L21Ts = [], []
        updates: list = [None] * tree.nodes
        logdet = 0.0
        for x in range(tree.nodes):
            n_f = int(nf[x])
            st, en = int(starts[x]), int(starts[x + 1])
            no = en - st
            F = np.zeros((n_f, n_f))
            Ff = F.reshape(-1)
            Ff[prior.qpos[x]] = prior.qval[x] * inv_s2
            Ff[prior.dpos[x]] += prec_var[st:en]
            for c in tree.children[x]:
                u = updates[c]
                if u is not None:
                    Ff[tree.ea_flat[c]] += u.reshape(-1)
                    updates[c] = None
            L11, info = lapack.dpotrf(F[:no, :no], lower=1, clean=1, overwrite_a=0)
            if info != 0:
                raise np.linalg.LinAlgError(f"posterior precision not positive definite (node {x}, info {info})")
            logdet += 2.0 * float(np.sum(np.log(np.diag(L11))))
            if n_f > no:
                L21T = blas.dtrsm(1.0, L11, F[:no, no:], lower=1)
                U = F[no:, no:]
                U -= L21T.T @ L21T
                updates[x] = U
            else:
                L21T = np.zeros((no, 0))
            L11s.append(L11)
            L21Ts.append(L21T)
        self.L11, self.L21T, self.logdet = L11s, L21Ts, logdet

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solves P x = b for b (nvar,) in elimination numbering."""
        tree = self.tree
        y = np.array(b, dtype=np.float64, copy=True)
        starts = tree.starts
        for x in range(tree.nodes):
            st, en = starts[x], starts[x + 1]
            z = blas.dtrsm(1.0, self.L11[x], y[st:en, None], lower=1)[:, 0]
            y[st:en] = z
            if self.L21T[x].shape[1]:
                y[tree.bnd[x]] -= self.L21T[x].T @ z
        for x in range(tree.nodes - 1, -1, -1):
            st, en = starts[x], starts[x + 1]
            rhs = y[st:en]
            if self.L21T[x].shape[1]:
                rhs = rhs - self.L21T[x] @ y[tree.bnd[x]]
            y[st:en] = blas.dtrsm(1.0, self.L11[x], rhs[:, None], lower=1, trans_a=1)[:, 0]
        return y

    def selected_inverse(self, readout: _Readout | None) -> tuple[np.ndarray, np.ndarray | None]:
        """diag(P^-1) (nvar,) and, with a read-out, the output variances w^T Sigma_block w (m,)."""
        tree = self.tree
        starts = tree.starts
        diag = np.empty(int(starts[-1]))
        out = None
        if readout is not None:
            out = np.empty(readout.resid.size)
        sig: list = [None] * tree.nodes
        last_child = [min(c) if c else -1 for c in tree.children]
        for x in range(tree.nodes - 1, -1, -1):
            st, en = int(starts[x]), int(starts[x + 1])
            no = en - st
            Linv, info = lapack.dtrtri(self.L11[x], lower=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"singular factor block (node {x})")
            Ainv = Linv.T @ Linv
            p = tree.parent[x]
            L21T = self.L21T[x]
            if L21T.shape[1] == 0:
                S = Ainv
                SJJ = Ainv
            else:
                loc = tree.loc[x]
                SBB = sig[p][np.ix_(loc, loc)]
                TT = Linv.T @ L21T  # L11^-T L21^T  (no, nb)
                SBJ = -(SBB @ TT.T)  # (nb, no)
                SJJ = Ainv - TT @ SBJ
                S = np.empty((tree.nf[x], tree.nf[x]))
                S[:no, :no] = SJJ
                S[:no, no:] = SBJ.T
                S[no:, :no] = SBJ
                S[no:, no:] = SBB
            diag[st:en] = np.diag(SJJ)
            if readout is not None and readout.node_groups[x] is not None:
                sel, pos, wgt = readout.node_groups[x]
                block = S[pos[:, :, None], pos[:, None, :]]
                out[sel] = np.einsum("mi,mij,mj->m", wgt, block, wgt)
            if tree.children[x]:
                sig[x] = S
            if p >= 0 and last_child[p] == x:
                sig[p] = None
        return diag, out


# ----------------------------------------------------------------------------- engine


class FastEngine:
    """Exact GP posterior on the pixel grid via the sparse precision (see the module docstring).

    The engine caches, per resolution and kernel, the elimination tree, the prior precision
    assembly and the output read-out, so a `DepthCompleter` (which keeps one engine) only pays
    the numeric factorisation from the second frame of a resolution on.

    Args:
        device: None for NumPy/SciPy on the CPU (default), or a torch device ("cpu", "cuda", ...)
            to run the same algorithm with torch in float64.
        leaf_pixels: Largest sub-grid (pixels) eliminated as one dense front.
        cache_size: Number of (resolution, kernel) set-ups kept.
    """

    name = "fast"

    def __init__(self, device=None, *, leaf_pixels: int | None = None, cache_size: int = 4):
        if leaf_pixels is not None and (not isinstance(leaf_pixels, int) or leaf_pixels < 1):
            raise InvalidInputError("leaf_pixels", "an integer >= 1", leaf_pixels)
        if not isinstance(cache_size, int) or cache_size < 1:
            raise InvalidInputError("cache_size", "an integer >= 1", cache_size)
        self.device = device
        self.leaf_pixels = leaf_pixels
        self.cache_size = cache_size
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

    def _tree(self, h: int, w: int, ds: int) -> _Tree:
        leaf = self.leaf_pixels or max(1, 48 // ds)
        return self._cached(self._trees, (h, w, ds, leaf), lambda: _build_tree(h, w, ds, leaf))

    def _prior(self, tree: _Tree, nu: float, lengthscale: float) -> _Prior:
        key = (tree.shape, tree.ds, id(tree), float(nu), float(lengthscale))
        return self._cached(self._priors, key, lambda: _build_prior(tree, nu, lengthscale))

    def _readout(self, tree: _Tree, problem: GridProblem) -> _Readout:
        k = problem.kernel
        key = (id(tree), problem.out_rows.tobytes(), problem.out_cols.tobytes(), float(k.nu), float(k.lengthscale))
        return self._cached(
            self._readouts, key, lambda: _build_readout(tree, problem.out_rows, problem.out_cols, k.nu, k.lengthscale)
        )

    # -- public
    def factorize(self, problem: GridProblem):
        """Factorises the posterior precision of ``problem``; returns (factor, tree, prior)."""
        _check_problem(problem)
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        tree = self._tree(h, w, d * d)
        prior = self._prior(tree, k.nu, k.lengthscale)
        prec_var = np.zeros(int(tree.starts[-1]))
        prec_var[::tree.ds] = np.asarray(problem.precision, dtype=np.float64).ravel()[tree.pix_order]
        inv_s2 = 1.0 / float(k.outputscale) ** 2
        if self.device is None:
            factor = _Factor(tree, prior, inv_s2, prec_var)
        else:
            from ._fast_torch import TorchFactor

            factor = TorchFactor(tree, prior, inv_s2, prec_var, self.device)
        return factor, tree, prior

    def solve(self, problem: GridProblem, *, variance: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None).

        Args:
            problem: The grid problem (either formulation).
            variance: Also compute the marginal variances (selected inversion).
        """
        factor, tree, prior = self.factorize(problem)
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        ds = tree.ds
        s2 = float(k.outputscale) ** 2
        prec = np.asarray(problem.precision, dtype=np.float64)
        resid = np.where(prec > 0, np.asarray(problem.obs, np.float64) - np.asarray(problem.prior_mean, np.float64), 0.0)
        b = np.zeros(int(tree.starts[-1]))
        b[::ds] = (prec * resid).ravel()[tree.pix_order]
        mu = factor.solve(b)
        states = mu.reshape(-1, ds)[tree.pix_pos].reshape(h, w, d, d)  # (r, c, k, l)
        same_grid = problem.output_is_input
        if same_grid:
            mean = np.asarray(problem.out_prior_mean, np.float64) + states[:, :, 0, 0]
        else:
            readout = self._readout(tree, problem)
            M = states.transpose(0, 2, 1, 3).reshape(h * d, w * d)
            mean = np.asarray(problem.out_prior_mean, np.float64) + readout.wv @ (readout.wu @ M.T).T
        if not variance:
            return mean, None
        if same_grid:
            diag, _ = factor.selected_inverse(None)
            var = diag.reshape(-1, ds)[tree.pix_pos, 0].reshape(h, w)
        else:
            _, out = factor.selected_inverse(readout)
            var = out.reshape(problem.out_shape) + s2 * readout.resid
        return mean, np.maximum(var, 0.0)

    def log_marginal_likelihood(self, problem: GridProblem) -> float:
        """Log marginal likelihood log p(y) of the observed pixels of ``problem`` (nats).

        Uses log p(y) = log N(y; f*, W^-1) + log N(f*; m, Q^-1) - log N(f*; f*, P^-1) at the
        posterior mean f*, with log det P from the sparse Cholesky factor.
        """
        factor, tree, prior = self.factorize(problem)
        k = problem.kernel
        ds = tree.ds
        s2 = float(k.outputscale) ** 2
        prec = np.asarray(problem.precision, dtype=np.float64)
        obs = prec > 0
        resid = np.where(obs, np.asarray(problem.obs, np.float64) - np.asarray(problem.prior_mean, np.float64), 0.0)
        b = np.zeros(int(tree.starts[-1]))
        b[::ds] = (prec * resid).ravel()[tree.pix_order]
        mu = factor.solve(b)
        f = np.zeros_like(resid)
        f.ravel()[tree.pix_order] = mu[::ds]
        data = -0.5 * float(np.sum(prec[obs] * (resid[obs] - f[obs]) ** 2))
        data += 0.5 * float(np.sum(np.log(prec[obs]))) - 0.5 * obs.sum() * np.log(2 * np.pi)
        # f^T Q f with Q = blocks / s^2: reuse the per-node assembly (each entry owned once).
        quad = 0.0
        for x in range(tree.nodes):
            n_f = tree.nf[x]
            st, en = tree.starts[x], tree.starts[x + 1]
            front = np.concatenate([np.arange(st, en), tree.bnd[x]])
            a, bb = np.divmod(prior.qpos[x], n_f)
            quad += float(np.sum(prior.qval[x] * mu[front[a]] * mu[front[bb]]))
        quad /= s2
        nvar = int(tree.starts[-1])
        logdet_q = prior.logdet - nvar * np.log(s2)
        return data - 0.5 * quad + 0.5 * logdet_q - 0.5 * factor.logdet


def _check_problem(problem: GridProblem) -> None:
    if not isinstance(problem, GridProblem):
        raise InvalidInputError("problem", "a GridProblem", type(problem).__name__)
    h, w = problem.shape
    if h < 2 or w < 2:
        raise ShapeError("problem", "a GP grid of at least 2 x 2 pixels", f"{h} x {w}")
    for name in ("obs", "precision"):
        a = getattr(problem, name)
        if np.shape(a) != (h, w):
            raise ShapeError(f"problem.{name}", f"shape {(h, w)}", np.shape(a))
    prec = np.asarray(problem.precision)
    if not np.all(np.isfinite(prec)) or np.any(prec < 0):
        raise InvalidInputError("problem.precision", "finite values >= 0", "negative or non-finite values")
    if np.shape(problem.out_prior_mean) != problem.out_shape:
        raise ShapeError("problem.out_prior_mean", f"shape {problem.out_shape}", np.shape(problem.out_prior_mean))
