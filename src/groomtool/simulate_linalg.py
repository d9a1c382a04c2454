"""Per-strand linear algebra of the semi-implicit step: the factorised step matrix and its solves.

Every strand has its own Mhat (3 N_s dofs, padded to 3 N in the batched arrays, padding = identity).
Factorisations go strand by strand through LAPACK on the real 3 N_s dofs (dpotrf / dpotri: they report
failure instead of raising, and a strand of 10 elements is not factorised as one of 36); the small
triangular solves are compiled loops (a multi-threaded BLAS is slow on 100 x 100 systems on a busy
machine).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.linalg import lapack


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


class StepCorrections:
    """The unstable-mode correction C_s = modified_step_matrix(A, B) - A - B of each strand that needed
    one, kept between steps (factor_step_matrix); stored compactly (only modified strands have a slot)."""

    def __init__(self, n_strands: int):
        self.slot = np.full(n_strands, -1, dtype=np.int64)
        self.data = np.zeros((0, 1, 1))

    def get(self, s: int) -> np.ndarray | None:
        k = self.slot[s]
        return None if k < 0 else self.data[k]

    def set(self, s: int, correction: np.ndarray | None) -> None:
        if correction is None:
            self.slot[s] = -1
            return
        n = correction.shape[0]
        if self.slot[s] < 0:
            used = set(self.slot[self.slot >= 0].tolist())
            free = [k for k in range(len(self.data)) if k not in used]
            if free:
                self.slot[s] = free[0]
            else:
                self.slot[s] = len(self.data)
                grown = np.zeros((max(2 * len(self.data), 4), max(self.data.shape[1], n), max(self.data.shape[1], n)))
                grown[:len(self.data), :self.data.shape[1], :self.data.shape[1]] = self.data
                self.data = grown
        if n > self.data.shape[1]:
            grown = np.zeros((len(self.data), n, n))
            grown[:, :self.data.shape[1], :self.data.shape[1]] = self.data
            self.data = grown
        block = self.data[self.slot[s]]
        block[:] = 0.0
        block[:n, :n] = correction


@njit(cache=True)
def _try_cholesky(a):
    """(L, True) with a = L L^T, or (a, False) where a is not positive definite (LAPACK dpotrf)."""
    try:
        return np.linalg.cholesky(a), True
    except Exception:  # numba's LinAlgError: not positive definite
        return a, False


@njit(cache=True)
def _factor_kernel(A, a_scale, Kd, k_scale, B, U, G, Dg, b_scale, n_elements, slot, corr, chol, status):
    """Per strand, on its 3 N_s real dofs: a = a_scale A + diag(k_scale Kd), b = b_scale B (B dense, or
    when B is empty the symmetric matrix with blocks U_j G_k for j < k and Dg_j on the diagonal: the
    generators of superhelix.gravity_force_jacobian, never stored densely); if a/2 + b
    is positive definite, chol = cholesky(a + b) (status 0); else with a kept correction C for which
    a/2 + b + C is, chol = cholesky(a + b + C) (status 1); else status 2 (a new eigendecomposition is
    needed: done by the caller).  Padding rows of chol are left as they are."""
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
        L, ok = _try_cholesky(0.5 * a + b)
        st = 0
        if ok:
            L, ok = _try_cholesky(a + b)
        if not ok and slot[s] >= 0:
            C = corr[slot[s], :n, :n]
            L, ok = _try_cholesky(0.5 * a + b + C)
            if ok:
                L, ok = _try_cholesky(a + b + C)
            st = 1
        if not ok:
            status[s] = 2
            continue
        status[s] = st
        for i in range(n):
            for j in range(n):
                chol[s, i, j] = L[i, j]


def _dense_from_parts(U, G, Dg, n_el: int) -> np.ndarray:
    """The symmetric (3 n_el, 3 n_el) matrix with blocks U_j G_k (j < k), their transposes, Dg_j."""
    out = np.zeros((3 * n_el, 3 * n_el))
    for j in range(n_el):
        out[3 * j:3 * j + 3, 3 * j:3 * j + 3] = Dg[j]
        for k in range(j + 1, n_el):
            block = U[j] @ G[k]
            out[3 * j:3 * j + 3, 3 * k:3 * k + 3] = block
            out[3 * k:3 * k + 3, 3 * j:3 * j + 3] = block.T
    return out


def factor_step_matrix(A: np.ndarray, B, n_elements: np.ndarray,
                       corrections: StepCorrections | None = None, *, a_scale: float = 1.0, stiffness=None,
                       k_scale: float = 0.0, b_scale: float = 1.0, out: np.ndarray | None = None
                       ) -> tuple[np.ndarray, int]:
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
    moved out of it; at rest the kept C is the fresh one.  Without it every modified strand is
    decomposed anew.  A, B (S, n, n) padded; returns the factors (S, n, n: padding rows and columns
    the identity; ``out`` is reused when given) and the number of strands whose step matrix was
    modified.  Compiled (LAPACK dpotrf per strand), one eigendecomposition in Python per new C.
    """
    S, n_pad, _ = A.shape
    n_elements = np.asarray(n_elements, dtype=np.int64)
    if out is None or out.shape != A.shape:
        out = np.zeros_like(A)
        for s in range(S):
            pad = np.arange(3 * int(n_elements[s]), n_pad)
            out[s, pad, pad] = 1.0
    Kd = np.zeros((S, n_pad)) if stiffness is None else np.ascontiguousarray(stiffness, dtype=np.float64).reshape(S, -1)
    keep = corrections if corrections is not None else StepCorrections(S)
    status = np.zeros(S, dtype=np.int64)
    if isinstance(B, tuple):
        U, G, Dg = (np.ascontiguousarray(x, dtype=np.float64) for x in B)
        dense = np.zeros((0, 1, 1))
    else:
        dense = np.ascontiguousarray(B, dtype=np.float64)
        U = G = Dg = np.zeros((0, 1, 3, 3))
    _factor_kernel(np.ascontiguousarray(A), float(a_scale), Kd, float(k_scale), dense, U, G, Dg,
                   float(b_scale), n_elements, keep.slot if corrections is not None else np.full(S, -1, np.int64),
                   keep.data, out, status)
    for s in np.flatnonzero(status == 2):
        n = 3 * int(n_elements[s])
        a = a_scale * A[s, :n, :n] + np.diag(k_scale * Kd[s, :n])
        if isinstance(B, tuple):
            b = b_scale * _dense_from_parts(U[s], G[s], Dg[s], n // 3)
        else:
            b = b_scale * B[s, :n, :n]
        m = modified_step_matrix(a, b)
        L = _cholesky(m)
        if L is None:
            raise np.linalg.LinAlgError(f"strand {s}: the step matrix is not positive definite")
        out[s, :n, :n] = L
        if corrections is not None:
            corrections.set(int(s), m - (a + b))
    if corrections is not None:
        for s in np.flatnonzero(status == 0):
            corrections.set(int(s), None)
    return out, int(np.count_nonzero(status > 0))


@njit(cache=True)
def _forward(L, b, n):
    """y = L^-1 b on the first n rows (L lower triangular)."""
    y = np.empty(n)
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    return y


@njit(cache=True)
def _backward(L, y, n):
    """x = L^-T y on the first n rows."""
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return x


@njit(cache=True)
def _cho_solve_kernel(L, b, out):
    for s in range(L.shape[0]):
        n = L.shape[1]
        out[s] = _backward(L[s], _forward(L[s], b[s], n), n)


def cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x = (L L^T)^-1 b for every strand; L (S, n, n) lower, b (S, n), compiled loops."""
    out = np.empty_like(b)
    _cho_solve_kernel(np.ascontiguousarray(L), np.ascontiguousarray(b), out)
    return out


def cho_inverse(L: np.ndarray, n: int) -> np.ndarray:
    """(L L^T)^-1 restricted to the first n dofs (a strand's real elements), LAPACK dpotri.
    L: lower triangular with zeros above the diagonal (as factor_step_matrix returns it)."""
    inv, info = lapack.dpotri(L[:n, :n], lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotri failed (info {info})")
    out = inv + inv.T  # dpotri wrote the lower triangle; the upper one is L's zeros
    out.flat[:: n + 1] *= 0.5
    return out


@njit(cache=True)
def _cho_inverse_kernel(L, n):
    """Reference (L L^T)^-1 on the first n dofs by triangular solves (kept for tests)."""
    Linv = np.zeros((n, n))
    e = np.zeros(n)
    for j in range(n):
        e[:] = 0.0
        e[j] = 1.0
        Linv[:, j] = _forward(L, e, n)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(j, n):  # Linv is lower triangular: rows k >= max(i, j)
                acc += Linv[k, i] * Linv[k, j]
            out[i, j] = acc
            out[j, i] = acc
    return out
