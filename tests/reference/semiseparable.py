"""References for groomtool.semiseparable: the dense matrices and factors its strand kernels stand for.

* :func:`dense_strand`: the dense symmetric matrix A_jj = diag_j, A_kj = later_k^T earlier_j (k > j) of one strand.
* :func:`dense_lower`: the dense Cholesky factor rebuilt from the kernel's (L, W): L_kj = later_k^T W_j (k > j).
* :func:`factor`, :func:`matvec`: the per-strand kernels over every strand of ``offsets`` (element offsets, S + 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from groomtool import semiseparable as ss


@dataclass
class Factor:
    """The strands' factors (L (E, 3, 3), W (E, r, 3)), their ``later`` generators, ``ok`` per strand."""

    L: np.ndarray
    W: np.ndarray
    later: np.ndarray
    offsets: np.ndarray
    ok: np.ndarray

    def solve(self, rhs) -> np.ndarray:
        """A^-1 rhs for rhs (3 E,) or (3 E, m), strand by strand (NaN on a strand that is not ok)."""
        rhs = np.asarray(rhs, dtype=np.float64)
        out = np.array(rhs if rhs.ndim == 2 else rhs[:, None], dtype=np.float64)
        for s in range(len(self.offsets) - 1):
            e0, e1 = int(self.offsets[s]), int(self.offsets[s + 1])
            for c in range(out.shape[1]):
                y = np.ascontiguousarray(out[3 * e0:3 * e1, c])
                if self.ok[s]:
                    ss.solve_strand(self.L, self.W, self.later, e0, e1, y)
                else:
                    y[:] = np.nan
                out[3 * e0:3 * e1, c] = y
        return out.reshape(rhs.shape)


def factor(diag, later, earlier, offsets) -> Factor:
    diag, later, earlier = (np.ascontiguousarray(a, dtype=np.float64) for a in (diag, later, earlier))
    L = np.zeros_like(diag)
    W = np.zeros_like(later)
    ok = np.array([ss.factor_strand(diag, later, earlier, int(offsets[s]), int(offsets[s + 1]), L, W)
                   for s in range(len(offsets) - 1)], dtype=bool)
    return Factor(L, W, later, np.asarray(offsets), ok)


def matvec(diag, later, earlier, offsets, x) -> np.ndarray:
    diag, later, earlier = (np.ascontiguousarray(a, dtype=np.float64) for a in (diag, later, earlier))
    x = np.ascontiguousarray(x, dtype=np.float64)
    out = np.empty_like(x)
    for s in range(len(offsets) - 1):
        e0, e1 = int(offsets[s]), int(offsets[s + 1])
        y = np.empty(3 * (e1 - e0))
        ss.matvec_strand(diag, later, earlier, e0, e1, x[3 * e0:3 * e1], y)
        out[3 * e0:3 * e1] = y
    return out


def dense_strand(diag, later, earlier, e0: int, e1: int) -> np.ndarray:
    n = 3 * (e1 - e0)
    A = np.zeros((n, n))
    for k in range(e0, e1):
        i = 3 * (k - e0)
        A[i:i + 3, i:i + 3] = diag[k]
        for j in range(e0, k):
            c = 3 * (j - e0)
            A[i:i + 3, c:c + 3] = later[k].T @ earlier[j]
            A[c:c + 3, i:i + 3] = A[i:i + 3, c:c + 3].T
    return A


def dense_lower(L, W, later, e0: int, e1: int) -> np.ndarray:
    n = 3 * (e1 - e0)
    out = np.zeros((n, n))
    for k in range(e0, e1):
        i = 3 * (k - e0)
        out[i:i + 3, i:i + 3] = L[k]
        for j in range(e0, k):
            c = 3 * (j - e0)
            out[i:i + 3, c:c + 3] = later[k].T @ W[j]
    return out
