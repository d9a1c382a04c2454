"""Stability of an equilibrium of Super-Helices (docs/maths.md section 8).

At an equilibrium the Hessian of the total potential is  K - dF/dq  (F the gravity force).
K = EI * Khat with Khat = l_j diag(GJ/EI, 1, 1), so the equilibrium is stable iff

    EI > EI_min = EI * lambda_max(K^-1/2 dF/dq K^-1/2),

and the **stiffness ratio** rho = lambda_max(K^-1/2 (dF/dq) K^-1/2) is the factor by which EI must at
least be multiplied for stability (rho < 1: stable, with margin 1 / rho).  This is the sufficient
condition EI / rhoS >= A(q) of Derouet-Jourdan et al. 2010 (dF/dq is proportional to rhoS).

With contacts, motions that push into a loaded contact are blocked: the *held* ratio uses the Hessian,
with the stiffness of the contact forces, restricted to the null space of the blocking rows of H: the
second-order condition of the constrained equilibrium (:func:`held_stiffness_ratios`).

Computation.  A = K^-1/2 dF/dq K^-1/2 is block diagonal plus semiseparable (3x3 blocks, generators from
superhelix.gravity_force_jacobian_parts scaled by K^-1/2):

    A_jk = u_j v_k^T (j < k),   A_kj = v_k u_j^T,   A_jj = d_j,

so products with A, and the block Cholesky of sigma I - A and its solves, cost O(N) (groomtool.semiseparable,
rank 3: later_k = v_k^T, earlier_j = u_j^T).  rho = lambda_max(A) is pinned between a Rayleigh
quotient theta <= lambda_max (Lanczos, then inverse iteration with shifts proved to lie above lambda_max)
and a shift theta + tol at which the Cholesky succeeds (lambda_max < theta + tol), tol = 1e-12 |theta| +
32 eps ||A||_F, the round-off level of a dense eigvalsh (100 tol accepted once theta has stopped moving); a
strand that does not get there falls back to the dense eigvalsh.

With the contacts that hold a strand (:func:`held_stiffness_ratios`) the Hessian gains the stiffness of the
contact forces (dead loads) and is restricted to the motions the loaded head contacts allow; dense per
strand (docs/stability.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from threadpoolctl import threadpool_limits

from . import semiseparable as ss
from .rods import clothoid as cl
from .rods import superhelix as sh

RTOL = 1e-12  # relative part of the certified gap lambda_max - theta
ATOL_EPS = 32.0  # absolute part, in units of eps ||A||_F
MAX_STEPS = 60
LANCZOS_STEPS = 12


def stiffness_ratios(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity,
                     chunk: int = 512, progress=None) -> np.ndarray:
    """rho per strand (S,): lambda_max(K^-1/2 dF/dq K^-1/2) over the strand's real dofs (module docstring).
    A Super Space Clothoid: :func:`clothoid_stiffness_ratios` (dense)."""
    if isinstance(helix, cl.SuperClothoid):
        return clothoid_stiffness_ratios(helix, stiffness_diag, linear_density, gravity, progress=progress)
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


def _clothoid_whitening(K: np.ndarray) -> np.ndarray:
    """L^-T for K = L L^T (K dense SPD): A = L^-1 M L^-T has the eigenvalues of K^-1/2 M K^-1/2 (similar
    matrices), and y = L^T dq maps the constraint rows C dq = 0 to C L^-T y = 0."""
    L = np.linalg.cholesky(K)
    return np.linalg.inv(L).T


def clothoid_stiffness_ratios(rod: cl.SuperClothoid, stiffness_diag, linear_density: float, gravity,
                              chunk: int = 128, progress=None) -> np.ndarray:
    """The stiffness ratio of Super Space Clothoids: lambda_max(L^-1 dF/dq L^-T), K = L L^T block tridiagonal
    (:func:`groomtool.rods.clothoid.stiffness_matrix`), dF/dq by the complex step
    (:func:`groomtool.rods.clothoid.gravity_force_jacobian`), dense eigvalsh per strand over its real dofs."""
    order = np.argsort(rod.n_elements, kind="stable")
    out = np.empty(rod.n_strands)
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, rod.n_strands, chunk):
            ids = order[start:start + chunk]
            sub = rod.subset(ids)
            dF = cl.gravity_force_jacobian(sub, linear_density, gravity)
            K = cl.stiffness_matrix(sub, stiffness_diag)
            for i in range(len(ids)):
                n = 3 * (int(sub.n_elements[i]) + 1)
                Wm = _clothoid_whitening(K[i, :n, :n])
                A = Wm.T @ dF[i, :n, :n] @ Wm
                out[ids[i]] = float(np.linalg.eigvalsh(0.5 * (A + A.T))[-1])
            if progress is not None:
                progress.update(len(ids))
    return out


def _scaled_generators(helix: sh.SuperHelix, stiffness_diag, linear_density, gravity):
    """u, v, d (S, N, 3, 3) of A = K^-1/2 dF/dq K^-1/2 (module docstring); zero on padding."""
    kin = sh.kinematics(helix)
    U, G, Dg = sh.gravity_force_jacobian_parts(helix, linear_density, gravity, kin)
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
    sh.assemble_gravity_jacobian(u[None, :n_elements], np.swapaxes(v[None, :n_elements], -1, -2).copy(),
                                  d[None, :n_elements], out)
    return out[0]


# --------------------------------------------------------------------------- O(N) kernels
@njit(cache=True)
def _semiseparable_form(u, v, N):
    """A's generators in semiseparable.py's form (A_kj = later_k^T earlier_j, k > j): later_k = v_k^T,
    earlier_j = u_j^T; and -later, the lower generators of sigma I - A."""
    later = np.empty((N, 3, 3))
    earlier = np.empty((N, 3, 3))
    for j in range(N):
        for a in range(3):
            for b in range(3):
                later[j, a, b] = v[j, b, a]
                earlier[j, a, b] = u[j, b, a]
    return later, earlier, -later


@njit(cache=True)
def _cholesky(d, neg_later, earlier, N, sigma, diag, L, W):
    """The semiseparable Cholesky factor (L, W) of sigma I - A (diag: scratch for its diagonal blocks).  False
    as soon as a pivot is not positive definite (then neither is sigma I - A)."""
    for j in range(N):
        for a in range(3):
            for b in range(3):
                diag[j, a, b] = -d[j, a, b]
            diag[j, a, a] += sigma
    return ss.factor_strand(diag, neg_later, earlier, 0, N, L, W)


@njit(cache=True)
def _solve(neg_later, L, W, N, b, x):
    """x = (sigma I - A)^-1 b with the factor of :func:`_cholesky`."""
    x[:] = b
    ss.solve_strand(L, W, neg_later, 0, N, x)


@njit(cache=True, error_model="numpy")
def _frobenius(d, later, earlier, N):
    """||A||_F = sqrt(sum_j |d_j|^2 + 2 sum_j <earlier_j earlier_j^T, sum_{k>j} later_k later_k^T>) (the lower blocks
    later_k^T earlier_j, k > j, counted twice)."""
    r = later.shape[1]
    acc = 0.0
    for j in range(N):
        for a in range(3):
            for b in range(3):
                acc += d[j, a, b] * d[j, a, b]
    suffix = np.zeros((r, r))
    for j in range(N - 1, -1, -1):
        for a in range(r):
            for b in range(r):
                ee = earlier[j, a, 0] * earlier[j, b, 0] + earlier[j, a, 1] * earlier[j, b, 1] + earlier[j, a, 2] * earlier[j, b, 2]
                acc += 2.0 * ee * suffix[a, b]
        for a in range(r):
            for b in range(r):
                suffix[a, b] += later[j, a, 0] * later[j, b, 0] + later[j, a, 1] * later[j, b, 1] + later[j, a, 2] * later[j, b, 2]
    return np.sqrt(max(acc, 0.0))


@njit(cache=True, error_model="numpy")
def _rayleigh(d, later, earlier, N, x, Ax):
    """theta = x^T A x / x^T x, with Ax = A x."""
    ss.matvec_strand(d, later, earlier, 0, N, x, Ax)
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
def _lanczos(d, later, earlier, N, m, x):
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
        ss.matvec_strand(d, later, earlier, 0, N, Q[k], w)
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
def _lambda_max(d, later, earlier, N, rtol, atol_eps, max_steps, lanczos_steps):
    """(lambda_max(A), certified) for one strand's A (semiseparable form: diagonal blocks d, lower blocks
    later_k^T earlier_j): theta is a Rayleigh quotient (theta <= lambda_max) and a Cholesky of
    (theta + tol) I - A succeeded (lambda_max <= theta + tol); see the module docstring."""
    n = 3 * N
    if N == 0:
        return 0.0, True
    norm = _frobenius(d, later, earlier, N)
    if norm == 0.0:
        return 0.0, True
    atol = atol_eps * 2.220446049250313e-16 * norm
    neg_later = -later
    diag = np.empty((N, 3, 3))
    L = np.empty((N, 3, 3))
    Y = np.empty((N, later.shape[1], 3))
    L2 = np.empty((N, 3, 3))
    Y2 = np.empty((N, later.shape[1], 3))
    x = np.empty(n)
    y = np.empty(n)
    Ax = np.empty(n)
    _, resid = _lanczos(d, later, earlier, N, lanczos_steps, x)
    theta = _rayleigh(d, later, earlier, N, x, Ax)
    # a first shift above lambda_max: theta + w, w growing until the Cholesky succeeds (at most ||A||_F)
    cap = norm * (1.0 + 1e-8) + atol
    w = max(2.0 * resid, 1e-6 * abs(theta), atol)
    hi = min(theta + w, cap)
    steps = 0
    while not _cholesky(d, neg_later, earlier, N, hi, diag, L, Y):
        steps += 1
        if hi >= cap or steps > max_steps:
            return theta, False
        w *= 8.0
        hi = min(theta + w, cap)
    prev = theta
    fails = 0  # Cholesky failures in a row just above theta: round-off, widen the step
    for _ in range(max_steps):
        # inverse iteration with the certified shift hi
        _solve(neg_later, L, Y, N, x, y)
        s = 0.0
        for i in range(n):
            s += y[i] * y[i]
        s = 1.0 / np.sqrt(s)
        for i in range(n):
            x[i] = y[i] * s
        t = _rayleigh(d, later, earlier, N, x, Ax)
        step = t - prev
        prev = t
        theta = max(theta, t)
        tol = rtol * abs(theta) + atol
        if hi <= theta + tol:
            return theta, True
        # a tighter shift just above the extrapolated limit of theta
        cand = theta + max(tol, 2.0 * abs(step)) * 4.0 ** fails
        if cand < hi:
            if _cholesky(d, neg_later, earlier, N, cand, diag, L2, Y2):
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
        later, earlier, _ = _semiseparable_form(u[s, :N], v[s, :N], N)
        out[s], ok[s] = _lambda_max(d[s, :N], later, earlier, N, rtol, atol_eps, max_steps, lanczos_steps)


@njit(cache=True, error_model="numpy")
def _projected_form(d, later, earlier, N, Q, beta):
    """The semiseparable form of B = P A P - beta Q^T Q, P = I - Q^T Q (Q: k orthonormal rows):

        B = A - (Q^T Y^T + Y Q),   Y = A Q^T - Q^T (Q A Q^T - beta I) / 2   (n x k),

    so B's lower blocks take 2 k more generator rows (-q_i, -y_i in later; y_i, q_i in earlier) and its diagonal
    blocks d_j - sum_i (q_ij y_ij^T + y_ij q_ij^T).  B is A restricted to null(Q) there and -beta I on its
    complement, so lambda_max(B) = lambda_max(A on null(Q)) when beta exceeds |lambda| of that restriction."""
    n = 3 * N
    k = Q.shape[0]
    r = later.shape[1]
    AQ = np.empty((n, k))
    col = np.empty(n)
    for i in range(k):
        ss.matvec_strand(d, later, earlier, 0, N, Q[i], col)
        AQ[:, i] = col
    T = Q @ AQ
    for i in range(k):
        T[i, i] -= beta
    Y = AQ - 0.5 * (Q.T @ T)
    later_b = np.empty((N, r + 2 * k, 3))
    earlier_b = np.empty((N, r + 2 * k, 3))
    d_b = np.empty((N, 3, 3))
    for j in range(N):
        for c in range(3):
            for a in range(r):
                later_b[j, a, c] = later[j, a, c]
                earlier_b[j, a, c] = earlier[j, a, c]
            for i in range(k):
                later_b[j, r + i, c] = -Q[i, 3 * j + c]
                later_b[j, r + k + i, c] = -Y[3 * j + c, i]
                earlier_b[j, r + i, c] = Y[3 * j + c, i]
                earlier_b[j, r + k + i, c] = Q[i, 3 * j + c]
            for e in range(3):
                acc = d[j, c, e]
                for i in range(k):
                    acc -= Q[i, 3 * j + c] * Y[3 * j + e, i] + Y[3 * j + c, i] * Q[i, 3 * j + e]
                d_b[j, c, e] = acc
    return d_b, later_b, earlier_b


@njit(cache=True, error_model="numpy")
def _held_lambda_max(d, later, earlier, N, C, rtol, atol_eps, max_steps, lanczos_steps):
    """(lambda_max of A on null(C), certified) in O(N k^2) for one Super-Helix strand, A in semiseparable form
    (diagonal blocks d (N, 3, 3), lower blocks later_k^T earlier_j), C (k, 3 N) its blocking rows: the certified
    lambda_max of B = P A P - beta Q^T Q (:func:`_projected_form`; Q the orthonormal rows of C's row space by
    :func:`constrained_top_eigenvalue`'s rank rule, beta = 2 ||A||_F + 1).  0 when the rows block every motion."""
    k = C.shape[0]
    if k > 0 and N > 0:
        _, sv, Vh = np.linalg.svd(C, full_matrices=False)
        cut = sv.max() * 2.220446049250313e-16 * max(k, 3 * N)
        rank = 0
        for i in range(sv.shape[0]):
            if sv[i] > cut:
                rank += 1
        if rank >= 3 * N:
            return 0.0, True
        if rank > 0:
            beta = 2.0 * _frobenius(d, later, earlier, N) + 1.0
            d, later, earlier = _projected_form(d, later, earlier, N, np.ascontiguousarray(Vh[:rank]), beta)
    return _lambda_max(d, later, earlier, N, rtol, atol_eps, max_steps, lanczos_steps)


@njit(cache=True, error_model="numpy")
def _held_batch(U, A_gen, diag, n_elements, C, c_ptr, rtol, atol_eps, max_steps, lanczos_steps, out, ok):
    """_held_lambda_max of each strand i of a chunk: its A from the whitened generators (u_j = U_j, v_k = A_k^T:
    later_k = A_k, earlier_j = U_j^T), its blocking rows C[c_ptr[i]:c_ptr[i + 1], :3 N] (none: the whole A)."""
    for i in range(U.shape[0]):
        N = n_elements[i]
        later = np.empty((N, 3, 3))
        earlier = np.empty((N, 3, 3))
        for j in range(N):
            for a in range(3):
                for b in range(3):
                    later[j, a, b] = A_gen[i, j, a, b]
                    earlier[j, a, b] = U[i, j, b, a]
        rows = np.ascontiguousarray(C[c_ptr[i]:c_ptr[i + 1], :3 * N])
        out[i], ok[i] = _held_lambda_max(np.ascontiguousarray(diag[i, :N]), later, earlier, N, rows, rtol, atol_eps,
                                         max_steps, lanczos_steps)


def _blocking_rows(head_ids, head_stick, lo, hi):
    """The rows of H that block each strand (docs/stability.md): per strand, those of its loaded head contacts
    head_ids[lo_i:hi_i] (all three for a sticking one, the normal row else), back to back; (rows, ptr)."""
    lens = hi - lo
    first = np.repeat(lo - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(lens.sum())
    contact, stick = head_ids[first], head_stick[first]
    count = np.where(stick, 3, 1)
    start = np.cumsum(count) - count
    rows = np.repeat(3 * contact, count) + np.arange(count.sum()) - np.repeat(start, count)
    per_strand = np.bincount(np.repeat(np.arange(len(lens)), lens), weights=count, minlength=len(lens))
    ptr = np.zeros(len(lens) + 1, dtype=np.int64)
    np.cumsum(per_strand.astype(np.int64), out=ptr[1:])
    return rows.astype(np.int64), ptr


@njit(cache=True)
def _scaled_rows(indptr, indices, data, rows, ptr, col0, n_elements, sc, out):
    """out[p] = row rows[p] of H over the columns of chunk strand i (p in ptr[i]:ptr[i + 1]), from col0[i], times the
    whitening sc[i] (K^-1/2 per dof)."""
    for i in range(ptr.shape[0] - 1):
        n = 3 * n_elements[i]
        for p in range(ptr[i], ptr[i + 1]):
            r = rows[p]
            for q in range(indptr[r], indptr[r + 1]):
                c = indices[q] - col0[i]
                if 0 <= c < n:
                    out[p, c] += data[q] * sc[i, c // 3, c % 3]


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


# --------------------------------------------------------------------------- stability with the contacts that hold it
STICK_SLACK = 1e-6  # a force with ||r_T|| < (1 - STICK_SLACK) mu r_N sticks; on the cone boundary it may slide


@dataclass
class HeldStability:
    """Per strand (S,): ``ratio`` rho = lambda_max of K^-1/2 (dF/dq + dF_c/dq) K^-1/2 on the motions the
    strand's contacts allow (with the *base* stiffness K: a strand whose stiffness is multiplied by f has the
    ratio rho / f, stable iff rho / f < 1); ``kind`` 0 where no loaded contact touches the strand (rho is the
    isolated ratio), 1 where contacts load it (the reduced Hessian below); ``blocked_rows`` the number of
    constraint rows, ``loaded_contacts`` the number of contacts with r_N > 0 on the strand."""

    ratio: np.ndarray
    kind: np.ndarray
    blocked_rows: np.ndarray
    loaded_contacts: np.ndarray


def contact_load_hessians(helix: sh.SuperHelix, strands, point_strand, point_s, point_force,
                          rotation_step: float = 1e-6, chunk_dofs: int = 6000, chunk: int = 256) -> list:
    """d(J^T f)/dq per listed strand (dense n x n, n = 3 N_s): the stiffness of the world point loads
    f_p at arc lengths s_p held fixed (dead loads), i.e. the Hessian of sum_p f_p . C(s_p; q).

    Super-Helices: **analytic** (superhelix.point_load_hessian_parts, O(N_s^2 + P) per strand).  With
    J_pk = dC(s_p)/domega_k, a change of omega_j (j < k) moves everything beyond S_{j+1} rigidly, so block
    (j, k) = Theta_j^T A_k with A_k = -sum_{e_p >= k} [f_p]x J_pk, from the suffix sums F_k = sum_{e_p > k} f_p
    and N_k = sum_{e_p > k} f_p (x_p - C_{k+1})^T:
        A_k = -[F_k]x R_k D_k + (N_k^T - tr(N_k) I) Theta_k - sum_{e_p = k} [f_p]x R_k D_k(t_p);
    diagonal block k: the Hessian in omega_k of R_k^T F_k . p_k(l_k) + sum_{e_p > k} R_k^T f_p . Q_k y_p
    + sum_{e_p = k} R_k^T f_p . p_k(t_p) (y_p = R_{k+1}^T (x_p - C_{k+1}) fixed).  Symmetric exactly (each
    off-diagonal block written once and transposed).  Strands go ``chunk`` at a time, grouped by length.

    Super Space Clothoids: central differences of the exact generalized force
    (contact.jacobian.point_forces_generalized), a step of ``rotation_step`` radians per node (truncation
    O(step^2), round-off O(eps / step), about 1e-10 relative), symmetrised, at most ``chunk_dofs`` perturbed
    copies at once (:func:`finite_difference_load_hessians`, also the tests' oracle for Super-Helices)."""
    if isinstance(helix, cl.SuperClothoid):
        return finite_difference_load_hessians(helix, strands, point_strand, point_s, point_force, rotation_step,
                                               chunk_dofs)
    strands = np.asarray(strands, dtype=np.int64)
    point_strand = np.asarray(point_strand, dtype=np.int64)
    order = np.argsort(point_strand, kind="stable")
    ps, pss = point_strand[order], np.asarray(point_s, float)[order]
    pf = np.asarray(point_force, float).reshape(-1, 3)[order]
    out = [None] * len(strands)
    by_length = np.argsort(helix.n_elements[strands], kind="stable")  # similar lengths together: less padding
    for start in range(0, len(strands), chunk):
        pos = by_length[start:start + chunk]
        sub = helix.subset(strands[pos])
        U, A, diag = _load_hessian_parts(sub, strands[pos], ps, pss, pf)
        for i, p in enumerate(pos):
            out[p] = _assemble_one(U, A, diag, i, int(sub.n_elements[i]))
    return out


def _load_hessian_parts(sub: sh.SuperHelix, ids, ps, pss, pf, kin=None):
    """superhelix.point_load_hessian_parts of the strands ``sub`` = helix.subset(ids), from the loads of all
    strands sorted by strand (ps, pss, pf)."""
    lo = np.searchsorted(ps, ids, "left")
    hi = np.searchsorted(ps, ids, "right")
    count = hi - lo
    local = np.repeat(np.arange(len(ids)), count)
    pidx = np.repeat(lo, count) + (np.arange(len(local)) - np.repeat(np.cumsum(count) - count, count))
    return sh.point_load_hessian_parts(sub, local, pss[pidx], pf[pidx], kin)


def _assemble_one(U, A, diag, i, m: int) -> np.ndarray:
    """The dense 3m x 3m matrix of strand i of a chunk's generators (superhelix.assemble_gravity_jacobian), at
    its own size."""
    full = np.empty((3 * m, 3 * m))
    sh.assemble_gravity_jacobian(U[i:i + 1, :m], A[i:i + 1, :m], diag[i:i + 1, :m], full[None])
    return full


def finite_difference_load_hessians(helix, strands, point_strand, point_s, point_force,
                                    rotation_step: float = 1e-6, chunk_dofs: int = 6000) -> list:
    """contact_load_hessians by central differences of the exact generalized force
    (contact.jacobian.point_forces_generalized), for either model: a step of ``rotation_step`` radians per dof
    (dq_j = rotation_step / l_j for a Super-Helix element, / the mean length of a clothoid node's elements),
    truncation O(step^2), round-off O(eps / step), about 1e-10 relative; symmetrised (it is a Hessian).  2n
    perturbed copies of each strand, at most ``chunk_dofs`` at once.  What the package uses for Super Space
    Clothoids, and the tests' oracle for the analytic Super-Helix Hessian."""
    from .contact.jacobian import point_forces_generalized

    clothoid = isinstance(helix, cl.SuperClothoid)
    mod = cl if clothoid else sh
    extra = 1 if clothoid else 0  # a clothoid's dofs are its N + 1 nodes
    strands = np.asarray(strands, dtype=np.int64)
    point_strand = np.asarray(point_strand, dtype=np.int64)
    order = np.argsort(point_strand, kind="stable")
    ps, pss = point_strand[order], np.asarray(point_s, float)[order]
    pf = np.asarray(point_force, float).reshape(-1, 3)[order]
    out = [None] * len(strands)
    start = 0
    while start < len(strands):
        stop, copies = start, 0
        while stop < len(strands) and (copies == 0 or copies + 6 * (helix.n_elements[strands[stop]] + extra)
                                       <= chunk_dofs):
            copies += 6 * (int(helix.n_elements[strands[stop]]) + extra)
            stop += 1
        ids = strands[start:stop]
        sub = helix.subset(ids)
        N = sub.max_elements + extra
        owner, signs, dofs = [], [], []
        for i in range(len(ids)):
            n = 3 * (int(sub.n_elements[i]) + extra)
            owner.append(np.full(2 * n, i))
            signs.append(np.repeat([1.0, -1.0], n))
            dofs.append(np.tile(np.arange(n), 2))
        owner, signs, dofs = np.concatenate(owner), np.concatenate(signs), np.concatenate(dofs)
        elem, comp = dofs // 3, dofs % 3
        if clothoid:  # node i: the mean length of its (one or two) elements
            lpad = np.concatenate([np.zeros((len(ids), 1)), sub.lengths, np.zeros((len(ids), 1))], axis=1)
            both = lpad[:, :-1] + lpad[:, 1:]
            nadj = (lpad[:, :-1] > 0).astype(float) + (lpad[:, 1:] > 0)
            step = rotation_step / (both / np.maximum(nadj, 1.0))[owner, elem]
        else:
            step = rotation_step / sub.lengths[owner, elem]
        q = sub.curvatures[owner].copy()
        q[np.arange(len(owner)), elem, comp] += signs * step
        copies_helix = type(sub)(sub.root_positions[owner], sub.root_frames[owner], sub.lengths[owner], q,
                                 sub.n_elements[owner])
        # every copy carries the loads of its strand
        lo = np.searchsorted(ps, ids, "left")
        hi = np.searchsorted(ps, ids, "right")
        count = (hi - lo)[owner]
        copy_of_point = np.repeat(np.arange(len(owner)), count)
        first = np.repeat(lo[owner], count)
        within = np.arange(len(copy_of_point)) - np.repeat(np.cumsum(count) - count, count)
        pidx = first + within
        g = point_forces_generalized(copies_helix, mod.kinematics(copies_helix), copy_of_point, pss[pidx], pf[pidx])
        g = g.reshape(len(owner), 3 * N)
        pos = 0
        for i in range(len(ids)):
            n = 3 * (int(sub.n_elements[i]) + extra)
            plus, minus = g[pos:pos + n, :n], g[pos + n:pos + 2 * n, :n]
            h = step[pos:pos + n]
            D = ((plus - minus) / (2.0 * h[:, None])).T  # column k: d g / d q_k
            out[start + i] = 0.5 * (D + D.T)
            pos += 2 * n
        start = stop
    return out


def held_stiffness_ratios(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity, contacts, forces,
                          H, mu, isolated_ratios=None, progress=None) -> HeldStability:
    """The stiffness ratio of every strand given the contacts that hold it (docs/stability.md).

    Second-order condition of the constrained equilibrium, strand by strand:
    lambda_max(Z^T K^-1/2 (dF/dq + dF_c/dq) K^-1/2 Z) < 1, with

    - dF_c/dq: the stiffness of the strand's contact forces as dead loads (contact_load_hessians; for
      Super-Helices its generators are added to gravity's and whitened before one dense assembly per strand);
    - Z: an orthonormal basis of the motions y = K^1/2 dq that keep the strand's **head** contacts with
      r_N > 0 in place: all three rows of H for a sticking one (||r_T|| < mu r_N), the normal row only for
      one on the cone boundary (it may slide; the head is a mesh, whose distance has no curvature inside a
      face); take-off contacts (r_N = 0) block nothing and carry no load.
    - Strand/strand contacts block nothing here; their forces stay as dead loads on both strands.  This is a
      **safe bound** for the coupled groom: the coupled Lagrangian Hessian is block diagonal over strands
      (a contact's constraint x_a(q_a) - x_b(q_b) has no mixed second derivative) and the coupled critical
      subspace lies inside the product of the per-strand ones, so every strand stable here makes the whole
      groom stable with every loaded contact sticking.

    Strands that no loaded contact touches keep their isolated ratio (``isolated_ratios`` or computed).
    Super-Helices in O(N k^2) per strand (k blocking rows): certified as the isolated ratios are, on
    P A P - beta Q^T Q (:func:`_held_lambda_max`); clothoids, and a strand not certified, by the dense
    eigvalsh of the reduced matrix (:func:`constrained_top_eigenvalue`)."""
    S = helix.n_strands
    forces = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (len(forces),))
    if isolated_ratios is None:
        isolated_ratios = stiffness_ratios(helix, stiffness_diag, linear_density, gravity)
    ratio = np.array(isolated_ratios, dtype=np.float64, copy=True)
    kind = np.zeros(S, dtype=np.int8)
    blocked_count = np.zeros(S, dtype=np.int64)
    loaded_count = np.zeros(S, dtype=np.int64)
    result = HeldStability(ratio, kind, blocked_count, loaded_count)
    if contacts is None or len(forces) == 0:
        return result
    loaded = np.flatnonzero(forces[:, 0] > 0.0)
    if len(loaded) == 0:
        return result
    strand_a = np.asarray(contacts.strand_a, dtype=np.int64)[loaded]
    strand_b = np.asarray(contacts.strand_b, dtype=np.int64)[loaded]
    frames = np.asarray(contacts.frame, dtype=np.float64).reshape(-1, 3, 3)[loaded]
    world = np.einsum("pji,pj->pi", frames, forces[loaded])
    on_b = strand_b >= 0
    point_strand = np.concatenate([strand_a, strand_b[on_b]])
    point_s = np.concatenate([np.asarray(contacts.s_a, float)[loaded], np.asarray(contacts.s_b, float)[loaded][on_b]])
    point_force = np.concatenate([world, -world[on_b]])
    np.add.at(loaded_count, point_strand, 1)
    strands = np.flatnonzero(loaded_count > 0)
    kind[strands] = 1
    # constraint rows: loaded head contacts, 3 rows if sticking, the normal row on the cone boundary
    head = ~on_b
    tangential = np.linalg.norm(forces[loaded, 1:], axis=1)
    sticking = tangential < (1.0 - STICK_SLACK) * mu[loaded] * forces[loaded, 0]
    head_ids, head_strand, head_stick = loaded[head], strand_a[head], sticking[head]
    by_strand = np.argsort(head_strand, kind="stable")
    head_ids, head_strand, head_stick = head_ids[by_strand], head_strand[by_strand], head_stick[by_strand]
    H = H.tocsr()
    cols = 3 * helix.flat_offsets()
    if progress is not None:
        progress.reset(total=len(strands))
    clothoid = isinstance(helix, cl.SuperClothoid)
    by_length = np.argsort(helix.n_elements[strands], kind="stable")  # similar lengths together: less padding
    if clothoid:
        hessians = contact_load_hessians(helix, strands, point_strand, point_s, point_force)
    else:
        by_strand = np.argsort(point_strand, kind="stable")
        ps, pss, pf = point_strand[by_strand], point_s[by_strand], point_force[by_strand]
        g = np.asarray(gravity, dtype=np.float64)
        skew_g = sh.skew(g)
    with threadpool_limits(1, user_api="blas"):
        for chunk_start in range(0, len(strands), 256):
            pos = by_length[chunk_start:chunk_start + 256]
            ids = strands[pos]
            sub = helix.subset(ids)
            if clothoid:  # K = L L^T block tridiagonal: whitening by L^-T (same eigenvalues)
                dF = cl.gravity_force_jacobian(sub, linear_density, gravity)
                K = cl.stiffness_matrix(sub, stiffness_diag)
            else:
                # dF/dq + dF_c/dq in one set of generators: gravity's block U_j G_k = Theta_j^T (-rhoS [g]x G_k),
                # the loads' Theta_j^T A_k; whitened by K^-1/2 = diag(sc) in the generators (U_j rows by sc_j,
                # A_k columns by sc_k, diag_k both ways), then assembled per strand
                kin = sh.kinematics(sub)
                U, A_gen, diag = _load_hessian_parts(sub, ids, ps, pss, pf, kin)
                _, G_grav, diag_grav = sh.gravity_force_jacobian_parts(sub, linear_density, g, kin)
                A_gen -= linear_density * np.einsum("ab,snbc->snac", skew_g, G_grav)
                diag += diag_grav
                K = sh.stiffness(sub, stiffness_diag)
                sc = np.divide(1.0, np.sqrt(K), out=np.zeros_like(K), where=K > 0)  # (s, N, 3), 0 on padding
                U *= sc[..., :, None]
                A_gen *= sc[..., None, :]
                diag *= sc[..., :, None] * sc[..., None, :]
            lo = np.searchsorted(head_strand, ids)
            hi = np.searchsorted(head_strand, ids + 1)
            if not clothoid:
                # every strand in O(N k^2): lambda_max of A = K^-1/2 (dF/dq + dF_c/dq) K^-1/2 on the null space of its
                # blocking rows (none: the whole A, in the form of gravity's alone), certified as the isolated ratios
                # are; the dense route where that is not certified
                rows, ptr = _blocking_rows(head_ids, head_stick, lo, hi)
                n_el = np.ascontiguousarray(sub.n_elements, dtype=np.int64)
                C = np.zeros((len(rows), 3 * int(n_el.max()) if len(n_el) else 0))
                _scaled_rows(H.indptr, H.indices, H.data, rows, ptr, np.ascontiguousarray(cols[ids], dtype=np.int64),
                             n_el, np.ascontiguousarray(sc), C)
                lam = np.empty(len(ids))
                ok = np.empty(len(ids), dtype=np.bool_)
                _held_batch(np.ascontiguousarray(U), np.ascontiguousarray(A_gen), np.ascontiguousarray(diag), n_el, C,
                            ptr, RTOL, ATOL_EPS, MAX_STEPS, LANCZOS_STEPS, lam, ok)
                for i in np.flatnonzero(~ok):
                    N = int(n_el[i])
                    lam[i] = constrained_top_eigenvalue(_assemble_one(U, A_gen, diag, i, N), C[ptr[i]:ptr[i + 1], :3 * N])
                ratio[ids] = lam
                blocked_count[ids] = np.diff(ptr)
                if progress is not None:
                    progress.update(len(ids))
                continue
            for i, s in enumerate(ids):
                n = 3 * (int(sub.n_elements[i]) + 1)
                Wm = _clothoid_whitening(K[i, :n, :n])
                A = Wm.T @ (dF[i, :n, :n] + hessians[pos[i]]) @ Wm
                A = 0.5 * (A + A.T)
                rows = [3 * c + np.arange(3) if stick else np.array([3 * c])
                        for c, stick in zip(head_ids[lo[i]:hi[i]], head_stick[lo[i]:hi[i]])]
                C = None
                if rows:
                    rows = np.concatenate(rows)
                    C = _csr_block(H, rows, cols[s], cols[s] + n) @ Wm
                    blocked_count[s] = len(rows)
                ratio[s] = constrained_top_eigenvalue(A, C)
                if progress is not None:
                    progress.update(1)
    return result


def constrained_top_eigenvalue(A: np.ndarray, C: np.ndarray | None) -> float:
    """lambda_max(Z^T A Z), Z an orthonormal basis of null(C) (C None or empty: lambda_max(A)); 0 when the
    rows block every motion.  The null space from the SVD of C with scipy.linalg.null_space's rank rule;
    dense eigvalsh (backward stable: exact to round-off of ||A||)."""
    if C is not None and len(C):
        _, sv, Vh = np.linalg.svd(C, full_matrices=True)
        rank = int(np.count_nonzero(sv > (sv.max() if len(sv) else 0.0) * np.finfo(float).eps * max(C.shape)))
        Z = Vh[rank:].T
        if Z.shape[1] == 0:
            return 0.0
        A = Z.T @ A @ Z
    return float(np.linalg.eigvalsh(0.5 * (A + A.T))[-1])
