"""Compiled multifrontal Cholesky, solve and selected inversion over a tree of dense fronts.

The CPU numeric phase of the ``fast`` engine's grid route (`gpdepth3d.gp.elimination_tree` builds
the tree): numba loops calling LAPACK/BLAS, exact to rounding, independent subtrees in parallel.
Recursions and layout: docs/engines.md#the-multifrontal-factorisation-in-detail.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass

import numba as nb
import numpy as np
from llvmlite import binding as llvm
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import get_cython_function_address, intrinsic


def _bind(lib: str, name: str, nargs: int):
    """A LAPACK/BLAS routine of SciPy's Cython bindings as a numba external function.

    The routine's address is registered with LLVM under a private symbol name, so the compiled
    kernels refer to it by name and can be cached on disk (a ctypes pointer would be baked in).
    """
    symbol = f"gpdepth3d_{name}"
    llvm.add_symbol(symbol, get_cython_function_address(f"scipy.linalg.cython_{lib}", name))
    return types.ExternalFunction(symbol, types.void(*([types.intp] * nargs)))


_dpotrf = _bind("lapack", "dpotrf", 5)  # uplo, n, a, lda, info
_dlauum = _bind("lapack", "dlauum", 5)  # uplo, n, a, lda, info
_dtrmm = _bind("blas", "dtrmm", 11)  # side, uplo, transa, diag, m, n, alpha, a, lda, b, ldb
_dsyrk = _bind("blas", "dsyrk", 10)  # uplo, trans, n, k, alpha, a, lda, beta, c, ldc
_dsymm = _bind("blas", "dsymm", 12)  # side, uplo, m, n, alpha, a, lda, b, ldb, beta, c, ldc
_dgemm = _bind("blas", "dgemm", 13)  # transa, transb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc
_dtrmv = _bind("blas", "dtrmv", 8)  # uplo, trans, diag, n, a, lda, x, incx
_dgemv = _bind("blas", "dgemv", 11)  # trans, m, n, alpha, a, lda, x, incx, beta, y, incy

_FLAGS = dict(nogil=True, cache=True, boundscheck=False)
# The compiled small-front loops may reassociate sums and fuse multiply-adds (vectorised dot
# products): a change of rounding only, like a different BLAS blocking.
_FAST = dict(_FLAGS, fastmath={"reassoc", "contract"})
_BLOCK = 32  # diagonal block of the triangular inversion
# Entries below this magnitude are set to zero as fronts are produced. Long-range couplings decay
# geometrically (rho^distance) and their products reach subnormal numbers, which x86 handles far
# more slowly; with every stored operand >= 1e-100 or 0, no product of up to three of them is subnormal.
# The change is far below rounding of any entry that matters (precisions and covariances here
# span ~1e-12 .. 1e12).
_TINY = 1e-100


@nb.njit(**_FLAGS)
def _flush(A, off, m, n, lda):
    """Zeroes the entries of magnitude < _TINY of the m x n block of flat column-major ``A`` at ``off``."""
    for j in range(n):
        c = off + j * lda
        for i in range(m):
            if abs(A[c + i]) < _TINY:
                A[c + i] = 0.0


def _prefetch_intrinsic(write: int):
    """An intrinsic hinting the CPU to load the cache line at an address (an integer), for reading
    (``write`` 0) or writing (1): LLVM's prefetch."""

    @intrinsic
    def prefetch_line(typingctx, address):
        def codegen(context, builder, signature, args):
            i8p = ir.IntType(8).as_pointer()
            i32 = ir.IntType(32)
            fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
            builder.call(fn, [builder.inttoptr(args[0], i8p), i32(write), i32(3), i32(1)])
            return context.get_dummy_value()

        return types.void(types.intp), codegen

    return prefetch_line


_prefetch_read = _prefetch_intrinsic(0)
_prefetch_write = _prefetch_intrinsic(1)


@nb.njit(**_FLAGS)
def _prefetch(a, lo, hi, write=False):
    """Prefetches the entries lo .. hi of the contiguous array ``a`` (flat index), a cache line at a time.

    The fronts' data (factor columns, assembly and read-out maps) stream from memory in pieces of
    a few KiB, too short for the hardware prefetcher; asking for the next front's piece while this
    front is computed hides that latency.
    """
    if hi <= lo:
        return
    base = a.ctypes.data
    size = a.itemsize
    for b in range(base + lo * size, base + hi * size, 64):
        if write:
            _prefetch_write(b)
        else:
            _prefetch_read(b)


# Constants passed to LAPACK/BLAS by reference. Module-level arrays are frozen into the compiled
# code as static data, so their addresses stay valid for the whole call (a local array's memory
# is released after its last use in numba's IR, which is before the BLAS calls that read it).
_CHARS = np.array([ord("L"), ord("N"), ord("T"), ord("R")], dtype=np.int8)  # Fortran characters
_CONST = np.array([1.0, -1.0, 0.0])  # alpha / beta values


@nb.njit(**_FAST)
def _tri_inv(A, off, n, lda, ip, t):
    """In-place inverse of the lower-triangular n x n block of flat column-major ``A`` at ``off``.

    Blocked as LAPACK's dtrtri, but every off-diagonal step is a dtrmm with an already inverted
    block (OpenBLAS's dtrsm, which dtrtri and a plain triangular solve use, is much slower than
    dtrmm on these shapes); the 32 x 32 diagonal blocks are inverted by compiled loops, with
    ``t`` (_BLOCK,) as scratch (passed in: the factorisation calls this once per front).
    """
    ch = _CHARS
    dp = _CONST
    ulda = np.uint64(lda)
    j = ((n - 1) // _BLOCK) * _BLOCK
    while j >= 0:
        jb = min(_BLOCK, n - j)
        d0 = np.uint64(off + j + j * lda)
        ujb = np.uint64(jb)
        for c in range(ujb - np.uint64(1), -1, -1):  # unblocked inverse of the diagonal block (as dtrti2)
            uc = np.uint64(c)
            col = d0 + uc * ulda
            A[col + uc] = 1.0 / A[col + uc]
            ajj = -A[col + uc]
            # column c below the diagonal: -X[c+1:, c+1:] L[c+1:, c] / L[c, c], as axpys over the
            # already inverted columns (contiguous; the row-wise dot products of dtrti2 are strided)
            for i in range(uc + np.uint64(1), ujb):
                t[i] = 0.0
            for k in range(uc + np.uint64(1), ujb):
                a = A[col + k]
                ck = d0 + k * ulda
                for i in range(k, ujb):
                    t[i] += A[ck + i] * a
            for i in range(uc + np.uint64(1), ujb):
                A[col + i] = t[i] * ajj
        m = n - j - jb
        if m > 0:
            ip[0], ip[1], ip[2] = m, jb, lda
            a21 = A.ctypes.data + (d0 + jb) * 8
            a22 = A.ctypes.data + (d0 + jb + jb * lda) * 8
            _dtrmm(ch.ctypes.data, ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 1, ip.ctypes.data,
                   ip.ctypes.data + 4, dp.ctypes.data, a22, ip.ctypes.data + 8, a21, ip.ctypes.data + 8)
            _dtrmm(ch.ctypes.data + 3, ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 1, ip.ctypes.data,
                   ip.ctypes.data + 4, dp.ctypes.data + 8, A.ctypes.data + d0 * 8, ip.ctypes.data + 8, a21,
                   ip.ctypes.data + 8)
        j -= _BLOCK


@nb.njit(**_FLAGS)
def _inverse_from_cholesky(A, n, ip):
    """In place: the lower Cholesky factor L (flat column-major n x n) -> lower triangle of (L L^T)^-1.

    L^-1 by `_tri_inv` (dtrmm-based), then (L^-1)^T L^-1 by LAPACK's dlauum: what dpotri computes, without dtrsm.
    """
    _tri_inv(A, 0, n, n, ip, np.empty(_BLOCK))
    ip[0], ip[1] = n, 0
    _dlauum(_CHARS.ctypes.data, ip.ctypes.data, A.ctypes.data, ip.ctypes.data, ip.ctypes.data + 4)
    return ip[1]


def inverse_from_cholesky(L: np.ndarray) -> np.ndarray:
    """(L L^T)^-1 (lower triangle; the upper one is left as it was) from a lower Cholesky factor, in place.

    Args:
        L: (n, n) Fortran-ordered float64 array holding the factor in its lower triangle.
    """
    if not (L.flags.f_contiguous and L.dtype == np.float64 and L.ndim == 2 and L.shape[0] == L.shape[1]):
        raise ValueError("internal error: L must be a square Fortran-ordered float64 array")
    info = _inverse_from_cholesky(L.ravel(order="F"), L.shape[0], np.zeros(4, dtype=np.int32))
    if info != 0:
        raise np.linalg.LinAlgError(f"dlauum failed (info={info})")
    return L


_SMALL = 96  # fronts up to this size are factorised by `_partial_cholesky` instead of LAPACK/BLAS calls


@nb.njit(**_FAST)
def _partial_cholesky(F, no, nf):
    """Eliminates the first ``no`` variables of the flat column-major nf x nf front ``F`` in place
    (lower triangle): [L11; L21] in the first ``no`` columns, F22 - L21 L21^T in the rest.

    Right-looking by panels of four columns: a panel is factorised (each of its columns updated
    by the panel's earlier ones), then the trailing matrix takes one rank-4 update (each of its
    entries loaded and stored once per panel; contiguous loops that vectorise). Entries of L
    below _TINY are flushed before they are used. For the small fronts at the bottom of the tree
    (nf <= _SMALL) it replaces dpotrf + dtrmm + dsyrk, whose call overhead and small-matrix paths
    dominate there. Returns 0, or j + 1 when pivot j is not positive.
    """
    unf = np.uint64(nf)
    j = np.int64(0)  # int64, not the literal 0: _trailing_update is compiled for one signature, not two
    while j < no:
        g = min(4, no - j)
        for p in range(g):  # the panel's columns
            uc = np.uint64(j + p)
            cc = uc * unf
            for q in range(np.uint64(j), uc):
                a = F[q * unf + uc]
                cq = q * unf
                for i in range(uc, unf):
                    F[cc + i] -= a * F[cq + i]
            d = F[cc + uc]
            if not d > 0.0:
                return j + p + 1
            d = np.sqrt(d)
            F[cc + uc] = d
            inv = 1.0 / d
            for i in range(uc + np.uint64(1), unf):
                v = F[cc + i] * inv
                F[cc + i] = v if abs(v) >= _TINY else 0.0
        _trailing_update(F, j, g, unf)
        j += g
    return 0


@nb.njit(**_FAST)
def _trailing_update(F, j, g, unf):
    """F[m:, m] -= sum_q F[m, q] F[m:, q] for the trailing columns m >= j + g, q the panel j .. j + g - 1."""
    uj = np.uint64(j)
    start = uj + np.uint64(g)
    if g == 4:
        c0, c1, c2, c3 = uj * unf, (uj + np.uint64(1)) * unf, (uj + np.uint64(2)) * unf, (uj + np.uint64(3)) * unf
        for m in range(start, unf):
            a0, a1, a2, a3 = F[c0 + m], F[c1 + m], F[c2 + m], F[c3 + m]
            cm = m * unf
            for i in range(m, unf):
                F[cm + i] -= (a0 * F[c0 + i] + a1 * F[c1 + i]) + (a2 * F[c2 + i] + a3 * F[c3 + i])
        return
    for m in range(start, unf):
        cm = m * unf
        for q in range(uj, start):
            cq = q * unf
            a = F[cq + m]
            for i in range(m, unf):
                F[cm + i] -= a * F[cq + i]


@nb.njit(**_FLAGS)
def _factor_run(order, st, no_, nb_, nf_, children_ptr, children, ea_ptr, ea_pos, asm_ptr, asm_pos, asm_src,
                qvals, prec, l_ptr, lbuf, upd_off, stack, touched, prior_l, prior_upd, u_ptr, save, work):
    """Multifrontal Cholesky of the fronts in ``order``; returns the first failing front or -1.

    Stores per front [L11^-1; L21] (nf x no, column-major) at ``lbuf[l_ptr[f]]``. With a prior
    factor (``touched`` non-empty), a front that no observation reaches is copied from
    ``prior_l`` and its update is read from ``prior_upd``; with ``save`` every front's update is
    stored there (building the prior factor). The log det is read from ``lbuf`` when asked
    (`_logdet`), sparing a logarithm per variable in every solve that does not use it.
    """
    ch = _CHARS
    ip = np.zeros(8, dtype=np.int32)  # integer scalars passed by reference
    ip2 = np.zeros(4, dtype=np.int32)
    tri = np.empty(_BLOCK)  # scratch of _tri_inv
    dp = _CONST
    cL, cN, cT, cR = ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 2, ch.ctypes.data + 3
    one, mone = dp.ctypes.data, dp.ctypes.data + 8
    skip = touched.size > 0
    for k in range(order.size):
        f = order[k]
        if k + 1 < order.size:  # the next front's assembly map, while this one is computed
            g = order[k + 1]
            _prefetch(asm_pos, asm_ptr[g], asm_ptr[g + 1])
            _prefetch(asm_src, asm_ptr[g], asm_ptr[g + 1])
            _prefetch(lbuf, l_ptr[g], l_ptr[g] + nf_[g] * no_[g], True)
        no, nbf, nf, s = no_[f], nb_[f], nf_[f], st[f]
        if skip and not touched[f]:
            l0 = np.uint64(l_ptr[f])
            for i in range(np.uint64(nf * no)):
                lbuf[l0 + i] = prior_l[l0 + i]
            continue
        F = work[: nf * nf]
        unf = np.uint64(nf)
        for uj in range(unf):
            for i in range(uj * unf + uj, (uj + np.uint64(1)) * unf):
                F[i] = 0.0
        for k in range(np.uint64(asm_ptr[f]), np.uint64(asm_ptr[f + 1])):
            F[np.uint64(asm_pos[k])] += qvals[np.uint64(asm_src[k])]
        for j in range(no):
            F[j * (nf + 1)] += prec[s + j]
        for kc in range(children_ptr[f], children_ptr[f + 1]):
            c = children[kc]
            nbc = np.uint64(nb_[c])
            upd = stack
            u0 = np.uint64(upd_off[c])
            if skip and not touched[c]:
                upd = prior_upd
                u0 = np.uint64(u_ptr[c])
            e0 = np.uint64(ea_ptr[c])
            for jj in range(nbc):
                cj = np.uint64(ea_pos[e0 + jj]) * unf
                col = u0 + jj * nbc
                for ii in range(jj, nbc):
                    F[np.uint64(ea_pos[e0 + ii]) + cj] += upd[col + ii]
        ip[0], ip[1], ip[2], ip[3] = no, nf, nbf, 0
        small = nf <= _SMALL
        if small:  # L11, L21 and the update in one compiled pass (no BLAS call overhead)
            if _partial_cholesky(F, no, nf) != 0:
                return f
        else:
            _dpotrf(cL, ip.ctypes.data, F.ctypes.data, ip.ctypes.data + 4, ip.ctypes.data + 12)
            if ip[3] != 0:
                return f
        _tri_inv(F, 0, no, nf, ip2, tri)
        _flush(F, 0, no, no, nf)
        if nbf > 0 and not small:
            a21 = F.ctypes.data + no * 8
            a22 = F.ctypes.data + (no + no * nf) * 8
            _dtrmm(cR, cL, cT, cN, ip.ctypes.data + 8, ip.ctypes.data, one, F.ctypes.data, ip.ctypes.data + 4,
                   a21, ip.ctypes.data + 4)
            _flush(F, no, nbf, no, nf)
            _dsyrk(cL, cN, ip.ctypes.data + 8, ip.ctypes.data, mone, a21, ip.ctypes.data + 4, one, a22,
                   ip.ctypes.data + 4)
        if nbf > 0:
            u0 = np.uint64(upd_off[f])
            unb = np.uint64(nbf)
            uno = np.uint64(no)
            for jj in range(unb):
                src = uno + (uno + jj) * unf
                dst = u0 + jj * unb
                for ii in range(jj, unb):
                    v = F[src + ii]
                    stack[dst + ii] = v if abs(v) >= _TINY else 0.0
            if save:
                p0 = np.uint64(u_ptr[f])
                for i in range(unb * unb):
                    prior_upd[p0 + i] = stack[u0 + i]
        l0 = np.uint64(l_ptr[f])
        for i in range(np.uint64(nf * no)):
            lbuf[l0 + i] = F[i]
    return -1


@nb.njit(**_FLAGS)
def _logdet(no_, nf_, l_ptr, lbuf):
    """log det(L L^T) from the stored fronts [L11^-1; L21]: the diagonal of L11^-1 holds 1 / L_jj."""
    ld = 0.0
    for f in range(no_.size):
        l0, nf = l_ptr[f], nf_[f]
        for j in range(no_[f]):
            ld -= 2.0 * np.log(lbuf[l0 + j * (nf + 1)])
    return ld


@nb.njit(**_FAST)
def _forward_run(order, st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs, tmp, seq_slot, acc):
    """Forward substitution L Z = Y over the fronts of ``order``, in place, for ``nrhs`` right-hand sides.

    ``y`` holds the right-hand sides column after column (column j of variable v at j * nvar + v,
    nvar = y.size // nrhs), so each front is read once for all of them. Updates of variables
    with ``seq_slot[v] >= 0`` are summed into ``acc`` (column j at j * nseq + slot) instead of
    ``y`` (they belong to fronts that other threads also update); pass an empty ``acc`` to
    update ``y``.
    """
    ch = _CHARS
    ip = np.zeros(8, dtype=np.int32)
    dp = _CONST
    cL, cN = ch.ctypes.data, ch.ctypes.data + 1
    one, zero = dp.ctypes.data, dp.ctypes.data + 16
    private = acc.size > 0
    ldy = y.size // nrhs
    nseq = acc.size // nrhs
    z = np.empty(_SMALL)
    for k in range(order.size):
        f = order[k]
        if k + 1 < order.size:  # the next front's factor columns, while this one is computed
            g = order[k + 1]
            _prefetch(lbuf, l_ptr[g], l_ptr[g] + nf_[g] * no_[g])
        no, nbf, nf, s = no_[f], nb_[f], nf_[f], st[f]
        if nf <= _SMALL:  # compiled loops: y_s <- L11^-1 y_s, tmp = L21 y_s
            l0 = np.uint64(l_ptr[f])
            uno, unb, unf = np.uint64(no), np.uint64(nbf), np.uint64(nf)
            for j in range(np.uint64(nrhs)):
                y0 = j * np.uint64(ldy) + np.uint64(s)
                for i in range(uno):
                    z[i] = 0.0
                for k in range(uno):
                    a = y[y0 + k]
                    ck = l0 + k * unf
                    for i in range(k, uno):
                        z[i] += lbuf[ck + i] * a
                t0 = j * unb
                for i in range(unb):
                    tmp[t0 + i] = 0.0
                for k in range(uno):
                    a = z[k]
                    y[y0 + k] = a
                    ck = l0 + k * unf + uno
                    for i in range(unb):
                        tmp[t0 + i] += lbuf[ck + i] * a
        else:
            ip[0], ip[1], ip[2], ip[3], ip[4] = no, nf, nbf, nrhs, ldy
            L = lbuf.ctypes.data + l_ptr[f] * 8
            ys = y.ctypes.data + s * 8
            _dtrmm(cL, cL, cN, cN, ip.ctypes.data, ip.ctypes.data + 12, one, L, ip.ctypes.data + 4, ys,
                   ip.ctypes.data + 16)
            if nbf > 0:
                _dgemm(cN, cN, ip.ctypes.data + 8, ip.ctypes.data + 12, ip.ctypes.data, one, L + no * 8,
                       ip.ctypes.data + 4, ys, ip.ctypes.data + 16, zero, tmp.ctypes.data, ip.ctypes.data + 8)
        if nbf > 0:
            b0 = bnd_ptr[f]
            for j in range(nrhs):
                for i in range(nbf):
                    v = bnd[b0 + i]
                    if private and seq_slot[v] >= 0:
                        acc[j * nseq + seq_slot[v]] += tmp[j * nbf + i]
                    else:
                        y[j * ldy + v] -= tmp[j * nbf + i]


@nb.njit(**_FAST)
def _backward_run(order, st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs, tmp):
    """Backward substitution L^T X = Z over the fronts of ``order`` (processed in reverse), in place
    (``y`` as in `_forward_run`)."""
    ch = _CHARS
    ip = np.zeros(8, dtype=np.int32)
    dp = _CONST
    cL, cN, cT = ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 2
    one, mone = dp.ctypes.data, dp.ctypes.data + 8
    ldy = y.size // nrhs
    for k in range(order.size - 1, -1, -1):
        f = order[k]
        if k > 0:  # the next front's factor columns, while this one is computed
            g = order[k - 1]
            _prefetch(lbuf, l_ptr[g], l_ptr[g] + nf_[g] * no_[g])
        no, nbf, nf, s = no_[f], nb_[f], nf_[f], st[f]
        if nf <= _SMALL:  # compiled loops: y_s <- L11^-T (y_s - L21^T y_B)
            l0 = np.uint64(l_ptr[f])
            uno, unb, unf = np.uint64(no), np.uint64(nbf), np.uint64(nf)
            b0 = np.uint64(bnd_ptr[f])
            for j in range(np.uint64(nrhs)):
                y0 = j * np.uint64(ldy)
                ys = y0 + np.uint64(s)
                for i in range(unb):
                    tmp[i] = y[y0 + np.uint64(bnd[b0 + i])]
                for kk in range(uno):
                    ck = l0 + kk * unf + uno
                    acc = 0.0
                    for i in range(unb):
                        acc += lbuf[ck + i] * tmp[i]
                    y[ys + kk] -= acc
                for kk in range(uno):  # in place: row kk of L11^-T reads y_s[kk:], which is not yet overwritten
                    ck = l0 + kk * unf
                    acc = 0.0
                    for i in range(kk, uno):
                        acc += lbuf[ck + i] * y[ys + i]
                    y[ys + kk] = acc
            continue
        ip[0], ip[1], ip[2], ip[3], ip[4] = no, nf, nbf, nrhs, ldy
        L = lbuf.ctypes.data + l_ptr[f] * 8
        ys = y.ctypes.data + s * 8
        if nbf > 0:
            b0 = bnd_ptr[f]
            for j in range(nrhs):
                for i in range(nbf):
                    tmp[j * nbf + i] = y[j * ldy + bnd[b0 + i]]
            _dgemm(cT, cN, ip.ctypes.data, ip.ctypes.data + 12, ip.ctypes.data + 8, mone, L + no * 8, ip.ctypes.data + 4,
                   tmp.ctypes.data, ip.ctypes.data + 8, one, ys, ip.ctypes.data + 16)
        _dtrmm(cL, cL, cT, cN, ip.ctypes.data, ip.ctypes.data + 12, one, L, ip.ctypes.data + 4, ys, ip.ctypes.data + 16)


@nb.njit(parallel=True, nogil=True, cache=True)
def _solve(bin_ptr, bin_order, seq_order, seq_vars, seq_slot, st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs,
           tmp, acc):
    """Solves (L L^T) X = Y in place (``y`` as in `_forward_run`): subtrees in parallel, then their
    ancestors, and back."""
    nbins = bin_ptr.size - 1
    ldy = y.size // nrhs
    nseq = seq_vars.size
    for b in nb.prange(nbins):
        acc[b, :] = 0.0
        _forward_run(bin_order[bin_ptr[b] : bin_ptr[b + 1]], st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs,
                     tmp[b], seq_slot, acc[b, : nseq * nrhs])
    for b in range(nbins):
        for j in range(nrhs):
            for k in range(nseq):
                y[j * ldy + seq_vars[k]] -= acc[b, j * nseq + k]
    _forward_run(seq_order, st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs, tmp[0], seq_slot, acc[0, :0])
    _backward_run(seq_order, st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs, tmp[0])
    for b in nb.prange(nbins):
        _backward_run(bin_order[bin_ptr[b] : bin_ptr[b + 1]], st, no_, nb_, nf_, bnd_ptr, bnd, l_ptr, lbuf, y, nrhs,
                      tmp[b])


@nb.njit(**_FLAGS)
def _w_block(L, no, nbf, nf, W, ip):
    """W = L21 L11^-1 (nb x no, column-major, leading dimension nb) from a front's [L11^-1; L21]."""
    ch = _CHARS
    dp = _CONST
    for j in range(no):
        W[j * nbf : (j + 1) * nbf] = L[no + j * nf : nf + j * nf]
    ip[5], ip[6], ip[7] = nbf, no, nf
    _dtrmm(ch.ctypes.data + 3, ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 1, ip.ctypes.data + 20,
           ip.ctypes.data + 24, dp.ctypes.data, L.ctypes.data, ip.ctypes.data + 28, W.ctypes.data, ip.ctypes.data + 20)
    _flush(W, 0, nbf, no, nbf)


@nb.njit(**_FLAGS)
def _prior_parts(st, no_, nb_, nf_, l_ptr, lbuf, w_ptr, prior_w, lam_ptr, prior_lam):
    """W = L21 L11^-1 and L11^-T L11^-1 of every front of a prior factor (for `_selinv_run`)."""
    ch = _CHARS
    ip = np.zeros(8, dtype=np.int32)
    for f in range(st.size):
        no, nbf, nf = no_[f], nb_[f], nf_[f]
        L = lbuf[l_ptr[f] : l_ptr[f] + nf * no]
        lam = prior_lam[lam_ptr[f] : lam_ptr[f] + no * no]
        for j in range(no):
            for i in range(j, no):
                lam[i + j * no] = L[i + j * nf]
        ip[0], ip[1] = no, 0
        _dlauum(ch.ctypes.data, ip.ctypes.data, lam.ctypes.data, ip.ctypes.data, ip.ctypes.data + 4)
        if nbf > 0:
            _w_block(L, no, nbf, nf, prior_w[w_ptr[f] : w_ptr[f] + nbf * no], ip)


@nb.njit(**_FAST)
def _leaf_diagonal(L, S, no, nbf, nf, W, diag):
    """diag(Sigma_JJ) of a leaf front: diag(L11^-T L11^-1) + diag(W^T Sigma_BB W), W = L21 L11^-1.

    ``L`` is the front's [L11^-1; L21], ``S`` its covariance front with Sigma_BB in place. The
    same quantities as the BLAS path (dtrmm, dsymm), in compiled loops: the quadratic forms use
    the lower triangle of Sigma_BB once (half of dsymm's products), and there is no call overhead.
    """
    uno, unb, unf = np.uint64(no), np.uint64(nbf), np.uint64(nf)
    _w_columns(L, no, nbf, nf, W)
    for j in range(uno):
        acc = 0.0
        for i in range(j, uno):
            acc += L[i + j * unf] * L[i + j * unf]
        diag[j] = acc
    for c in range(unb):  # w^T Sigma_BB w from the lower triangle, column c of Sigma_BB at a time
        sc = uno + (uno + c) * unf
        d = S[sc + c]
        for j in range(uno):
            wj = j * unb
            acc = 0.0
            for i in range(c + np.uint64(1), unb):
                acc += S[sc + i] * W[wj + i]
            diag[j] += W[wj + c] * (d * W[wj + c] + 2.0 * acc)


@nb.njit(**_FAST)
def _w_columns(L, no, nbf, nf, W):
    """W = L21 L11^-1 (nb x no, column-major, leading dimension nb) from a front's [L11^-1; L21], by axpys."""
    uno, unb, unf = np.uint64(no), np.uint64(nbf), np.uint64(nf)
    for j in range(uno):
        wj = j * unb
        for i in range(unb):
            W[wj + i] = 0.0
        k = j
        while k + np.uint64(4) <= uno:  # four columns of L21 per pass over W's column
            a0, a1 = L[k + j * unf], L[k + np.uint64(1) + j * unf]
            a2, a3 = L[k + np.uint64(2) + j * unf], L[k + np.uint64(3) + j * unf]
            l0 = uno + k * unf
            l1 = l0 + unf
            l2 = l1 + unf
            l3 = l2 + unf
            for i in range(unb):
                W[wj + i] += (L[l0 + i] * a0 + L[l1 + i] * a1) + (L[l2 + i] * a2 + L[l3 + i] * a3)
            k += np.uint64(4)
        while k < uno:
            a = L[k + j * unf]
            lk = uno + k * unf
            for i in range(unb):
                W[wj + i] += L[lk + i] * a
            k += np.uint64(1)
        for i in range(unb):
            if abs(W[wj + i]) < _TINY:
                W[wj + i] = 0.0


@nb.njit(**_FAST)
def _lam_lower(L, S, no, nf):
    """Lower triangle of L11^-T L11^-1 into the S_JJ block of ``S`` (both nf x nf-strided fronts), as
    dot products of the columns of the stored L11^-1 (what dlauum computes, without call overhead)."""
    uno, unf = np.uint64(no), np.uint64(nf)
    for j in range(uno):
        cj = j * unf
        for i in range(j, uno):
            ci = i * unf
            acc = 0.0
            for k in range(i, uno):
                acc += L[ci + k] * L[cj + k]
            S[cj + i] = acc


@nb.njit(**_FAST)
def _small_cov(S, no, nbf, nf, W):
    """Sigma_BJ = -Sigma_BB W and the lower triangle of Sigma_JJ = L11^-T L11^-1 - Sigma_BJ^T W, in place.

    ``S`` is a covariance front holding Sigma_BB (lower triangle) and L11^-T L11^-1 (lower) in
    Sigma_JJ; ``W`` = L21 L11^-1 (nb x no, leading dimension nb). The products of dsymm and dgemm
    in compiled loops, for the small fronts where those calls' overhead dominates: Sigma_BB is
    mirrored into its upper triangle, so that Sigma_BJ is built from axpys of whole columns (loops
    of one length, which vectorise) rather than from the triangle's ragged ones.
    """
    uno, unb, unf = np.uint64(no), np.uint64(nbf), np.uint64(nf)
    for c in range(unb):
        sc = uno + (uno + c) * unf
        for i in range(c + np.uint64(1), unb):
            S[uno + c + (uno + i) * unf] = S[sc + i]
    s0 = uno + uno * unf
    for j in range(uno):  # column j of Sigma_BJ, four columns of Sigma_BB per pass over it
        bj = uno + j * unf
        wj = j * unb
        for i in range(unb):
            S[bj + i] = 0.0
        c = np.uint64(0)
        while c + np.uint64(4) <= unb:
            w0, w1, w2, w3 = W[wj + c], W[wj + c + np.uint64(1)], W[wj + c + np.uint64(2)], W[wj + c + np.uint64(3)]
            c0 = s0 + c * unf
            c1 = c0 + unf
            c2 = c1 + unf
            c3 = c2 + unf
            for i in range(unb):
                S[bj + i] -= (S[c0 + i] * w0 + S[c1 + i] * w1) + (S[c2 + i] * w2 + S[c3 + i] * w3)
            c += np.uint64(4)
        while c < unb:
            wc = W[wj + c]
            c0 = s0 + c * unf
            for i in range(unb):
                S[bj + i] -= S[c0 + i] * wc
            c += np.uint64(1)
    for j in range(uno):  # Sigma_JJ: four rows per pass over W's column j
        wj = j * unb
        i = j
        while i + np.uint64(4) <= uno:
            b0 = uno + i * unf
            b1 = b0 + unf
            b2 = b1 + unf
            b3 = b2 + unf
            acc0 = acc1 = acc2 = acc3 = 0.0
            for k in range(unb):
                w = W[wj + k]
                acc0 += S[b0 + k] * w
                acc1 += S[b1 + k] * w
                acc2 += S[b2 + k] * w
                acc3 += S[b3 + k] * w
            S[i + j * unf] -= acc0
            S[i + np.uint64(1) + j * unf] -= acc1
            S[i + np.uint64(2) + j * unf] -= acc2
            S[i + np.uint64(3) + j * unf] -= acc3
            i += np.uint64(4)
        while i < uno:
            bi = uno + i * unf
            acc = 0.0
            for k in range(unb):
                acc += S[bi + k] * W[wj + k]
            S[i + j * unf] -= acc
            i += np.uint64(1)

@nb.njit(**_FAST)
def _readout_forms(S, nf, r0, r1, ro_out, ro_pos, ro_wgt, out):
    """out[ro_out[r]] = w^T Sigma w for the read-outs r0 .. r1 of a covariance front ``S`` (lower triangle).

    Each form as sum_a w_a (w_a Sigma_aa + 2 sum_{b<a} w_b Sigma_ab): every distinct entry read once.
    """
    unf = np.uint64(nf)
    nw = ro_pos.shape[1]
    for r in range(r0, r1):
        acc = 0.0
        for a in range(nw):
            pa = np.uint64(ro_pos[r, a])
            t = 0.0
            for b in range(a):
                pb = np.uint64(ro_pos[r, b])
                t += ro_wgt[r, b] * (S[pa + pb * unf] if pa >= pb else S[pb + pa * unf])
            wa = ro_wgt[r, a]
            acc += wa * (wa * S[pa + pa * unf] + 2.0 * t)
        out[ro_out[r]] = acc


@nb.njit(**_FLAGS)
def _selinv_run(order, parent, st, no_, nb_, nf_, ea_ptr, ea_pos, l_ptr, lbuf, sig_off, sig, touched, prior_w,
                w_ptr, prior_lam, lam_ptr, children_ptr, work, diag, ro_ptr, ro_out, ro_pos, ro_wgt, out):
    """Selected inverse over the fronts of ``order`` (processed in reverse, i.e. pre-order):
    diag(P^-1) and the read-out quadratic forms. Fronts that no observation reaches (``touched``
    non-empty and False) take W and L11^-T L11^-1 from the prior factor. A leaf front without
    read-outs needs only the diagonal of its Sigma_JJ (no child reads its covariance front):
    diag(L11^-T L11^-1) - diag(Sigma_BJ^T W), without the no x no products."""
    ch = _CHARS
    ip = np.zeros(8, dtype=np.int32)
    dp = _CONST
    cL, cN, cT = ch.ctypes.data, ch.ctypes.data + 1, ch.ctypes.data + 2
    one, mone, zero = dp.ctypes.data, dp.ctypes.data + 8, dp.ctypes.data + 16
    nw = ro_pos.shape[1]
    for k in range(order.size - 1, -1, -1):
        f = order[k]
        if k > 0:  # the next front's factor columns and read-out maps, while this one is computed
            g = order[k - 1]
            _prefetch(lbuf, l_ptr[g], l_ptr[g] + nf_[g] * no_[g])
            _prefetch(ro_pos, ro_ptr[g] * nw, ro_ptr[g + 1] * nw)
            _prefetch(ro_wgt, ro_ptr[g] * nw, ro_ptr[g + 1] * nw)
            _prefetch(ro_out, ro_ptr[g], ro_ptr[g + 1])
        no, nbf, nf, s = no_[f], nb_[f], nf_[f], st[f]
        S = sig[sig_off[f] : sig_off[f] + nf * nf]
        L = lbuf[l_ptr[f] : l_ptr[f] + nf * no]
        if nbf > 0:  # Sigma_BB from the parent's covariance front
            p = parent[f]
            nfp = nf_[p]
            P = sig[sig_off[p] : sig_off[p] + nfp * nfp]
            e0 = np.uint64(ea_ptr[f])
            unb, uno, unf, unfp = np.uint64(nbf), np.uint64(no), np.uint64(nf), np.uint64(nfp)
            for jj in range(unb):
                cj = np.uint64(ea_pos[e0 + jj]) * unfp
                dst = uno + (uno + jj) * unf
                for ii in range(jj, unb):
                    S[dst + ii] = P[np.uint64(ea_pos[e0 + ii]) + cj]
        ip[0], ip[1], ip[2], ip[3], ip[4] = no, nf, nbf, 0, nbf
        prior_front = touched.size > 0 and not touched[f]
        if (not prior_front and children_ptr[f + 1] == children_ptr[f] and ro_ptr[f + 1] == ro_ptr[f]
                and nbf > 0 and nf <= _SMALL):  # a small leaf without read-outs: the diagonal only, compiled
            _leaf_diagonal(L, S, no, nbf, nf, work, diag[s : s + no])
            continue
        if (not prior_front and children_ptr[f + 1] == children_ptr[f] and ro_ptr[f + 1] == ro_ptr[f]
                and nbf > 0):  # a leaf without read-outs: the diagonal only
            _w_block(L, no, nbf, nf, work, ip)
            sbj = S.ctypes.data + no * 8
            _dsymm(cL, cL, ip.ctypes.data + 8, ip.ctypes.data, mone, S.ctypes.data + (no + no * nf) * 8,
                   ip.ctypes.data + 4, work.ctypes.data, ip.ctypes.data + 16, zero, sbj, ip.ctypes.data + 4)
            for j in range(no):
                acc = 0.0
                for i in range(j, no):
                    acc += L[i + j * nf] * L[i + j * nf]
                for i in range(nbf):
                    acc -= S[no + i + j * nf] * work[i + j * nbf]
                diag[s + j] = acc
            continue
        w_small = work  # W of a small front (one call of _small_cov below: its loops compiled once)
        if prior_front:  # prior front: W and L11^-T L11^-1 are cached
            lam0 = lam_ptr[f]
            for j in range(no):
                for i in range(j, no):
                    S[i + j * nf] = prior_lam[lam0 + i + j * no]
            wp = prior_w[w_ptr[f] :].ctypes.data
            w_small = prior_w[w_ptr[f] : w_ptr[f] + nbf * no]
        elif nf <= _SMALL:  # compiled loops instead of dlauum, dtrmm, dsymm and dgemm
            _lam_lower(L, S, no, nf)
            _w_columns(L, no, nbf, nf, work)
        else:
            for j in range(no):
                for i in range(j, no):
                    S[i + j * nf] = L[i + j * nf]
            _dlauum(cL, ip.ctypes.data, S.ctypes.data, ip.ctypes.data + 4, ip.ctypes.data + 12)  # L11^-T L11^-1
            wp = work.ctypes.data
            if nbf > 0:
                _w_block(L, no, nbf, nf, work, ip)
        if nf <= _SMALL:
            _small_cov(S, no, nbf, nf, w_small)
        if nbf > 0 and nf > _SMALL:
            sbj = S.ctypes.data + no * 8
            _dsymm(cL, cL, ip.ctypes.data + 8, ip.ctypes.data, mone, S.ctypes.data + (no + no * nf) * 8,
                   ip.ctypes.data + 4, wp, ip.ctypes.data + 16, zero, sbj, ip.ctypes.data + 4)
            _dgemm(cT, cN, ip.ctypes.data, ip.ctypes.data, ip.ctypes.data + 8, mone, sbj, ip.ctypes.data + 4,
                   wp, ip.ctypes.data + 16, one, S.ctypes.data, ip.ctypes.data + 4)
        _flush(S, 0, nf, no, nf)
        for j in range(no):
            diag[s + j] = S[j * (nf + 1)]
        _readout_forms(S, nf, ro_ptr[f], ro_ptr[f + 1], ro_out, ro_pos, ro_wgt, out)


@nb.njit(**_FLAGS)
def _touched(order, parent, st, no_, prec):
    """Fronts that an observation (prec > 0) reaches: those owning one, and their ancestors."""
    out = np.zeros(order.size, dtype=np.bool_)
    for f in order:
        if not out[f]:
            for i in range(st[f], st[f] + no_[f]):
                if prec[i] > 0.0:
                    out[f] = True
                    break
        if out[f] and parent[f] >= 0:
            out[parent[f]] = True
    return out


@nb.njit(parallel=True, nogil=True, cache=True)
def _factor_bins(bin_ptr, bin_order, st, no_, nb_, nf_, children_ptr, children, ea_ptr, ea_pos, asm_ptr,
                 asm_pos, asm_src, qvals, prec, l_ptr, lbuf, upd_off, stack, touched, prior_l, prior_upd, u_ptr,
                 save, work):
    """Factorises the independent subtrees, one bin per thread; returns the first failing front or -1."""
    nbins = bin_ptr.size - 1
    bad = np.full(nbins, -1, dtype=np.int64)
    for b in nb.prange(nbins):
        bad[b] = _factor_run(
            bin_order[bin_ptr[b] : bin_ptr[b + 1]], st, no_, nb_, nf_, children_ptr, children, ea_ptr, ea_pos,
            asm_ptr, asm_pos, asm_src, qvals, prec, l_ptr, lbuf, upd_off, stack, touched, prior_l, prior_upd, u_ptr,
            save, work[b])
    return bad.max()


@nb.njit(parallel=True, nogil=True, cache=True)
def _selinv_bins(bin_ptr, bin_order, parent, st, no_, nb_, nf_, ea_ptr, ea_pos, l_ptr, lbuf, sig_off, sig,
                 touched, prior_w, w_ptr, prior_lam, lam_ptr, children_ptr, work, diag, ro_ptr, ro_out, ro_pos, ro_wgt,
                 out):
    """Selected inverse of the independent subtrees (their ancestors done), one bin per thread."""
    for b in nb.prange(bin_ptr.size - 1):
        _selinv_run(bin_order[bin_ptr[b] : bin_ptr[b + 1]], parent, st, no_, nb_, nf_, ea_ptr, ea_pos, l_ptr, lbuf,
                    sig_off, sig, touched, prior_w, w_ptr, prior_lam, lam_ptr, children_ptr, work[b], diag, ro_ptr,
                    ro_out, ro_pos, ro_wgt, out)


_POOL_LOCK = threading.Lock()
_RUN_LOCK = threading.Lock()


@contextmanager
def numeric_section():
    """One numeric phase at a time per process, with single-threaded BLAS.

    Each phase already uses every numba thread, so concurrent callers (threads of a Dask worker,
    a viewer's server) lose nothing by waiting; it also keeps numba's parallel regions un-nested,
    which its workqueue threading layer requires. A thread that runs its parallel regions on one
    numba thread (``numba.set_num_threads(1)``: `gpdepth3d.completion.DepthCompleter.map`'s
    workers, one frame each) does not wait when the threading layer is thread-safe (omp, tbb).
    BLAS runs single-threaded inside (one BLAS call per numba thread).
    """
    from .blas_threads import single_threaded_blas

    with _RUN_LOCK if _exclusive() else nullcontext(), single_threaded_blas():
        yield


def _exclusive() -> bool:
    """True when this thread's numeric phase must not overlap another's (see `numeric_section`)."""
    if nb.get_num_threads() > 1:
        return True
    try:
        return nb.threading_layer() == "workqueue"
    except ValueError:  # no parallel region has run yet: the layer is chosen by the first one
        return True


def _post_order(kids: list, roots: list, n: int) -> np.ndarray:
    """(n,) fronts in depth-first post-order (children before parents)."""
    order = np.empty(n, dtype=np.int64)
    k = 0
    stack = [(r, False) for r in reversed(roots)]
    while stack:  # iterative: trees of thousands of levels
        f, done = stack.pop()
        if done:
            order[k] = f
            k += 1
            continue
        stack.append((f, True))
        stack.extend((c, False) for c in reversed(kids[f]))
    return order


def _update_stacks(bins: list, seq: list, kids: list, in_seq: np.ndarray, nbv: np.ndarray) -> tuple[np.ndarray, int]:
    """Offsets of each front's update matrix: one LIFO region per bin, then one for the common ancestors."""
    upd_off = np.zeros(in_seq.size, dtype=np.int64)
    base = 0
    for part in [*bins, seq]:
        top = peak = base
        for f in part:
            own_kids = [c for c in kids[f] if in_seq[c] == in_seq[f]]
            if own_kids:
                top = min(upd_off[c] for c in own_kids)
            upd_off[f] = top
            top += int(nbv[f]) ** 2
            peak = max(peak, top)
        base = peak
    return upd_off, base


def _covariance_stacks(bins: list, seq: list, parent: np.ndarray, in_seq: np.ndarray,
                       nf: np.ndarray) -> tuple[np.ndarray, int]:
    """Offsets of each front's covariance block: a region per common ancestor, then per bin a root-path stack."""
    sig_off = np.zeros(in_seq.size, dtype=np.int64)
    base = 0
    for f in seq:
        sig_off[f] = base
        base += int(nf[f]) ** 2
    for part in bins:
        end = base
        for f in part[::-1]:
            p = parent[f]
            sig_off[f] = base if p < 0 or in_seq[p] else sig_off[p] + int(nf[p]) ** 2
            end = max(end, sig_off[f] + int(nf[f]) ** 2)
        base = end
    return sig_off, base


@dataclass
class FrontTree:
    """Symbolic structure of the elimination: fronts, their variables and buffer offsets.

    Front ``f`` owns variables ``st[f] .. st[f] + no[f]`` and has the boundary variables
    ``bnd[bnd_ptr[f]:bnd_ptr[f + 1]]`` (sorted by their position in the parent front, which is
    ``ea_pos`` at the same offsets). Variables must be numbered so that a front's variables come
    after those of its descendants.
    """

    nvar: int
    st: np.ndarray
    no: np.ndarray
    nb: np.ndarray
    nf: np.ndarray
    parent: np.ndarray
    order: np.ndarray  # post-order (children before parents, subtrees contiguous)
    children_ptr: np.ndarray
    children: np.ndarray
    bnd_ptr: np.ndarray
    bnd: np.ndarray
    ea_pos: np.ndarray
    l_ptr: np.ndarray
    l_size: int
    upd_off: np.ndarray
    stack_size: int
    sig_off: np.ndarray
    sig_size: int
    work_size: int
    front_of: np.ndarray  # (nvar,) owning front of each variable
    bin_ptr: np.ndarray  # fronts of independent subtrees, one bin per thread: bin_order[bin_ptr[b]:bin_ptr[b+1]]
    bin_order: np.ndarray  # (each bin in post-order)
    seq_order: np.ndarray  # their common ancestors, post-order
    seq_vars: np.ndarray  # variables of the common ancestors
    seq_slot: np.ndarray  # (nvar,) index of a variable in seq_vars, -1 for the others

    @classmethod
    def build(cls, st, no, parent, boundaries, nvar: int, threads: int | None = None) -> "FrontTree":
        """Builds the structure from each front's own range, parent (-1 = root) and boundary variables.

        ``threads`` (default: numba's thread count) independent groups of subtrees are formed for
        the parallel part of the factorisation and of the selected inversion.
        """
        st = np.asarray(st, dtype=np.int64)
        no = np.asarray(no, dtype=np.int64)
        parent = np.asarray(parent, dtype=np.int64)
        n = st.size
        kids: list[list[int]] = [[] for _ in range(n)]
        roots = []
        for f in range(n):
            (kids[parent[f]] if parent[f] >= 0 else roots).append(f)
        order = _post_order(kids, roots, n)
        front_of = np.full(nvar, -1, dtype=np.int64)
        for f in range(n):
            front_of[st[f] : st[f] + no[f]] = f
        if np.any(front_of < 0):
            raise RuntimeError("internal error: a variable belongs to no front")
        threads = nb.get_num_threads() if threads is None else int(threads)
        # boundaries sorted by their position in the parent front (pre-order: parents first)
        bnd = [np.asarray(b, dtype=np.int64) for b in boundaries]
        ea = [np.zeros(0, dtype=np.int64)] * n
        where = np.full(nvar, -1, dtype=np.int64)
        for f in order[::-1]:
            if not kids[f]:
                continue
            where[st[f] : st[f] + no[f]] = np.arange(no[f])
            where[bnd[f]] = no[f] + np.arange(bnd[f].size)
            for c in kids[f]:
                pos = where[bnd[c]]
                if np.any(pos < 0):
                    raise RuntimeError("internal error: a boundary variable is not in the parent front")
                srt = np.argsort(pos, kind="stable")
                bnd[c], ea[c] = bnd[c][srt], pos[srt]
            where[st[f] : st[f] + no[f]] = -1
            where[bnd[f]] = -1
        nbv = np.array([b.size for b in bnd], dtype=np.int64)
        nf = no + nbv
        for f in range(n):
            if parent[f] < 0 and nbv[f]:
                raise RuntimeError("internal error: a root front has a boundary")
        bnd_ptr = np.concatenate([[0], np.cumsum(nbv)])
        l_ptr = np.concatenate([[0], np.cumsum(nf * no)])
        bins, seq = _split(order, kids, roots, no, nbv, threads)
        in_seq = np.zeros(n, dtype=bool)
        in_seq[seq] = True
        upd_off, stack_size = _update_stacks(bins, seq, kids, in_seq, nbv)
        sig_off, base = _covariance_stacks(bins, seq, parent, in_seq, nf)
        children_ptr = np.concatenate([[0], np.cumsum([len(c) for c in kids])]).astype(np.int64)
        children = np.array([c for cs in kids for c in cs], dtype=np.int64)
        bin_ptr = np.concatenate([[0], np.cumsum([len(b) for b in bins])]).astype(np.int64)
        seq_vars = np.concatenate([np.arange(st[f], st[f] + no[f]) for f in seq] or [np.zeros(0, np.int64)])
        seq_slot = np.full(nvar, -1, dtype=np.int64)
        seq_slot[seq_vars] = np.arange(seq_vars.size)
        return cls(
            nvar=int(nvar), st=st, no=no, nb=nbv, nf=nf, parent=parent, order=order,
            children_ptr=children_ptr, children=children, bnd_ptr=bnd_ptr.astype(np.int64),
            bnd=np.concatenate(bnd) if n else np.zeros(0, np.int64),
            ea_pos=np.concatenate(ea) if n else np.zeros(0, np.int64),
            l_ptr=l_ptr.astype(np.int64), l_size=int(l_ptr[-1]), upd_off=upd_off, stack_size=max(stack_size, 1),
            sig_off=sig_off, sig_size=int(max(1, base)),
            work_size=int(max(1, (nf * nf).max(), (nbv * no).max())), front_of=front_of,
            bin_ptr=bin_ptr, bin_order=np.array([f for b in bins for f in b], dtype=np.int64),
            seq_order=np.asarray(seq, dtype=np.int64), seq_vars=seq_vars.astype(np.int64), seq_slot=seq_slot,
        )

    @property
    def prior_bytes(self) -> int:
        """Memory of a `PriorFactor` of this tree (bytes)."""
        return 8 * (self.l_size + int(np.sum(self.nb * self.nb + self.nb * self.no + self.no * self.no)))

    def touched_share(self, prec: np.ndarray) -> float:
        """Share of the fronts that an observation (prec > 0, per variable) reaches."""
        return float(np.mean(_touched(self.order, self.parent, self.st, self.no, np.asarray(prec, np.float64))))

    def acquire(self) -> "_Workspace":
        """Buffers for a factorisation: reused across frames (no allocation, no page faults)."""
        with _POOL_LOCK:
            pool = self.__dict__.setdefault("_pool", [])
            if pool:
                return pool.pop()
        return _Workspace(self)

    def release(self, ws: "_Workspace") -> None:
        """Returns buffers taken by `acquire` (a factor does so when it is freed)."""
        with _POOL_LOCK:
            pool = self.__dict__.setdefault("_pool", [])
            if len(pool) < 2:
                pool.append(ws)

    def positions(self, fronts: np.ndarray, variables: np.ndarray) -> np.ndarray:
        """Positions of ``variables`` in the given ``fronts`` (same shapes; each must be in its front)."""
        fronts = np.asarray(fronts, dtype=np.int64)
        v = np.asarray(variables, dtype=np.int64)
        out = v - self.st[fronts]
        own = (out >= 0) & (out < self.no[fronts])
        if not np.all(own):
            keys = self._bnd_keys()
            q = fronts[~own] * (self.nvar + 1) + v[~own]
            i = np.searchsorted(keys[0], q)
            if np.any(i >= keys[0].size) or np.any(keys[0][np.minimum(i, keys[0].size - 1)] != q):
                raise RuntimeError("internal error: variable not in front")
            out[~own] = keys[1][i]
        return out

    def _bnd_keys(self):
        if not hasattr(self, "_keys"):
            f = np.repeat(np.arange(self.st.size), self.nb)
            local = np.arange(self.bnd.size) - self.bnd_ptr[f] + self.no[f]
            key = f * (self.nvar + 1) + self.bnd
            srt = np.argsort(key)
            self._keys = (key[srt], local[srt])
        return self._keys

    def assembly(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Assembly map of the symmetric matrix entries (rows[k], cols[k]) (each pair once).

        Returns (ptr, flat positions, source index k) grouped by front: the entry goes to the
        front owning the earlier of its two variables, in the lower triangle.
        """
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
        f = self.front_of[lo]
        pa = self.positions(f, lo)
        pb = self.positions(f, hi)
        r, c = np.maximum(pa, pb), np.minimum(pa, pb)
        flat = r + c * self.nf[f]
        srt = np.argsort(f, kind="stable")
        ptr = np.searchsorted(f[srt], np.arange(self.st.size + 1)).astype(np.int64)
        return ptr, flat[srt], srt.astype(np.int64)


def _lpt(tasks: list, sub: np.ndarray, threads: int) -> tuple[float, list[list[int]]]:
    """Longest-processing-time-first assignment of subtrees to ``threads`` bins: (largest load, groups)."""
    loads = [0.0] * max(threads, 1)
    groups: list[list[int]] = [[] for _ in loads]
    for f in sorted(tasks, key=lambda f: -sub[f]):
        b = int(np.argmin(loads))
        loads[b] += sub[f]
        groups[b].append(f)
    return max(loads), groups


def _split(order, kids, roots, no, nbv, threads: int):
    """Groups subtrees into ``threads`` bins of similar work (longest-processing-time first).

    The subtrees are found by splitting the heaviest one into its children, step by step; the
    step kept is the one with the least modelled time, the fronts split off (which run on one
    thread, after the bins) plus the largest bin: with 2 threads on a pixel grid that is
    usually the root alone, with two balanced halves below it.

    Returns (bins: list of post-ordered front lists, seq: post-ordered common ancestors).
    """
    n = order.size
    cost = no**3 / 3.0 + no**2 * nbv + no * nbv**2 + (no + nbv) ** 2 * 8.0
    sub = cost.astype(np.float64).copy()
    size = np.ones(n, dtype=np.int64)
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    for f in order:
        for c in kids[f]:
            sub[f] += sub[c]
            size[f] += size[c]
    tasks = list(roots)
    best, groups = _lpt(tasks, sub, threads)
    if threads > 1:
        ancestors = 0.0
        for _ in range(16 * threads):
            heavy = max(tasks, key=lambda f: sub[f])
            if not kids[heavy]:
                break
            tasks.remove(heavy)
            tasks.extend(kids[heavy])
            ancestors += cost[heavy]
            span, g = _lpt(tasks, sub, threads)
            if ancestors + span < best:
                best, groups = ancestors + span, g
    bins = []
    in_task = np.zeros(n, dtype=bool)
    for g in groups:
        segs = [order[pos[f] - size[f] + 1 : pos[f] + 1] for f in sorted(g, key=lambda f: pos[f])]
        b = np.concatenate(segs) if segs else np.zeros(0, np.int64)
        in_task[b] = True
        bins.append([int(f) for f in b])
    seq = [int(f) for f in order if not in_task[f]]
    return bins, seq


class FrontalFactor:
    """Cholesky factor of ``A = Q / scale2 + diag(prec)`` over a `FrontTree` (CPU, float64).

    The factorisation is of ``scale2 * A = Q + scale2 diag(prec)``, so that the fronts of ``Q``
    alone do not depend on the frame's scale: a `PriorFactor` of Q then supplies every front that
    no observation reaches (in the residual formulation with sparse points, most of them).

    Args:
        tree: The symbolic structure.
        asm: ``(ptr, positions, sources)`` from `FrontTree.assembly` for the entries of Q.
        qvals: Values of those entries.
        prec: (nvar,) diagonal added to A (observation precisions; 0 where unobserved).
        scale2: Divides Q (the prior variance s^2 of a unit-variance prior precision).
        prior: Factor of Q alone (same tree and values) whose unreached fronts are reused.
    """

    def __init__(self, tree: FrontTree, asm, qvals: np.ndarray, prec: np.ndarray, *, scale2: float = 1.0,
                 prior: "PriorFactor | None" = None):
        if not np.isfinite(scale2) or scale2 <= 0:
            raise ValueError(f"scale2 must be finite and > 0, got {scale2}")
        self.tree = tree
        self.scale2 = float(scale2)
        t = tree
        self._ws = ws = tree.acquire()
        self.lbuf, stack, work = ws.lbuf, ws.stack, ws.work
        q = np.ascontiguousarray(qvals, dtype=np.float64)
        d = np.ascontiguousarray(prec, dtype=np.float64) * self.scale2
        if prior is not None:
            if prior.tree is not t:
                raise ValueError("the prior factor belongs to another tree")
            touched = _touched(t.order, t.parent, t.st, t.no, d)
            skip = (touched, prior.lbuf, prior.upd, prior.u_ptr)
            self._reuse = (touched, prior.w, prior.w_ptr, prior.lam, prior.lam_ptr)
        else:
            skip = (np.zeros(0, np.bool_), np.zeros(0), np.zeros(0), t.l_ptr)
            self._reuse = (np.zeros(0, np.bool_), np.zeros(0), t.l_ptr, np.zeros(0), t.l_ptr)
        common = (t.st, t.no, t.nb, t.nf, t.children_ptr, t.children, t.bnd_ptr, t.ea_pos, asm[0], asm[1], asm[2], q, d,
                  t.l_ptr, self.lbuf, t.upd_off, stack, *skip, False)
        with numeric_section():
            bad = _factor_bins(t.bin_ptr, t.bin_order, *common, work)
            if bad < 0:
                bad = _factor_run(t.seq_order, *common, work[0])
        if bad >= 0:
            raise np.linalg.LinAlgError("posterior precision not positive definite (check precisions and scales)")
        self._logdet: float | None = None

    @property
    def logdet(self) -> float:
        """log det A (computed from the stored factor on first use: most solves never ask)."""
        if self._logdet is None:
            t = self.tree
            self._logdet = float(_logdet(t.no, t.nf, t.l_ptr, self.lbuf)) - t.nvar * np.log(self.scale2)
        return self._logdet

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x = A^-1 b for b (nvar,) or (nvar, r): r right-hand sides in one pass over the factor."""
        t = self.tree
        b = np.asarray(b, dtype=np.float64)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        y = np.ascontiguousarray(b.T, dtype=np.float64).ravel() * self.scale2  # column after column
        nbins = t.bin_ptr.size - 1
        tmp = np.empty((nbins, max(1, int(t.nb.max(initial=0))) * nrhs))
        acc = np.empty((nbins, max(1, t.seq_vars.size * nrhs)))
        with numeric_section():
            _solve(t.bin_ptr, t.bin_order, t.seq_order, t.seq_vars, t.seq_slot, t.st, t.no, t.nb, t.nf, t.bnd_ptr,
                   t.bnd, t.l_ptr, self.lbuf, y, nrhs, tmp, acc)
        return y if b.ndim == 1 else y.reshape(nrhs, -1).T

    def selected_inverse(self, readout=None) -> tuple[np.ndarray, np.ndarray | None]:
        """diag(A^-1) (nvar,) and, given a read-out ``(ptr, out index, positions, weights, n_out)``,
        the quadratic forms w^T Sigma w of each output (all its positions inside one front)."""
        t = self.tree
        sig, work = self._ws.sig, self._ws.work
        diag = np.empty(t.nvar)
        if readout is None:
            ro = (np.zeros(t.st.size + 1, np.int64), np.zeros(0, np.int64), np.zeros((0, 1), np.int64),
                  np.zeros((0, 1)), 0)
        else:
            ro = readout
        out = np.empty(ro[4])
        common = (t.parent, t.st, t.no, t.nb, t.nf, t.bnd_ptr, t.ea_pos, t.l_ptr, self.lbuf, t.sig_off, sig,
                  *self._reuse, t.children_ptr)
        ro_args = (diag, ro[0], ro[1], ro[2], ro[3], out)
        with numeric_section():
            _selinv_run(t.seq_order, *common, work[0], *ro_args)
            _selinv_bins(t.bin_ptr, t.bin_order, *common, work, *ro_args)
        diag *= self.scale2
        out *= self.scale2
        return diag, (out if readout is not None else None)

    def __del__(self):
        ws, self._ws = getattr(self, "_ws", None), None
        if ws is not None:
            self.tree.release(ws)


class PriorFactor:
    """The fronts of the prior precision Q alone (no observation): L, update, W = L21 L11^-1 and
    L11^-T L11^-1 of every front.

    Kept per tree and kernel; a `FrontalFactor` copies the fronts that no observation of its
    frame reaches instead of recomputing them, and its selected inverse skips their dlauum and
    dtrmm. Memory: `FrontTree.prior_bytes`.
    """

    def __init__(self, tree: FrontTree, asm, qvals: np.ndarray):
        self.tree = t = tree
        nb2 = t.nb * t.nb
        self.u_ptr = np.concatenate([[0], np.cumsum(nb2)]).astype(np.int64)
        self.upd = np.empty(max(1, int(self.u_ptr[-1])))
        self.lbuf = np.empty(t.l_size)
        stack = np.empty(t.stack_size)
        work = np.empty((t.bin_ptr.size - 1, t.work_size))
        q = np.ascontiguousarray(qvals, dtype=np.float64)
        common = (t.st, t.no, t.nb, t.nf, t.children_ptr, t.children, t.bnd_ptr, t.ea_pos, asm[0], asm[1], asm[2], q,
                  np.zeros(t.nvar), t.l_ptr, self.lbuf, t.upd_off, stack, np.zeros(0, np.bool_), self.lbuf, self.upd,
                  self.u_ptr, True)
        with numeric_section():
            bad = _factor_bins(t.bin_ptr, t.bin_order, *common, work)
            if bad < 0:
                bad = _factor_run(t.seq_order, *common, work[0])
        if bad >= 0:
            raise np.linalg.LinAlgError("prior precision not positive definite")
        self.w_ptr = np.concatenate([[0], np.cumsum(t.nb * t.no)]).astype(np.int64)
        self.lam_ptr = np.concatenate([[0], np.cumsum(t.no * t.no)]).astype(np.int64)
        self.w = np.empty(max(1, int(self.w_ptr[-1])))
        self.lam = np.empty(max(1, int(self.lam_ptr[-1])))
        with numeric_section():
            _prior_parts(t.st, t.no, t.nb, t.nf, t.l_ptr, self.lbuf, self.w_ptr, self.w, self.lam_ptr, self.lam)


class _Workspace:
    """Buffers of one factorisation (the factor itself, the update stack, the covariance fronts)."""

    def __init__(self, tree: FrontTree):
        self.lbuf = np.empty(tree.l_size)
        self.stack = np.empty(tree.stack_size)
        self.work = np.empty((tree.bin_ptr.size - 1, tree.work_size))
        self.sig = np.empty(tree.sig_size)
