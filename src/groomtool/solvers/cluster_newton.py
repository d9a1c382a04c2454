"""Newton steps on the Coulomb law of a small cluster of contacts, between Gauss-Seidel sweeps (issue 15).

On the README example's sagging run, every step that ran out of its 500 sweeps had the same cause: one
heavily loaded, slipping contact near the roots of two neighbouring strands (rho = 113, i.e. W_ii a
thousand to a million times smaller than its neighbours'; r_N 5-15 % of the largest free reaction) while
every other contact was within 1e-7..1e-6.  The 56 contacts on those two strands form a subproblem whose
W_SS is singular (rank 125 of 168: more contact rows than the dofs the contacts move) and on which block
Gauss-Seidel converges linearly at 0.997 a sweep (100 sweeps restricted to the 56 contacts lower their
residual 2.25e-5 -> 2.11e-5), whereas a Newton step on the cluster's natural map brings it to 1e-9 in one
iteration.

A cluster step, for the contacts whose natural-map residual (residual.py) exceeds the target:

1. the cluster S = those contacts and every contact W couples them to (the contacts on the same strands);
2. W_SS dense and c_S = u_S - W_SS r_S (the other contacts' forces fixed);
3. Levenberg-Marquardt (Gauss-Newton on the natural map F_i = r_i - P_K(r_i - rho_i u_eff,i), generalised
   Jacobian, damping proportional to ||F||: quadratic near a regular solution, well defined where W_SS is
   singular), Armijo backtracking on ||F||^2, a few iterations;
4. the caller measures the global residual at the new point and keeps it only if it is lower.

So a step never makes the residual worse; the returned point need not be a sweep's output, but its
residual is measured exactly on u = W r + b like every other point.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
from numba import njit

from .cones import COULOMB, natural_map_norm, project_cone

CLUSTER_MAX = 200  #: contacts in a cluster above which no step is tried (the dense LM system is 3|S| square)
CLUSTER_ITER = 8  #: Levenberg-Marquardt iterations per step
WORST_FRACTION = 0.1  #: a cluster gathers the contacts over the target and over this fraction of the worst one


_CONTROLLER = []


def one_blas_thread():
    """A context holding BLAS to one thread (threadpoolctl, its controller built once: ~0.03 ms a use, where
    ``threadpool_limits`` rescans the loaded libraries each time, ~3 ms).  On a loaded 2-core machine a 216-row
    dense solve took 86 ms with OpenBLAS's threads and 2 ms with one."""
    if not _CONTROLLER:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0].limit(limits=1, user_api="blas")


@njit(cache=True)
def contact_errors(law, r, u, mu, rho, out):
    """out_i = ||e_i|| (natural map, residual.py) per contact."""
    for i in range(r.shape[0]):
        out[i] = natural_map_norm(law, mu[i], rho[i], r[i, 0], r[i, 1], r[i, 2], u[i, 0], u[i, 1], u[i, 2])


@njit(cache=True)
def _project_jacobian(mu, zn, zt1, zt2, J):
    """Generalised Jacobian (3x3, into J) of the projection onto K_mu at z."""
    for a in range(3):
        for b in range(3):
            J[a, b] = 0.0
    nt = math.sqrt(zt1 * zt1 + zt2 * zt2)
    if nt <= mu * zn and zn >= 0.0:
        J[0, 0] = 1.0
        J[1, 1] = 1.0
        J[2, 2] = 1.0
        return
    if mu * nt <= -zn:
        return
    q = 1.0 / (1.0 + mu * mu)
    a = (zn + mu * nt) * q
    w1 = zt1 / nt
    w2 = zt2 / nt
    J[0, 0] = q
    J[0, 1] = mu * w1 * q
    J[0, 2] = mu * w2 * q
    J[1, 0] = mu * w1 * q
    J[2, 0] = mu * w2 * q
    g = mu * a / nt
    J[1, 1] = mu * mu * w1 * w1 * q + g * (1.0 - w1 * w1)
    J[1, 2] = mu * mu * w1 * w2 * q - g * w1 * w2
    J[2, 1] = J[1, 2]
    J[2, 2] = mu * mu * w2 * w2 * q + g * (1.0 - w2 * w2)


@njit(cache=True)
def coulomb_map(W, c, r, mu, rho, F, J, want_jac):
    """F = the Coulomb natural map of u = W r + c (r, c, F: (3k,), W: (3k, 3k)) per contact with its rho;
    with want_jac, J = dF/dr (a generalised Jacobian; u_eff = u + mu ||u_T|| e_N differentiated where
    u_T != 0)."""
    n = r.shape[0]
    k = n // 3
    u = W @ r + c
    dP = np.empty((3, 3))
    dU = np.empty((3, n))
    for i in range(k):
        i0 = 3 * i
        un, ut1, ut2 = u[i0], u[i0 + 1], u[i0 + 2]
        nut = math.sqrt(ut1 * ut1 + ut2 * ut2)
        zn = r[i0] - rho[i] * (un + mu[i] * nut)
        zt1 = r[i0 + 1] - rho[i] * ut1
        zt2 = r[i0 + 2] - rho[i] * ut2
        pn, pt1, pt2 = project_cone(mu[i], zn, zt1, zt2)
        F[i0] = r[i0] - pn
        F[i0 + 1] = r[i0 + 1] - pt1
        F[i0 + 2] = r[i0 + 2] - pt2
        if not want_jac:
            continue
        _project_jacobian(mu[i], zn, zt1, zt2, dP)
        # dz/dr = E_i - rho_i dU,  dU = d u_eff,i / dr
        for col in range(n):
            w0 = W[i0, col]
            w1 = W[i0 + 1, col]
            w2 = W[i0 + 2, col]
            if nut > 0.0:
                w0 += mu[i] * (ut1 * w1 + ut2 * w2) / nut
            dU[0, col] = -rho[i] * w0
            dU[1, col] = -rho[i] * w1
            dU[2, col] = -rho[i] * w2
        for a in range(3):
            dU[a, i0 + a] += 1.0
        # J_i = E_i - dP dz/dr
        for a in range(3):
            for col in range(n):
                J[i0 + a, col] = -(dP[a, 0] * dU[0, col] + dP[a, 1] * dU[1, col] + dP[a, 2] * dU[2, col])
            J[i0 + a, i0 + a] += 1.0


def _max_contact_norm(F):
    return float(np.max(np.linalg.norm(F.reshape(-1, 3), axis=1), initial=0.0))


def newton_cluster(W, c, r, mu, rho, scale, target, max_iter=CLUSTER_ITER):
    """Levenberg-Marquardt on the Coulomb natural map of the dense subproblem u = W r + c (module
    docstring).  Stops when max_i ||F_i|| <= target * scale or after max_iter iterations.
    Returns (r, max_i ||F_i|| / scale, iterations)."""
    n = r.shape[0]
    r = np.array(r, dtype=np.float64)
    W = np.ascontiguousarray(W, dtype=np.float64)
    c = np.ascontiguousarray(c, dtype=np.float64)
    mu = np.ascontiguousarray(mu, dtype=np.float64)
    rho = np.ascontiguousarray(rho, dtype=np.float64)
    F = np.empty(n)
    Fn = np.empty(n)
    J = np.empty((n, n))
    coulomb_map(W, c, r, mu, rho, F, J, True)
    f = float(F @ F)
    it = 0
    while it < max_iter and _max_contact_norm(F) > target * scale and f > 0.0:
        it += 1
        JtJ = J.T @ J
        g = J.T @ F
        lam = (1e-10 + min(1e-2, math.sqrt(f) / scale)) * max(float(np.trace(JtJ)) / n, 1e-300)
        JtJ[np.diag_indices(n)] += lam
        try:
            d = sla.solve(JtJ, -g, assume_a="pos", check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            break
        if not np.all(np.isfinite(d)):
            break
        t = 1.0
        accepted = False
        while t >= 1.0 / 64:
            rn = r + t * d
            coulomb_map(W, c, rn, mu, rho, Fn, J, False)
            fn = float(Fn @ Fn)
            if fn <= (1.0 - 1e-4 * t) * f:
                accepted = True
                break
            t *= 0.5
        if not accepted:
            break
        r = rn
        coulomb_map(W, c, r, mu, rho, F, J, True)
        f = float(F @ F)
    return r, _max_contact_norm(F) / scale, it


class ClusterNewton:
    """Cluster steps (module docstring) on a Gauss-Seidel operator (gauss_seidel.AssembledOperator or
    MatrixFreeOperator: both provide ``neighbours(idx)`` and ``dense_block(idx)`` in their internal order)."""

    def __init__(self, op, law=COULOMB, max_contacts: int | None = None, max_iter: int | None = None):
        self.op = op
        self.law = law
        self.max_contacts = int(CLUSTER_MAX if max_contacts is None else max_contacts)
        self.max_iter = int(CLUSTER_ITER if max_iter is None else max_iter)
        self._e = np.empty(op.b.shape[0])
        self.last = {"size": 0, "iterations": 0, "residual": math.nan}

    def cluster(self, r, u, threshold):
        """The contacts whose ||e_i|| > threshold and their neighbours (sorted); if that is over max_contacts,
        the same with the threshold raised to WORST_FRACTION of the worst ||e_i|| (the worst contacts' cluster,
        e.g. at a tight tolerance); None when both are over max_contacts or nothing is over the threshold."""
        op = self.op
        contact_errors(self.law, r, u, op.mu, op.rho, self._e)
        worst = float(np.max(self._e, initial=0.0))
        for level in (threshold, max(threshold, WORST_FRACTION * worst)):
            bad = np.flatnonzero(self._e > level)
            if bad.size == 0 or bad.size > self.max_contacts:
                continue
            idx = op.neighbours(bad)
            if idx.size <= self.max_contacts:
                return idx
        return None

    def step(self, r, u, scale, tol):
        """A new r (m, 3) with the cluster of the contacts above tol * scale solved by Newton, or None
        (no cluster, or Newton made no progress on it).  r, u: internal order, u = W r + b."""
        idx = self.cluster(r, u, tol * scale)
        self.last = {"size": 0 if idx is None else int(idx.size), "iterations": 0, "residual": math.nan}
        if idx is None:
            return None
        op = self.op
        # dense products and solves of at most 600 rows: BLAS threads only wait (86 ms -> 2 ms a solve)
        with one_blas_thread():
            Wss = op.dense_block(idx)
            rS = np.ascontiguousarray(r[idx]).reshape(-1)
            c = np.ascontiguousarray(u[idx]).reshape(-1) - Wss @ rS
            before = float(np.max(self._e[idx])) / scale
            new, after, its = newton_cluster(Wss, c, rS, op.mu[idx], op.rho[idx], scale, 0.1 * tol, self.max_iter)
        self.last.update(iterations=its, residual=after)
        if not (its > 0 and after < before and np.all(np.isfinite(new))):
            return None
        out = r.copy()
        out[idx] = new.reshape(-1, 3)
        return out
