"""Sparse 3x3-block storage of the Delassus operator, and of H / HD per contact.

UpperBlockDelassus: W's upper block triangle (W_ij != 0 only when contacts i and j share a strand), the
form Gauss-Seidel and APGD multiply by (upper_block_matvec); from a scipy matrix through BlockDelassus (all
blocks, both triangles, in block-CSR), or strand by strand from a ContactProblem (assemble_upper).

PackedRows: a (3m, n) sparse matrix regrouped per contact: the union of the columns its three rows
touch, and a (k, 3) value panel, so one index load serves the normal and both tangent rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit

# numba fastmath flags: fused multiply-add only (IEEE semantics otherwise)
_FM = {"contract"}


@dataclass
class BlockDelassus:
    """W (3m x 3m) as block-CSR: row i's blocks are blocks[indptr[i]:indptr[i+1]], columns indices[...]."""

    indptr: np.ndarray
    indices: np.ndarray
    blocks: np.ndarray

    @classmethod
    def from_sparse(cls, W) -> "BlockDelassus":
        """From any scipy sparse (3m, 3m) matrix; the diagonal blocks are always stored."""
        W = sp.csr_matrix(W, dtype=np.float64)
        if W.shape[0] != W.shape[1] or W.shape[0] % 3:
            raise ValueError(f"W must be square with a multiple of 3 rows, got {W.shape}")
        n = W.shape[0]
        eye = sp.identity(n, format="csr")
        Wb = sp.bsr_matrix(W + eye, blocksize=(3, 3))
        Wb.sort_indices()
        data = np.ascontiguousarray(Wb.data, dtype=np.float64)
        indptr = np.ascontiguousarray(Wb.indptr, dtype=np.int64)
        indices = np.ascontiguousarray(Wb.indices, dtype=np.int64)
        rows = np.repeat(np.arange(n // 3), np.diff(indptr))
        diag = rows == indices
        data[diag] -= np.eye(3)
        return cls(indptr, indices, data)

    @property
    def n_contacts(self) -> int:
        return self.indptr.shape[0] - 1


@njit(cache=True, fastmath=_FM)
def upper_block_matvec(indptr, indices, blocks, r, b, out):
    """out = W r + b for W stored as its upper block triangle (row i: blocks (i, j), j >= i, the diagonal
    block first when it is stored).  The off-diagonal loop has no branch (25-30 % faster than testing
    j != i per block, issue 22)."""
    m = indptr.shape[0] - 1
    for i in range(m):
        out[i, 0] = b[i, 0]
        out[i, 1] = b[i, 1]
        out[i, 2] = b[i, 2]
    for i in range(m):
        y0 = r[i, 0]
        y1 = r[i, 1]
        y2 = r[i, 2]
        u0 = 0.0
        u1 = 0.0
        u2 = 0.0
        p0 = indptr[i]
        p1 = indptr[i + 1]
        if p0 < p1 and indices[p0] == i:
            u0 = blocks[p0, 0, 0] * y0 + blocks[p0, 0, 1] * y1 + blocks[p0, 0, 2] * y2
            u1 = blocks[p0, 1, 0] * y0 + blocks[p0, 1, 1] * y1 + blocks[p0, 1, 2] * y2
            u2 = blocks[p0, 2, 0] * y0 + blocks[p0, 2, 1] * y1 + blocks[p0, 2, 2] * y2
            p0 += 1
        for p in range(p0, p1):
            j = indices[p]
            x0 = r[j, 0]
            x1 = r[j, 1]
            x2 = r[j, 2]
            b00 = blocks[p, 0, 0]
            b01 = blocks[p, 0, 1]
            b02 = blocks[p, 0, 2]
            b10 = blocks[p, 1, 0]
            b11 = blocks[p, 1, 1]
            b12 = blocks[p, 1, 2]
            b20 = blocks[p, 2, 0]
            b21 = blocks[p, 2, 1]
            b22 = blocks[p, 2, 2]
            u0 += b00 * x0 + b01 * x1 + b02 * x2
            u1 += b10 * x0 + b11 * x1 + b12 * x2
            u2 += b20 * x0 + b21 * x1 + b22 * x2
            out[j, 0] += b00 * y0 + b10 * y1 + b20 * y2
            out[j, 1] += b01 * y0 + b11 * y1 + b21 * y2
            out[j, 2] += b02 * y0 + b12 * y1 + b22 * y2
        out[i, 0] += u0
        out[i, 1] += u1
        out[i, 2] += u2


@dataclass
class UpperBlockDelassus:
    """W (symmetric) stored as its upper block triangle: row i holds blocks (i, j), j >= i, the
    diagonal block first.  Half the memory traffic of BlockDelassus; the lower part is used as
    W_ji = W_ij^T."""

    indptr: np.ndarray
    indices: np.ndarray
    blocks: np.ndarray

    @classmethod
    def from_block(cls, W: BlockDelassus) -> "UpperBlockDelassus":
        m = W.n_contacts
        rows = np.repeat(np.arange(m), np.diff(W.indptr))
        keep = W.indices >= rows
        # diagonal first in each row (indices are sorted, so it is already first among j >= i)
        indptr = np.zeros(m + 1, dtype=np.int64)
        np.add.at(indptr, rows[keep] + 1, 1)
        indptr = np.cumsum(indptr)
        idx_type = np.int32 if m < 2**31 else np.int64
        return cls(indptr, np.ascontiguousarray(W.indices[keep], dtype=idx_type), np.ascontiguousarray(W.blocks[keep]))

    @classmethod
    def from_sparse(cls, W) -> "UpperBlockDelassus":
        return cls.from_block(BlockDelassus.from_sparse(W))

    @property
    def n_contacts(self) -> int:
        return self.indptr.shape[0] - 1

    @property
    def nbytes(self) -> int:
        return self.indptr.nbytes + self.indices.nbytes + self.blocks.nbytes

    def diagonal(self) -> np.ndarray:
        return self.blocks[self.indptr[:-1]].copy()


@njit(cache=True)
def _merge_rows(indptr, indices, data, ptr, cols, vals, count_only):
    """Merge the sorted column lists of rows 3i, 3i+1, 3i+2 of a CSR matrix.  count_only: ptr[i+1] =
    number of distinct columns of contact i; else fill cols / vals (ptr then holds the offsets)."""
    m = ptr.shape[0] - 1
    for i in range(m):
        p0 = indptr[3 * i]
        p1 = indptr[3 * i + 1]
        p2 = indptr[3 * i + 2]
        e0 = p1
        e1 = p2
        e2 = indptr[3 * i + 3]
        out = 0 if count_only else ptr[i]
        k = e0 - p0
        same = e1 - p1 == k and e2 - p2 == k
        if same:
            for t in range(k):
                if indices[p0 + t] != indices[p1 + t] or indices[p0 + t] != indices[p2 + t]:
                    same = False
                    break
        if same:  # the usual case: a frame times one point Jacobian
            if count_only:
                ptr[i + 1] = k
            else:
                for t in range(k):
                    cols[out + t] = indices[p0 + t]
                    vals[out + t, 0] = data[p0 + t]
                    vals[out + t, 1] = data[p1 + t]
                    vals[out + t, 2] = data[p2 + t]
            continue
        big = np.iinfo(np.int64).max
        while p0 < e0 or p1 < e1 or p2 < e2:
            c0 = np.int64(indices[p0]) if p0 < e0 else big
            c1 = np.int64(indices[p1]) if p1 < e1 else big
            c2 = np.int64(indices[p2]) if p2 < e2 else big
            c = min(c0, min(c1, c2))
            if not count_only:
                cols[out] = c
            if c0 == c:
                if not count_only:
                    vals[out, 0] += data[p0]
                p0 += 1
            if c1 == c:
                if not count_only:
                    vals[out, 1] += data[p1]
                p1 += 1
            if c2 == c:
                if not count_only:
                    vals[out, 2] += data[p2]
                p2 += 1
            out += 1
        if count_only:
            ptr[i + 1] = out


@dataclass
class PackedRows:
    """Per-contact column panels of a (3m, n) sparse matrix: contact i touches columns
    cols[ptr[i]:ptr[i+1]] with values vals[ptr[i]:ptr[i+1], 0:3] (its N, T1, T2 rows)."""

    ptr: np.ndarray
    cols: np.ndarray
    vals: np.ndarray

    @classmethod
    def from_sparse(cls, M) -> "PackedRows":
        M = sp.csr_matrix(M, dtype=np.float64)
        if not M.has_sorted_indices:
            M = M.copy()
            M.sort_indices()
        m = M.shape[0] // 3
        indptr = M.indptr
        indices = M.indices
        ptr = np.zeros(m + 1, dtype=np.int64)
        _merge_rows(indptr, indices, M.data, ptr, np.zeros(0, dtype=np.int32 if M.shape[1] < 2**31 else np.int64),
                    np.zeros((0, 3)), True)
        ptr = np.cumsum(ptr)
        cols = np.empty(ptr[-1], dtype=np.int32 if M.shape[1] < 2**31 else np.int64)
        vals = np.zeros((ptr[-1], 3))
        _merge_rows(indptr, indices, M.data, ptr, cols, vals, False)
        return cls(ptr, cols, vals)

    @property
    def nbytes(self) -> int:
        return self.ptr.nbytes + self.cols.nbytes + self.vals.nbytes


@njit(cache=True)
def _take_panels(ptr, cols, vals, idx, col_map, out_ptr, out_cols, out_vals):
    """Contact i of the output (where idx[i] >= 0) takes the panel of contact idx[i], its columns through col_map
    (empty: kept)."""
    remap = col_map.shape[0] > 0
    for i in range(idx.shape[0]):
        src = idx[i]
        if src < 0:
            continue
        o = out_ptr[i]
        for p in range(ptr[src], ptr[src + 1]):
            out_cols[o] = col_map[cols[p]] if remap else cols[p]
            out_vals[o, 0] = vals[p, 0]
            out_vals[o, 1] = vals[p, 1]
            out_vals[o, 2] = vals[p, 2]
            o += 1


def merge_rows(sources) -> "PackedRows":
    """PackedRows whose contact i is, for the one source (P, idx, col_map) with idx[i] >= 0, the panel of P's contact
    idx[i] with its columns through col_map (old column -> new; None: kept).  Every contact of the output must have
    exactly one source.  One compiled pass over the entries taken."""
    sources = list(sources)
    m = len(sources[0][1])
    counts = np.zeros(m, dtype=np.int64)
    for P, idx, _ in sources:
        idx = np.asarray(idx, dtype=np.int64)
        on = idx >= 0
        counts[on] += P.ptr[idx[on] + 1] - P.ptr[idx[on]]
    ptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    dtype = np.result_type(*[P.cols.dtype for P, _, _ in sources])
    cols = np.empty(int(ptr[-1]), dtype=dtype)
    vals = np.empty((int(ptr[-1]), 3))
    for P, idx, col_map in sources:
        col_map = np.zeros(0, dtype=np.int64) if col_map is None else np.ascontiguousarray(col_map, dtype=np.int64)
        _take_panels(P.ptr, P.cols, P.vals, np.ascontiguousarray(idx, dtype=np.int64), col_map, ptr, cols, vals)
    return PackedRows(ptr, cols, vals)


def upper_from_blocks(m: int, i, j, blocks) -> "UpperBlockDelassus":
    """W's upper block triangle from its blocks W_ij (k, 3, 3), given once each with either i <= j or i > j (then
    transposed into (j, i)); every contact needs its diagonal block among them (none is added)."""
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    blocks = np.asarray(blocks, dtype=np.float64)
    swap = i > j
    if np.any(swap):
        i, j = np.where(swap, j, i), np.where(swap, i, j)
        blocks = np.where(swap[:, None, None], np.transpose(blocks, (0, 2, 1)), blocks)
    indptr, cols, out = _rows_from_pairs(m, i, j, np.ascontiguousarray(blocks), 0.0)
    return UpperBlockDelassus(indptr, cols.astype(np.int32 if m < 2**31 else np.int64), out)


def upper_blocks(W: "UpperBlockDelassus") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(i, j, blocks) of every stored block of W (i <= j)."""
    m = W.n_contacts
    return np.repeat(np.arange(m), np.diff(W.indptr)), np.asarray(W.indices, dtype=np.int64), W.blocks


# ----------------------------------------------------------------------------------------------
# direct assembly of the upper block triangle of W = H D H^T + 2 gamma I, strand by strand
# ----------------------------------------------------------------------------------------------
def flat_strand_blocks(problem):
    """D as flat storage (data, ptr, is_diagonal): strand s's block is data[ptr[s]:ptr[s+1]]
    (n_s entries if diagonal, n_s * n_s row-major otherwise)."""
    return problem.D_data, problem.D_ptr, problem.D_is_diag


@njit(cache=True, fastmath=_FM)
def strand_blocks_apply(d_data, d_ptr, d_diag, offsets, x, out):
    """out = D x for block-diagonal D in flat storage."""
    for s in range(offsets.shape[0] - 1):
        off = offsets[s]
        ns = offsets[s + 1] - off
        dp = d_ptr[s]
        if d_diag[s]:
            for k in range(ns):
                out[off + k] = d_data[dp + k] * x[off + k]
        else:
            for a in range(ns):
                acc = 0.0
                row = dp + a * ns
                for k in range(ns):
                    acc += d_data[row + k] * x[off + k]
                out[off + a] = acc


@njit(cache=True)
def _pack_hd(h_ptr, h_cols, h_vals, offsets, d_data, d_ptr, d_diag, strand_of, g_ptr, g_cols, g_vals, count_only):
    """Packed rows of H D from packed H, per contact and strand segment: G[p] = d_p H[p] where D_s is
    diagonal; a dense D_s's segment takes the strand's n_s dofs (counted here, filled by
    _pack_dense_strands)."""
    m = h_ptr.shape[0] - 1
    for i in range(m):
        out = g_ptr[i]
        p = h_ptr[i]
        cnt = 0
        while p < h_ptr[i + 1]:
            s = strand_of[p]
            q = p
            while q < h_ptr[i + 1] and strand_of[q] == s:
                q += 1
            off = offsets[s]
            if d_diag[s]:
                if not count_only:
                    dp = d_ptr[s]
                    for t in range(p, q):
                        dd = d_data[dp + h_cols[t] - off]
                        g_cols[out + cnt] = h_cols[t]
                        g_vals[out + cnt, 0] = dd * h_vals[t, 0]
                        g_vals[out + cnt, 1] = dd * h_vals[t, 1]
                        g_vals[out + cnt, 2] = dd * h_vals[t, 2]
                        cnt += 1
                else:
                    cnt += q - p
            else:
                cnt += offsets[s + 1] - off
            p = q
        if count_only:
            g_ptr[i + 1] = cnt


@njit(cache=True)
def _dense_segments(h_ptr, strand_of, offsets, d_diag, g_ptr, count_only, seg_strand, seg_p, seg_q, seg_out):
    """The runs of each contact's packed H entries on one strand whose D block is dense: strand, entry
    range [p, q) and where its H D panel starts in the packed output (g_ptr filled).  Returns their count."""
    n = 0
    for i in range(h_ptr.shape[0] - 1):
        out = g_ptr[i]
        p = h_ptr[i]
        while p < h_ptr[i + 1]:
            s = strand_of[p]
            q = p
            while q < h_ptr[i + 1] and strand_of[q] == s:
                q += 1
            if d_diag[s]:
                out += q - p
            else:
                if not count_only:
                    seg_strand[n], seg_p[n], seg_q[n], seg_out[n] = s, p, q, out
                n += 1
                out += offsets[s + 1] - offsets[s]
            p = q
    return n


@njit(cache=True)
def _pack_dense_strands(h_cols, h_vals, offsets, d_data, d_ptr, order, seg_strand, seg_p, seg_q, seg_out,
                        g_cols, g_vals):
    """H D panels of the dense strands, strand by strand: H_s (3 c_s x n_s, the strand's c_s contact
    segments) times D_s in one BLAS product (np.dot), scattered into the packed output.  ``order``
    lists the segments grouped by strand."""
    n = order.shape[0]
    a = 0
    while a < n:
        s = seg_strand[order[a]]
        b = a
        while b < n and seg_strand[order[b]] == s:
            b += 1
        off = offsets[s]
        ns = offsets[s + 1] - off
        Hs = np.zeros((3 * (b - a), ns))
        for r in range(b - a):
            g = order[a + r]
            for t in range(seg_p[g], seg_q[g]):
                c = h_cols[t] - off
                Hs[3 * r, c] = h_vals[t, 0]
                Hs[3 * r + 1, c] = h_vals[t, 1]
                Hs[3 * r + 2, c] = h_vals[t, 2]
        Gs = np.dot(Hs, d_data[d_ptr[s]:d_ptr[s + 1]].reshape(ns, ns))
        for r in range(b - a):
            out = seg_out[order[a + r]]
            for k in range(ns):
                g_cols[out + k] = off + k
                g_vals[out + k, 0] = Gs[3 * r, k]
                g_vals[out + k, 1] = Gs[3 * r + 1, k]
                g_vals[out + k, 2] = Gs[3 * r + 2, k]
        a = b


def dof_strands(offsets) -> np.ndarray:
    """(n,) the strand of every dof (strand s owns dofs offsets[s]:offsets[s+1]): a gather, where searchsorted on
    every packed column cost ~5 ms a step on the README example."""
    offsets = np.asarray(offsets, dtype=np.int64)
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))


def pack_HD(H: "PackedRows", offsets, d_data, d_ptr, d_diag) -> "PackedRows":
    """H D regrouped per contact, from packed H and D in flat storage (no sparse product).  Diagonal
    D blocks entry by entry; dense ones strand by strand as one BLAS product H_s D_s (the simulator's
    Mhat^-1 blocks: 3-4x faster than the row-by-row loop)."""
    m = H.ptr.shape[0] - 1
    strand_of = dof_strands(offsets)[H.cols]
    ptr = np.zeros(m + 1, dtype=np.int64)
    z_cols = np.zeros(0, dtype=H.cols.dtype)
    z_vals = np.zeros((0, 3))
    _pack_hd(H.ptr, H.cols, H.vals, offsets, d_data, d_ptr, d_diag, strand_of, ptr, z_cols, z_vals, True)
    ptr = np.cumsum(ptr)
    cols = np.empty(ptr[-1], dtype=H.cols.dtype)
    vals = np.empty((ptr[-1], 3))
    dense = ~np.asarray(d_diag, dtype=np.bool_)
    if np.any(dense):
        z = np.zeros(0, dtype=np.int64)
        n_seg = _dense_segments(H.ptr, strand_of, offsets, d_diag, ptr, True, z, z, z, z)
        seg = [np.empty(n_seg, dtype=np.int64) for _ in range(4)]
        _dense_segments(H.ptr, strand_of, offsets, d_diag, ptr, False, *seg)
        order = np.argsort(seg[0], kind="stable")
        _pack_dense_strands(H.cols, H.vals, offsets, d_data, d_ptr, order, *seg, cols, vals)
    if not np.all(dense):
        _pack_hd(H.ptr, H.cols, H.vals, offsets, d_data, d_ptr, d_diag, strand_of, ptr, cols, vals, False)
    return PackedRows(ptr, cols, vals)


@njit(cache=True, fastmath=_FM)
def _strand_pair_blocks(seg_ptr, seg_contact, seg_h0, seg_h1, h_cols, h_vals, offsets, d_data, d_ptr, d_diag,
                        out_i, out_j, out_blocks):
    """For every strand s and every pair (a <= b) of contact segments on s:
    W_{i_a i_b} += sum_{p, q} H_a[p] D_s[p, q] H_b[q]^T  (written as the upper-triangle block).
    Returns the number of blocks written."""
    n_out = 0
    S = seg_ptr.shape[0] - 1
    kmax = 0
    nmax = 0
    for s in range(S):
        kmax = max(kmax, seg_ptr[s + 1] - seg_ptr[s])
        nmax = max(nmax, offsets[s + 1] - offsets[s])
    G = np.empty((kmax, nmax, 3))  # scratch: G[a, q] = (D_s H_a^T)[q]
    for s in range(S):
        k0 = seg_ptr[s]
        k1 = seg_ptr[s + 1]
        k = k1 - k0
        if k == 0:
            continue
        off = offsets[s]
        ns = offsets[s + 1] - off
        for a in range(k):
            for q in range(ns):
                G[a, q, 0] = 0.0
                G[a, q, 1] = 0.0
                G[a, q, 2] = 0.0
        dp = d_ptr[s]
        for a in range(k):
            for p in range(seg_h0[k0 + a], seg_h1[k0 + a]):
                col = h_cols[p] - off
                v0 = h_vals[p, 0]
                v1 = h_vals[p, 1]
                v2 = h_vals[p, 2]
                if d_diag[s]:
                    dd = d_data[dp + col]
                    G[a, col, 0] += dd * v0
                    G[a, col, 1] += dd * v1
                    G[a, col, 2] += dd * v2
                else:
                    for q in range(ns):
                        dd = d_data[dp + col * ns + q]
                        G[a, q, 0] += dd * v0
                        G[a, q, 1] += dd * v1
                        G[a, q, 2] += dd * v2
        for a in range(k):
            ia = seg_contact[k0 + a]
            for b in range(k):
                ib = seg_contact[k0 + b]
                if ib < ia or (ib == ia and b < a):
                    continue
                # block (ia, ib)[x, y] = sum_q G[a, q, x] H_b[q, y]
                b00 = b01 = b02 = b10 = b11 = b12 = b20 = b21 = b22 = 0.0
                for p in range(seg_h0[k0 + b], seg_h1[k0 + b]):
                    q = h_cols[p] - off
                    g0 = G[a, q, 0]
                    g1 = G[a, q, 1]
                    g2 = G[a, q, 2]
                    y0 = h_vals[p, 0]
                    y1 = h_vals[p, 1]
                    y2 = h_vals[p, 2]
                    b00 += g0 * y0
                    b01 += g0 * y1
                    b02 += g0 * y2
                    b10 += g1 * y0
                    b11 += g1 * y1
                    b12 += g1 * y2
                    b20 += g2 * y0
                    b21 += g2 * y1
                    b22 += g2 * y2
                out_i[n_out] = ia
                out_j[n_out] = ib
                blk = out_blocks[n_out]
                blk[0, 0] = b00
                blk[0, 1] = b01
                blk[0, 2] = b02
                blk[1, 0] = b10
                blk[1, 1] = b11
                blk[1, 2] = b12
                blk[2, 0] = b20
                blk[2, 1] = b21
                blk[2, 2] = b22
                if ia == ib and a != b:
                    # two segments of one contact on the same strand: the pair (b, a) is the transpose
                    for x in range(3):
                        for y in range(x + 1, 3):
                            t = blk[x, y] + blk[y, x]
                            blk[x, y] = t
                            blk[y, x] = t
                    for x in range(3):
                        blk[x, x] *= 2.0
                n_out += 1
    return n_out


@njit(cache=True)
def _segments(h_ptr, h_cols, offsets, count_only, seg_strand, seg_contact, seg_h0, seg_h1):
    """Runs of each contact's packed columns that fall in one strand (columns sorted per contact).
    Returns the number of runs."""
    S = offsets.shape[0] - 1
    n = 0
    for i in range(h_ptr.shape[0] - 1):
        p = h_ptr[i]
        while p < h_ptr[i + 1]:
            col = h_cols[p]
            lo = 0
            hi = S  # offsets[lo] <= col < offsets[hi]
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if offsets[mid] <= col:
                    lo = mid
                else:
                    hi = mid
            end = offsets[lo + 1]
            q = p
            while q < h_ptr[i + 1] and h_cols[q] < end:
                q += 1
            if not count_only:
                seg_strand[n] = lo
                seg_contact[n] = i
                seg_h0[n] = p
                seg_h1[n] = q
            n += 1
            p = q
    return n


@njit(cache=True)
def _bucket_by_strand(S, seg_strand, seg_contact, seg_h0, seg_h1):
    """Counting sort of the runs by strand (stable: contacts stay increasing within a strand)."""
    n = seg_strand.shape[0]
    ptr = np.zeros(S + 1, dtype=np.int64)
    for k in range(n):
        ptr[seg_strand[k] + 1] += 1
    for s in range(S):
        ptr[s + 1] += ptr[s]
    pos = ptr[:-1].copy()
    c = np.empty(n, dtype=np.int64)
    h0 = np.empty(n, dtype=np.int64)
    h1 = np.empty(n, dtype=np.int64)
    for k in range(n):
        s = seg_strand[k]
        j = pos[s]
        pos[s] += 1
        c[j] = seg_contact[k]
        h0[j] = seg_h0[k]
        h1[j] = seg_h1[k]
    return ptr, c, h0, h1


def contact_segments(problem, H: "PackedRows"):
    """Per (strand, contact) runs of H's packed panels: (seg_ptr over strands, contact, h0, h1), cached
    on the problem."""
    if "segments" in problem._cache:
        return problem._cache["segments"]
    offsets = problem.dof_offsets
    z = np.zeros(0, dtype=np.int64)
    n = _segments(H.ptr, H.cols, offsets, True, z, z, z, z)
    st = np.empty(n, dtype=np.int64)
    sc = np.empty(n, dtype=np.int64)
    h0 = np.empty(n, dtype=np.int64)
    h1 = np.empty(n, dtype=np.int64)
    _segments(H.ptr, H.cols, offsets, False, st, sc, h0, h1)
    out = _bucket_by_strand(problem.n_strands, st, sc, h0, h1)
    problem._cache["segments"] = out
    return out


def assemble_upper(problem, H: "PackedRows | None" = None) -> UpperBlockDelassus:
    """The upper block triangle of W = H D H^T + 2 gamma I, assembled strand by strand in numba
    (no sparse-sparse product; cost sum_s k_s^2 * nnz per contact panel)."""
    H = problem.packed_H() if H is None else H
    m = problem.n_contacts
    seg_ptr, seg_contact, h0, h1 = contact_segments(problem, H)
    k = np.diff(seg_ptr)
    n_pairs = int(np.sum(k * (k + 1) // 2))
    out_i = np.empty(n_pairs, dtype=np.int64)
    out_j = np.empty(n_pairs, dtype=np.int64)
    out_b = np.empty((n_pairs, 3, 3))
    d_data, d_ptr, d_diag = flat_strand_blocks(problem)
    n = _strand_pair_blocks(seg_ptr, seg_contact, h0, h1, H.cols, H.vals, problem.dof_offsets, d_data, d_ptr, d_diag,
                            out_i, out_j, out_b)
    indptr, cols, blocks = _rows_from_pairs(m, out_i[:n], out_j[:n], out_b[:n], 2.0 * problem.gamma)
    idx_type = np.int32 if m < 2**31 else np.int64
    return UpperBlockDelassus(indptr, cols.astype(idx_type), blocks)


@njit(cache=True)
def _rows_from_pairs(m, pi, pj, pb, gamma2):
    """Group (i, j, block) contributions (i <= j) into block-CSR rows: diagonal first, columns sorted,
    duplicates summed, + 2 gamma I on every diagonal (present for every contact)."""
    n = pi.shape[0]
    cnt = np.ones(m + 1, dtype=np.int64)  # one slot per row for the diagonal
    cnt[0] = 0
    for k in range(n):
        if pi[k] != pj[k]:
            cnt[pi[k] + 1] += 1
    for i in range(m):
        cnt[i + 1] += cnt[i]
    cap = cnt
    cols = np.empty(cap[m], dtype=np.int64)
    blocks = np.zeros((cap[m], 3, 3))
    fill = cap[:-1].copy() + 1
    for i in range(m):
        cols[cap[i]] = i
        for x in range(3):
            blocks[cap[i], x, x] = gamma2
    for k in range(n):
        i = pi[k]
        if pj[k] == i:
            dst = cap[i]
        else:
            dst = fill[i]
            fill[i] += 1
            cols[dst] = pj[k]
        for x in range(3):
            for y in range(3):
                blocks[dst, x, y] += pb[k, x, y]
    # sort each row's off-diagonal part by column and merge duplicates (rows are short: insertion sort)
    out_ptr = np.zeros(m + 1, dtype=np.int64)
    w = 0
    for i in range(m):
        a = cap[i] + 1
        e = cap[i + 1]
        for t in range(a + 1, e):
            c = cols[t]
            blk = blocks[t].copy()
            u = t - 1
            while u >= a and cols[u] > c:
                cols[u + 1] = cols[u]
                blocks[u + 1] = blocks[u]
                u -= 1
            cols[u + 1] = c
            blocks[u + 1] = blk
        # compact: diagonal, then merged off-diagonals
        cols[w] = cols[cap[i]]
        blocks[w] = blocks[cap[i]]
        w += 1
        last = -1
        for t in range(a, e):
            if cols[t] == last:
                blocks[w - 1] += blocks[t]
            else:
                cols[w] = cols[t]
                blocks[w] = blocks[t]
                last = cols[t]
                w += 1
        out_ptr[i + 1] = w
    return out_ptr, cols[:w].copy(), blocks[:w].copy()


@njit(cache=True)
def symmetrize_add_diagonal(out, i, gamma2):
    """out[i] <- (out[i] + out[i]^T) / 2 + gamma2 I: a contact's 3 x 3 diagonal block of W, accumulated
    unsymmetrically, made exactly symmetric and given its 2 gamma I."""
    for x in range(3):
        for y in range(x + 1, 3):
            t = 0.5 * (out[i, x, y] + out[i, y, x])
            out[i, x, y] = t
            out[i, y, x] = t
        out[i, x, x] += gamma2


@njit(cache=True, fastmath=_FM)
def _diagonal_from_packed(h_ptr, h_cols, h_vals, g_ptr, g_cols, g_vals, gamma2, out):
    """out_i = sum_q G_i[q] H_i[q]^T + 2 gamma I (merge of the two sorted column lists)."""
    for i in range(h_ptr.shape[0] - 1):
        for x in range(3):
            for y in range(3):
                out[i, x, y] = 0.0
        p = h_ptr[i]
        q = g_ptr[i]
        pe = h_ptr[i + 1]
        qe = g_ptr[i + 1]
        while p < pe and q < qe:
            if h_cols[p] < g_cols[q]:
                p += 1
            elif h_cols[p] > g_cols[q]:
                q += 1
            else:
                for x in range(3):
                    gx = g_vals[q, x]
                    for y in range(3):
                        out[i, x, y] += gx * h_vals[p, y]
                p += 1
                q += 1
        symmetrize_add_diagonal(out, i, gamma2)


def diagonal_blocks(H: "PackedRows", G: "PackedRows", gamma: float) -> np.ndarray:
    """(m, 3, 3) W_ii = H_i D H_i^T + 2 gamma I from packed H and G = H D."""
    m = H.ptr.shape[0] - 1
    out = np.empty((m, 3, 3))
    _diagonal_from_packed(H.ptr, H.cols, H.vals, G.ptr, G.cols, G.vals, 2.0 * gamma, out)
    return out
