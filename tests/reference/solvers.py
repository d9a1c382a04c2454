"""References for groomtool.solvers: what only the tests use.

* :func:`solve_local`: many 3x3 local problems at once through the package's per-block kernels
  (:func:`groomtool.solvers.local.normalize_block`, :func:`groomtool.solvers.local.solve_block`), as
  Gauss-Seidel calls them for each contact.
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
