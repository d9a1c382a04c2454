"""Block Gauss-Seidel over contacts (docs/maths.md section 6), matrix-free or on the assembled W.

One sweep visits the contacts in a fixed order; contact i solves its 3x3 local problem

    u_i = W_ii r_i + c_i,   c_i = b_i + sum_{j != i} W_ij r_j = u_i(r) - W_ii r_i

exactly (local.py) with the others fixed.  Two ways to get u_i(r):

* "assembled":   W's upper block triangle (blocks.UpperBlockDelassus): u_i = b_i + acc_i + sum_{j>=i} W_ij r_j,
                 acc_i = sum_{j<i} W_ji^T r_j scattered by the earlier rows of the same sweep (each block
                 is read once per sweep: about 45 % less memory traffic than full block rows);
* "matrix_free": keep v = D H^T r (n,); u_i = H_i v + 2 gamma r_i + b_i, and after the update
                 v += (D H_i^T) (r_i_new - r_i_old)  (HD rows packed per contact, blocks.PackedRows).

Over-relaxation (SOC law only): contact i instead takes the W_ii-metric projection onto K_mu of the
relaxed unconstrained step r_i - omega W_ii^{-1} u_i, i.e. the local problem with
c'_i = omega c_i + (omega - 1) W_ii r_i  (omega = 1 is plain Gauss-Seidel).

The sweep map r -> G(r) is Anderson-accelerated (anderson.py): after a few plain sweeps, the next
iterate mixes the last few (r, G(r)) pairs; the returned r is always a sweep's output.  On the hair
problems this cuts the sweeps 3-4x (see docs/solvers.md).  On the assembled W (SOC law), subspace Newton
steps on the faces the sweeps have identified (subspace_newton.py) are tried at the residual checks from
sweep 20 on: another 3-6x fewer sweeps on the shared generator's problems (issue 22).  On the Coulomb law
(either form), the contacts still over the tolerance and the contacts on their strands are solved together
by Levenberg-Marquardt (cluster_newton.py) at the residual checks from sweep 20 on (issue 15).

Deterministic (sequential, fixed order).  Stops when the residual of residual.py is <= tol, checked
every few sweeps on the exact u = W r + b.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit

from . import residual as _res
from .anderson import AndersonMixer
from .blocks import UpperBlockDelassus, assemble_upper, dof_strands, upper_block_matvec
from .cluster_newton import ClusterNewton
from .cones import COULOMB, SOC, law_code
from .subspace_newton import SubspaceNewton
from .local import FAILED, LOCAL_TOL, NEWTON_MAX_ITER, normalize_block, solve_block

# numba fastmath flags: fused multiply-add, reciprocal division, no signed zeros
_FM = {"contract", "arcp", "nsz"}


# ----------------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", fastmath=_FM)
def _pack_sym6(a, out):
    """A row-major 3x3 (9-vector) as the symmetric 6-vector (a00, a01, a02, a11, a12, a22), off-diagonals averaged."""
    out[0] = a[0]
    out[1] = 0.5 * (a[1] + a[3])
    out[2] = 0.5 * (a[2] + a[6])
    out[3] = a[4]
    out[4] = 0.5 * (a[5] + a[7])
    out[5] = a[8]


@njit(cache=True, fastmath=_FM)
def normalize_diagonal(diag):
    """Per contact: s = tr(W_ii)/3, W_ii / s and its inverse as symmetric 6-vectors
    (a00, a01, a02, a11, a12, a22), and an invertible flag."""
    m = diag.shape[0]
    s = np.empty(m)
    An = np.empty((m, 6))
    Ainv = np.empty((m, 6))
    ok = np.empty(m, dtype=np.bool_)
    for i in range(m):
        si, a, ai, oki = normalize_block(diag[i])
        s[i] = si
        _pack_sym6(a, An[i])
        _pack_sym6(ai, Ainv[i])
        ok[i] = oki
    return s, An, Ainv, ok


@njit(cache=True, inline="always", fastmath=_FM)
def _sym9(M, i):
    """Row-major 9-tuple of the symmetric 3x3 stored as M[i, 0:6] = (a00, a01, a02, a11, a12, a22)."""
    a00 = M[i, 0]
    a01 = M[i, 1]
    a02 = M[i, 2]
    a11 = M[i, 3]
    a12 = M[i, 4]
    a22 = M[i, 5]
    return (a00, a01, a02, a01, a11, a12, a02, a12, a22)


@njit(cache=True, inline="always", fastmath=_FM)
def _local_update(law, mu, s, An, Ainv, ok, i, c0, c1, c2, r, omega, tol, max_newton, atol):
    """Solve contact i's local problem u_i = W_ii r_i + c_i (c_i: everything but the diagonal term);
    returns (status, new r_i).  omega != 1: c_i <- omega c_i + (omega - 1) W_ii r_i (over-relaxation)."""
    A = _sym9(An, i)
    Ai = _sym9(Ainv, i)
    si = s[i]
    r0 = r[i, 0]
    r1 = r[i, 1]
    r2 = r[i, 2]
    if omega != 1.0:
        w0 = si * (A[0] * r0 + A[1] * r1 + A[2] * r2)
        w1 = si * (A[3] * r0 + A[4] * r1 + A[5] * r2)
        w2 = si * (A[6] * r0 + A[7] * r1 + A[8] * r2)
        c0 = omega * c0 + (omega - 1.0) * w0
        c1 = omega * c1 + (omega - 1.0) * w1
        c2 = omega * c2 + (omega - 1.0) * w2
    return solve_block(law, mu[i], si, A, Ai, ok[i], c0, c1, c2, r0, r1, r2, tol, max_newton, atol)


@njit(cache=True, inline="always", fastmath=_FM)
def _solve_row(law, i, indptr, indices, blocks, b, mu, s, An, Ainv, ok, omega, r, acc, tol, max_newton, atol):
    """Row i of a sweep on the upper block triangle: c_i = b_i + acc_i + sum_{j > i} W_ij r_j (the diagonal
    block comes first in the row; its term s_i An_i r_i is left out of c_i), the local solve, r_i written.
    Returns (1 if the local solve failed else 0, r_i)."""
    u0 = b[i, 0] + acc[i, 0]
    u1 = b[i, 1] + acc[i, 1]
    u2 = b[i, 2] + acc[i, 2]
    for p in range(indptr[i] + 1, indptr[i + 1]):
        j = indices[p]
        x0 = r[j, 0]
        x1 = r[j, 1]
        x2 = r[j, 2]
        u0 += blocks[p, 0, 0] * x0 + blocks[p, 0, 1] * x1 + blocks[p, 0, 2] * x2
        u1 += blocks[p, 1, 0] * x0 + blocks[p, 1, 1] * x1 + blocks[p, 1, 2] * x2
        u2 += blocks[p, 2, 0] * x0 + blocks[p, 2, 1] * x1 + blocks[p, 2, 2] * x2
    st, n0, n1, n2 = _local_update(law, mu, s, An, Ainv, ok, i, u0, u1, u2, r, omega, tol, max_newton, atol)
    r[i, 0] = n0
    r[i, 1] = n1
    r[i, 2] = n2
    return (1 if st == FAILED else 0), n0, n1, n2


@njit(cache=True, fastmath=_FM)
def sweep_upper(law, indptr, indices, blocks, b, mu, s, An, Ainv, ok, omega, r, acc, tol, max_newton, atol):
    """One forward sweep on the upper block triangle of W (natural order): c_i = b_i + acc_i +
    sum_{j > i} W_ij r_j (old values), acc_i = sum_{j < i} W_ji^T r_j (new values, scattered by the
    rows before i).  r (m, 3) updated in place; acc (m, 3) is scratch.  Returns local failures."""
    m = indptr.shape[0] - 1
    for i in range(m):
        acc[i, 0] = 0.0
        acc[i, 1] = 0.0
        acc[i, 2] = 0.0
    fails = 0
    for i in range(m):
        failed, n0, n1, n2 = _solve_row(law, i, indptr, indices, blocks, b, mu, s, An, Ainv, ok, omega, r, acc,
                                        tol, max_newton, atol)
        fails += failed
        if n0 != 0.0 or n1 != 0.0 or n2 != 0.0:
            for p in range(indptr[i] + 1, indptr[i + 1]):
                j = indices[p]
                acc[j, 0] += blocks[p, 0, 0] * n0 + blocks[p, 1, 0] * n1 + blocks[p, 2, 0] * n2
                acc[j, 1] += blocks[p, 0, 1] * n0 + blocks[p, 1, 1] * n1 + blocks[p, 2, 1] * n2
                acc[j, 2] += blocks[p, 0, 2] * n0 + blocks[p, 1, 2] * n1 + blocks[p, 2, 2] * n2
    return fails


@njit(cache=True, fastmath=_FM)
def sweep_upper_backward(law, indptr, indices, blocks, b, mu, s, An, Ainv, ok, omega, r, acc, tol, max_newton, atol):
    """One backward sweep (rows m-1 .. 0) right after sweep_upper: c_i = b_i + acc_i + sum_{j > i} W_ij r_j
    with r_j (j > i) this sweep's new values and acc_i = sum_{j < i} W_ji^T r_j as the forward sweep left it
    (rows j < i are not yet touched by this sweep, so acc_i is still exact).  Every block is read once, only
    gathered.  Forward + backward is symmetric Gauss-Seidel.  Returns local failures."""
    fails = 0
    for i in range(indptr.shape[0] - 2, -1, -1):
        failed, _, _, _ = _solve_row(law, i, indptr, indices, blocks, b, mu, s, An, Ainv, ok, omega, r, acc,
                                     tol, max_newton, atol)
        fails += failed
    return fails


@njit(cache=True, inline="always", fastmath=_FM)
def _packed_row(i, ptr, cols, vals, v, gamma2, r, b):
    """u_i = b_i + 2 gamma r_i + H_i v, H_i contact i's packed panel (v = D H^T r)."""
    u0 = b[i, 0] + gamma2 * r[i, 0]
    u1 = b[i, 1] + gamma2 * r[i, 1]
    u2 = b[i, 2] + gamma2 * r[i, 2]
    for p in range(ptr[i], ptr[i + 1]):
        x = v[cols[p]]
        u0 += vals[p, 0] * x
        u1 += vals[p, 1] * x
        u2 += vals[p, 2] * x
    return u0, u1, u2


@njit(cache=True, fastmath=_FM)
def sweep_matrix_free(
    law, order, h_ptr, h_cols, h_vals, g_ptr, g_cols, g_vals, gamma2, b, mu, s, An, Ainv, ok, omega, r, v, tol, max_newton,
    atol,
):
    """One sweep keeping v = D H^T r: u_i = H_i v + 2 gamma r_i + b_i, then v += (H D)_i^T dr_i."""
    fails = 0
    for k in range(order.shape[0]):
        i = order[k]
        u0, u1, u2 = _packed_row(i, h_ptr, h_cols, h_vals, v, gamma2, r, b)
        # c_i = u_i - W_ii r_i
        A = _sym9(An, i)
        si = s[i]
        r0 = r[i, 0]
        r1 = r[i, 1]
        r2 = r[i, 2]
        u0 -= si * (A[0] * r0 + A[1] * r1 + A[2] * r2)
        u1 -= si * (A[3] * r0 + A[4] * r1 + A[5] * r2)
        u2 -= si * (A[6] * r0 + A[7] * r1 + A[8] * r2)
        st, n0, n1, n2 = _local_update(law, mu, s, An, Ainv, ok, i, u0, u1, u2, r, omega, tol, max_newton, atol)
        if st == FAILED:
            fails += 1
        d0 = n0 - r[i, 0]
        d1 = n1 - r[i, 1]
        d2 = n2 - r[i, 2]
        if d0 != 0.0 or d1 != 0.0 or d2 != 0.0:
            for p in range(g_ptr[i], g_ptr[i + 1]):
                v[g_cols[p]] += g_vals[p, 0] * d0 + g_vals[p, 1] * d1 + g_vals[p, 2] * d2
        r[i, 0] = n0
        r[i, 1] = n1
        r[i, 2] = n2
    return fails


@njit(cache=True, fastmath=_FM)
def packed_apply(ptr, cols, vals, v, gamma2, r, b, out):
    """out_i = H_i v + 2 gamma r_i + b_i (u from v = D H^T r)."""
    for i in range(ptr.shape[0] - 1):
        u0, u1, u2 = _packed_row(i, ptr, cols, vals, v, gamma2, r, b)
        out[i, 0] = u0
        out[i, 1] = u1
        out[i, 2] = u2


@njit(cache=True, fastmath=_FM)
def packed_transpose_apply(ptr, cols, vals, r, n, out):
    """out = sum_i (panel_i) r_i, i.e. M^T r for the packed (3m, n) matrix M."""
    for k in range(n):
        out[k] = 0.0
    for i in range(ptr.shape[0] - 1):
        d0 = r[i, 0]
        d1 = r[i, 1]
        d2 = r[i, 2]
        for p in range(ptr[i], ptr[i + 1]):
            out[cols[p]] += vals[p, 0] * d0 + vals[p, 1] * d1 + vals[p, 2] * d2


@njit(cache=True)
def dense_upper_block(indptr, indices, blocks, idx, pos, out):
    """out (3k, 3k) = W[idx][:, idx] from W's upper block triangle; pos (m,) all -1 on entry (restored)."""
    k = idx.shape[0]
    for a in range(k):
        pos[idx[a]] = a
    for a in range(k):
        i = idx[a]
        for p in range(indptr[i], indptr[i + 1]):
            c = pos[indices[p]]
            if c < 0:
                continue
            for x in range(3):
                for y in range(3):
                    out[3 * a + x, 3 * c + y] = blocks[p, x, y]
                    out[3 * c + y, 3 * a + x] = blocks[p, x, y]
    for a in range(k):
        pos[idx[a]] = -1


@njit(cache=True)
def dense_packed_block(h_ptr, h_cols, h_vals, g_ptr, g_cols, g_vals, idx, colpos, gamma2, dof_strand):
    """W[idx][:, idx] = sum_s H_S,s (D_s H_S,s^T) + 2 gamma I from the packed panels of H and H D, strand by strand
    (D is block diagonal: strand s couples only the contacts on it, through its columns; dof_strand (n,) the strand
    of each dof): sum_s (3 c_s)^2 w_s products instead of (3 k)^2 w for the whole cluster (a Coulomb cluster of
    200 contacts on ~10 strands: ~25x fewer).  colpos (n,) all -1 on entry (restored)."""
    k = idx.shape[0]
    n_entries = 0
    for a in range(k):
        n_entries += h_ptr[idx[a] + 1] - h_ptr[idx[a]]
    cols = np.empty(n_entries, np.int64)
    nc = 0
    for a in range(k):
        i = idx[a]
        for p in range(h_ptr[i], h_ptr[i + 1]):
            if colpos[h_cols[p]] == -1:
                colpos[h_cols[p]] = -2
                cols[nc] = h_cols[p]
                nc += 1
    cols = np.sort(cols[:nc])  # H_S's columns by dof, hence grouped by strand
    for c in range(nc):
        colpos[cols[c]] = c
    Hs = np.zeros((3 * k, nc))
    Gs = np.zeros((3 * k, nc))
    for a in range(k):
        i = idx[a]
        for p in range(h_ptr[i], h_ptr[i + 1]):
            c = colpos[h_cols[p]]
            for x in range(3):
                Hs[3 * a + x, c] = h_vals[p, x]
        for p in range(g_ptr[i], g_ptr[i + 1]):
            c = colpos[g_cols[p]]
            if c >= 0:
                for x in range(3):
                    Gs[3 * a + x, c] = g_vals[p, x]
    for c in range(nc):
        colpos[cols[c]] = -1
    out = np.zeros((3 * k, 3 * k))
    rows = np.empty(k, np.int64)
    c0 = 0
    while c0 < nc:
        s = dof_strand[cols[c0]]
        c1 = c0
        while c1 < nc and dof_strand[cols[c1]] == s:
            c1 += 1
        nr = 0  # the contacts whose H has a nonzero on strand s (the others' H_S,s and G_S,s are zero there)
        for a in range(k):
            on = False
            for x in range(3):
                for c in range(c0, c1):
                    if Hs[3 * a + x, c] != 0.0:
                        on = True
                        break
                if on:
                    break
            if on:
                rows[nr] = a
                nr += 1
        Hsub = np.empty((3 * nr, c1 - c0))
        Gsub = np.empty((3 * nr, c1 - c0))
        for r in range(nr):
            for x in range(3):
                for c in range(c0, c1):
                    Hsub[3 * r + x, c - c0] = Hs[3 * rows[r] + x, c]
                    Gsub[3 * r + x, c - c0] = Gs[3 * rows[r] + x, c]
        P = Hsub @ Gsub.T
        for r in range(nr):
            for q in range(nr):
                for x in range(3):
                    for y in range(3):
                        out[3 * rows[r] + x, 3 * rows[q] + y] += P[3 * r + x, 3 * q + y]
        c0 = c1
    for a in range(3 * k):
        out[a, a] += gamma2
    return out


# ----------------------------------------------------------------------------------------------
# operators: the two ways to evaluate u_i during a sweep
# ----------------------------------------------------------------------------------------------
def _expand_order(order: np.ndarray) -> np.ndarray:
    """Contact permutation -> permutation of the 3m rows."""
    return (3 * order[:, None] + np.arange(3)[None, :]).reshape(-1)


class AssembledOperator:
    """Gauss-Seidel on W stored as its upper 3x3-block triangle (blocks.UpperBlockDelassus).

    A sweep order other than 0..m-1 is realised by permuting the contacts once, so a sweep always runs
    over rows 0..m-1 and reads every stored block exactly once.  ``order`` maps internal row k to the
    caller's contact order[k]."""

    form = "assembled"

    def __init__(self, W: UpperBlockDelassus, b: np.ndarray, mu: np.ndarray, order: np.ndarray | None = None):
        m = W.n_contacts
        self.order = None if order is None else np.ascontiguousarray(order, dtype=np.int64)
        b = np.asarray(b, dtype=np.float64).reshape(m, 3)
        mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (m,))
        if self.order is not None:
            b = b[self.order]
            mu = mu[self.order]
        self.W = W
        self.b = np.ascontiguousarray(b)
        self.mu = np.ascontiguousarray(mu)
        self.diag = W.diagonal()
        self.s, self.An, self.Ainv, self.ok = normalize_diagonal(self.diag)
        self.rho = _res.rho_from_diagonal(self.diag)
        self.acc = np.zeros((m, 3))
        self._pattern = None  # W's block pattern, both triangles (neighbours)
        self._pos = None  # scratch of dense_block

    @classmethod
    def from_sparse(cls, W, b, mu, order: np.ndarray | None = None) -> "AssembledOperator":
        """From a scipy sparse (3m, 3m) W of 3x3 blocks."""
        if order is not None:
            rows = _expand_order(np.asarray(order, dtype=np.int64))
            W = sp.csr_matrix(W)[rows][:, rows]
        return cls(UpperBlockDelassus.from_sparse(W), b, mu, order)

    @classmethod
    def from_problem(cls, problem, order: np.ndarray | None = None) -> "AssembledOperator":
        """From a ContactProblem, assembling W's upper blocks strand by strand (blocks.assemble_upper).  The blocks
        are kept in the problem's cache (for this order), which the problems of ContactProblem.with_free_velocity
        share: a simulator step at rest solves with the kept W and its own b without assembling W again."""
        source = problem
        cached = source._cache.get("upper")
        if cached is not None and ((order is None and cached[0] is None) or (
                order is not None and cached[0] is not None and np.array_equal(cached[0], order))):
            return cls(cached[1], source.b, source.mu, order)
        if order is not None:
            rows = _expand_order(np.asarray(order, dtype=np.int64))
            problem = type(problem)(problem.H[rows], problem.D_blocks, problem.dof_offsets, problem.gamma,
                                    problem.b, problem.mu)  # only H is permuted here: __init__ permutes b, mu
        W = assemble_upper(problem)
        source._cache["upper"] = (None if order is None else np.array(order, dtype=np.int64), W)
        op = cls(W, source.b, source.mu, order)
        if "diag" not in source._cache:  # share the diagonal blocks (saves forming H D for rho)
            diag = op.diag if order is None else np.empty_like(op.diag)
            if order is not None:
                diag[op.order] = op.diag
            source._cache["diag"] = diag
        return op

    @property
    def nbytes(self) -> int:
        return self.W.nbytes + 2 * self.An.nbytes + self.acc.nbytes

    def to_internal(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
        return np.array(r if self.order is None else r[self.order], order="C")

    def to_external(self, r: np.ndarray) -> np.ndarray:
        if self.order is None:
            return r.reshape(-1).copy()
        out = np.empty_like(r)
        out[self.order] = r
        return out.reshape(-1)

    def sweep(self, law, omega, r, continuing=False, tol=LOCAL_TOL, max_newton=NEWTON_MAX_ITER, atol=0.0) -> int:
        """One sweep over r (m, 3) in place; local solves to the relative tol or the absolute atol
        (local.solve_block).  Returns the number of failed local solves."""
        W = self.W
        return sweep_upper(
            law, W.indptr, W.indices, W.blocks, self.b, self.mu, self.s, self.An, self.Ainv, self.ok,
            float(omega), r, self.acc, tol, max_newton, float(atol),
        )

    def sweep_back(self, law, omega, r, tol=LOCAL_TOL, max_newton=NEWTON_MAX_ITER, atol=0.0) -> int:
        """A backward sweep over r, valid only right after ``sweep`` on the same r (symmetric GS)."""
        W = self.W
        return sweep_upper_backward(
            law, W.indptr, W.indices, W.blocks, self.b, self.mu, self.s, self.An, self.Ainv, self.ok,
            float(omega), r, self.acc, tol, max_newton, float(atol),
        )

    def velocity(self, r: np.ndarray) -> np.ndarray:
        out = np.empty_like(r)
        upper_block_matvec(self.W.indptr, self.W.indices, self.W.blocks, r, self.b, out)
        return out

    def neighbours(self, idx: np.ndarray) -> np.ndarray:
        """The contacts W couples to those of idx (internal order), idx included, sorted."""
        if self._pattern is None:
            m = self.W.n_contacts
            rows = np.repeat(np.arange(m), np.diff(self.W.indptr))
            A = sp.csr_matrix((np.ones(rows.size, dtype=np.int32), (rows, self.W.indices)), shape=(m, m))
            self._pattern = sp.csr_matrix(A + A.T)
        return np.union1d(idx, self._pattern[idx].indices).astype(np.int64)

    def dense_block(self, idx: np.ndarray) -> np.ndarray:
        """W[idx][:, idx] as a dense (3k, 3k) array (internal order)."""
        if self._pos is None:
            self._pos = np.full(self.W.n_contacts, -1, dtype=np.int64)
        idx = np.ascontiguousarray(idx, dtype=np.int64)
        out = np.zeros((3 * idx.size, 3 * idx.size))
        dense_upper_block(self.W.indptr, self.W.indices, self.W.blocks, idx, self._pos, out)
        return out


class MatrixFreeOperator:
    """Gauss-Seidel keeping v = D H^T r, from the factored ContactProblem (H and H D packed per
    contact, blocks.PackedRows)."""

    form = "matrix_free"

    def __init__(self, problem, order: np.ndarray | None = None):
        m = problem.n_contacts
        self.order = np.arange(m, dtype=np.int64) if order is None else np.ascontiguousarray(order, dtype=np.int64)
        self.H, self.G = problem.packed()  # H and H D (rows of H D = (D H_i^T)^T) per contact
        self.n = problem.n_dofs
        self.gamma2 = 2.0 * problem.gamma
        self.b = np.ascontiguousarray(problem.b.reshape(-1, 3)).copy()
        self.mu = problem.mu
        self.diag = problem.diagonal_blocks()
        self.s, self.An, self.Ainv, self.ok = problem.normalized_diagonal()
        self.rho = problem.rho()
        self.v = np.zeros(self.n)
        self.problem = problem
        self._order_rev = None
        self.dof_offsets = np.asarray(problem.dof_offsets, dtype=np.int64)
        self._incidence = None
        self._colpos = None
        self._dof_strand = None

    @property
    def nbytes(self) -> int:
        return self.H.nbytes + self.G.nbytes + 2 * self.An.nbytes + self.v.nbytes

    def to_internal(self, r: np.ndarray) -> np.ndarray:
        return np.array(np.asarray(r, dtype=np.float64).reshape(-1, 3), order="C")

    def to_external(self, r: np.ndarray) -> np.ndarray:
        return r.reshape(-1).copy()

    def _refresh_v(self, r: np.ndarray) -> None:
        """v = D H^T r exactly (drops the drift of the incremental updates; ContactProblem.dof_velocity, which keeps
        the last one for its r)."""
        self.v[:] = self.problem.dof_velocity(r)

    def sweep(self, law, omega, r, continuing=False, tol=LOCAL_TOL, max_newton=NEWTON_MAX_ITER, atol=0.0) -> int:
        """continuing: r is the output of the previous sweep (or of velocity()), so v is already D H^T r."""
        H, G = self.H, self.G
        if not continuing:
            self._refresh_v(r)
        return sweep_matrix_free(
            law, self.order, H.ptr, H.cols, H.vals, G.ptr, G.cols, G.vals, self.gamma2, self.b, self.mu,
            self.s, self.An, self.Ainv, self.ok, float(omega), r, self.v, tol, max_newton, float(atol),
        )

    def sweep_back(self, law, omega, r, tol=LOCAL_TOL, max_newton=NEWTON_MAX_ITER, atol=0.0) -> int:
        """A sweep in reverse order, continuing from ``sweep`` (v = D H^T r is current): symmetric GS."""
        H, G = self.H, self.G
        if self._order_rev is None:
            self._order_rev = np.ascontiguousarray(self.order[::-1])
        return sweep_matrix_free(
            law, self._order_rev, H.ptr, H.cols, H.vals, G.ptr, G.cols, G.vals, self.gamma2, self.b, self.mu,
            self.s, self.An, self.Ainv, self.ok, float(omega), r, self.v, tol, max_newton, float(atol),
        )

    def velocity(self, r: np.ndarray) -> np.ndarray:
        """u = W r + b (m, 3), leaving v = D H^T r.  With the problem's own b (the fixed point shifts this
        operator's), ContactProblem.velocity: the same product, its last one kept."""
        self._refresh_v(r)
        if np.array_equal(self.b.reshape(-1), self.problem.b):
            return self.problem.velocity(r).reshape(-1, 3)
        out = np.empty_like(r)
        packed_apply(self.H.ptr, self.H.cols, self.H.vals, self.v, self.gamma2, r, self.b, out)
        return out

    def velocity_current(self, r: np.ndarray) -> np.ndarray:
        """u = W r + b from the v this operator keeps (right after a sweep that left r: v = D H^T r up to the
        round-off of its incremental updates): H's panels only, no D H^T r (run_gauss_seidel's quick checks)."""
        out = np.empty_like(r)
        packed_apply(self.H.ptr, self.H.cols, self.H.vals, self.v, self.gamma2, r, self.b, out)
        return out

    def neighbours(self, idx: np.ndarray) -> np.ndarray:
        """The contacts on the strands those of idx touch (W couples them through D's strand blocks), idx
        included, sorted."""
        if self._incidence is None:
            m = self.b.shape[0]
            counts = np.diff(self.H.ptr)
            strand = np.searchsorted(self.dof_offsets, self.H.cols, side="right") - 1
            rows = np.repeat(np.arange(m), counts)
            inc = sp.csr_matrix((np.ones(rows.size, dtype=np.int32), (rows, strand)),
                                shape=(m, max(len(self.dof_offsets) - 1, 1)))
            self._incidence = (inc, sp.csr_matrix(inc.T))
        inc, inc_t = self._incidence
        strands = np.unique(inc[idx].indices)
        return np.union1d(idx, inc_t[strands].indices).astype(np.int64)

    def dense_block(self, idx: np.ndarray) -> np.ndarray:
        """W[idx][:, idx] as a dense (3k, 3k) array."""
        if self._colpos is None:
            self._colpos = np.full(self.n, -1, dtype=np.int64)
        H, G = self.H, self.G
        if self._dof_strand is None:
            self._dof_strand = dof_strands(self.dof_offsets)
        return dense_packed_block(H.ptr, H.cols, H.vals, G.ptr, G.cols, G.vals,
                                  np.ascontiguousarray(idx, dtype=np.int64), self._colpos, self.gamma2,
                                  self._dof_strand)


def contact_order(H: sp.spmatrix, how: str = "natural") -> np.ndarray | None:
    """Sweep order.  'natural': 0..m-1 (None).  'columns': by the largest dof each contact touches (for
    chain-like strands: by strand, then root to tip).  'columns_reversed': tip to root."""
    m = H.shape[0] // 3
    if how == "natural":
        return None
    H = sp.csr_matrix(H)
    rowmax = np.full(H.shape[0], -1, dtype=np.int64)
    nz = np.diff(H.indptr) > 0
    if H.nnz:
        rowmax[nz] = np.maximum.reduceat(H.indices, H.indptr[:-1][nz])
    key = rowmax.reshape(m, 3).max(axis=1)
    if how == "columns":
        return np.argsort(key, kind="stable").astype(np.int64)
    if how == "columns_reversed":
        return np.argsort(-key, kind="stable").astype(np.int64)
    raise ValueError(f"unknown order {how!r}")


# ----------------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------------
@dataclass
class GSOutcome:
    r: np.ndarray  # (3m,) in the caller's contact order
    residual: float
    sweeps: int
    converged: bool
    local_failures: int
    history: list = field(default_factory=list)  # [(sweep, residual, seconds)]
    solve_s: float = 0.0
    stalled: bool = False
    projected_sweeps: float | None = None  # set when stopped by ``give_up``
    stopped_by_rule: bool = False  # the caller's ``stop`` accepted r (before the residual reached tol)
    newton: list | None = None  # subspace Newton steps: [(sweep, accepted, alpha, CG iterations, seconds)]
    cluster: list | None = None  # Coulomb cluster steps: [(sweep, accepted, contacts, LM iterations, residual, seconds)]


NEWTON_START = 20  #: first sweep after which a subspace Newton step is tried (SOC law, assembled W; issue 22)
NEWTON_CG = (30, 200)  #: CG iterations per Newton step: while the classification changes / once a full step was taken
CLUSTER_START = 20  #: first sweep after which a Coulomb cluster step is tried (cluster_newton.py; issue 15)
GIVE_UP_MIN_SWEEPS = 400  #: sweeps before ``give_up`` may judge a run
GIVE_UP_WINDOW = 0.2  #: ``give_up`` needs the projection over its limit at every check of this last fraction of the run


def projected_sweeps(history, tol: float) -> float:
    """Sweeps a run would need in all to reach ``tol`` at the geometric rate of the second half of its
    ``history`` [(sweep, residual, ...), ...]:  s + log(res_s / tol) / rate,  rate = log(res_h / res_s) /
    (s - h) with h the first check at or after s / 2 (best residuals so far, so Anderson's bumps do not
    count).  Exact for a linear rate (a Gauss-Seidel chain: 29,000 projected at 500 sweeps, 24,000 needed);
    optimistic where convergence slows down as it goes (dense grooms); a slow start can overestimate, hence
    give_up's margin.  inf when the residual did not decrease."""
    sweeps = np.array([h[0] for h in history], dtype=np.float64)
    best = np.minimum.accumulate(np.array([h[1] for h in history], dtype=np.float64))
    s, res_s = sweeps[-1], best[-1]
    if res_s <= tol:
        return float(s)
    k = int(np.searchsorted(sweeps, 0.5 * s))
    if k >= len(sweeps) - 1 or not best[k] > res_s > 0:
        return math.inf
    rate = math.log(best[k] / res_s) / (s - sweeps[k])
    return float(s + math.log(res_s / tol) / rate)


def give_up_projection(history, tol: float, limit: float, first_judged: int) -> float | None:
    """The projection that stops a run (give_up), or None to go on.

    Stop at sweep s >= ``first_judged`` when :func:`projected_sweeps` exceeded ``limit`` at every check of
    the last GIVE_UP_WINDOW of the run (from (1 - GIVE_UP_WINDOW) s to s, at least two checks).  A
    single check is not enough: Gauss-Seidel on contacts goes through plateaus while the active set
    settles, then speeds up again (the draped test groom: projections over 12,000 for 170 sweeps around
    sweep 1,500 of a run that converges at 3,560)."""
    s = history[-1][0]
    if s < first_judged:
        return None
    start = (1.0 - GIVE_UP_WINDOW) * s
    checks = [k for k in range(len(history)) if history[k][0] >= start]
    if len(checks) < 2:
        return None
    for k in checks:
        if not projected_sweeps(history[:k + 1], tol) > limit:
            return None
    return projected_sweeps(history, tol)


def run_gauss_seidel(
    op,
    law: str = "soc",
    *,
    tol: float = 1e-8,
    max_sweeps: int = 2000,
    r0: np.ndarray | None = None,
    omega: float = 1.0,
    anderson: int = 8,
    anderson_start: int = 10,
    check_every: int = 10,
    scale: float | None = None,
    time_limit: float | None = None,
    stall_window: int | None = None,
    local_tol_fraction: float = 1e-5,
    give_up: float | None = None,
    symmetric: bool | float = False,
    newton: int | None = NEWTON_START,
    newton_every: int = 10,
    newton_cg=NEWTON_CG,
    cluster: int | None = CLUSTER_START,
    cluster_every: int = 10,
    quick_check: int | None = None,
    callback=None,
    stop=None,
) -> GSOutcome:
    """Sweep until residual <= tol (residual.py; checked every ``check_every`` sweeps) or max_sweeps.

    op: AssembledOperator or MatrixFreeOperator.  anderson: memory of the Anderson acceleration of the
    sweep map (0 = plain Gauss-Seidel), switched on after ``anderson_start`` plain sweeps; a step whose
    fixed-point residual ||G(x) - x|| grows tenfold over the best seen restarts the history.
    stall_window: stop (outcome.stalled) when the best residual of the last ``stall_window`` sweeps is not
    half the best before them (Gauss-Seidel on the Coulomb law can cycle).
    give_up: stop (outcome.stalled, outcome.projected_sweeps) once, after GIVE_UP_MIN_SWEEPS sweeps and a
    quarter of the budget, projected_sweeps has said over the last fifth of the run that it needs more
    than ``give_up * max_sweeps`` sweeps (:func:`give_up_projection`; dense redundant contacts,
    docs/solvers.md section 9: the budget would be spent for nothing).
    symmetric: True: follow every forward sweep by a backward one (symmetric Gauss-Seidel; each half counts
    as a sweep).  A number s: forward sweeps until the residual is <= s, then symmetric ones with a fresh
    Anderson history (the active set has settled and the rest is linear, where symmetric sweeps converge
    faster).  Measured on the shared generator's 30k problem (issue 22): symmetric from the start 1,210
    sweeps against 900 forward (its backward sweeps run tip to root there); see docs/solvers.md.
    local_tol_fraction: each local solve stops once its natural map is below this fraction of the
    global target (tol * scale, in the residual's units) or at local.LOCAL_TOL relative, whichever
    comes first (contacts with tiny forces then take one Newton step instead of three or four).  Keep it
    small: inexact local solves slow Anderson-accelerated sweeps down on hard problems (the bundled
    example at tol 1e-6: 1e-5 converges in 4,460 sweeps, 1e-4 and 1e-3 do not within 5,000).
    newton: the sweep from which subspace Newton steps are tried (subspace_newton.py; None: never): at a
    residual check (every ``check_every`` sweeps) at or after it, one Newton step on the faces the current
    sweep output lies on (take-off / stick / slip), with ``newton_cg`` = (few, many) CG iterations (few while
    the last step had to be shortened); taken only if it lowers the objective, the sweeps then go on from it
    with a fresh Anderson history.  Next try after ``newton_every`` sweeps, doubled after every rejected step.
    SOC law, omega = 1 and the assembled form only (ignored otherwise).  On the shared generator's 30k problem
    (issue 22): 900 -> 160 sweeps to 1e-8, 9 s -> 3 s CPU.
    cluster: the sweep from which Coulomb cluster steps are tried (cluster_newton.py; None: never; Coulomb law
    only): at a residual check at or after it, the contacts over tol and every contact on their strands
    (at most cluster_newton.CLUSTER_MAX) are solved together by Levenberg-Marquardt on their natural map, the
    others held; the point is kept only if it lowers the global residual (then the sweeps go on from it, or
    the run stops there if it is within tol).  Next try after ``cluster_every`` sweeps, doubled after every
    step that did not halve the residual.  On the README example's sagging run, the 43 steps that ran out of
    500 sweeps all had one loaded slipping contact near two strands' roots converging at 0.997 a sweep.
    quick_check: between the residual checks, every ``quick_check`` sweeps (None: never), a matrix-free operator
    measures the residual from the v = D H^T r its sweep kept (velocity_current: H's panels only, about a quarter
    of a sweep, where a check first computes D H^T r); where that is within tol, the exact check is made and the
    run stops if it is within tol too (a run whose residual is within tol after 3 sweeps does not sweep on to the
    tenth).  Nothing else happens at a quick check (no history entry, callback, cluster or Newton step), so the
    returned r and its residual are those of an exact check at that sweep.
    callback(sweeps, residual): called at every residual check (progress bars).
    stop(r, u) -> bool: the caller's own stopping rule, asked at every residual check with the current r and
    u = W r + b (both (3m,), the caller's contact order); True ends the run (outcome.stopped_by_rule), e.g.
    once a certified error bound (certificate.py) is small enough.
    The returned r is always a Gauss-Seidel image (so each r_i solves its local problem, to within
    local_tol_fraction of the target) and its residual is measured exactly; non-convergence is
    reported, never hidden."""
    code = law_code(law)
    if omega != 1.0 and code != SOC:
        raise ValueError("over-relaxation (omega != 1) is only valid for the SOC law")
    if not (0.0 < omega < 2.0):
        raise ValueError("omega must be in (0, 2)")
    m = op.b.shape[0]
    x = np.zeros((m, 3)) if r0 is None else op.to_internal(r0)
    if scale is None:
        scale = _res.residual_scale(op.b, op.rho)
    mu, rho = op.mu, op.rho
    atol = max(0.0, float(local_tol_fraction)) * tol * scale

    last_u = [None]

    def measure(r):
        u = op.velocity(r)
        last_u[0] = u
        emax, _ = _res.residual_max_rms(code, r, u, mu, rho)
        return emax / scale

    t0 = time.perf_counter()
    res = measure(x)
    history = [(0, res, 0.0)]
    g = x.copy()
    sweeps = 0
    fails = 0
    stalled = False
    gave_up_at = None  # the projection that stopped the run (give_up)
    by_rule = False
    if res <= tol or max_sweeps <= 0:
        return GSOutcome(op.to_external(x), float(res), 0, bool(res <= tol), 0, history, time.perf_counter() - t0)
    mixer = AndersonMixer(3 * m, anderson) if anderson > 0 else None
    subspace = None
    if newton is not None and code == SOC and omega == 1.0 and isinstance(op, AssembledOperator):
        subspace = SubspaceNewton(op, cg_iter=newton_cg)
    next_newton = newton
    clusters = None
    if cluster is not None and code == COULOMB and hasattr(op, "dense_block"):
        clusters = ClusterNewton(op)
    next_cluster = cluster
    cluster_gap = max(1, int(cluster_every))
    cluster_log = [] if clusters is not None else None
    stale = False  # v of a matrix-free operator no longer matches x (a cluster step was measured)
    newton_gap = max(1, int(newton_every))
    newton_log = [] if subspace is not None else None
    xf = x.reshape(-1)
    gf = g.reshape(-1)
    f = np.empty(3 * m)
    next_check = check_every
    quick = int(quick_check) if quick_check and hasattr(op, "velocity_current") else 0
    sym_on = symmetric is True
    sym_at = None if isinstance(symmetric, bool) else float(symmetric)
    while sweeps < max_sweeps:
        # g = G(x): one sweep from x
        if mixer is not None and sweeps >= anderson_start:
            if g is x:  # first accelerated step: split the buffers
                g = x.copy()
                gf = g.reshape(-1)
            else:
                g[:] = x
        else:
            g = x  # plain Gauss-Seidel updates in place
            gf = g.reshape(-1)
        # continuing: v = D H^T g is current (g is x, swept in place, or just measured: measure(x) before the
        # first sweep refreshed v for x), so a matrix-free sweep need not recompute it
        fails += op.sweep(code, omega, g, continuing=g is x and not stale, atol=atol)
        stale = False
        sweeps += 1
        if sym_on and sweeps < max_sweeps:  # the backward half: a sweep of its own in the count
            fails += op.sweep_back(code, omega, g, atol=atol)
            sweeps += 1
        if quick and sweeps % quick == 0 and not (sweeps >= next_check or sweeps >= max_sweeps):
            emax, _ = _res.residual_max_rms(code, g, op.velocity_current(g), mu, rho)
            if emax / scale <= tol:
                res = measure(g)
                if res <= tol:
                    history.append((sweeps, res, time.perf_counter() - t0))
                    if callback is not None:
                        callback(sweeps, res)
                    break
        if sweeps >= next_check or sweeps >= max_sweeps:
            next_check = sweeps + check_every
            res = measure(g)
            history.append((sweeps, res, time.perf_counter() - t0))
            if callback is not None:
                callback(sweeps, res)
            if res <= tol or not math.isfinite(res):
                break
            if stop is not None and stop(op.to_external(g), op.to_external(last_u[0])):
                by_rule = True
                break
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                break
            if stall_window and sweeps >= 2 * stall_window:
                recent = min(h[1] for h in history if h[0] > sweeps - stall_window)
                before = min(h[1] for h in history if h[0] <= sweeps - stall_window)
                if recent > 0.5 * before:
                    stalled = True
                    break
            if give_up is not None:
                projected = give_up_projection(history, tol, give_up * max_sweeps,
                                               max(GIVE_UP_MIN_SWEEPS, max_sweeps // 4))
                if projected is not None:
                    stalled = True
                    gave_up_at = projected
                    break
            if clusters is not None and sweeps >= next_cluster:
                tn = time.perf_counter()
                u_g = last_u[0]
                cand = clusters.step(g, u_g, scale, tol)
                res_c = math.nan
                if cand is not None:
                    res_c = measure(cand)
                    stale = True
                accepted = cand is not None and res_c < res
                cluster_log.append((sweeps, accepted, clusters.last["size"], clusters.last["iterations"], res_c,
                                    time.perf_counter() - tn))
                # again at the next check after a step that halved the residual, or when there was no cluster (none
                # or too large: that cost one pass over the contacts); otherwise wait twice as long: a step on 200
                # contacts costs as much as tens of sweeps on the README example, and where the sweeps cycle, steps
                # that each lower the residual a little (the 2,000-contact test hair problem) must not be paid often
                if (accepted and res_c <= 0.5 * res) or clusters.last["size"] == 0:
                    cluster_gap = max(1, int(cluster_every))
                else:
                    cluster_gap = min(2 * cluster_gap, 640)
                next_cluster = sweeps + cluster_gap
                if accepted:
                    res = res_c
                    history.append((sweeps, res, time.perf_counter() - t0))
                    x[:] = cand
                    if g is not x:
                        g[:] = x
                    if mixer is not None:
                        mixer.reset()
                    if res <= tol:
                        break
                    continue
                last_u[0] = u_g
            if subspace is not None and sweeps >= next_newton:
                tn = time.perf_counter()
                step = subspace.step(g, last_u[0])
                newton_log.append((sweeps, step is not None, subspace.last["alpha"], subspace.last["cg"],
                                   time.perf_counter() - tn))
                # a rejected step doubles the wait for the next one (a step costs as much as 5-20 sweeps)
                newton_gap = max(1, int(newton_every)) if step is not None else min(2 * newton_gap, 640)
                next_newton = sweeps + newton_gap
                if step is not None:  # a lower objective: sweep on from there, with a fresh Anderson history
                    x[:] = step[0]
                    if mixer is not None:
                        mixer.reset()
                    if g is not x:
                        g[:] = x
                    continue
        if sym_at is not None and not sym_on and res <= sym_at:
            sym_on = True  # from here on symmetric sweeps, with a fresh Anderson history
            if mixer is not None:
                mixer.reset()
        if mixer is None or sweeps < anderson_start:
            x = g
            xf = gf
            continue
        np.subtract(gf, xf, out=f)
        mixer.guarded_step(xf, f, xf)  # x <- Anderson mix of (x, G(x))
    if history[-1][0] != sweeps:
        res = measure(g)
        history.append((sweeps, res, time.perf_counter() - t0))
    solve_s = time.perf_counter() - t0
    return GSOutcome(op.to_external(g), float(res), sweeps, bool(res <= tol), int(fails), history, solve_s, stalled,
                     gave_up_at, by_rule, newton_log, cluster_log)
