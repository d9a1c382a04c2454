"""References for groomtool.solvers: what only the tests use.

* :func:`solve_local`: many 3x3 local problems at once through the package's per-block kernels
  (:func:`groomtool.solvers.local.normalize_block`, :func:`groomtool.solvers.local.solve_block`), as
  Gauss-Seidel calls them for each contact.
* :func:`coulomb_contact_errors`: per contact the distance to Coulomb's law stated disjunctively (take-off |
  stick | slip), independent of the natural map the solvers stop on.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from groomtool.solvers.cones import law_code
from groomtool.solvers.local import LOCAL_TOL, NEWTON_MAX_ITER, normalize_block, solve_block


@njit(cache=True, fastmath={"contract"})  # as the package's kernels
def _solve_local_batch(law, mu, A, c, r_init, tol, max_newton, atol, r_out, status):
    for i in range(A.shape[0]):
        s, An, Ainv, ok = normalize_block(A[i])
        st, x0, x1, x2 = solve_block(
            law, mu[i], s, An, Ainv, ok, c[i, 0], c[i, 1], c[i, 2],
            r_init[i, 0], r_init[i, 1], r_init[i, 2], tol, max_newton, atol,
        )
        r_out[i, 0] = x0
        r_out[i, 1] = x1
        r_out[i, 2] = x2
        status[i] = st


def solve_local(A, c, mu, law="soc", r0=None, tol=LOCAL_TOL, max_newton=NEWTON_MAX_ITER, atol=0.0):
    """Solve one or many 3x3 local problems u = A r + c under ``law`` ('soc' or 'coulomb').

    A: (3, 3) or (k, 3, 3); c: (3,) or (k, 3); mu: float or (k,); r0: optional warm start.
    A slip solution is accurate to ||r - P_K(r - u_eff / s)|| <= max(tol (relative), atol), s = tr(A)/3.
    Returns (r, status) with status codes from this module (STATUS_NAMES)."""
    A = np.asarray(A, dtype=np.float64)
    single = A.ndim == 2
    A = np.ascontiguousarray(A.reshape(-1, 3, 3))
    k = A.shape[0]
    c = np.ascontiguousarray(np.asarray(c, dtype=np.float64).reshape(k, 3))
    mu = np.ascontiguousarray(np.broadcast_to(np.asarray(mu, dtype=np.float64), (k,)))
    if np.any(mu < 0) or not np.all(np.isfinite(mu)):
        raise ValueError("friction coefficients must be finite and >= 0")
    r_init = np.zeros((k, 3)) if r0 is None else np.ascontiguousarray(np.asarray(r0, float).reshape(k, 3))
    r = np.empty((k, 3))
    status = np.empty(k, dtype=np.int64)
    _solve_local_batch(law_code(law), mu, A, c, r_init, float(tol), int(max_newton), float(atol), r, status)
    if single:
        return r[0], int(status[0])
    return r, status


def coulomb_contact_errors(P, r):
    """Per contact the distance to Coulomb's law stated disjunctively (not the natural map the solvers use):
    take-off (r = 0, u_N >= 0) | stick (r in the cone, u = 0) | slip (||r_T|| = mu r_N, u_N = 0,
    u_T = -alpha r_T, alpha >= 0); a frictionless contact (mu = 0) slips with r_T = 0."""
    r = r.reshape(-1, 3)
    u = P.velocity(r.reshape(-1)).reshape(-1, 3)
    sr = np.abs(r).max()
    su = max(np.abs(u).max(), np.abs(P.b).max())
    out = []
    for i in range(P.n_contacts):
        ri, ui, mu = r[i], u[i], P.mu[i]
        if np.linalg.norm(ri) <= 1e-10 * sr:
            out.append(max(0.0, -ui[0]) / su)
            continue
        cone = max(0.0, np.linalg.norm(ri[1:]) - mu * ri[0]) / sr
        stick = np.linalg.norm(ui) / su
        nrt = np.linalg.norm(ri[1:])
        if nrt > 0:
            alpha = max(0.0, -ui[1:] @ ri[1:] / nrt**2)
            slip = max(abs(nrt - mu * ri[0]) / sr, abs(ui[0]) / su,
                       np.linalg.norm(ui[1:] + alpha * ri[1:]) / (su + alpha * sr))
        else:
            slip = abs(ui[0]) / su if mu == 0 else np.inf
        out.append(max(cone, min(stick, slip)))
    return np.array(out)
