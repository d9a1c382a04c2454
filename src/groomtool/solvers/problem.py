"""The factored contact problem  u = W r + b,  W = H D H^T + 2 gamma I.

m contacts, each a 3-vector block [normal, tangent1, tangent2]; n degrees of freedom split in
strands: strand s owns the columns dof_offsets[s]:dof_offsets[s+1] of H and one SPD block D_s of D.
In the inverse problem D = K^{-2} (diagonal); in dynamics D = M^{-1} (dense per strand).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from . import residual as _res
from .blocks import (PackedRows, diagonal_blocks, merge_rows, pack_HD, strand_blocks_apply, upper_blocks,
                     upper_from_blocks)


@dataclass
class ContactProblem:
    """u = (H D H^T + 2 gamma I) r + b with per-contact friction coefficients mu.

    H:           (3m, n) sparse contact Jacobian, rows 3i..3i+2 = contact i's [N, T1, T2] frame.
    D_blocks:    one block per strand, either (n_s, n_s) dense SPD or (n_s,) a diagonal; or a single
                 (n,) array, the diagonal of D over all dofs.  (A dense block that is exactly diagonal
                 is stored as its diagonal.)
    dof_offsets: (S + 1,) strand s owns dofs dof_offsets[s]:dof_offsets[s+1].
    gamma:       regularisation, W gets + 2 gamma I.
    b:           (3m,) free velocity (b = H v_free in dynamics, -H K^{-1} d in the inversion).
    mu:          friction coefficient(s), scalar or (m,), >= 0.
    """

    H: sp.spmatrix
    D_blocks: Sequence[np.ndarray] | np.ndarray
    dof_offsets: np.ndarray
    gamma: float
    b: np.ndarray
    mu: np.ndarray | float
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def from_dense_blocks(cls, H, D_blocks, dof_offsets, gamma, b, mu, like: "ContactProblem | None" = None
                          ) -> "ContactProblem":
        """The problem with dense (n_s, n_s) D blocks that are not diagonal (the simulator's Mhat^-1 blocks), stored
        without the constructor's per-block test for an exactly diagonal block (harolongo: ~0.5 s for its 4,706
        blocks).  ``like``: a problem whose D storage is shared (not copied: harolongo's is 185 MB) where D_blocks
        are its own blocks, every one, in order."""
        self = cls.__new__(cls)
        self.H, self.dof_offsets, self.gamma, self.b, self.mu = H, dof_offsets, gamma, b, mu
        self._cache = {}
        self._check()
        sizes = np.diff(self.dof_offsets)
        if (like is not None and len(like.D_blocks) == len(D_blocks) and not np.any(like.D_is_diag)
                and all(d is e for d, e in zip(D_blocks, like.D_blocks))):
            self.D_is_diag, self.D_ptr, self.D_data, self.D_blocks = like.D_is_diag, like.D_ptr, like.D_data, like.D_blocks
            return self
        blocks = [np.asarray(d, dtype=np.float64) for d in D_blocks]
        if len(blocks) != len(sizes) or any(d.shape != (k, k) for d, k in zip(blocks, sizes)):
            raise ValueError("D_blocks must be one dense (n_s, n_s) block per strand")
        self.D_is_diag = np.zeros(len(blocks), dtype=np.bool_)
        self.D_ptr = np.zeros(len(blocks) + 1, dtype=np.int64)
        np.cumsum(sizes * sizes, out=self.D_ptr[1:])
        self.D_data = np.concatenate([d.reshape(-1) for d in blocks]) if blocks else np.zeros(0)
        self.D_blocks = [self.D_data[a:a + k * k].reshape(k, k) for a, k in zip(self.D_ptr[:-1].tolist(), sizes.tolist())]
        return self

    def __post_init__(self) -> None:
        self._check()
        self.D_blocks = self._normalise_blocks(self.D_blocks)

    def _check(self) -> None:
        self.H = sp.csr_matrix(self.H, dtype=np.float64)
        self.H.sort_indices()
        self.dof_offsets = np.ascontiguousarray(self.dof_offsets, dtype=np.int64)
        n3m, n = self.H.shape
        if n3m % 3:
            raise ValueError(f"H has {n3m} rows, not a multiple of 3")
        m = n3m // 3
        if self.dof_offsets[0] != 0 or self.dof_offsets[-1] != n or np.any(np.diff(self.dof_offsets) < 0):
            raise ValueError("dof_offsets must increase from 0 to H.shape[1]")
        self.b = np.ascontiguousarray(self.b, dtype=np.float64).reshape(-1)
        if self.b.shape[0] != n3m:
            raise ValueError(f"b has {self.b.shape[0]} entries, expected {n3m}")
        self.mu = np.ascontiguousarray(np.broadcast_to(np.asarray(self.mu, dtype=np.float64), (m,)))
        if np.any(self.mu < 0) or not np.all(np.isfinite(self.mu)):
            raise ValueError("friction coefficients must be finite and >= 0")
        self.gamma = float(self.gamma)
        if self.gamma < 0:
            raise ValueError("gamma must be >= 0")

    def _normalise_blocks(self, blocks):
        """Store D flat (self.D_data, D_ptr, D_is_diag: strand s's block is D_data[D_ptr[s]:D_ptr[s+1]],
        n_s entries if diagonal, n_s^2 row-major if dense) and return the blocks as views into it."""
        sizes = np.diff(self.dof_offsets)
        if isinstance(blocks, np.ndarray) and blocks.ndim == 1:
            if blocks.shape[0] != self.n_dofs:
                raise ValueError(f"diagonal D has {blocks.shape[0]} entries, expected {self.n_dofs}")
            blocks = [blocks[a:b] for a, b in zip(self.dof_offsets[:-1], self.dof_offsets[1:])]
        blocks = [np.asarray(d, dtype=np.float64) for d in blocks]
        # a dense block that is exactly diagonal (e.g. np.diag(K^-2)) is stored as its diagonal: its nonzeros
        # (NaN included) are all on the diagonal (counted without the two n x n temporaries of d - diag(d))
        blocks = [np.ascontiguousarray(np.diagonal(d)) if d.ndim == 2 and d.shape[0] == d.shape[1]
                  and np.count_nonzero(d) == np.count_nonzero(np.diagonal(d)) else d for d in blocks]
        if len(blocks) != len(sizes):
            raise ValueError(f"{len(blocks)} D blocks for {len(sizes)} strands")
        for s, (d, k) in enumerate(zip(blocks, sizes)):
            if d.shape not in ((k,), (k, k)):
                raise ValueError(f"D block {s} has shape {d.shape}, expected ({k},) or ({k}, {k})")
        self.D_is_diag = np.array([d.ndim == 1 for d in blocks], dtype=np.bool_)
        self.D_ptr = np.zeros(len(blocks) + 1, dtype=np.int64)
        np.cumsum([d.size for d in blocks], out=self.D_ptr[1:])
        self.D_data = np.concatenate([d.reshape(-1) for d in blocks]) if blocks else np.zeros(0)
        return [
            self.D_data[a:b] if diag else self.D_data[a:b].reshape(k, k)
            for a, b, diag, k in zip(self.D_ptr[:-1], self.D_ptr[1:], self.D_is_diag, sizes)
        ]

    # ------------------------------------------------------------------ sizes
    @property
    def n_contacts(self) -> int:
        return self.H.shape[0] // 3

    @property
    def n_dofs(self) -> int:
        return self.H.shape[1]

    @property
    def n_strands(self) -> int:
        return len(self.dof_offsets) - 1

    @property
    def is_diagonal(self) -> bool:
        """True when every D block is a diagonal (the inverse problem, D = K^{-2})."""
        return all(d.ndim == 1 for d in self.D_blocks)

    # ------------------------------------------------------------------ operators
    def D_apply(self, x: np.ndarray) -> np.ndarray:
        """D x, strand block by strand block.  x: (n,)."""
        out = np.empty(self.n_dofs)
        strand_blocks_apply(self.D_data, self.D_ptr, self.D_is_diag, self.dof_offsets,
                            np.ascontiguousarray(x, dtype=np.float64), out)
        return out

    def delassus_apply(self, r: np.ndarray) -> np.ndarray:
        """W r = H (D (H^T r)) + 2 gamma r, matrix-free.  r: (3m,)."""
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        return self.H @ self.D_apply(self.H.T @ r) + 2.0 * self.gamma * r

    def velocity(self, r: np.ndarray) -> np.ndarray:
        """u = W r + b (3m,).  Once H D is packed (packed()): u_i = H_i v + 2 gamma r_i + b_i with v = D H^T r
        (dof_velocity), the Gauss-Seidel operator's own product; the last u is kept for its r and b (the solver's
        last measure, asked again by its caller, costs nothing)."""
        if "packed" not in self._cache:
            return self.delassus_apply(r) + self.b
        from .gauss_seidel import packed_apply

        r3 = np.ascontiguousarray(r, dtype=np.float64).reshape(-1, 3)
        last = self._cache.get("velocity")
        if last is not None and last[1] is self.b and np.array_equal(last[0], r3):
            return last[2].copy()
        v = self.dof_velocity(r3)
        H = self._cache["packed"][0]
        u = np.empty_like(r3)
        packed_apply(H.ptr, H.cols, H.vals, v, 2.0 * self.gamma, r3, self.b.reshape(-1, 3), u)
        u = u.reshape(-1)
        self._cache["velocity"] = (r3.copy(), self.b, u)
        return u.copy()

    def dof_velocity(self, r3: np.ndarray) -> np.ndarray:
        """v = D H^T r (n,) from the packed H D panels (packed(); r3 (m, 3)).  The last v is kept for its r: the
        problems of with_free_velocity share it, so a step at rest that starts from the last solve's impulses (the
        same W) does not compute it again.  Do not modify the result."""
        from .gauss_seidel import packed_transpose_apply

        r3 = np.ascontiguousarray(r3, dtype=np.float64).reshape(-1, 3)
        last = self._cache.get("dof_velocity")
        if last is not None and np.array_equal(last[0], r3):
            return last[1]
        G = self.packed()[1]
        v = np.empty(self.n_dofs)
        packed_transpose_apply(G.ptr, G.cols, G.vals, r3, self.n_dofs, v)
        self._cache["dof_velocity"] = (r3.copy(), v)
        return v

    def assemble_W(self) -> sp.csr_matrix:
        """W = H D H^T + 2 gamma I as a sparse (3m, 3m) matrix (small cases, tests), through the sparse
        block-diagonal D (built in one go, no per-block sparse objects) and H D."""
        rows, cols, vals = [], [], []
        for o, d in zip(self.dof_offsets[:-1], self.D_blocks):
            k = d.shape[0]
            if d.ndim == 1:
                idx = o + np.arange(k)
                rows.append(idx)
                cols.append(idx)
            else:
                rows.append(o + np.repeat(np.arange(k), k))
                cols.append(o + np.tile(np.arange(k), k))
            vals.append(d.reshape(-1))
        cat = (lambda a, dt: np.concatenate(a).astype(dt)) if rows else (lambda a, dt: np.zeros(0, dt))
        D = sp.csr_matrix((cat(vals, np.float64), (cat(rows, np.int64), cat(cols, np.int64))),
                          shape=(self.n_dofs, self.n_dofs))
        HD = (self.H @ D).tocsr()
        HD.sort_indices()
        W = (HD @ self.H.T).tocsr() + 2.0 * self.gamma * sp.identity(self.H.shape[0], format="csr")
        W.sort_indices()
        return W

    def packed_H(self) -> PackedRows:
        """H regrouped per contact (blocks.PackedRows), cached."""
        if "packed_H" not in self._cache:
            self._cache["packed_H"] = PackedRows.from_sparse(self.H)
        return self._cache["packed_H"]

    def packed(self):
        """(H, H D) regrouped per contact (blocks.PackedRows, H D computed panel by panel), cached."""
        if "packed" not in self._cache:
            H = self.packed_H()
            self._cache["packed"] = (H, pack_HD(H, self.dof_offsets, self.D_data, self.D_ptr, self.D_is_diag))
        return self._cache["packed"]

    def diagonal_blocks(self) -> np.ndarray:
        """The (m, 3, 3) diagonal blocks W_ii = H_i D H_i^T + 2 gamma I."""
        if "diag" not in self._cache:
            H, G = self.packed()
            self._cache["diag"] = diagonal_blocks(H, G, self.gamma)
        return self._cache["diag"]

    def normalized_diagonal(self):
        """gauss_seidel.normalize_diagonal of the diagonal blocks (s, W_ii / s and its inverse, invertible flags),
        cached: every solve of a step at rest, and both solves of a step (the warm start's sweep, then the rest),
        share them."""
        if "normalized" not in self._cache:
            from .gauss_seidel import normalize_diagonal

            self._cache["normalized"] = normalize_diagonal(self.diagonal_blocks())
        return self._cache["normalized"]

    def with_free_velocity(self, b: np.ndarray) -> "ContactProblem":
        """The same W (H, D, gamma, mu, and what is cached from them: packed rows, diagonal blocks, rho) with another
        free velocity b (3m,): a new problem object, the cache shared (it does not depend on b)."""
        b = np.ascontiguousarray(b, dtype=np.float64).reshape(-1)
        if b.shape[0] != self.H.shape[0]:
            raise ValueError(f"b has {b.shape[0]} entries, expected {self.H.shape[0]}")
        other = copy.copy(self)
        other.b = b
        return other

    def part(self, contacts) -> tuple["ContactProblem", np.ndarray]:
        """The problem of the contacts ``contacts`` (sorted indices) alone, on the strands they touch: (problem, those
        strands); b = 0.  W's blocks among those contacts are this problem's."""
        contacts = np.asarray(contacts, dtype=np.int64)
        rows = (3 * contacts[:, None] + np.arange(3)).ravel()
        Hc = self.H[rows]
        strand_of = np.searchsorted(self.dof_offsets, Hc.indices, side="right") - 1
        strands = np.unique(strand_of)
        sizes = np.diff(self.dof_offsets)[strands]
        offsets = np.zeros(len(strands) + 1, dtype=np.int64)
        np.cumsum(sizes, out=offsets[1:])
        shift = offsets[:-1] - self.dof_offsets[strands]
        cols = Hc.indices + shift[np.searchsorted(strands, strand_of)]
        H = sp.csr_matrix((Hc.data, cols, Hc.indptr), shape=(len(rows), int(offsets[-1])))
        part = ContactProblem(H, [self.D_blocks[s] for s in strands], offsets, self.gamma, np.zeros(len(rows)),
                              self.mu[contacts])
        return part, strands

    def carry_cache(self, old: "ContactProblem", rows: np.ndarray, columns: np.ndarray) -> None:
        """Take what ``old`` has cached of W (its diagonal blocks; the upper block triangle, natural order; the packed
        H D panels) for the contacts that kept their rows of W, and compute the rest on the other contacts alone.

        rows (m,): per contact of this problem, its index in ``old`` where its H row (the columns renumbered by
        ``columns``: old dof -> this problem's, -1 none) and the D blocks of its strands are old's, else -1.  W_ij of
        two such contacts is old's (they touch only strands whose blocks are old's); every block of W with another
        contact is computed here (part(): the contacts on the strands that the others touch), as are their diagonal
        blocks and H D panels.  The same W as computing it all anew, to round-off (a simulator's partial step:
        Simulator._partial_contacts)."""
        rows = np.asarray(rows, dtype=np.int64)
        columns = np.asarray(columns, dtype=np.int64)
        m = self.n_contacts
        kept = np.flatnonzero(rows >= 0)
        fresh = np.flatnonzero(rows < 0)
        cache = old._cache
        upper = cache.get("upper")
        upper = upper[1] if upper is not None and upper[0] is None else None
        if len(kept) == 0 or ("diag" not in cache and upper is None):
            return
        H = self.packed_H()
        contact_of = np.repeat(np.arange(m), np.diff(H.ptr))
        strand_of = np.repeat(np.arange(self.n_strands), np.diff(self.dof_offsets))[H.cols]
        on_fresh = np.zeros(self.n_strands, dtype=bool)
        on_fresh[strand_of[np.isin(contact_of, fresh)]] = True
        # the contacts whose blocks are computed: the fresh ones, and (for W's off-diagonal blocks) those they share a
        # strand with
        near = np.unique(contact_of[on_fresh[strand_of]]) if upper is not None else fresh
        near = np.union1d(near, fresh)
        if len(near):
            part, strands = self.part(near)
            where = np.searchsorted(near, fresh)
            pdiag = part.diagonal_blocks()
        if "diag" in cache:
            diag = np.empty((m, 3, 3))
            diag[kept] = cache["diag"][rows[kept]]
            if len(fresh):
                diag[fresh] = pdiag[where]
            self._cache["diag"] = diag
        if upper is not None:
            new_of_old = np.full(old.n_contacts, -1, dtype=np.int64)
            new_of_old[rows[kept]] = kept
            i, j, blk = upper_blocks(upper)
            i, j = new_of_old[i], new_of_old[j]
            both = (i >= 0) & (j >= 0)
            parts_i, parts_j, parts_b = [i[both]], [j[both]], [blk[both]]
            if len(fresh):
                from .blocks import assemble_upper

                pi, pj, pb = upper_blocks(assemble_upper(part))
                pi, pj = near[pi], near[pj]
                is_fresh = rows < 0
                sel = is_fresh[pi] | is_fresh[pj]
                parts_i.append(pi[sel])
                parts_j.append(pj[sel])
                parts_b.append(pb[sel])
            self._cache["upper"] = (None, upper_from_blocks(m, np.concatenate(parts_i), np.concatenate(parts_j),
                                                            np.concatenate(parts_b)))
        if "packed" in cache and upper is None:
            sources = [(cache["packed"][1], rows, columns)]
            if len(fresh):
                idx = np.full(m, -1, dtype=np.int64)
                idx[fresh] = where
                col_map = np.concatenate([np.arange(self.dof_offsets[s], self.dof_offsets[s + 1]) for s in strands])
                sources.append((part.packed()[1], idx, col_map))
            self._cache["packed"] = (H, merge_rows(sources))

    # ------------------------------------------------------------------ measures
    def rho(self) -> np.ndarray:
        """rho_i = 3 / trace(W_ii), the per-contact step of the natural map."""
        if "rho" not in self._cache:
            self._cache["rho"] = _res.rho_from_diagonal(self.diagonal_blocks())
        return self._cache["rho"]

    def residual_scale(self) -> float:
        """max_i rho_i ||b_i|| (see residual.py)."""
        return _res.residual_scale(self.b, self.rho())

    def objective(self, r: np.ndarray) -> float:
        """1/2 r^T W r + b^T r."""
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        return float(0.5 * r @ self.delassus_apply(r) + self.b @ r)

    def cone_violation(self, r: np.ndarray) -> float:
        """max over contacts of max(0, ||r_T|| - mu r_N)."""
        return _res.cone_violation(r, self.mu)

    def residual(self, r: np.ndarray, law: str = "soc", norm: str = "max", u: np.ndarray | None = None) -> float:
        """max_i ||r_i - P_K(r_i - rho_i u_eff_i)|| / max_i rho_i ||b_i||  (norm='max'; 'rms' also).
        See residual.py for the definition; 1e-8 means converged."""
        u = self.velocity(r) if u is None else u
        return _res.residual(r, u, self.mu, self.rho(), self.residual_scale(), law=law, norm=norm)

    def bogus_error(self, r: np.ndarray, law: str = "soc") -> float:
        """so-bogus's stopping figure (residual.py), for comparisons with that library."""
        tr = np.einsum("kii->k", self.diagonal_blocks())
        return _res.bogus_error(r, self.velocity(r), self.mu, tr, law=law)
