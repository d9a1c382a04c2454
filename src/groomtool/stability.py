"""Stability of an equilibrium of Super-Helices (MATH.md section 6).

At an equilibrium the Hessian of the total potential is  K - dF/dq  (F the gravity force).
K = EI * Khat with Khat = l_j diag(GJ/EI, 1, 1), so the equilibrium is stable iff

    EI > EI_min = EI * lambda_max(K^-1/2 dF/dq K^-1/2),

and the **stiffness ratio** rho = lambda_max(K^-1/2 (dF/dq) K^-1/2) is the factor by which EI must at
least be multiplied for stability (rho < 1: stable, with margin 1 / rho).  This is the sufficient
condition EI / rhoS >= A(q) of Derouet-Jourdan et al. 2010 (dF/dq is proportional to rhoS).

With contacts, motions that push into an active contact are blocked: the *contact-held* ratio uses
the Hessian restricted to the motions that keep every active contact point fixed (the null space of
its rows of H), the second-order condition for a sticking contact set.

Computation.  A = K^-1/2 dF/dq K^-1/2 is block diagonal plus semiseparable (3x3 blocks, generators from
superhelix._gravity_hessian_parts scaled by K^-1/2):

    A_jk = u_j v_k^T (j < k),   A_kj = v_k u_j^T,   A_jj = d_j,

so products with A, and the block Cholesky of sigma I - A and its solves, cost O(N) (the Schur
complements keep the form through one 3x3 Phi).  rho = lambda_max(A) is pinned between a Rayleigh
quotient theta <= lambda_max (Lanczos, then inverse iteration with shifts proved to lie above lambda_max)
and a shift theta + tol at which the Cholesky succeeds (lambda_max < theta + tol), tol = 1e-12 |theta| +
32 eps ||A||_F, the round-off level of a dense eigvalsh (100 tol accepted once theta has stopped moving); a
strand that does not get there falls back to the dense eigvalsh.  The contact-held ratio is certified the same way, by a dense Cholesky
(:func:`contact_held_ratios`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.linalg.blas
import scipy.linalg.lapack
from numba import njit
from threadpoolctl import threadpool_limits

from .rods import superhelix as sh

RTOL = 1e-12  # relative part of the certified gap lambda_max - theta
ATOL_EPS = 32.0  # absolute part, in units of eps ||A||_F
MAX_STEPS = 60
LANCZOS_STEPS = 12
HELD_LANCZOS_STEPS = 20


def stiffness_ratios(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity,
                     chunk: int = 512, progress=None) -> np.ndarray:
    """rho per strand (S,): lambda_max(K^-1/2 dF/dq K^-1/2) over the strand's real dofs (module docstring)."""
    order = np.argsort(helix.n_elements, kind="stable")  # similar lengths together: less padding
    out = np.empty(helix.n_strands)
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, helix.n_strands, chunk):
            ids = order[start:start + chunk]
            sub = helix.subset(ids)
            u, v, d = _scaled_generators(sub, stiffness_diag, linear_density, gravity)
            lam = np.empty(len(ids))
            ok = np.empty(len(ids), dtype=np.bool_)
            _lambda_max_batch(u, v, d, sub.n_elements, RTOL, ATOL_EPS, MAX_STEPS, LANCZOS_STEPS, lam, ok)
            for i in np.flatnonzero(~ok):  # not certified: the dense route
                lam[i] = np.linalg.eigvalsh(_dense(u[i], v[i], d[i], int(sub.n_elements[i])))[-1]
            out[ids] = lam
            if progress is not None:
                progress.update(len(ids))
    return out


def _scaled_generators(helix: sh.SuperHelix, stiffness_diag, linear_density, gravity):
    """u, v, d (S, N, 3, 3) of A = K^-1/2 dF/dq K^-1/2 (module docstring); zero on padding."""
    kin = sh.kinematics(helix)
    U, G, Dg = sh._gravity_hessian_parts(helix, linear_density, gravity, kin)
    K = sh.stiffness(helix, stiffness_diag)
    scale = 1.0 / np.sqrt(np.where(K > 0, K, 1.0))
    u = np.empty_like(U)
    v = np.empty_like(G)
    d = np.empty_like(Dg)
    _scale_kernel(U, G, Dg, scale, u, v, d)
    return u, v, d


@njit(cache=True)
def _scale_kernel(U, G, Dg, scale, u, v, d):
    """u_j = S_j U_j, v_j = S_j G_j^T, d_j = S_j Dg_j S_j with S_j = diag(scale_j)."""
    for s in range(U.shape[0]):
        for j in range(U.shape[1]):
            for a in range(3):
                sa = scale[s, j, a]
                for b in range(3):
                    u[s, j, a, b] = sa * U[s, j, a, b]
                    v[s, j, a, b] = sa * G[s, j, b, a]
                    d[s, j, a, b] = (sa * scale[s, j, b]) * Dg[s, j, a, b]  # exactly symmetric


def _dense(u, v, d, n_elements):
    """A (3n x 3n) from its generators (one strand, n real elements)."""
    out = np.empty((1, 3 * n_elements, 3 * n_elements))
    sh._assemble_gravity_jacobian(u[None, :n_elements], np.swapaxes(v[None, :n_elements], -1, -2).copy(),
                                  d[None, :n_elements], out)
    return out[0]


# --------------------------------------------------------------------------- O(N) kernels
@njit(cache=True, error_model="numpy")
def _cholesky(u, v, d, N, sigma, L, Y):
    """Block Cholesky of sigma I - A: pivots P_j = L_j L_j^T, Y_j = L_j^-1 (v_j Phi - u_j), Phi -= Y_j^T Y_j.
    False as soon as a pivot is not positive definite (then neither is sigma I - A)."""
    Phi = np.zeros((3, 3))
    T = np.empty((3, 3))
    P = np.empty((3, 3))
    for j in range(N):
        for a in range(3):
            for b in range(3):
                T[a, b] = v[j, a, 0] * Phi[0, b] + v[j, a, 1] * Phi[1, b] + v[j, a, 2] * Phi[2, b]
        for a in range(3):
            for b in range(a + 1):
                P[a, b] = -d[j, a, b] + T[a, 0] * v[j, b, 0] + T[a, 1] * v[j, b, 1] + T[a, 2] * v[j, b, 2]
            P[a, a] += sigma
        l00 = P[0, 0]
        if not l00 > 0.0:
            return False
        l00 = np.sqrt(l00)
        l10 = P[1, 0] / l00
        l20 = P[2, 0] / l00
        l11 = P[1, 1] - l10 * l10
        if not l11 > 0.0:
            return False
        l11 = np.sqrt(l11)
        l21 = (P[2, 1] - l20 * l10) / l11
        l22 = P[2, 2] - l20 * l20 - l21 * l21
        if not l22 > 0.0:
            return False
        l22 = np.sqrt(l22)
        L[j, 0] = l00
        L[j, 1] = l10
        L[j, 2] = l11
        L[j, 3] = l20
        L[j, 4] = l21
        L[j, 5] = l22
        for b in range(3):
            y0 = (T[0, b] - u[j, 0, b]) / l00
            y1 = (T[1, b] - u[j, 1, b] - l10 * y0) / l11
            y2 = (T[2, b] - u[j, 2, b] - l20 * y0 - l21 * y1) / l22
            Y[j, 0, b] = y0
            Y[j, 1, b] = y1
            Y[j, 2, b] = y2
        for a in range(3):
            for b in range(3):
                Phi[a, b] -= Y[j, 0, a] * Y[j, 0, b] + Y[j, 1, a] * Y[j, 1, b] + Y[j, 2, a] * Y[j, 2, b]
    return True


@njit(cache=True, error_model="numpy")
def _solve(v, L, Y, N, b, x):
    """x = (sigma I - A)^-1 b with the factors of :func:`_cholesky` (forward, then backward)."""
    h0 = h1 = h2 = 0.0
    for a in range(N):
        l00, l10, l11, l20, l21, l22 = L[a, 0], L[a, 1], L[a, 2], L[a, 3], L[a, 4], L[a, 5]
        r0 = b[3 * a] - (v[a, 0, 0] * h0 + v[a, 0, 1] * h1 + v[a, 0, 2] * h2)
        r1 = b[3 * a + 1] - (v[a, 1, 0] * h0 + v[a, 1, 1] * h1 + v[a, 1, 2] * h2)
        r2 = b[3 * a + 2] - (v[a, 2, 0] * h0 + v[a, 2, 1] * h1 + v[a, 2, 2] * h2)
        z0 = r0 / l00
        z1 = (r1 - l10 * z0) / l11
        z2 = (r2 - l20 * z0 - l21 * z1) / l22
        x[3 * a] = z0
        x[3 * a + 1] = z1
        x[3 * a + 2] = z2
        h0 += Y[a, 0, 0] * z0 + Y[a, 1, 0] * z1 + Y[a, 2, 0] * z2
        h1 += Y[a, 0, 1] * z0 + Y[a, 1, 1] * z1 + Y[a, 2, 1] * z2
        h2 += Y[a, 0, 2] * z0 + Y[a, 1, 2] * z1 + Y[a, 2, 2] * z2
    r0 = r1 = r2 = 0.0
    for j in range(N - 1, -1, -1):
        l00, l10, l11, l20, l21, l22 = L[j, 0], L[j, 1], L[j, 2], L[j, 3], L[j, 4], L[j, 5]
        t0 = x[3 * j] - (Y[j, 0, 0] * r0 + Y[j, 0, 1] * r1 + Y[j, 0, 2] * r2)
        t1 = x[3 * j + 1] - (Y[j, 1, 0] * r0 + Y[j, 1, 1] * r1 + Y[j, 1, 2] * r2)
        t2 = x[3 * j + 2] - (Y[j, 2, 0] * r0 + Y[j, 2, 1] * r1 + Y[j, 2, 2] * r2)
        x2 = t2 / l22
        x1 = (t1 - l21 * x2) / l11
        x0 = (t0 - l10 * x1 - l20 * x2) / l00
        x[3 * j] = x0
        x[3 * j + 1] = x1
        x[3 * j + 2] = x2
        r0 += v[j, 0, 0] * x0 + v[j, 1, 0] * x1 + v[j, 2, 0] * x2
        r1 += v[j, 0, 1] * x0 + v[j, 1, 1] * x1 + v[j, 2, 1] * x2
        r2 += v[j, 0, 2] * x0 + v[j, 1, 2] * x1 + v[j, 2, 2] * x2


@njit(cache=True, error_model="numpy")
def _matvec(u, v, d, N, x, y):
    """y = A x: y_j = d_j x_j + v_j sum_{k<j} u_k^T x_k + u_j sum_{k>j} v_k^T x_k."""
    p0 = p1 = p2 = 0.0
    for j in range(N):
        x0, x1, x2 = x[3 * j], x[3 * j + 1], x[3 * j + 2]
        for a in range(3):
            y[3 * j + a] = (d[j, a, 0] * x0 + d[j, a, 1] * x1 + d[j, a, 2] * x2
                            + v[j, a, 0] * p0 + v[j, a, 1] * p1 + v[j, a, 2] * p2)
        p0 += u[j, 0, 0] * x0 + u[j, 1, 0] * x1 + u[j, 2, 0] * x2
        p1 += u[j, 0, 1] * x0 + u[j, 1, 1] * x1 + u[j, 2, 1] * x2
        p2 += u[j, 0, 2] * x0 + u[j, 1, 2] * x1 + u[j, 2, 2] * x2
    q0 = q1 = q2 = 0.0
    for j in range(N - 1, -1, -1):
        x0, x1, x2 = x[3 * j], x[3 * j + 1], x[3 * j + 2]
        for a in range(3):
            y[3 * j + a] += u[j, a, 0] * q0 + u[j, a, 1] * q1 + u[j, a, 2] * q2
        q0 += v[j, 0, 0] * x0 + v[j, 1, 0] * x1 + v[j, 2, 0] * x2
        q1 += v[j, 0, 1] * x0 + v[j, 1, 1] * x1 + v[j, 2, 1] * x2
        q2 += v[j, 0, 2] * x0 + v[j, 1, 2] * x1 + v[j, 2, 2] * x2


@njit(cache=True, error_model="numpy")
def _frobenius(u, v, d, N):
    """||A||_F = sqrt(sum_j |d_j|^2 + 2 sum_{j<k} <u_j^T u_j, v_k^T v_k>)."""
    acc = 0.0
    for j in range(N):
        for a in range(3):
            for b in range(3):
                acc += d[j, a, b] * d[j, a, b]
    suffix = np.zeros((3, 3))
    for j in range(N - 1, -1, -1):
        for a in range(3):
            for b in range(3):
                uu = u[j, 0, a] * u[j, 0, b] + u[j, 1, a] * u[j, 1, b] + u[j, 2, a] * u[j, 2, b]
                acc += 2.0 * uu * suffix[a, b]
        for a in range(3):
            for b in range(3):
                suffix[a, b] += v[j, 0, a] * v[j, 0, b] + v[j, 1, a] * v[j, 1, b] + v[j, 2, a] * v[j, 2, b]
    return np.sqrt(max(acc, 0.0))


@njit(cache=True, error_model="numpy")
def _rayleigh(u, v, d, N, x, Ax):
    """theta = x^T A x / x^T x, with Ax = A x."""
    _matvec(u, v, d, N, x, Ax)
    num = 0.0
    den = 0.0
    for i in range(3 * N):
        num += x[i] * Ax[i]
        den += x[i] * x[i]
    return num / den


@njit(cache=True, error_model="numpy")
def _tridiagonal_top(alpha, beta, kk, sv):
    """Top eigenpair of the kk x kk tridiagonal (alpha, beta): the eigenvalue by bisection on Sturm counts in
    its Gershgorin interval, the eigenvector (in sv, unit) by two inverse iterations just above it.
    Returns the eigenvalue and the width of the Gershgorin interval."""
    if kk == 1:
        sv[0] = 1.0
        return alpha[0], 0.0
    lo = np.inf
    hi = -np.inf
    for i in range(kk):
        r = (beta[i - 1] if i > 0 else 0.0) + (beta[i] if i < kk - 1 else 0.0)
        lo = min(lo, alpha[i] - r)
        hi = max(hi, alpha[i] + r)
    lo0 = lo
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if not (lo < mid < hi):
            break
        above = 0  # eigenvalues of T above mid: negative pivots of mid I - T
        piv = 1.0
        for i in range(kk):
            piv = (mid - alpha[i]) - ((beta[i - 1] * beta[i - 1]) / piv if i > 0 else 0.0)
            if piv == 0.0:
                piv = -1e-300
            if piv < 0.0:
                above += 1
        if above > 0:
            lo = mid
        else:
            hi = mid
    theta = hi
    # its eigenvector: two inverse iterations with sigma I - T, sigma a little above theta (positive definite)
    sigma = theta + 1e-8 * (hi - lo0) + 1e-300
    for i in range(kk):
        sv[i] = 1.0
    piv = np.empty(kk)
    for _ in range(2):
        for i in range(kk):  # forward elimination of (sigma I - T) s = sv
            p = sigma - alpha[i]
            if i > 0:
                f = -beta[i - 1] / piv[i - 1]
                p -= f * (-beta[i - 1])
                sv[i] -= f * sv[i - 1]
            piv[i] = p if p != 0.0 else 1e-300
        sv[kk - 1] /= piv[kk - 1]
        for i in range(kk - 2, -1, -1):
            sv[i] = (sv[i] + beta[i] * sv[i + 1]) / piv[i]
        nrm = 0.0
        for i in range(kk):
            nrm += sv[i] * sv[i]
        nrm = 1.0 / np.sqrt(nrm)
        for i in range(kk):
            sv[i] *= nrm
    return theta, hi - lo0


@njit(cache=True, error_model="numpy")
def _lanczos(u, v, d, N, m, x):
    """m Lanczos steps from a fixed start: returns the largest Ritz value and its residual bound
    |beta_m s_m|, its Ritz vector in x (a starting point only: nothing relies on its accuracy)."""
    n = 3 * N
    m = min(m, n)
    Q = np.empty((m, n))
    alpha = np.zeros(m)
    beta = np.zeros(m)
    w = np.empty(n)
    nrm = 0.0
    for i in range(n):
        Q[0, i] = 1.0 + 0.5 * np.sin(1.7 * i + 0.3)
        nrm += Q[0, i] * Q[0, i]
    nrm = 1.0 / np.sqrt(nrm)
    for i in range(n):
        Q[0, i] *= nrm
    kk = m
    for k in range(m):
        _matvec(u, v, d, N, Q[k], w)
        a = 0.0
        for i in range(n):
            a += w[i] * Q[k, i]
        alpha[k] = a
        for i in range(n):
            w[i] -= a * Q[k, i]
            if k > 0:
                w[i] -= beta[k - 1] * Q[k - 1, i]
        b = 0.0
        for i in range(n):
            b += w[i] * w[i]
        b = np.sqrt(b)
        beta[k] = b
        if k == m - 1 or not b > 1e-300 * (abs(a) + 1.0):
            kk = k + 1
            break
        for i in range(n):
            Q[k + 1, i] = w[i] / b
    sv = np.empty(kk)
    theta, _ = _tridiagonal_top(alpha, beta, kk, sv)
    for i in range(n):
        acc = 0.0
        for j in range(kk):
            acc += sv[j] * Q[j, i]
        x[i] = acc
    return theta, abs(beta[kk - 1] * sv[kk - 1])


@njit(cache=True, error_model="numpy")
def _lambda_max(u, v, d, N, rtol, atol_eps, max_steps, lanczos_steps):
    """(lambda_max(A), certified) for one strand: theta is a Rayleigh quotient (theta <= lambda_max) and a
    Cholesky of (theta + tol) I - A succeeded (lambda_max <= theta + tol); see the module docstring."""
    n = 3 * N
    if N == 0:
        return 0.0, True
    norm = _frobenius(u, v, d, N)
    if norm == 0.0:
        return 0.0, True
    atol = atol_eps * 2.220446049250313e-16 * norm
    L = np.empty((N, 6))
    Y = np.empty((N, 3, 3))
    L2 = np.empty((N, 6))
    Y2 = np.empty((N, 3, 3))
    x = np.empty(n)
    y = np.empty(n)
    Ax = np.empty(n)
    _, resid = _lanczos(u, v, d, N, lanczos_steps, x)
    theta = _rayleigh(u, v, d, N, x, Ax)
    # a first shift above lambda_max: theta + w, w growing until the Cholesky succeeds (at most ||A||_F)
    cap = norm * (1.0 + 1e-8) + atol
    w = max(2.0 * resid, 1e-6 * abs(theta), atol)
    hi = min(theta + w, cap)
    steps = 0
    while not _cholesky(u, v, d, N, hi, L, Y):
        steps += 1
        if hi >= cap or steps > max_steps:
            return theta, False
        w *= 8.0
        hi = min(theta + w, cap)
    prev = theta
    fails = 0  # Cholesky failures in a row just above theta: round-off, widen the step
    for _ in range(max_steps):
        # inverse iteration with the certified shift hi
        _solve(v, L, Y, N, x, y)
        s = 0.0
        for i in range(n):
            s += y[i] * y[i]
        s = 1.0 / np.sqrt(s)
        for i in range(n):
            x[i] = y[i] * s
        t = _rayleigh(u, v, d, N, x, Ax)
        step = t - prev
        prev = t
        theta = max(theta, t)
        tol = rtol * abs(theta) + atol
        if hi <= theta + tol:
            return theta, True
        # a tighter shift just above the extrapolated limit of theta
        cand = theta + max(tol, 2.0 * abs(step)) * 4.0 ** fails
        if cand < hi:
            if _cholesky(u, v, d, N, cand, L2, Y2):
                hi = cand
                L, L2 = L2, L
                Y, Y2 = Y2, Y
                fails = 0
                if hi <= theta + tol:
                    return theta, True
            else:
                fails += 1
        if abs(step) <= tol and hi <= theta + 100.0 * tol:  # theta has stopped moving: certified to 100 tol
            return theta, True
    return theta, False


@njit(cache=True, error_model="numpy")
def _lambda_max_batch(u, v, d, n_elements, rtol, atol_eps, max_steps, lanczos_steps, out, ok):
    for s in range(u.shape[0]):
        N = n_elements[s]
        out[s], ok[s] = _lambda_max(u[s, :N], v[s, :N], d[s, :N], N, rtol, atol_eps, max_steps, lanczos_steps)


# --------------------------------------------------------------------------- contact-held ratios
def contact_held_ratio(helix: sh.SuperHelix, strand: int, stiffness_diag, linear_density: float, gravity,
                       blocked_rows: np.ndarray) -> float:
    """rho for one strand when the motions in the row space of ``blocked_rows`` (k x 3n) are blocked."""
    return float(contact_held_ratios(helix, [strand], stiffness_diag, linear_density, gravity, [blocked_rows])[0])


def contact_held_ratios(helix: sh.SuperHelix, strands, stiffness_diag, linear_density: float, gravity,
                        blocked_rows, chunk: int = 512) -> np.ndarray:
    """rho of each listed strand with the motions in the row space of its ``blocked_rows[i]`` (k x 3n, or None)
    blocked: lambda_max(Z^T A Z), Z an orthonormal basis of null(C), C = blocked K^-1/2 (0 if it is empty).

    With Q an orthonormal basis of C's row space (SVD of C, rank as in scipy's null_space), Z^T A Z has the
    eigenvalues of B = P A P - c Q Q^T (P = I - Q Q^T, c = 2 ||A||_F) but for r copies of -c.  A Rayleigh
    quotient theta of A on null(C) (Lanczos, then if needed constrained inverse iteration, both O(N) per step)
    is accepted when a dense Cholesky of (theta + tol) I - B succeeds; otherwise the top eigenvalue of B."""
    strands = np.asarray(strands, dtype=np.int64)
    out = np.empty(len(strands))
    order = np.argsort(helix.n_elements[strands], kind="stable")
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, len(strands), chunk):
            ids = order[start:start + chunk]
            sub = helix.subset(strands[ids])
            u, v, d = _scaled_generators(sub, stiffness_diag, linear_density, gravity)
            K = sh.stiffness(sub, stiffness_diag).reshape(len(ids), -1)
            scale = 1.0 / np.sqrt(np.where(K > 0, K, 1.0))
            for i, k in enumerate(ids):
                N = int(sub.n_elements[i])
                rows = blocked_rows[k]
                if rows is None or len(rows) == 0:
                    lam, ok = _lambda_max(u[i, :N], v[i, :N], d[i, :N], N, RTOL, ATOL_EPS, MAX_STEPS, LANCZOS_STEPS)
                    out[k] = lam if ok else np.linalg.eigvalsh(_dense(u[i], v[i], d[i], N))[-1]
                    continue
                out[k] = _held_top(u[i, :N], v[i, :N], d[i, :N], N,
                                   np.asarray(rows, dtype=np.float64) * scale[i, :3 * N])
    return out


def _csr_block(H, rows, c0, c1) -> np.ndarray:
    """H[rows][:, c0:c1] as a dense array, H in CSR form."""
    out = np.zeros((len(rows), c1 - c0))
    _csr_block_kernel(H.indptr, H.indices, H.data, np.asarray(rows, dtype=np.int64), c0, c1, out)
    return out


@njit(cache=True)
def _csr_block_kernel(indptr, indices, data, rows, c0, c1, out):
    for i in range(rows.shape[0]):
        r = rows[i]
        for p in range(indptr[r], indptr[r + 1]):
            c = indices[p]
            if c0 <= c < c1:
                out[i, c - c0] += data[p]


def _held_top(u, v, d, N, C):
    """lambda_max(Z^T A Z) for Z an orthonormal basis of null(C) (contact_held_ratios); 0 if it is empty."""
    A = _dense(u, v, d, N)
    n = A.shape[0]
    # as scipy.linalg.null_space: the SVD of C (its right singular vectors, so that an ill-conditioned C gives
    # the same subspace to round-off) and its rank threshold
    _, s, Vh = np.linalg.svd(C, full_matrices=False)
    r = int(np.count_nonzero(s > (s.max() if len(s) else 0.0) * np.finfo(float).eps * max(C.shape[0], n)))
    if r == n:
        return 0.0
    Q = np.ascontiguousarray(Vh[:r].T)
    AQ = A @ Q
    norm = np.linalg.norm(A)
    c = 2.0 * norm or 1.0
    W = AQ + Q @ (0.5 * (c * np.eye(r) - Q.T @ AQ))  # B = P A P - c Q Q^T = A - Q W^T - W Q^T
    x = np.empty(n)
    theta, spread = _held_lanczos(u, v, d, N, Q, HELD_LANCZOS_STEPS, x)
    for attempt in range(2):  # the Lanczos Rayleigh quotient, else refined by inverse iteration
        if attempt:
            theta = _held_refine(u, v, d, N, Q, x, theta, spread, MAX_STEPS)
        if np.isfinite(theta):
            shifted = np.asfortranarray(-A)  # (theta + tol) I - B, lower triangle
            shifted.flat[::n + 1] += theta + RTOL * abs(theta) + ATOL_EPS * np.finfo(float).eps * (norm + c)
            shifted = scipy.linalg.blas.dsyr2k(1.0, Q, W, beta=1.0, c=shifted, lower=1, overwrite_c=1)
            if scipy.linalg.lapack.dpotrf(shifted, lower=1, clean=0, overwrite_a=1)[1] == 0:
                return float(theta)
    B = A - Q @ W.T - W @ Q.T
    return float(scipy.linalg.lapack.dsyevr(B, compute_v=0, range="I", il=n, iu=n, overwrite_a=1)[0][0])


@njit(cache=True, error_model="numpy")
def _ldl(u, v, d, N, sigma, Pinv, W):
    """Block LDL^T of sigma I - A without pivoting (it may be indefinite): pivots P_j (their inverses kept),
    W_j = v_j Phi - u_j, Phi -= W_j^T P_j^-1 W_j.  False if a pivot is singular."""
    Phi = np.zeros((3, 3))
    T = np.empty((3, 3))
    P = np.empty((3, 3))
    for j in range(N):
        for a in range(3):
            for b in range(3):
                T[a, b] = v[j, a, 0] * Phi[0, b] + v[j, a, 1] * Phi[1, b] + v[j, a, 2] * Phi[2, b]
        for a in range(3):
            for b in range(3):
                P[a, b] = -d[j, a, b] + T[a, 0] * v[j, b, 0] + T[a, 1] * v[j, b, 1] + T[a, 2] * v[j, b, 2]
            P[a, a] += sigma
        c00 = P[1, 1] * P[2, 2] - P[1, 2] * P[2, 1]
        c01 = P[1, 2] * P[2, 0] - P[1, 0] * P[2, 2]
        c02 = P[1, 0] * P[2, 1] - P[1, 1] * P[2, 0]
        det = P[0, 0] * c00 + P[0, 1] * c01 + P[0, 2] * c02
        if not (det != 0.0 and np.isfinite(det)):
            return False
        inv = 1.0 / det
        Pinv[j, 0, 0] = c00 * inv
        Pinv[j, 1, 0] = c01 * inv
        Pinv[j, 2, 0] = c02 * inv
        Pinv[j, 0, 1] = (P[0, 2] * P[2, 1] - P[0, 1] * P[2, 2]) * inv
        Pinv[j, 1, 1] = (P[0, 0] * P[2, 2] - P[0, 2] * P[2, 0]) * inv
        Pinv[j, 2, 1] = (P[0, 1] * P[2, 0] - P[0, 0] * P[2, 1]) * inv
        Pinv[j, 0, 2] = (P[0, 1] * P[1, 2] - P[0, 2] * P[1, 1]) * inv
        Pinv[j, 1, 2] = (P[0, 2] * P[1, 0] - P[0, 0] * P[1, 2]) * inv
        Pinv[j, 2, 2] = (P[0, 0] * P[1, 1] - P[0, 1] * P[1, 0]) * inv
        for a in range(3):
            for b in range(3):
                W[j, a, b] = T[a, b] - u[j, a, b]
        for a in range(3):  # Phi -= W^T (P^-1 W)
            for b in range(3):
                acc = 0.0
                for e in range(3):
                    pw = Pinv[j, e, 0] * W[j, 0, b] + Pinv[j, e, 1] * W[j, 1, b] + Pinv[j, e, 2] * W[j, 2, b]
                    acc += W[j, e, a] * pw
                Phi[a, b] -= acc
    return True


@njit(cache=True, error_model="numpy")
def _ldl_solve(v, Pinv, W, N, b, x):
    """x = (sigma I - A)^-1 b with the factors of :func:`_ldl`."""
    h = np.zeros(3)
    w = np.empty(3)
    for a in range(N):
        for e in range(3):
            w[e] = b[3 * a + e] - (v[a, e, 0] * h[0] + v[a, e, 1] * h[1] + v[a, e, 2] * h[2])
        for e in range(3):
            x[3 * a + e] = Pinv[a, e, 0] * w[0] + Pinv[a, e, 1] * w[1] + Pinv[a, e, 2] * w[2]
        for e in range(3):
            h[e] += W[a, 0, e] * x[3 * a] + W[a, 1, e] * x[3 * a + 1] + W[a, 2, e] * x[3 * a + 2]
    r = np.zeros(3)
    for j in range(N - 1, -1, -1):
        for e in range(3):
            w[e] = W[j, e, 0] * r[0] + W[j, e, 1] * r[1] + W[j, e, 2] * r[2]
        for e in range(3):
            x[3 * j + e] -= Pinv[j, e, 0] * w[0] + Pinv[j, e, 1] * w[1] + Pinv[j, e, 2] * w[2]
        for e in range(3):
            r[e] += v[j, 0, e] * x[3 * j] + v[j, 1, e] * x[3 * j + 1] + v[j, 2, e] * x[3 * j + 2]


@njit(cache=True, error_model="numpy")
def _project(Q, x):
    """x -= Q (Q^T x)."""
    for c in range(Q.shape[1]):
        acc = 0.0
        for i in range(x.shape[0]):
            acc += Q[i, c] * x[i]
        for i in range(x.shape[0]):
            x[i] -= acc * Q[i, c]


@njit(cache=True, error_model="numpy")
def _held_lanczos(u, v, d, N, Q, steps, x):
    """Lanczos on P A P from a vector in null(C) (= null(Q^T)): the Rayleigh quotient of A at the top Ritz
    vector (a lower bound of lambda_max(Z^T A Z)), that vector in x, and the spread of the Ritz values."""
    n = 3 * N
    m = min(steps, n - Q.shape[1])
    if m < 1:
        return np.nan, 0.0
    Qk = np.empty((m, n))
    alpha = np.zeros(m)
    beta = np.zeros(m)
    w = np.empty(n)
    for i in range(n):
        x[i] = 1.0 + 0.5 * np.sin(1.7 * i + 0.3)
    _project(Q, x)
    nrm = np.sqrt(np.sum(x * x))
    if not nrm > 0.0:
        return np.nan, 0.0
    Qk[0] = x / nrm
    kk = m
    for k in range(m):
        _matvec(u, v, d, N, Qk[k], w)
        _project(Q, w)
        a = np.sum(w * Qk[k])
        alpha[k] = a
        w -= a * Qk[k]
        if k > 0:
            w -= beta[k - 1] * Qk[k - 1]
        b = np.sqrt(np.sum(w * w))
        beta[k] = b
        if k == m - 1 or not b > 1e-300 * (abs(a) + 1.0):
            kk = k + 1
            break
        Qk[k + 1] = w / b
    sv = np.empty(kk)
    top, width = _tridiagonal_top(alpha, beta, kk, sv)
    for i in range(n):
        acc = 0.0
        for j in range(kk):
            acc += sv[j] * Qk[j, i]
        x[i] = acc
    _project(Q, x)
    x /= np.sqrt(np.sum(x * x))
    _matvec(u, v, d, N, x, w)
    return np.sum(x * w), max(width, abs(top), 1e-300)


@njit(cache=True, error_model="numpy")
def _held_refine(u, v, d, N, Q, x, theta, spread, max_steps):
    """Inverse iteration on the constrained problem from x: y = z - G S^-1 Q^T z, z = M^-1 x, G = M^-1 Q,
    S = Q^T G, M = sigma I - A (:func:`_ldl`), sigma just above the current Rayleigh quotient.  Returns the
    last Rayleigh quotient of A (a lower bound of lambda_max(Z^T A Z)); NaN when it fails."""
    n = 3 * N
    r = Q.shape[1]
    Pinv = np.empty((N, 3, 3))
    Wf = np.empty((N, 3, 3))
    G = np.empty((n, r))
    col = np.empty(n)
    z = np.empty(n)
    Ax = np.empty(n)
    sigma = theta + 1e-6 * spread
    prev = theta
    for _ in range(max_steps):
        if not _ldl(u, v, d, N, sigma, Pinv, Wf):
            sigma += 1e-6 * spread
            continue
        for c in range(r):
            for i in range(n):
                col[i] = Q[i, c]
            _ldl_solve(v, Pinv, Wf, N, col, z)
            for i in range(n):
                G[i, c] = z[i]
        _ldl_solve(v, Pinv, Wf, N, x, z)
        mu = np.linalg.solve(Q.T @ G, Q.T @ z)
        for i in range(n):
            x[i] = z[i] - np.sum(G[i] * mu)
        _project(Q, x)
        nrm = np.sqrt(np.sum(x * x))
        if not (nrm > 0.0 and np.isfinite(nrm)):
            return np.nan
        x /= nrm
        _matvec(u, v, d, N, x, Ax)
        t = np.sum(x * Ax)
        if abs(t - prev) <= 1e-14 * abs(t):
            return t
        sigma = t + 1e-3 * abs(t - prev) + 1e-9 * spread  # just above: fast, and not singular
        prev = t
    return prev


def _stiffness_ratios_reference(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity,
                                chunk: int = 256, progress=None) -> np.ndarray:
    """The original dense route: batched eigvalsh of the padded matrices (tests and benchmarks only; with
    chunk > 1 a strand shorter than the longest of its chunk gets max(rho, 0), the padding's zeros)."""
    order = np.argsort(helix.n_elements, kind="stable")
    out = np.empty(helix.n_strands)
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, helix.n_strands, chunk):
            ids = order[start:start + chunk]
            out[ids] = _ratios_reference(helix.subset(ids), stiffness_diag, linear_density, gravity)
            if progress is not None:
                progress.update(len(ids))
    return out


def _ratios_reference(helix, stiffness_diag, linear_density, gravity):
    dF = sh._gravity_force_jacobian_reference(helix, linear_density, gravity)
    K = sh.stiffness(helix, stiffness_diag).reshape(helix.n_strands, -1)
    K = np.where(K > 0, K, 1.0)  # padding dofs: dF is zero there, any K works
    scale = 1.0 / np.sqrt(K)
    A = scale[:, :, None] * dF * scale[:, None, :]
    return np.linalg.eigvalsh(A)[:, -1]


def _contact_held_ratio_reference(helix: sh.SuperHelix, strand: int, stiffness_diag, linear_density: float,
                                  gravity, blocked_rows: np.ndarray) -> float:
    """The original one-strand route (SVD null space, Z^T A Z, eigvalsh): tests and benchmarks only."""
    sub = helix.subset([strand])
    n = 3 * int(sub.n_elements[0])
    dF = sh._gravity_force_jacobian_reference(sub, linear_density, gravity)[0, :n, :n]
    K = sh.stiffness(sub, stiffness_diag).reshape(-1)[:n]
    scale = 1.0 / np.sqrt(K)
    A = scale[:, None] * dF * scale[None, :]
    if blocked_rows is not None and len(blocked_rows):
        # motions dq = K^-1/2 y with blocked_rows dq = 0
        Z = scipy.linalg.null_space(np.asarray(blocked_rows) * scale[None, :])
        if Z.shape[1] == 0:
            return 0.0
        A = Z.T @ A @ Z
    return float(np.linalg.eigvalsh(A)[-1])
