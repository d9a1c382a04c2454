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
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from threadpoolctl import threadpool_limits

from .rods import superhelix as sh


def stiffness_ratios(helix: sh.SuperHelix, stiffness_diag, linear_density: float, gravity,
                     chunk: int = 256, progress=None) -> np.ndarray:
    """rho per strand (S,): lambda_max(K^-1/2 dF/dq K^-1/2) over the strand's real dofs."""
    order = np.argsort(helix.n_elements, kind="stable")  # similar lengths together: less padding
    out = np.empty(helix.n_strands)
    # many small eigenproblems: one BLAS thread each is several times faster than a thread pool
    # fighting over the cores (measured 7x on a loaded 2-core machine)
    with threadpool_limits(1, user_api="blas"):
        for start in range(0, helix.n_strands, chunk):
            ids = order[start:start + chunk]
            out[ids] = _ratios(helix.subset(ids), stiffness_diag, linear_density, gravity)
            if progress is not None:
                progress.update(len(ids))
    return out


def _ratios(helix, stiffness_diag, linear_density, gravity):
    dF = sh.gravity_force_jacobian(helix, linear_density, gravity)
    K = sh.stiffness(helix, stiffness_diag).reshape(helix.n_strands, -1)
    K = np.where(K > 0, K, 1.0)  # padding dofs: dF is zero there, any K works
    scale = 1.0 / np.sqrt(K)
    A = scale[:, :, None] * dF * scale[:, None, :]
    return np.linalg.eigvalsh(A)[:, -1]


def contact_held_ratio(helix: sh.SuperHelix, strand: int, stiffness_diag, linear_density: float, gravity,
                       blocked_rows: np.ndarray) -> float:
    """rho for one strand when the motions in the row space of ``blocked_rows`` (k x 3n) are blocked."""
    sub = helix.subset([strand])
    n = 3 * int(sub.n_elements[0])
    dF = sh.gravity_force_jacobian(sub, linear_density, gravity)[0, :n, :n]
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
