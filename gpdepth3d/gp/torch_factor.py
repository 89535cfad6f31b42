"""The grid route's numeric phase in torch (any device): batched Cholesky, solves and selected inverse per template node.

The tiles' fronts of one template node run as one batched cholesky_ex / solve_triangular / matmul
call, the top separators one by one; float64 throughout. See docs/engines.md.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from .elimination_tree import EliminationTree
from .grid_prior import BatchedPrior
from .readout import Readout


def _device_arrays(tree: EliminationTree, prior: BatchedPrior, readout: "Readout | None", device):
    """Index arrays and prior values of the tree as torch tensors on ``device`` (cached on the objects)."""
    import torch

    key = str(device)
    cache = tree.__dict__.setdefault("_dev", {})
    if key not in cache:
        t = lambda a: None if a is None else torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
        cache[key] = {
            "t_bnd": [t(b) for b in tree.t_bnd],
            "t_loc": [t(x) for x in tree.t_loc],
            "t_ea": [t(x) for x in tree.t_ea],
            "top_bnd": [t(b) for b in tree.top_bnd],
            "top_loc": [t(x) for x in tree.top_loc],
            "top_ea": [t(x) for x in tree.top_ea],
            "tile_loc": t(tree.tile_loc),
            "tile_ea": t(tree.tile_ea),
            "top_tiles": [t(np.array(x, dtype=np.int64)) for x in tree.top_tiles],
            "t_diag": [t(np.arange(no) * (nf + 1)) for no, nf in zip(tree.t_no, tree.t_nf)],
            "top_diag": [
                t(np.arange(tree.top_starts[x + 1] - tree.top_starts[x]) * (tree.top_nf[x] + 1))
                for x in range(tree.ntop)
            ],
        }
    pcache = prior.__dict__.setdefault("_dev", {})
    if key not in pcache:
        t = lambda a: torch.as_tensor(np.asarray(a), device=device)  # noqa: E731
        pcache[key] = {
            "t_qpos": [t(x) for x in prior.t_qpos],
            "t_qval": [t(x) for x in prior.t_qval],
            "top_qpos": [t(x) for x in prior.top_qpos],
            "top_qval": [t(x) for x in prior.top_qval],
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


class TorchFactor:
    """Cholesky factor of the posterior precision over the tree's fronts (torch, float64, any device)."""

    def __init__(self, tree: EliminationTree, prior: BatchedPrior, inv_s2: float, prec_var: np.ndarray, device=None):
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

    def selected_inverse(self, readout: Readout | None) -> tuple[np.ndarray, np.ndarray | None]:
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


@contextmanager
def torch_threads(threads: int | None):
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
