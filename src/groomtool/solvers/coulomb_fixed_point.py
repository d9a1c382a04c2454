"""Coulomb friction as a fixed point of SOCQPs (Acary, Cadoux, Lemarechal & Malick 2011).

With De Saxce's change of variable, (u, r) satisfy Coulomb's law iff (u + s e_N, r) satisfy the SOC law
with s_i = mu_i ||u_T,i||.  For s fixed that is the KKT system of the convex SOCQP

    min 1/2 r^T W r + (b + s e_N)^T r,   r_i in K_mu_i,

so the iteration  s <- mu ||u_T(r*(s))||  solves the Coulomb problem when it converges (it does for
moderate friction; it is a contraction for small mu).  Each SOCQP is solved by the accelerated
Gauss-Seidel, warm-started, to a tolerance that tightens with the outer residual; the outer map on s
(m numbers) is Anderson-accelerated.  Gauss-Seidel applied directly to the Coulomb law can cycle
on strongly coupled problems; this iteration is the robust fallback.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import residual as _res
from .anderson import AndersonMixer
from .cones import COULOMB
from .gauss_seidel import run_gauss_seidel


@dataclass
class FixedPointOutcome:
    r: np.ndarray
    residual: float
    sweeps: int
    outer: int
    converged: bool
    local_failures: int
    history: list = field(default_factory=list)  # [(total sweeps, Coulomb residual, seconds)]
    solve_s: float = 0.0


def run_coulomb_fixed_point(
    op,
    *,
    tol: float = 1e-8,
    max_sweeps: int = 5000,
    max_outer: int = 200,
    r0: np.ndarray | None = None,
    anderson: int = 5,
    inner_ratio: float = 0.05,
    time_limit: float | None = None,
    scale: float | None = None,
    **gs_options,
) -> FixedPointOutcome:
    """op: a Gauss-Seidel operator (its free velocity op.b is shifted by s e_N during the solve and
    restored).  Stops when the Coulomb residual (residual.py; ``scale`` overrides max_i rho_i ||b_i||)
    <= tol."""
    t0 = time.perf_counter()
    m = op.b.shape[0]
    b_internal = op.b.copy()
    if scale is None:
        scale = _res.residual_scale(b_internal, op.rho)
    r = np.zeros(3 * m) if r0 is None else np.asarray(r0, dtype=np.float64).reshape(-1).copy()

    def coulomb_state(r_ext):
        """(Coulomb residual, s = mu ||u_T||) at r (caller's order)."""
        ri = op.to_internal(r_ext)
        op.b[:] = b_internal
        u = op.velocity(ri)
        emax, _ = _res.residual_max_rms(COULOMB, ri, u, op.mu, op.rho)
        s_int = op.mu * np.sqrt(u[:, 1] ** 2 + u[:, 2] ** 2)
        return emax / scale, s_int

    res, s = coulomb_state(r)
    history = [(0, res, 0.0)]
    mixer = AndersonMixer(m, anderson) if anderson > 0 else None
    sweeps = 0
    fails = 0
    outer = 0
    try:
        while res > tol and outer < max_outer and sweeps < max_sweeps:
            shifted = b_internal.copy()
            shifted[:, 0] += s
            op.b[:] = shifted
            inner_tol = max(0.1 * tol, min(1e-3, inner_ratio * res))
            out = run_gauss_seidel(op, "soc", tol=inner_tol, max_sweeps=max_sweeps - sweeps, r0=r, scale=scale,
                                   **gs_options)
            sweeps += out.sweeps
            fails += out.local_failures
            outer += 1
            r = out.r
            res, g = coulomb_state(r)
            history.append((sweeps, res, time.perf_counter() - t0))
            if res <= tol or (time_limit is not None and time.perf_counter() - t0 > time_limit):
                break
            if mixer is None:
                s = g
            else:
                nxt = np.empty(m)
                mixer.step(s, g - s, nxt)
                s = np.maximum(nxt, 0.0)
    finally:
        op.b[:] = b_internal
    return FixedPointOutcome(r, float(res), sweeps, outer, bool(res <= tol), fails, history, time.perf_counter() - t0)
