"""Per-strand linear algebra of the semi-implicit step: the factorised step matrix and its solves.

Every strand has its own Mhat on its 3 N_s real dofs.  The factors are stored back to back as packed
lower triangles (StrandFactors: memory sum n_s (n_s + 1) / 2, not S max(n_s)^2), made in one compiled
pass (LAPACK dpotrf through numba, failure reported instead of raised) with the eigendecompositions of
the unstable-mode correction in Python (kept packed too: StepCorrections); the small triangular solves
are compiled loops, the inverses LAPACK dpotri (a multi-threaded BLAS is slow on 100 x 100 systems on a
busy machine: the simulator holds it to one thread).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.linalg import lapack

from .rods.dynamics import MassGenerators
from .semiseparable import (apply_lower_strand, apply_upper_strand, factor_strand, matvec_strand, solve_lower_strand,
                            solve_upper_strand)


def _cholesky(a: np.ndarray) -> np.ndarray | None:
    """Lower Cholesky factor of the symmetric positive definite ``a`` (LAPACK dpotrf), None if it is not."""
    c, info = lapack.dpotrf(a, lower=1, clean=1, overwrite_a=0)
    return c if info == 0 else None


def modified_step_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mhat = A V diag(d) V^T A with B V = A V Lambda, V^T A V = I, d = 1 + lambda (lambda >= 0),
    d = 1 + |lambda| / 2 (lambda < 0): stable modes implicit, unstable ones grow at most threefold.

    Through A = L L^T and the standard eigenproblem C = L^-1 B L^-T = U Lambda U^T (A V = L U):
    Mhat = A + B + P diag(1.5 |lambda_i|) P^T over the negative lambda_i, P = L U_neg."""
    from scipy.linalg import solve_triangular

    L = _cholesky(a)
    if L is None:
        raise np.linalg.LinAlgError("the step matrix's A = M + h^2 K is not positive definite")
    X = solve_triangular(L, b, lower=True, check_finite=False)  # L^-1 B
    C = solve_triangular(L, X.T, lower=True, check_finite=False)  # L^-1 B L^-T (B symmetric)
    C = 0.5 * (C + C.T)
    lam, U = np.linalg.eigh(C)
    neg = lam < 0.0
    P = L @ U[:, neg]
    m = a + b + (P * (1.5 * np.abs(lam[neg]))) @ P.T
    return 0.5 * (m + m.T)


CHUNK_BYTES = 64 * 2**20  # the mass matrices of one chunk of strands (simulator)
STEP_RANK = 6  # the rank of the step matrix's semiseparable generators (factor_step_generators)


def strand_chunks(n_elements: np.ndarray, max_bytes: int = CHUNK_BYTES) -> list[tuple[int, int]]:
    """Consecutive strand ranges (first, stop) whose padded (chunk, 3 N_c, 3 N_c) matrices fit in
    ``max_bytes`` (N_c the chunk's largest element count)."""
    n_elements = np.asarray(n_elements, dtype=np.int64)
    chunks, a = [], 0
    while a < len(n_elements):
        b, widest = a, 0
        while b < len(n_elements):
            w = max(widest, int(n_elements[b]))
            if b > a and (b + 1 - a) * (3 * w) ** 2 * 8 > max_bytes:
                break
            widest, b = w, b + 1
        chunks.append((a, b))
        a = b
    return chunks


def packed_size(n):
    """Entries of the lower triangle of an n x n matrix (the packed storage of StrandFactors, StepCorrections)."""
    return n * (n + 1) // 2


@njit(cache=True)
def _pack_lower(m, out):
    """out[i (i + 1) / 2 + j] = m[i, j] for j <= i (row-major lower triangle)."""
    n = m.shape[0]
    o = 0
    for i in range(n):
        for j in range(i + 1):
            out[o] = m[i, j]
            o += 1


@njit(cache=True)
def _unpack_lower(data, o, n):
    """The (n, n) lower triangular matrix packed at data[o:] (zeros above the diagonal)."""
    out = np.zeros((n, n))
    for i in range(n):
        r = o + i * (i + 1) // 2
        for j in range(i + 1):
            out[i, j] = data[r + j]
    return out


class StepCorrections:
    """The unstable-mode correction C_s = modified_step_matrix(a, b) - a - b of each strand that needed
    one, kept between steps (factor_step_matrix; a kept C is only used while the strand needs one).

    C is symmetric: its lower triangle is stored (row-major, n (n + 1) / 2 entries, symmetrised on the way in)
    in arenas of exact size, one per factor_step_matrix call that brought new strands (the simulator's chunks):
    a new C of a strand that has a slot overwrites it; new strands of a range get one new arena holding that
    range's kept slots too (only the range's own data is copied, no buffer of the whole groom grows).  The
    compiled kernels read one arena and per strand its offset (``range_arena``), -1 for none."""

    def __init__(self, n_strands: int):
        self.start = np.full(n_strands, -1, dtype=np.int64)  # offset in its arena
        self.arena = np.full(n_strands, -1, dtype=np.int64)  # index into self.arenas
        self.size = np.zeros(n_strands, dtype=np.int64)
        self.arenas: list[np.ndarray | None] = []

    def get(self, s: int) -> np.ndarray | None:
        """Strand s's C (n, n), symmetric (a new array), or None."""
        if self.start[s] < 0:
            return None
        n = int(self.size[s])
        L = _unpack_lower(self.arenas[self.arena[s]], int(self.start[s]), n)
        return L + np.tril(L, -1).T

    def nbytes(self) -> int:
        """Bytes held by the arenas in use."""
        return sum(a.nbytes for a in self.arenas if a is not None)

    def set(self, s: int, correction: np.ndarray) -> None:
        """Keep strand s's C (store for one strand; factor_step_matrix stores a call's new ones at once)."""
        self.store(s, s + 1, [(s, correction)])

    def store(self, first: int, stop: int, items) -> None:
        """Keep the corrections ``items`` [(s, C)] of strands s in first..stop-1: in place where s has a slot of
        its size, else in one new arena of exact size for the range's kept slots and the new ones."""
        new = [s for s, c in items if self.start[s] < 0 or self.size[s] != c.shape[0]]
        if new:
            for s, c in items:
                self.size[s] = c.shape[0]
            self._rearrange(first, stop, new)
        for s, c in items:
            c = np.asarray(c, dtype=np.float64)
            n = c.shape[0]
            o = int(self.start[s])
            _pack_lower(0.5 * (c + c.T), self.arenas[self.arena[s]][o:o + packed_size(n)])

    def _rearrange(self, first: int, stop: int, new=()) -> None:
        """One new arena for the strands of first..stop-1 that have a slot (copied) and those in ``new`` (empty
        slots of size self.size[s]); arenas left without a strand are released."""
        idx = np.arange(first, stop)
        kept = idx[self.start[first:stop] >= 0]
        kept = kept[~np.isin(kept, new)]
        strands = np.concatenate([kept, np.asarray(new, dtype=np.int64)])
        sizes = packed_size(self.size[strands])
        offsets = np.zeros(len(strands) + 1, dtype=np.int64)
        np.cumsum(sizes, out=offsets[1:])
        arena = np.empty(int(offsets[-1]))
        for k, s in enumerate(kept):
            o, m = int(self.start[s]), int(sizes[k])
            arena[offsets[k]:offsets[k] + m] = self.arenas[self.arena[s]][o:o + m]
        released = set(int(a) for a in self.arena[strands] if a >= 0)
        self.arenas.append(arena)
        self.arena[strands] = len(self.arenas) - 1
        self.start[strands] = offsets[:-1]
        in_use = set(np.unique(self.arena[self.arena >= 0]).tolist())
        for a in released - in_use:
            self.arenas[a] = None

    def range_arena(self, first: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """(arena, offsets) of the strands first..stop-1 (offset -1: no C), the range's slots moved into one arena
        if they were in several."""
        arenas = np.unique(self.arena[first:stop][self.arena[first:stop] >= 0])
        if len(arenas) == 0:
            return np.zeros(0), np.full(stop - first, -1, dtype=np.int64)
        if len(arenas) > 1:
            self._rearrange(first, stop)
            arenas = self.arena[first:stop][self.arena[first:stop] >= 0][:1]
        start = np.where(self.arena[first:stop] == arenas[0], self.start[first:stop], -1)
        return self.arenas[int(arenas[0])], np.ascontiguousarray(start)

    def by_arena(self):
        """(arena, offsets (S,), -1 for strands elsewhere or without C) for each arena in use."""
        for k, a in enumerate(self.arenas):
            if a is not None:
                yield a, np.where(self.arena == k, self.start, -1)


class StrandFactors:
    """Cholesky factors of every strand's step matrix on its n_s = 3 N_s real dofs, each strand's either dense or
    block semiseparable (``structured[s]``).

    Tip first: with P the reversal of the dofs, the factor L is lower triangular with P Mhat P = L L^T, i.e.
    Mhat = (P L P)(P L P)^T with P L P upper triangular.  A contact on element e moves the dofs of elements 0..e
    only, so the contact problem needs just the leading block D[:k, :k] of D = Mhat^-1, and that is (T T^T)^-1
    (reversed) for the trailing block T = L[n-k:, n-k:]: O(k^3) instead of O(n^3) (:meth:`leading_inverse`).

    Dense: stored back to back as packed lower triangles (memory sum n_s (n_s + 1) / 2, not S max(n_s)^2): strand
    s's factor is data[ptr[s]:ptr[s+1]], row i of L at ptr[s] + i (i + 1) / 2.  Structured (factor_step_generators,
    groomtool.semiseparable): L_kk = L3[e], L_kj = V_k^T W_j (k > j) over the strand's elements in tip-first order,
    flat over the groom's elements from elem_ptr[s] (9 + 6 r numbers per element; V the later generators of
    P Mhat P).  :meth:`factor` gives either as a dense (n, n) array."""

    def __init__(self, n_elements: np.ndarray, rank: int = STEP_RANK):
        self.sizes = 3 * np.asarray(n_elements, dtype=np.int64)
        self.ptr = np.zeros(len(self.sizes) + 1, dtype=np.int64)
        np.cumsum(packed_size(self.sizes), out=self.ptr[1:])
        self.data = np.zeros(int(self.ptr[-1]))
        self.elem_ptr = np.zeros(len(self.sizes) + 1, dtype=np.int64)
        np.cumsum(self.sizes // 3, out=self.elem_ptr[1:])
        E = int(self.elem_ptr[-1])
        self.L3 = np.zeros((E, 3, 3))
        self.W = np.zeros((E, rank, 3))
        self.V = np.zeros((E, rank, 3))
        self.structured = np.zeros(len(self.sizes), dtype=bool)
        # per strand: whether its factor includes an unstable-mode correction C (factor_step_matrix), and whether
        # that C is kept in the StepCorrections given (False: a fresh C made without one, not stored anywhere)
        self.corrected = np.zeros(len(self.sizes), dtype=bool)
        self.correction_kept = np.ones(len(self.sizes), dtype=bool)

    def factor(self, s: int) -> np.ndarray:
        """The (tip-first, lower triangular) factor L of P Mhat_s P as a new dense (n, n) array."""
        n = int(self.sizes[s])
        if self.structured[s]:
            return _structured_trailing(self.L3, self.W, self.V, int(self.elem_ptr[s]), int(self.elem_ptr[s + 1]), n)
        return _unpack_lower(self.data, int(self.ptr[s]), n)

    def set_factor(self, s: int, L: np.ndarray) -> None:
        """Store the lower triangle of ``L`` as strand s's (dense) factor."""
        _pack_lower(np.ascontiguousarray(L, dtype=np.float64), self.data[self.ptr[s]:self.ptr[s + 1]])
        self.structured[s] = False

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """x = Mhat^-1 rhs per strand; rhs (S, n_pad) padded (padding rows are copied: identity)."""
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        out = rhs.copy()
        _solve_kernel(self.data, self.ptr, self.sizes, self.structured, self.elem_ptr, self.L3, self.W, self.V,
                      rhs, out)
        return out

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Mhat x = P L L^T P x per strand; x (S, n_pad) padded (padding rows are copied: identity)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = x.copy()
        _apply_kernel(self.data, self.ptr, self.sizes, self.structured, self.elem_ptr, self.L3, self.W, self.V, x,
                      out)
        return out

    def leading_inverse(self, s: int, k: int) -> np.ndarray:
        """(Mhat_s^-1)[:k, :k]: (T T^T)^-1 for the factor's trailing k x k block T, reversed (dense: LAPACK dpotri on
        T, O(k^3); structured: two block substitutions on the identity, O(k^2 r): _structured_trailing_inverse)."""
        if self.structured[s]:
            inv = _structured_trailing_inverse(self.L3, self.W, self.V, int(self.elem_ptr[s]),
                                               int(self.elem_ptr[s + 1]), int(k))
        else:
            inv = cho_inverse(_trailing_block(self.data, int(self.ptr[s]), int(self.sizes[s]), int(k)), k)
        return np.ascontiguousarray(inv[::-1, ::-1])


@njit(cache=True)
def _structured_trailing_inverse(L3, W, V, e0, e1, k):
    """(T T^T)^-1 for T = L[n-k:, n-k:] of the semiseparable L of elements e0..e1-1 (StrandFactors), in O(k^2 r): on
    the m = 3 ne dofs of the ne elements that T touches (then cropped to the last k: the trailing block of the inverse
    of a lower triangular matrix's trailing block), Z = T^-1 by the forward substitution on the identity (column c is
    zero above its element: Z_i = L_ii^-1 (I_i - V_i^T t), t += W_i Z_i over the columns < 3 (i + 1)), then
    D = T^-T Z by the backward one on the columns at or before each row's element (D_i = L_ii^-T (Z_i - W_i^T s),
    s += V_i D_i), the rest by symmetry."""
    n = 3 * (e1 - e0)
    first = e0 + (n - k) // 3
    ne = e1 - first
    m = 3 * ne
    r = W.shape[1]
    Z = np.zeros((m, m))
    t = np.zeros((r, m))
    for i in range(ne):  # rows 3i..3i+2 of Z, columns < c1 (the inner loops run along the columns)
        e = first + i
        c1 = 3 * (i + 1)
        z0, z1, z2 = Z[3 * i], Z[3 * i + 1], Z[3 * i + 2]
        z0[3 * i], z1[3 * i + 1], z2[3 * i + 2] = 1.0, 1.0, 1.0
        for a in range(r):
            v0, v1, v2 = V[e, a, 0], V[e, a, 1], V[e, a, 2]
            ta = t[a]
            for c in range(c1):
                z0[c] -= v0 * ta[c]
                z1[c] -= v1 * ta[c]
                z2[c] -= v2 * ta[c]
        l00, l10, l11, l20, l21, l22 = L3[e, 0, 0], L3[e, 1, 0], L3[e, 1, 1], L3[e, 2, 0], L3[e, 2, 1], L3[e, 2, 2]
        for c in range(c1):
            x0 = z0[c] / l00
            x1 = (z1[c] - l10 * x0) / l11
            z2[c] = (z2[c] - l20 * x0 - l21 * x1) / l22
            z0[c], z1[c] = x0, x1
        for a in range(r):
            w0, w1, w2 = W[e, a, 0], W[e, a, 1], W[e, a, 2]
            ta = t[a]
            for c in range(c1):
                ta[c] += w0 * z0[c] + w1 * z1[c] + w2 * z2[c]
    D = Z  # row block i of D overwrites Z's: the backward substitution reads only its own rows of Z
    sv = np.zeros((r, m))
    for i in range(ne - 1, -1, -1):
        e = first + i
        c1 = 3 * (i + 1)
        d0, d1, d2 = D[3 * i], D[3 * i + 1], D[3 * i + 2]
        for a in range(r):
            w0, w1, w2 = W[e, a, 0], W[e, a, 1], W[e, a, 2]
            sa = sv[a]
            for c in range(c1):
                d0[c] -= w0 * sa[c]
                d1[c] -= w1 * sa[c]
                d2[c] -= w2 * sa[c]
        l00, l10, l11, l20, l21, l22 = L3[e, 0, 0], L3[e, 1, 0], L3[e, 1, 1], L3[e, 2, 0], L3[e, 2, 1], L3[e, 2, 2]
        for c in range(c1):
            x2 = d2[c] / l22
            x1 = (d1[c] - l21 * x2) / l11
            d0[c] = (d0[c] - l10 * x1 - l20 * x2) / l00
            d1[c], d2[c] = x1, x2
        for a in range(r):
            v0, v1, v2 = V[e, a, 0], V[e, a, 1], V[e, a, 2]
            sa = sv[a]
            for c in range(c1):
                sa[c] += v0 * d0[c] + v1 * d1[c] + v2 * d2[c]
    for i in range(m):  # the upper part by symmetry (the diagonal blocks: their lower triangles)
        for c in range(i + 1, m):
            D[i, c] = D[c, i]
    return D[m - k:, m - k:]


@njit(cache=True)
def _structured_trailing(L3, W, V, e0, e1, k):
    """L[n-k:, n-k:] (dense, zeros above the diagonal) of the semiseparable lower triangular L of elements e0..e1-1:
    L_ii = L3[i], L_ij = V_i^T W_j (i > j); n = 3 (e1 - e0)."""
    n = 3 * (e1 - e0)
    first = e0 + (n - k) // 3  # the first element with a row in the block
    m = 3 * (e1 - first)
    full = np.zeros((m, m))
    r = W.shape[1]
    for i in range(first, e1):
        a0 = 3 * (i - first)
        for x in range(3):
            for y in range(x + 1):
                full[a0 + x, a0 + y] = L3[i, x, y]
        for j in range(first, i):
            b0 = 3 * (j - first)
            for x in range(3):
                for y in range(3):
                    acc = 0.0
                    for c in range(r):
                        acc += V[i, c, x] * W[j, c, y]
                    full[a0 + x, b0 + y] = acc
    return np.ascontiguousarray(full[m - k:, m - k:])


@njit(cache=True)
def _trailing_block(data, o, n, k):
    """L[n-k:, n-k:] of the packed lower triangular L at data[o:] (zeros above the diagonal)."""
    out = np.zeros((k, k))
    for i in range(k):
        r = o + (n - k + i) * (n - k + i + 1) // 2 + n - k
        for j in range(i + 1):
            out[i, j] = data[r + j]
    return out


@njit(cache=True)
def _solve_kernel(data, ptr, sizes, structured, elem_ptr, L3, W, V, rhs, out):
    """x = P (L L^T)^-1 P rhs per strand (L stored tip first, P the reversal; dense or structured: StrandFactors).  A
    zero rhs gives x = 0 without a solve, and the forward substitution starts at the first non-zero of P rhs (a
    right-hand side H^T r on the dofs up to a strand's farthest contact is zero towards the tip): the same x."""
    for s in range(sizes.shape[0]):
        n = sizes[s]
        first = n
        for i in range(n):
            if rhs[s, n - 1 - i] != 0.0:
                first = i
                break
        if first == n:
            for i in range(n):
                out[s, i] = 0.0
            continue
        if structured[s]:
            e0, e1 = elem_ptr[s], elem_ptr[s + 1]
            x = rhs[s, :n][::-1].copy()
            ef = first // 3  # elements before it: zero rows of P rhs, zero forward solution
            solve_lower_strand(L3, W, V, e0 + ef, e1, x[3 * ef:])
            solve_upper_strand(L3, W, V, e0, e1, x)
        else:
            L = data[ptr[s]:ptr[s + 1]]
            y = _forward_from(L, rhs[s, :n][::-1].copy(), n, first)
            x = _backward(L, y, n)
        for i in range(n):
            out[s, i] = x[n - 1 - i]


@njit(cache=True)
def _apply_kernel(data, ptr, sizes, structured, elem_ptr, L3, W, V, x, out):
    """out = P L L^T P x per strand (L stored tip first, P the reversal; dense or structured: StrandFactors)."""
    for s in range(sizes.shape[0]):
        n = sizes[s]
        if structured[s]:
            e0, e1 = elem_ptr[s], elem_ptr[s + 1]
            y = x[s, :n][::-1].copy()
            apply_upper_strand(L3, W, V, e0, e1, y)
            apply_lower_strand(L3, W, V, e0, e1, y)
            for i in range(n):
                out[s, n - 1 - i] = y[i]
            continue
        L = data[ptr[s]:ptr[s + 1]]  # packed rows: L[i, k] = L[i (i + 1) / 2 + k]
        y = np.zeros(n)
        for i in range(n):  # y = L^T P x
            xi = x[s, n - 1 - i]
            r = i * (i + 1) // 2
            for k in range(i + 1):
                y[k] += L[r + k] * xi
        for i in range(n):  # out = P L y
            acc = 0.0
            r = i * (i + 1) // 2
            for k in range(i + 1):
                acc += L[r + k] * y[k]
            out[s, n - 1 - i] = acc


@njit(cache=True)
def _try_cholesky(a):
    """(L, True) with a = L L^T, or (a, False) where a is not positive definite (LAPACK dpotrf)."""
    try:
        return np.linalg.cholesky(a), True
    except Exception:  # numba's LinAlgError: not positive definite
        return a, False


@njit(cache=True)
def _factor_kernel(A, a_scale, Kd, k_scale, B, U, G, Dg, b_scale, n_elements, corr_start, corr, out_data, out_ptr,
                   status):
    """Per strand, on its 3 N_s real dofs: a = a_scale A + diag(k_scale Kd), b = b_scale B (B dense, or
    when B is empty the symmetric matrix with blocks U_j G_k for j < k and Dg_j on the diagonal: the
    generators of superhelix.gravity_force_jacobian, never stored densely); if a/2 + b is positive
    definite, L = cholesky(a + b) (status 0); else with a kept correction C (packed in corr at corr_start[s]) for
    which a/2 + b + C is, L = cholesky(a + b + C) (status 1); else status 2 (a new eigendecomposition
    is needed: done by the caller).  A strand with status 3 on entry skips the test of a/2 + b (known not
    positive definite).  The Cholesky factors are of the matrices with the dofs reversed (tip first,
    StrandFactors); L goes to out_data[out_ptr[s]:] (packed lower triangle)."""
    for s in range(A.shape[0]):
        n = 3 * n_elements[s]
        a = np.empty((n, n))
        b = np.empty((n, n))
        for i in range(n):
            for j in range(n):
                a[i, j] = a_scale * A[s, i, j]
            a[i, i] += k_scale * Kd[s, i]
        if B.shape[0] > 0:
            for i in range(n):
                for j in range(n):
                    b[i, j] = b_scale * B[s, i, j]
        else:
            for r in range(n // 3):
                for x in range(3):
                    for y in range(3):
                        b[3 * r + x, 3 * r + y] = b_scale * Dg[s, r, x, y]
                for k in range(r + 1, n // 3):
                    for x in range(3):
                        for y in range(3):
                            v = b_scale * (U[s, r, x, 0] * G[s, k, 0, y] + U[s, r, x, 1] * G[s, k, 1, y]
                                           + U[s, r, x, 2] * G[s, k, 2, y])
                            b[3 * r + x, 3 * k + y] = v
                            b[3 * k + y, 3 * r + x] = v
        # tip first: factor P (.) P (StrandFactors)
        a = a[::-1, ::-1]
        b = b[::-1, ::-1]
        st = 0
        L = np.empty((n, n))
        ok = False
        if status[s] != 3:  # 3 on entry: a/2 + b is known not to be positive definite (factor_step_generators)
            L, ok = _try_cholesky(0.5 * a + b)
            if ok:
                L, ok = _try_cholesky(a + b)
        if not ok and corr_start[s] >= 0:
            C = _symmetric_reversed(corr, corr_start[s], n)
            L, ok = _try_cholesky(0.5 * a + b + C)
            if ok:
                L, ok = _try_cholesky(a + b + C)
            st = 1
        if not ok:
            status[s] = 2
            continue
        status[s] = st
        o = out_ptr[s]
        for i in range(n):  # packed lower triangle (StrandFactors)
            for j in range(i + 1):
                out_data[o + j] = L[i, j]
            o += i + 1


@njit(cache=True)
def _symmetric_reversed(data, o, n):
    """P C P (P the reversal) of the symmetric C whose lower triangle is packed at data[o:] (StepCorrections)."""
    out = np.empty((n, n))
    for i in range(n):
        r = o + i * (i + 1) // 2
        for j in range(i + 1):
            v = data[r + j]
            out[n - 1 - i, n - 1 - j] = v
            out[n - 1 - j, n - 1 - i] = v
    return out


@njit(cache=True)
def _dense_from_parts(U, G, Dg, n_el):
    """The symmetric (3 n_el, 3 n_el) matrix with blocks U_j G_k (j < k), their transposes, Dg_j."""
    out = np.zeros((3 * n_el, 3 * n_el))
    for j in range(n_el):
        for x in range(3):
            for y in range(3):
                out[3 * j + x, 3 * j + y] = Dg[j, x, y]
        for k in range(j + 1, n_el):
            for x in range(3):
                for y in range(3):
                    v = U[j, x, 0] * G[k, 0, y] + U[j, x, 1] * G[k, 1, y] + U[j, x, 2] * G[k, 2, y]
                    out[3 * j + x, 3 * k + y] = v
                    out[3 * k + y, 3 * j + x] = v
    return out


def factor_step_matrix(A: np.ndarray, B, n_elements: np.ndarray,
                       corrections: StepCorrections | None = None, *, a_scale: float = 1.0, stiffness=None,
                       k_scale: float = 0.0, b_scale: float = 1.0, out: StrandFactors | None = None,
                       first: int = 0) -> tuple[StrandFactors, int]:
    """Cholesky factors of Mhat = a + b per strand, a = a_scale A + k_scale diag(stiffness) (SPD; e.g.
    A = M, a_scale = 1 + h alpha, k_scale = h^2 + h beta), b = b_scale B (B = dF/dq, b_scale = -h^2;
    B dense (S, n, n) or the tuple (U, G, Dg) of superhelix.gravity_force_jacobian_parts).

    Where a/2 + b is positive definite (every mode's step factor 1 + lambda >= 1/2, lambda the
    eigenvalues of b relative to a) Mhat = a + b: gravity is linearly implicit.  Elsewhere a mode of
    the potential is unstable enough that 1 + lambda would approach or cross 0 (amplification
    1 / (1 + lambda) unbounded): Mhat = a + b + C with C = modified_step_matrix(a, b) - a - b.

    ``corrections`` (StepCorrections, updated in place) keeps each strand's C between steps: a kept C
    is used again as long as a/2 + b + C stays positive definite (the same bound on every mode's step
    factor as for an unmodified strand), so the eigendecomposition is only redone when the strand
    moved out of it; at rest the kept C is the fresh one.  A strand that no longer needs its C keeps it
    (unused while a/2 + b is positive definite), ready if it needs one again.  Without ``corrections``
    every modified strand is decomposed anew.  A, B: (S, n, n) padded, for the strands first .. first + S - 1
    of ``out`` (a StrandFactors of the whole groom, filled in place; new when None, then first = 0).
    Returns the factors and the number of these strands whose step matrix was modified.  Compiled (LAPACK dpotrf
    per strand), one eigendecomposition in Python per new C.
    """
    S = A.shape[0]
    if out is None:
        out = StrandFactors(n_elements)
        first = 0
    return out, _factor_dense(A, B, n_elements, corrections, float(a_scale), stiffness, float(k_scale),
                              float(b_scale), out, first, first + S, first + np.arange(S))


def _factor_dense(A, B, n_elements, corrections, a_scale, stiffness, k_scale, b_scale, out, first, stop, ids,
                  indefinite=None) -> int:
    """factor_step_matrix's work on the strands ``ids`` (absolute, increasing, in first..stop-1, the range whose
    corrections one arena holds): A (len(ids), n, n) their padded mass matrices, B their dense dF/dq or
    generators, n_elements and stiffness per row of A; ``indefinite`` (per row): a/2 + b is known not to be
    positive definite (its dense test skipped).  Returns the number modified."""
    S, n_pad, _ = A.shape
    n_elements = np.asarray(n_elements, dtype=np.int64)
    ids = np.asarray(ids, dtype=np.int64)
    Kd = (np.zeros((S, n_pad)) if stiffness is None
          else np.ascontiguousarray(np.asarray(stiffness, dtype=np.float64).reshape(S, -1)[:, :n_pad]))
    if isinstance(B, tuple):
        U, G, Dg = (np.ascontiguousarray(x, dtype=np.float64) for x in B)
        dense = np.zeros((0, 1, 1))
    else:
        dense = np.ascontiguousarray(B, dtype=np.float64)
        U = G = Dg = np.zeros((0, 1, 3, 3))
    if corrections is not None:
        corr, corr_start = corrections.range_arena(first, stop)
        corr_start = np.ascontiguousarray(corr_start[ids - first])
    else:
        corr, corr_start = np.zeros(0), np.full(S, -1, dtype=np.int64)
    status = np.zeros(S, dtype=np.int64)
    if indefinite is not None:
        status[np.asarray(indefinite, dtype=bool)] = 3
    _factor_kernel(np.ascontiguousarray(A), a_scale, Kd, k_scale, dense, U, G, Dg, b_scale,
                   n_elements, corr_start, corr, out.data, np.ascontiguousarray(out.ptr[ids]), status)
    out.structured[ids] = False
    out.corrected[ids] = status > 0
    out.correction_kept[ids] = (status < 2) | (corrections is not None)
    fresh = []
    for s in np.flatnonzero(status == 2):
        n = 3 * int(n_elements[s])
        a = a_scale * A[s, :n, :n] + np.diag(k_scale * Kd[s, :n])
        if isinstance(B, tuple):
            b = b_scale * _dense_from_parts(U[s], G[s], Dg[s], n // 3)
        else:
            b = b_scale * B[s, :n, :n]
        m = modified_step_matrix(a, b)
        L = _cholesky(np.ascontiguousarray(m[::-1, ::-1]))  # tip first (StrandFactors)
        if L is None:
            raise np.linalg.LinAlgError(f"strand {int(ids[s])}: the step matrix is not positive definite")
        out.set_factor(int(ids[s]), L)
        if corrections is not None:
            fresh.append((int(ids[s]), m - (a + b)))
    if fresh:  # the call's new corrections at once: at most one new arena (StepCorrections.store)
        corrections.store(first, stop, fresh)
    return int(np.count_nonzero(status > 0))


DENSE_BELOW = 0  # strands of fewer elements take the dense factorisation (factor_step_generators; measured crossover)


def gravity_jacobian_left(linear_density: float, gravity) -> np.ndarray:
    """X = -rhoS [g]x, with which superhelix.gravity_force_jacobian_parts's U_j = Theta_j^T X: the blocks of dF/dq
    below the diagonal, (U_j G_k)^T = (X G_k)^T Theta_j (k > j), have Theta_j on their right as the mass matrix's do
    (its earlier_j = [B_j; Theta_j])."""
    g = np.asarray(gravity, dtype=np.float64)
    gx = np.array([[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]])
    return -float(linear_density) * gx


def factor_step_generators(mass, gravity_parts, gravity_left, n_elements, corrections: StepCorrections | None = None,
                           *, a_scale: float = 1.0, stiffness=None, k_scale: float = 0.0, b_scale: float = 1.0,
                           out: StrandFactors, first: int = 0, dense_below: int | None = None) -> int:
    """factor_step_matrix from the mass matrix's generators (dynamics.MassGenerators of the strands first ..
    first + S - 1) and dF/dq's (U, G, Dg) (gravity_force_jacobian_parts; None: b_scale 0) without forming M: the
    step matrix Mhat = a_scale M + k_scale K + b_scale dF/dq is block semiseparable of rank 6,

        Mhat_jj = a M_jj + k diag(K_j) + b Dg_j,    Mhat_kj = later_k^T [B_j; Theta_j]  (k > j),
        later_k = a right_k + b [0; X G_k]          (X = gravity_jacobian_left: U_j = Theta_j^T X),

    and so is the tip-first P Mhat P (later and earlier swap, each element's dofs reversed).  Per strand of at least
    ``dense_below`` elements (default DENSE_BELOW), compiled: the block Cholesky of P (a/2 + b) P (the positive
    definiteness test of factor_step_matrix) and of P Mhat P, O(N r^2) (groomtool.semiseparable.factor_strand), into
    ``out``'s structured storage.  The others, and those whose a/2 + b or a + b is not positive definite (an
    unstable-mode correction C, kept or new), take factor_step_matrix's dense path on M formed from the generators
    (only theirs).  Returns the number of strands whose step matrix was modified."""
    diag, later, earlier = mass.diag, mass.later, mass.earlier
    S, N = diag.shape[:2]
    n_elements = np.asarray(n_elements, dtype=np.int64)
    dense_below = DENSE_BELOW if dense_below is None else int(dense_below)
    Kd = (np.zeros((S, N, 3)) if stiffness is None
          else np.ascontiguousarray(np.asarray(stiffness, dtype=np.float64).reshape(S, -1, 3)[:, :N]))
    if gravity_parts is None or b_scale == 0.0:
        G = Dg = np.zeros((S, N, 3, 3))
        X = np.zeros((3, 3))
        b_scale = 0.0 if gravity_parts is None else b_scale
    else:
        G, Dg = (np.ascontiguousarray(x[:, :N], dtype=np.float64) for x in gravity_parts[1:])
        X = np.ascontiguousarray(gravity_left, dtype=np.float64)
    use = n_elements >= dense_below
    status = np.full(S, -1, dtype=np.int64)
    _structured_factor_kernel(diag, later, earlier, float(a_scale), Kd, float(k_scale), G, Dg, X, float(b_scale),
                              n_elements, use, np.ascontiguousarray(out.elem_ptr[first:first + S]), out.L3, out.W,
                              out.V, status)
    done = status == 0
    out.structured[first:first + S] = done
    out.corrected[first:first + S][done] = False
    out.correction_kept[first:first + S][done] = True
    rest = np.flatnonzero(~done)
    if not len(rest):
        return 0
    Nd = max(int(n_elements[rest].max()), 1)
    M = MassGenerators(diag[rest, :Nd], later[rest, :Nd], earlier[rest, :Nd]).dense(n_elements[rest])
    B = (tuple(np.ascontiguousarray(x[rest, :Nd]) for x in gravity_parts) if gravity_parts is not None
         else np.zeros_like(M))
    return _factor_dense(M, B, n_elements[rest], corrections, float(a_scale), Kd[rest, :Nd], float(k_scale),
                         float(b_scale), out, first, first + S, first + rest, indefinite=status[rest] == 2)


@njit(cache=True)
def _structured_factor_kernel(diag, later, earlier, a_s, Kd, k_s, G, Dg, X, b_s, n_elements, use, elem_start, L3, W,
                              V, status):
    """Per strand s with use[s] (factor_step_generators): the tip-first generators of P (a/2 + b) P and P Mhat P
    (element k -> n - 1 - k, each block's dofs reversed: later' = [B; Theta] reversed, earlier' = later_hat
    reversed), the first's factor as a test, the second's into L3, W, V from elem_start[s]; status 0, or 2 where
    either is not positive definite (then a/2 + b is not, as a + b = (a/2 + b) + a/2: the dense path takes it with
    the unstable-mode correction)."""
    r = later.shape[2]
    for s in range(diag.shape[0]):
        if not use[s]:
            continue
        n = n_elements[s]
        e0 = elem_start[s]
        Vs = V[e0:e0 + n]
        d_half = np.empty((n, 3, 3))
        d_full = np.empty((n, 3, 3))
        ear_half = np.empty((n, r, 3))
        ear_full = np.empty((n, r, 3))
        for k in range(n):
            kk = n - 1 - k
            for x in range(3):
                for y in range(3):
                    m = a_s * diag[s, k, x, y]
                    g = b_s * Dg[s, k, x, y]
                    if x == y:
                        m += k_s * Kd[s, k, x]
                    d_half[kk, 2 - x, 2 - y] = 0.5 * m + g
                    d_full[kk, 2 - x, 2 - y] = m + g
            for c in range(r):
                for y in range(3):
                    Vs[kk, c, 2 - y] = earlier[s, k, c, y]
                    m = a_s * later[s, k, c, y]
                    g = 0.0
                    if c >= 3:
                        g = b_s * (X[c - 3, 0] * G[s, k, 0, y] + X[c - 3, 1] * G[s, k, 1, y]
                                   + X[c - 3, 2] * G[s, k, 2, y])
                    ear_half[kk, c, 2 - y] = 0.5 * m + g
                    ear_full[kk, c, 2 - y] = m + g
        L_test = np.empty((n, 3, 3))
        W_test = np.empty((n, r, 3))
        if not factor_strand(d_half, Vs, ear_half, 0, n, L_test, W_test):
            status[s] = 2
            continue
        if not factor_strand(d_full, Vs, ear_full, 0, n, L3[e0:e0 + n], W[e0:e0 + n]):
            status[s] = 2
            continue
        status[s] = 0


def mass_apply(mass, x: np.ndarray, n_elements) -> np.ndarray:
    """M x per strand from the generators (dynamics.MassGenerators), O(N): x and the result (S, N, 3) padded."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    out = np.zeros_like(x)
    _mass_apply_kernel(mass.diag, mass.later, mass.earlier, np.asarray(n_elements, dtype=np.int64),
                       x.reshape(x.shape[0], -1), out.reshape(x.shape[0], -1))
    return out


@njit(cache=True)
def _mass_apply_kernel(diag, later, earlier, n_elements, x, out):
    for s in range(diag.shape[0]):
        n = n_elements[s]
        matvec_strand(diag[s], later[s], earlier[s], 0, n, x[s, :3 * n], out[s, :3 * n])


@njit(cache=True)
def _forward_from(L, b, n, first):
    """y = L^-1 b on the first n rows when b[:first] = 0 (then y[:first] = 0): the rows from ``first`` on, over the
    columns from ``first`` on (L lower triangular, packed rows: StrandFactors)."""
    y = np.zeros(n)
    for i in range(first, n):
        acc = b[i]
        r = i * (i + 1) // 2
        for k in range(first, i):
            acc -= L[r + k] * y[k]
        y[i] = acc / L[r + i]
    return y


@njit(cache=True)
def _backward(L, y, n):
    """x = L^-T y on the first n rows (column i of L^T is row i of L: contiguous; packed rows)."""
    x = y[:n].copy()
    for i in range(n - 1, -1, -1):
        r = i * (i + 1) // 2
        xi = x[i] / L[r + i]
        x[i] = xi
        for k in range(i):
            x[k] -= L[r + k] * xi
    return x


def cho_inverse(L: np.ndarray, n: int) -> np.ndarray:
    """(L L^T)^-1 restricted to the first n dofs (a strand's real elements), LAPACK dpotri.
    L: lower triangular with zeros above the diagonal (as factor_step_matrix returns it)."""
    inv, info = lapack.dpotri(L[:n, :n], lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotri failed (info {info})")
    out = inv + inv.T  # dpotri wrote the lower triangle; the upper one is L's zeros
    out.flat[:: n + 1] *= 0.5
    return out


# --------------------------------------------------------------------------- the step matrix's parts, applied
def step_difference_apply(factors: StrandFactors, corrections: StepCorrections | None, x: np.ndarray, *,
                          a_scale: float, stiffness, k_scale: float, gravity_parts, b_scale: float) -> np.ndarray:
    """(Mhat - M) x per strand without M, from the parts factor_step_matrix put into Mhat = a_scale M + k_scale K
    + b_scale dF/dq + C (C on the strands ``factors.corrected``):

        (Mhat - M) x = ((a_scale - 1) Mhat x + k_scale K x + b_scale dF/dq x + C x) / a_scale,

    Mhat x from the factors (only when a_scale != 1), dF/dq x from the generators ``gravity_parts`` (U, G, Dg) of
    superhelix.gravity_force_jacobian_parts in O(N) (None: b_scale 0), C from ``corrections``.  x and the result
    (S, N, 3) padded (zero on padding); stiffness K (S, N, 3) diagonal."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    S, N, _ = x.shape
    n_elements = factors.sizes // 3
    out = k_scale * np.asarray(stiffness, dtype=np.float64) * x
    if gravity_parts is not None and b_scale != 0.0:
        U, G, Dg = gravity_parts
        _gravity_jacobian_apply(U, G, Dg, n_elements, b_scale, x, out)
    if np.any(factors.corrected):
        if corrections is None or not np.all(factors.correction_kept[factors.corrected]):
            raise ValueError("a correction of the step matrix was not kept (StepCorrections)")
        for data, start in corrections.by_arena():
            _corrections_apply(data, start, corrections.size, factors.corrected, x.reshape(S, 3 * N),
                               out.reshape(S, 3 * N))
    if a_scale != 1.0:
        out += (a_scale - 1.0) * factors.apply(x.reshape(S, 3 * N)).reshape(S, N, 3)
        out /= a_scale
    return out


@njit(cache=True)
def _gravity_jacobian_apply(U, G, Dg, n_elements, scale, x, out):
    """out += scale dF/dq x per strand, dF/dq with blocks U_j G_k (j < k), (U_k G_j)^T (j > k), Dg_j (j = k):
    y_j = Dg_j x_j + U_j sum_{k>j} G_k x_k + G_j^T sum_{k<j} U_k^T x_k (prefix and suffix sums, O(N))."""
    for s in range(x.shape[0]):
        N = n_elements[s]
        p0 = p1 = p2 = 0.0  # sum_{k<j} U_k^T x_k
        for j in range(N):
            x0, x1, x2 = x[s, j, 0], x[s, j, 1], x[s, j, 2]
            for a in range(3):
                out[s, j, a] += scale * (Dg[s, j, a, 0] * x0 + Dg[s, j, a, 1] * x1 + Dg[s, j, a, 2] * x2
                                         + G[s, j, 0, a] * p0 + G[s, j, 1, a] * p1 + G[s, j, 2, a] * p2)
            p0 += U[s, j, 0, 0] * x0 + U[s, j, 1, 0] * x1 + U[s, j, 2, 0] * x2
            p1 += U[s, j, 0, 1] * x0 + U[s, j, 1, 1] * x1 + U[s, j, 2, 1] * x2
            p2 += U[s, j, 0, 2] * x0 + U[s, j, 1, 2] * x1 + U[s, j, 2, 2] * x2
        q0 = q1 = q2 = 0.0  # sum_{k>j} G_k x_k
        for j in range(N - 1, -1, -1):
            for a in range(3):
                out[s, j, a] += scale * (U[s, j, a, 0] * q0 + U[s, j, a, 1] * q1 + U[s, j, a, 2] * q2)
            x0, x1, x2 = x[s, j, 0], x[s, j, 1], x[s, j, 2]
            q0 += G[s, j, 0, 0] * x0 + G[s, j, 0, 1] * x1 + G[s, j, 0, 2] * x2
            q1 += G[s, j, 1, 0] * x0 + G[s, j, 1, 1] * x1 + G[s, j, 1, 2] * x2
            q2 += G[s, j, 2, 0] * x0 + G[s, j, 2, 1] * x1 + G[s, j, 2, 2] * x2


@njit(cache=True)
def _corrections_apply(data, start, size, corrected, x, out):
    """out[s, :n] += C_s x[s, :n] on the strands ``corrected`` with start[s] >= 0 (C_s symmetric, its lower
    triangle packed at data[start[s]:])."""
    y = np.empty(x.shape[1])
    for s in range(x.shape[0]):
        if not corrected[s] or start[s] < 0:
            continue
        n = size[s]
        o = start[s]
        # one pass over the packed rows: row i gives y_i its terms k <= i and y_k (k < i) its term C[k, i] = C[i, k],
        # so every y_i is summed over k = 0 .. n - 1 in order (the dense row product's sum, bit for bit)
        for i in range(n):
            r = o + i * (i + 1) // 2
            xi = x[s, i]
            acc = 0.0
            for k in range(i):
                c = data[r + k]
                acc += c * x[s, k]
                y[k] += c * xi
            y[i] = acc + data[r + i] * xi
        for i in range(n):
            out[s, i] += y[i]


# --------------------------------------------------------------------------- H on the dofs the contacts move
@njit(cache=True)
def _contact_row_norms(indptr, data):
    """Per contact (3 rows) the largest row norm of H."""
    m = (indptr.shape[0] - 1) // 3
    out = np.zeros(m)
    for i in range(m):
        best = 0.0
        for r in range(3 * i, 3 * i + 3):
            acc = 0.0
            for p in range(indptr[r], indptr[r + 1]):
                acc += data[p] * data[p]
            best = max(best, acc)
        out[i] = np.sqrt(best)
    return out


@njit(cache=True)
def _moved_dofs_kernel(indptr, indices, data, keep, dof_strand, strand_start, n_strands):
    """H restricted to the kept contacts' rows (indptr, indices, data) and the per-strand count k_s of leading
    dofs any kept entry touches (largest local dof + 1)."""
    m = keep.shape[0]
    k = np.zeros(n_strands, np.int64)
    new_ptr = np.zeros(3 * int(keep.sum()) + 1, np.int64)
    r_out = 0
    for i in range(m):
        if not keep[i]:
            continue
        for r in range(3 * i, 3 * i + 3):
            new_ptr[r_out + 1] = new_ptr[r_out] + indptr[r + 1] - indptr[r]
            for p in range(indptr[r], indptr[r + 1]):
                c = indices[p]
                s = dof_strand[c]
                loc = c - strand_start[s] + 1
                if loc > k[s]:
                    k[s] = loc
            r_out += 1
    nnz = new_ptr[r_out]
    new_idx = np.empty(nnz, indices.dtype)
    new_data = np.empty(nnz)
    q = 0
    for i in range(m):
        if not keep[i]:
            continue
        for r in range(3 * i, 3 * i + 3):
            for p in range(indptr[r], indptr[r + 1]):
                new_idx[q] = indices[p]
                new_data[q] = data[p]
                q += 1
    return new_ptr, new_idx, new_data, k


@njit(cache=True)
def _shift_columns(indices, dof_strand, strand_start, new_start):
    """Column c of strand s -> new_start[s] + (c - strand_start[s])."""
    out = np.empty(indices.shape[0], np.int64)
    for p in range(indices.shape[0]):
        c = indices[p]
        s = dof_strand[c]
        out[p] = new_start[s] + c - strand_start[s]
    return out


def moved_dofs(H, dof_offsets: np.ndarray, min_relative_norm: float = 1e-9):
    """The contact Jacobian on the dofs the contacts move (Simulator._build_problem): a contact on element e
    moves the dofs of elements 0..e of its strands only, so strand s needs its first k_s dofs.

    H: (3m, n) CSR with sorted indices, strand s owning columns dof_offsets[s]:dof_offsets[s + 1].  Contacts whose
    rows are all below ``min_relative_norm`` of the largest (no dof moves them: at a clamped root) are dropped.
    Returns (keep (m,) bool, H on the kept rows (3m', n), k (S,), H_moved (3m', sum k) with strand s's columns
    at sum_{t<s} k_t), or None when no contact is kept.  O(nnz) compiled passes (no temporaries of nnz size
    besides the outputs)."""
    H = sp.csr_matrix(H)
    indptr = np.ascontiguousarray(H.indptr, dtype=np.int64)
    norms = _contact_row_norms(indptr, H.data)
    keep = norms > min_relative_norm * float(np.max(norms, initial=0.0))
    if not np.any(keep):
        return None
    dof_offsets = np.asarray(dof_offsets, dtype=np.int64)
    S = len(dof_offsets) - 1
    dof_strand = np.repeat(np.arange(S, dtype=np.int64), np.diff(dof_offsets))
    if np.all(keep):
        ptr, idx, data = indptr, np.ascontiguousarray(H.indices), H.data
        k = _max_local_dofs(indptr, idx, dof_strand, dof_offsets, S)
        H_kept = H
    else:
        ptr, idx, data, k = _moved_dofs_kernel(indptr, H.indices, H.data, keep, dof_strand, dof_offsets, S)
        H_kept = sp.csr_matrix((data, idx, ptr), shape=(len(ptr) - 1, H.shape[1]))
    new_start = np.zeros(S, dtype=np.int64)
    np.cumsum(k[:-1], out=new_start[1:])
    H_moved = sp.csr_matrix((data, _shift_columns(idx, dof_strand, dof_offsets, new_start), ptr),
                            shape=(len(ptr) - 1, int(k.sum())))
    return keep, H_kept, k, H_moved


@njit(cache=True)
def _max_local_dofs(indptr, indices, dof_strand, strand_start, n_strands):
    """Per strand the largest local column + 1 over all entries."""
    k = np.zeros(n_strands, np.int64)
    for p in range(indices.shape[0]):
        c = indices[p]
        s = dof_strand[c]
        loc = c - strand_start[s] + 1
        if loc > k[s]:
            k[s] = loc
    return k
