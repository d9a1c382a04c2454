"""References for groomtool.semiseparable: the dense matrices and factors its strand kernels stand for.

* :func:`dense_strand`: the dense symmetric matrix A_jj = diag_j, A_kj = later_k^T earlier_j (k > j) of one strand.
* :func:`dense_lower`: the dense Cholesky factor rebuilt from the kernel's (L, W): L_kj = later_k^T W_j (k > j).
"""

from __future__ import annotations

import numpy as np


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
