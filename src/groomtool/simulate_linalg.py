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


def _stable_enough(a: np.ndarray, b: np.ndarray) -> bool:
    """A/2 + B positive definite: every mode's step factor 1 + lambda (B v = lambda A v) exceeds 1/2."""
    return _cholesky(0.5 * a + b) is not None


def factor_step_matrix(A: np.ndarray, B: np.ndarray, n_elements: np.ndarray,
                       corrections: list | None = None) -> tuple[np.ndarray, int]:
    """Cholesky factors of Mhat = A + B per strand, A = M + h^2 K + ... (SPD), B = -h^2 dF/dq.

    Where A/2 + B is positive definite (every mode's step factor 1 + lambda >= 1/2, lambda the
    eigenvalues of B relative to A) Mhat = A + B: gravity is linearly implicit.  Elsewhere a mode of
    the potential is unstable enough that 1 + lambda would approach or cross 0 (amplification
    1 / (1 + lambda) unbounded): Mhat = A + B + C with C = modified_step_matrix(A, B) - A - B.

    ``corrections`` (a list of S entries, None or C, updated in place) keeps each strand's C between
    steps: a kept C is used again as long as A/2 + B + C stays positive definite (the same bound on
    every mode's step factor as for an unmodified strand), so the eigendecomposition is only redone
    when the strand moved out of it; at rest the kept C is the fresh one.  Without it every
    modified strand is decomposed anew.  A, B (S, n, n) padded (A's padding is the identity, B's
    zero); returns the factors (S, n, n) and the number of strands whose step matrix was modified.
    """
    S, n_pad, _ = A.shape
    chol = np.zeros_like(A)
    modified = 0
    for s in range(S):
        n = 3 * int(n_elements[s])
        a, b = A[s, :n, :n], B[s, :n, :n]
        L = None
        if _stable_enough(a, b):
            L = _cholesky(a + b)  # = A/2 + (A/2 + B): positive definite too
        if L is None:
            modified += 1
            kept = corrections[s] if corrections is not None else None
            if kept is not None and kept.shape == a.shape and _stable_enough(a, b + kept):
                L = _cholesky(a + b + kept)
            if L is None:
                m = modified_step_matrix(a, b)
                L = _cholesky(m)
                if L is None:
                    raise np.linalg.LinAlgError(f"strand {s}: the step matrix is not positive definite")
                if corrections is not None:
                    corrections[s] = m - (a + b)
        elif corrections is not None:
            corrections[s] = None
        chol[s, :n, :n] = L
        pad = np.arange(n, n_pad)
        chol[s, pad, pad] = np.sqrt(A[s, pad, pad] + B[s, pad, pad])
    return chol, modified


def factor_spd(A: np.ndarray, n_elements: np.ndarray) -> np.ndarray:
    """Cholesky factors of SPD (S, n, n) matrices on each strand's 3 N_s dofs (padding: sqrt of the diagonal)."""
    S, n_pad, _ = A.shape
    chol = np.zeros_like(A)
    for s in range(S):
        n = 3 * int(n_elements[s])
        L = _cholesky(A[s, :n, :n])
        if L is None:
            raise np.linalg.LinAlgError(f"strand {s}: the step matrix is not positive definite")
        chol[s, :n, :n] = L
        pad = np.arange(n, n_pad)
        chol[s, pad, pad] = np.sqrt(A[s, pad, pad])
    return chol


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
