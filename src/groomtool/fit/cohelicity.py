"""Co-helicity relaxation: move the samples, keep the tangents (docs/maths.md section 4.3).

Per strand, given samples Q_0..Q_N and unit tangents t_0..t_N, find the closest points

    min 1/2 sum_j |P_j - Q_j|^2   with P_0 = Q_0,   s.t.  g_i = (P_{i+1} - P_i) . dt_i = 0,  i < N,

dt_i = t_{i+1} - t_i.  Stationarity of L = 1/2 sum |P - Q|^2 - sum_i lambda_i g_i gives

    P_j = Q_j + lambda_{j-1} dt_{j-1} - lambda_j dt_j        (lambda_{-1} dt_{-1} := 0 is P_0 = Q_0, lambda_N := 0)

and substituting into the constraints a symmetric tridiagonal system A A^T lambda = -b,
b_i = (Q_{i+1} - Q_i) . dt_i:

    diag_0 = |dt_0|^2,  diag_i = 2 |dt_i|^2 (i >= 1),  off_i = -dt_i . dt_{i+1}.

A A^T is the Gram matrix of the constraint gradients: positive semi-definite, singular where
dt_i = 0 (a straight piece has no constraint).  It is regularised by EPS on the diagonal, which only
shrinks the moves (lambda_i dt_i) and leaves a residual g_i <= |Q_{i+1} - Q_i| sqrt(EPS) where
|dt_i|^2 < EPS.  Solved by the Thomas algorithm (no pivoting needed: SPD), a numba kernel strand by
strand (``project_numpy`` in tests/reference/fit.py: the same, vectorised over strands, the tests'
reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .kernels import dot

EPS = 1e-24


def relax_points(samples, tangents, n_elements=None, eps: float = EPS) -> np.ndarray:
    """Closest co-helical points P (S, N+1, 3) to samples Q (S, N+1, 3) keeping the tangents, P_0 = Q_0.

    Strands are padded to N elements; strand k uses its first n_elements[k] + 1 samples (the rest
    are copied unchanged).  A single strand (N+1, 3) is accepted too.
    """
    Q = np.asarray(samples, dtype=np.float64)
    T = np.asarray(tangents, dtype=np.float64)
    single = Q.ndim == 2
    if single:
        Q, T = Q[None], T[None]
    S, N1, _ = Q.shape
    n_elements = np.full(S, N1 - 1, dtype=np.int64) if n_elements is None else np.asarray(n_elements, dtype=np.int64)
    P = Q.copy() if N1 == 1 else _project(Q, T, n_elements, eps)
    return P[0] if single else P


def constraint_residuals(points, tangents, n_elements=None) -> np.ndarray:
    """g_i = (P_{i+1} - P_i) . (t_{i+1} - t_i), (S, N) (zero on padding)."""
    P = np.asarray(points, dtype=np.float64)
    T = np.asarray(tangents, dtype=np.float64)
    single = P.ndim == 2
    if single:
        P, T = P[None], T[None]
    g = dot(P[:, 1:] - P[:, :-1], T[:, 1:] - T[:, :-1])
    if n_elements is not None:
        g = np.where(np.arange(g.shape[1])[None, :] < np.asarray(n_elements)[:, None], g, 0.0)
    return g[0] if single else g


def _project(X, T, n_elements, eps):
    """The projection above with V = T[:, 1:] - T[:, :-1] (numba)."""
    out = np.empty(X.shape)
    _project_kernel(np.ascontiguousarray(X), np.ascontiguousarray(T), np.ascontiguousarray(n_elements, dtype=np.int64),
                    eps, out)
    return out


@njit(cache=True, error_model="numpy")
def _project_kernel(X, T, n_elements, eps, out):
    """Strand by strand, the operations of the reference ``project_numpy`` (padding included)."""
    S, N1, _ = X.shape
    N = N1 - 1
    V, dx = np.zeros((N, 3)), np.zeros((N, 3))
    diag, off, rhs, cp, rp, lam = np.empty(N), np.zeros(N), np.empty(N), np.empty(N), np.empty(N), np.empty(N)
    for s in range(S):
        for i in range(N):
            real = i < n_elements[s]
            for c in range(3):
                V[i, c] = T[s, i + 1, c] - T[s, i, c] if real else 0.0
                dx[i, c] = X[s, i + 1, c] - X[s, i, c] if real else 0.0
            diag[i] = 2.0 * (V[i, 0] * V[i, 0] + V[i, 1] * V[i, 1] + V[i, 2] * V[i, 2])
            rhs[i] = -(dx[i, 0] * V[i, 0] + dx[i, 1] * V[i, 1] + dx[i, 2] * V[i, 2])
        diag[0] *= 0.5
        for i in range(N):
            diag[i] += eps
        for i in range(N - 1):
            off[i] = -(V[i, 0] * V[i + 1, 0] + V[i, 1] * V[i + 1, 1] + V[i, 2] * V[i + 1, 2])
        cp[0], rp[0] = diag[0], rhs[0]
        for i in range(1, N):
            w = off[i - 1] / cp[i - 1]
            cp[i] = diag[i] - w * off[i - 1]
            rp[i] = rhs[i] - w * rp[i - 1]
        lam[N - 1] = rp[N - 1] / cp[N - 1]
        for i in range(N - 2, -1, -1):
            lam[i] = (rp[i] - off[i] * lam[i + 1]) / cp[i]
        for c in range(3):
            out[s, 0, c] = X[s, 0, c]
            for j in range(1, N1):
                out[s, j, c] = X[s, j, c] + lam[j - 1] * V[j - 1, c]
                if j < N:
                    out[s, j, c] -= lam[j] * V[j, c]


