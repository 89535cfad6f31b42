"""Tests of the compiled multifrontal kernels (gpdepth3d.gp.multifrontal) and of the fast engine's back-ends."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.errors import InvalidInputError
from gpdepth3d.gp.exact import ExactEngine
from gpdepth3d.gp.fast import FastEngine
from gpdepth3d.gp.model import GridProblem, Kernel
from gpdepth3d.gp.multifrontal import _SMALL, FrontalFactor, FrontTree

from test_fast import assert_thread_safe, random_problem


def arrow_system(rng, sizes=(3, 4, 2, 5)):
    """A random SPD matrix with the elimination tree 0, 1 -> 2 -> 3 (fronts of ``sizes`` variables).

    Variables are numbered front by front; each front couples to all of its ancestors, and the
    boundaries are given in a random order (the tree sorts them).
    """
    st = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    n = int(np.sum(sizes))
    parent = [2, 2, 3, -1]
    own = [np.arange(st[f], st[f] + sizes[f]) for f in range(4)]
    # coupling pattern: a front's own variables with its own and with its ancestors' variables
    mask = np.zeros((n, n), dtype=bool)
    for f in range(4):
        anc = []
        p = parent[f]
        while p >= 0:
            anc.append(own[p])
            p = parent[p]
        vs = np.concatenate([own[f], *anc]) if anc else own[f]
        mask[np.ix_(own[f], vs)] = True
    mask |= mask.T
    A = np.where(mask, rng.normal(size=(n, n)), 0.0)
    A = 0.5 * (A + A.T)
    A += np.eye(n) * (np.abs(A).sum(1).max() + 1.0)  # diagonally dominant: SPD
    bnds = []
    for f in range(4):
        cols = np.nonzero(mask[own[f]].any(0))[0]
        b = cols[cols >= st[f] + sizes[f]]
        bnds.append(rng.permutation(b))
    return A, st, np.array(sizes), parent, bnds


def arrow_tree(seed: int, threads=None):
    """(A, its FrontTree, the assembly map of its lower triangle, entry values, rng, st, boundaries)."""
    rng = np.random.default_rng(seed)
    A, st, no, parent, bnds = arrow_system(rng)
    tree = FrontTree.build(st, no, parent, bnds, A.shape[0], threads=threads)
    rows, cols = np.nonzero(np.tril(A))
    return A, tree, tree.assembly(rows, cols), (rows, cols), rng, st, bnds


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_factor_solve_selinv_match_dense(threads):
    A, tree, asm, (rows, cols), rng, _, _ = arrow_tree(0, threads)
    n = A.shape[0]
    # split A into an off-diagonal "prior" part and a diagonal "observation" part
    d = rng.uniform(0.1, 1.0, n)
    vals = A[rows, cols] - np.where(rows == cols, d[rows], 0.0)
    factor = FrontalFactor(tree, asm, vals, d)
    b = rng.normal(size=n)
    np.testing.assert_allclose(factor.solve(b), np.linalg.solve(A, b), rtol=1e-11, atol=1e-12)
    diag, _ = factor.selected_inverse()
    np.testing.assert_allclose(diag, np.diag(np.linalg.inv(A)), rtol=1e-11)
    assert factor.logdet == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-12)


@pytest.mark.parametrize("sizes", [(3, 4, 2, 5), (3, 100, 2, 5), (40, 30, 60, 8)])
def test_small_and_large_front_paths_match_dense(sizes):
    """Fronts up to multifrontal._SMALL variables run compiled loops, larger ones LAPACK/BLAS: mixed
    trees (one front of each kind, or all large) give the dense answers, with several right-hand sides."""
    rng = np.random.default_rng(7)
    A, st, no, parent, bnds = arrow_system(rng, sizes)
    tree = FrontTree.build(st, no, parent, bnds, A.shape[0], threads=1)
    assert (tree.nf <= _SMALL).any()
    assert (tree.nf > _SMALL).any() == (max(sizes) > _SMALL // 2)  # the cases cover both paths
    rows, cols = np.nonzero(np.tril(A))
    n = A.shape[0]
    d = rng.uniform(0.1, 1.0, n)
    factor = FrontalFactor(tree, tree.assembly(rows, cols), A[rows, cols] - np.where(rows == cols, d[rows], 0.0), d)
    B = rng.normal(size=(n, 3))
    np.testing.assert_allclose(factor.solve(B), np.linalg.solve(A, B), rtol=1e-11, atol=1e-12)
    diag, _ = factor.selected_inverse()
    np.testing.assert_allclose(diag, np.diag(np.linalg.inv(A)), rtol=1e-11)
    assert factor.logdet == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-12)


@pytest.mark.parametrize("threads", [1, 2])
def test_several_right_hand_sides_in_one_solve(threads):
    """(n, r) right-hand sides: each column is the solve of that column alone (one pass over the factor)."""
    A, tree, asm, (rows, cols), rng, _, _ = arrow_tree(4, threads)
    n = A.shape[0]
    d = rng.uniform(0.1, 1.0, n)
    factor = FrontalFactor(tree, asm, A[rows, cols] - np.where(rows == cols, d[rows], 0.0), d)
    B = rng.normal(size=(n, 3))
    X = factor.solve(B)
    assert X.shape == (n, 3)
    np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-11, atol=1e-12)
    for j in range(3):
        np.testing.assert_allclose(X[:, j], factor.solve(B[:, j]), rtol=1e-13, atol=1e-14)


def test_readout_quadratic_forms():
    A, tree, asm, (rows, cols), rng, st, bnds = arrow_tree(1)
    factor = FrontalFactor(tree, asm, A[rows, cols], np.zeros(A.shape[0]))
    Sigma = np.linalg.inv(A)
    # outputs reading variables of one front each (own + boundary of front 0, own of the root)
    groups = [np.array([0, 1, bnds[0][0]]), np.array([st[3], st[3] + 1, st[3] + 4])]
    fronts = np.array([0, 3])
    w = rng.normal(size=(2, 3))
    pos = np.stack([tree.positions(np.full(3, f), g) for f, g in zip(fronts, groups)])
    order = np.argsort(fronts)
    ptr = np.searchsorted(fronts[order], np.arange(tree.st.size + 1))
    _, out = factor.selected_inverse((ptr, order, pos[order], w[order], 2))
    for k in range(2):
        g = groups[k]
        assert out[k] == pytest.approx(w[k] @ Sigma[np.ix_(g, g)] @ w[k], rel=1e-11)


def test_not_positive_definite_raises():
    A, tree, asm, (rows, cols), _, _, _ = arrow_tree(2)
    with pytest.raises(np.linalg.LinAlgError):
        FrontalFactor(tree, asm, -A[rows, cols], np.zeros(A.shape[0]))


def test_factors_alive_together_keep_their_own_buffers():
    A, tree, asm, (rows, cols), rng, _, _ = arrow_tree(3)
    n = A.shape[0]
    f1 = FrontalFactor(tree, asm, A[rows, cols], np.zeros(n))
    f2 = FrontalFactor(tree, asm, A[rows, cols], np.full(n, 5.0))
    b = rng.normal(size=n)
    np.testing.assert_allclose(f1.solve(b), np.linalg.solve(A, b), rtol=1e-11)
    np.testing.assert_allclose(f2.solve(b), np.linalg.solve(A + 5 * np.eye(n), b), rtol=1e-11)
    del f1, f2
    f3 = FrontalFactor(tree, asm, A[rows, cols], np.zeros(n))  # reuses a released workspace
    np.testing.assert_allclose(f3.solve(b), np.linalg.solve(A, b), rtol=1e-11)


class TestBackends:
    @pytest.mark.parametrize("nu", [0.5, 1.5])
    @pytest.mark.parametrize("balanced", [False, True])
    def test_compiled_and_torch_agree(self, nu, balanced):
        problem = random_problem(np.random.default_rng(4), 31, 45, nu=nu, balanced=balanced, out=(40, 52))
        m0, v0 = FastEngine(backend="torch", tile=9).solve(problem)
        m1, v1 = FastEngine(backend="compiled", tile=9).solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-9)
        lml0 = FastEngine(backend="torch", tile=9).log_marginal_likelihood(problem)
        assert FastEngine(backend="compiled", tile=9).log_marginal_likelihood(problem) == pytest.approx(lml0, rel=1e-10)

    def test_torch_backend_matches_exact(self):
        problem = random_problem(np.random.default_rng(5), 17, 23, out=(17, 23))
        m0, v0 = ExactEngine().solve(problem)
        m1, v1 = FastEngine(backend="torch", tile=6).solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-9)

    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_vanishing_couplings_are_exact(self):
        # l = 0.04 px: neighbour correlation e^-25, couplings across fronts far below 1e-100
        # (flushed to zero to avoid subnormal arithmetic); the posterior must still be exact.
        problem = random_problem(np.random.default_rng(6), 40, 50, lengthscale=0.04, balanced=True)
        m0, v0 = ExactEngine(max_points=10_000).solve(problem)
        m1, v1 = FastEngine().solve(problem)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-9)

    def test_bad_backend(self, monkeypatch):
        torch = pytest.importorskip("torch")
        with pytest.raises(InvalidInputError, match="backend"):
            FastEngine(backend="fortran")
        with pytest.raises(InvalidInputError, match="backend"):
            FastEngine(device="cuda", backend="compiled")
        assert FastEngine().backend == "compiled"
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # only the back-end choice is tested
        monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
        assert FastEngine(device="cuda").backend == "torch"


def test_completer_reuses_per_resolution_setup_and_buffers():
    from gpdepth3d.completion.complete import DepthCompleter
    from gpdepth3d.gp.model import DepthGPConfig
    from gpdepth3d.measurements import SparseDepth

    rng = np.random.default_rng(7)
    from gpdepth3d.gp import EngineConfig

    # 50 points: "auto" would take the Woodbury route
    completer = DepthCompleter(DepthGPConfig.residual(lengthscale=5.0), engine=EngineConfig(name="fast", route="grid"))
    engine = completer.engine

    def frame():
        mde = rng.uniform(2.0, 4.0, (30, 40))
        r, c = rng.integers(0, 30, 50), rng.integers(0, 40, 50)
        return mde, SparseDepth.from_arrays(c.astype(float), r.astype(float), mde[r, c] * 1.1, (30, 40))

    completer(*frame())
    (tree,) = engine._trees.values()
    fronts = tree.__dict__["_fronts"]
    (ws,) = fronts._pool
    second = frame()
    post = completer(*second)
    assert list(engine._trees.values()) == [tree] and tree.__dict__["_fronts"] is fronts
    assert fronts._pool == [ws]  # the second frame factorised into the first frame's buffers
    ref = DepthCompleter(completer.config, engine=EngineConfig(name="exact"))(*second)
    np.testing.assert_allclose(post.mean, ref.mean, atol=1e-9)
    np.testing.assert_allclose(post.variance, ref.variance, rtol=1e-8)


def test_concurrent_callers_get_their_own_answers():
    problems = [random_problem(np.random.default_rng(20 + k), 26, 34, balanced=k % 2 == 0) for k in range(6)]
    assert_thread_safe(FastEngine(tile=8, route="grid"), problems)


def test_alternating_resolutions_with_a_one_entry_cache():
    # set-ups are evicted and rebuilt; cached priors and read-outs must never meet a wrong tree
    engine = FastEngine(cache_size=1)
    problems = [random_problem(np.random.default_rng(30 + k), 18 + 3 * (k % 2), 24, out=(20, 30)) for k in range(4)]
    for p in problems:
        m0, v0 = ExactEngine().solve(p)
        m1, v1 = engine.solve(p)
        np.testing.assert_allclose(m1, m0, atol=1e-9)
        np.testing.assert_allclose(v1, v0, rtol=1e-8)


class TestPriorReuse:
    @staticmethod
    def sparse_problem(seed, h=40, w=56, n=12, nu=0.5, out=None):
        """Residual-style problem: a handful of observed pixels, most fronts see none."""
        rng = np.random.default_rng(seed)
        p = random_problem(rng, h, w, nu=nu, frac=0.0, out=out)
        prec = np.zeros((h, w))
        idx = rng.choice(h * w, n, replace=False)
        prec.flat[idx] = rng.uniform(10.0, 1e4, n)
        return GridProblem(
            p.prior_mean, p.obs, prec, p.out_rows, p.out_cols, p.out_prior_mean, Kernel(nu, 3.0, rng.uniform(0.5, 2.0))
        )

    @pytest.mark.parametrize("nu", [0.5, 1.5])
    def test_frames_reusing_the_prior_factor_are_exact(self, nu):
        engine = FastEngine(tile=7, route="grid")  # few points: "auto" would take the Woodbury route
        fresh = FastEngine(tile=7, prior_cache_mb=0, route="grid")
        for k in range(4):  # a new scale and new points every frame
            problem = self.sparse_problem(40 + k, nu=nu, out=(50, 60) if k == 3 else None)
            m0, v0 = ExactEngine().solve(problem)
            m1, v1 = engine.solve(problem)
            np.testing.assert_allclose(m1, m0, atol=1e-9)
            np.testing.assert_allclose(v1, v0, rtol=1e-8)
            assert engine.log_marginal_likelihood(problem) == pytest.approx(
                fresh.log_marginal_likelihood(problem), rel=1e-10
            )
        assert engine._prior_factor is not None and fresh._prior_factor is None
        fronts = engine._prior_factor[1].tree
        prec = np.zeros(fronts.nvar)
        assert fronts.touched_share(prec) == 0.0

    def test_dense_observations_do_not_build_it(self):
        engine = FastEngine(tile=7)
        for k in range(3):
            engine.solve(random_problem(np.random.default_rng(50 + k), 30, 40, balanced=True))
        assert engine._prior_factor is None

    def test_bad_budget(self):
        with pytest.raises(InvalidInputError, match="prior_cache_mb"):
            FastEngine(prior_cache_mb=-1)


@pytest.mark.parametrize("threads", [2, 3])
def test_bins_and_ancestors_partition_a_grid_tree(threads):
    """The parallel split of a pixel-grid tree: every front once; the common ancestors closed upwards; a bin
    holds whole subtrees; with 2 threads the 93 x 414 KITTI lattice keeps at most 3 sequential fronts."""
    from gpdepth3d.gp.elimination_tree import build_tree as _build_tree, front_tree as _front_tree

    base = _front_tree(_build_tree(93, 414, 1, 24, 40))
    fronts = FrontTree.build(
        base.st,
        base.no,
        base.parent,
        [base.bnd[base.bnd_ptr[f] : base.bnd_ptr[f + 1]] for f in range(base.st.size)],
        base.nvar,
        threads=threads,
    )
    bins = [set(fronts.bin_order[fronts.bin_ptr[b] : fronts.bin_ptr[b + 1]].tolist()) for b in range(threads)]
    seq = set(fronts.seq_order.tolist())
    assert sum(len(b) for b in bins) + len(seq) == fronts.st.size
    assert set().union(*bins, seq) == set(range(fronts.st.size))
    for f in seq:
        assert fronts.parent[f] < 0 or fronts.parent[f] in seq
    for b in bins:
        for f in b:
            assert fronts.parent[f] < 0 or fronts.parent[f] in b or fronts.parent[f] in seq
    if threads == 2:
        assert len(seq) <= 3 and all(len(b) > 0 for b in bins)
