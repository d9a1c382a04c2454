"""Symmetric block-semiseparable matrices of strands, and their Cholesky factors in O(E r^2).

A strand of E elements with 3 dofs each gives a symmetric matrix of 3 x 3 blocks

    A_jj = diag_j,     A_kj = later_k^T earlier_j   (k > j),     A_jk = A_kj^T,

with generators later_k and earlier_j of r rows (r x 3).  A Super-Helix's mass matrix, its step matrix and the
strand-split ADMM's D^-1 + J^T J / rho have this form: the velocity of a point beyond element j depends on
element j's rates through the rigid generators of j alone (docs/simulation.md section 7, docs/solvers.md
section 12).  Its Cholesky factor A = L L^T keeps the form,

    L_kj = later_k^T W_j  (k > j),   L_jj L_jj^T = diag_j - later_j^T Sigma_j later_j,
    W_j = (earlier_j - Sigma_j later_j) L_jj^-T,   Sigma_1 = 0,   Sigma_{j+1} = Sigma_j + W_j W_j^T,

(check: sum_{l<=j} L_kl L_jl^T = later_k^T (Sigma_j later_j + W_j L_jj^T) = later_k^T earlier_j), so a factor
costs O(E r^2), stores 9 + 3 r numbers per element, and A x = y is solved (L y and L^T y applied) in O(E r):

    forward   z_k = L_kk^-1 (y_k - later_k^T t_k),      t_k = sum_{j<k} W_j z_j,
    backward  x_j = L_jj^-T (z_j - W_j^T s_j),           s_j = sum_{k>j} later_k x_k.

Several strands are stored back to back: element arrays (E_total, ...), strand s on elements e0 .. e1 - 1; its
dofs are 3 e0 .. 3 e1 of the flat vector (3 per element, in element order).  The njit functions work on one
strand and are called from the kernels that own the strands' matrices (solvers/admm_structured.py,
simulate_linalg.py, stability.py); tests/reference/semiseparable.py batches them over strands for the tests.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _chol3(a, out) -> bool:
    """out = the lower Cholesky factor of the symmetric 3 x 3 ``a``; False when a is not positive definite."""
    d0 = a[0, 0]
    if not d0 > 0.0:
        return False
    l00 = np.sqrt(d0)
    l10 = a[1, 0] / l00
    l20 = a[2, 0] / l00
    d1 = a[1, 1] - l10 * l10
    if not d1 > 0.0:
        return False
    l11 = np.sqrt(d1)
    l21 = (a[2, 1] - l20 * l10) / l11
    d2 = a[2, 2] - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return False
    out[0, 0], out[0, 1], out[0, 2] = l00, 0.0, 0.0
    out[1, 0], out[1, 1], out[1, 2] = l10, l11, 0.0
    out[2, 0], out[2, 1], out[2, 2] = l20, l21, np.sqrt(d2)
    return True


@njit(cache=True, error_model="numpy")
def factor_strand(diag, later, earlier, e0, e1, L, W) -> bool:
    """The factor (L_jj, W_j) of elements e0 .. e1 - 1 (module docstring) into L[e0:e1], W[e0:e1].  False when a
    pivot diag_j - later_j^T Sigma_j later_j is not positive definite (then A is not; L, W are partial)."""
    r = later.shape[1]
    sigma = np.zeros((r, r))
    t = np.empty((r, 3))
    piv = np.empty((3, 3))
    for j in range(e0, e1):
        for a in range(r):  # t = Sigma later_j
            for c in range(3):
                acc = 0.0
                for b in range(r):
                    acc += sigma[a, b] * later[j, b, c]
                t[a, c] = acc
        for c in range(3):  # pivot = diag_j - later_j^T t
            for d in range(3):
                acc = diag[j, c, d]
                for a in range(r):
                    acc -= later[j, a, c] * t[a, d]
                piv[c, d] = acc
        if not _chol3(piv, L[j]):
            return False
        l00, l10, l11 = L[j, 0, 0], L[j, 1, 0], L[j, 1, 1]
        l20, l21, l22 = L[j, 2, 0], L[j, 2, 1], L[j, 2, 2]
        for a in range(r):  # W_j = (earlier_j - t) L_jj^-T: each row w solves L_jj w^T = (earlier_j - t)^T row
            b0 = earlier[j, a, 0] - t[a, 0]
            b1 = earlier[j, a, 1] - t[a, 1]
            b2 = earlier[j, a, 2] - t[a, 2]
            w0 = b0 / l00
            w1 = (b1 - l10 * w0) / l11
            w2 = (b2 - l20 * w0 - l21 * w1) / l22
            W[j, a, 0], W[j, a, 1], W[j, a, 2] = w0, w1, w2
        for a in range(r):  # Sigma += W_j W_j^T
            for b in range(r):
                sigma[a, b] += W[j, a, 0] * W[j, b, 0] + W[j, a, 1] * W[j, b, 1] + W[j, a, 2] * W[j, b, 2]
    return True


@njit(cache=True, error_model="numpy")
def solve_lower_strand(L, W, later, e0, e1, y):
    """y <- L^-1 y in place (y: the strand's 3 (e1 - e0) entries)."""
    r = later.shape[1]
    t = np.zeros(r)
    for k in range(e0, e1):
        i = 3 * (k - e0)
        y0, y1, y2 = y[i], y[i + 1], y[i + 2]
        for a in range(r):
            ta = t[a]
            y0 -= later[k, a, 0] * ta
            y1 -= later[k, a, 1] * ta
            y2 -= later[k, a, 2] * ta
        z0 = y0 / L[k, 0, 0]
        z1 = (y1 - L[k, 1, 0] * z0) / L[k, 1, 1]
        z2 = (y2 - L[k, 2, 0] * z0 - L[k, 2, 1] * z1) / L[k, 2, 2]
        y[i], y[i + 1], y[i + 2] = z0, z1, z2
        for a in range(r):
            t[a] += W[k, a, 0] * z0 + W[k, a, 1] * z1 + W[k, a, 2] * z2


@njit(cache=True, error_model="numpy")
def solve_upper_strand(L, W, later, e0, e1, y):
    """y <- L^-T y in place."""
    r = later.shape[1]
    s = np.zeros(r)
    for j in range(e1 - 1, e0 - 1, -1):
        i = 3 * (j - e0)
        z0, z1, z2 = y[i], y[i + 1], y[i + 2]
        for a in range(r):
            sa = s[a]
            z0 -= W[j, a, 0] * sa
            z1 -= W[j, a, 1] * sa
            z2 -= W[j, a, 2] * sa
        x2 = z2 / L[j, 2, 2]
        x1 = (z1 - L[j, 2, 1] * x2) / L[j, 1, 1]
        x0 = (z0 - L[j, 1, 0] * x1 - L[j, 2, 0] * x2) / L[j, 0, 0]
        y[i], y[i + 1], y[i + 2] = x0, x1, x2
        for a in range(r):
            s[a] += later[j, a, 0] * x0 + later[j, a, 1] * x1 + later[j, a, 2] * x2


@njit(cache=True, error_model="numpy")
def solve_strand(L, W, later, e0, e1, y):
    """y <- A^-1 y = L^-T L^-1 y in place (y: the strand's 3 (e1 - e0) entries)."""
    solve_lower_strand(L, W, later, e0, e1, y)
    solve_upper_strand(L, W, later, e0, e1, y)


@njit(cache=True, error_model="numpy")
def apply_upper_strand(L, W, later, e0, e1, y):
    """y <- L^T y in place: (L^T y)_j = L_jj^T y_j + W_j^T sum_{k>j} later_k y_k."""
    r = W.shape[1]
    acc = np.zeros(r)
    for j in range(e1 - 1, e0 - 1, -1):
        i = 3 * (j - e0)
        y0, y1, y2 = y[i], y[i + 1], y[i + 2]
        for c in range(3):
            v = L[j, 0, c] * y0 + L[j, 1, c] * y1 + L[j, 2, c] * y2
            for a in range(r):
                v += W[j, a, c] * acc[a]
            y[i + c] = v
        for a in range(r):
            acc[a] += later[j, a, 0] * y0 + later[j, a, 1] * y1 + later[j, a, 2] * y2


@njit(cache=True, error_model="numpy")
def apply_lower_strand(L, W, later, e0, e1, y):
    """y <- L y in place: (L y)_k = L_kk y_k + later_k^T sum_{j<k} W_j y_j."""
    r = W.shape[1]
    acc = np.zeros(r)
    for k in range(e0, e1):
        i = 3 * (k - e0)
        y0, y1, y2 = y[i], y[i + 1], y[i + 2]
        for c in range(3):
            v = L[k, c, 0] * y0 + L[k, c, 1] * y1 + L[k, c, 2] * y2
            for a in range(r):
                v += later[k, a, c] * acc[a]
            y[i + c] = v
        for a in range(r):
            acc[a] += W[k, a, 0] * y0 + W[k, a, 1] * y1 + W[k, a, 2] * y2


@njit(cache=True, error_model="numpy")
def matvec_strand(diag, later, earlier, e0, e1, x, y):
    """y = A x for one strand: y_j = diag_j x_j + later_j^T sum_{l<j} earlier_l x_l + earlier_j^T sum_{k>j} later_k x_k."""
    r = later.shape[1]
    acc = np.zeros(r)
    for j in range(e0, e1):  # the diagonal and lower part
        i = 3 * (j - e0)
        x0, x1, x2 = x[i], x[i + 1], x[i + 2]
        v0 = diag[j, 0, 0] * x0 + diag[j, 0, 1] * x1 + diag[j, 0, 2] * x2
        v1 = diag[j, 1, 0] * x0 + diag[j, 1, 1] * x1 + diag[j, 1, 2] * x2
        v2 = diag[j, 2, 0] * x0 + diag[j, 2, 1] * x1 + diag[j, 2, 2] * x2
        for a in range(r):
            ta = acc[a]
            v0 += later[j, a, 0] * ta
            v1 += later[j, a, 1] * ta
            v2 += later[j, a, 2] * ta
            acc[a] = ta + earlier[j, a, 0] * x0 + earlier[j, a, 1] * x1 + earlier[j, a, 2] * x2
        y[i], y[i + 1], y[i + 2] = v0, v1, v2
    acc[:] = 0.0
    for j in range(e1 - 1, e0 - 1, -1):  # the upper part
        i = 3 * (j - e0)
        x0, x1, x2 = x[i], x[i + 1], x[i + 2]
        v0 = v1 = v2 = 0.0
        for a in range(r):
            ta = acc[a]
            v0 += earlier[j, a, 0] * ta
            v1 += earlier[j, a, 1] * ta
            v2 += earlier[j, a, 2] * ta
            acc[a] = ta + later[j, a, 0] * x0 + later[j, a, 1] * x1 + later[j, a, 2] * x2
        y[i] += v0
        y[i + 1] += v1
        y[i + 2] += v2
