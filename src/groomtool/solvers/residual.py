"""Convergence measures of a contact problem u = W r + b, computed from (r, u) per contact.

The residual every solver in this package stops on (and reports):

    e_i        = r_i - P_{K_mu_i}( r_i - rho_i u_eff_i )          (natural map, cones.py)
    rho_i      = 3 / trace(W_ii)                                  (inverse of the mean eigenvalue of W_ii)
    scale      = max_i rho_i ||b_i||                              (the largest "free" reaction; 1 if b = 0)
    residual   = max_i ||e_i|| / scale        (norm="max", the default)
               or sqrt(mean_i ||e_i||^2) / scale  (norm="rms")

u_eff = u for the SOC law and u + mu ||u_T|| e_N for Coulomb (De Saxcé).  e_i = 0 exactly when contact i
satisfies its law, and ||e_i|| has the units of a force (rho_i u_i is the reaction that would cancel
u_i), so ``residual <= 1e-8`` reads: every contact satisfies its law to 1e-8 of the largest free
reaction.  The measure is invariant to scaling W, b (and hence r) by positive constants.

``bogus_error`` is the figure the so-bogus library stops on, for comparisons only:
sum_i ||phi_FB(s_i r_i, u_i)||^2 / (1 + m) with s_i = max(1, trace W_ii) -- absolute (it scales with
b^2) and a mean of squares, hence much looser than the residual above at the same tolerance.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .cones import cone_excess, fischer_burmeister_sq, law_code, natural_map_norm


@njit(cache=True)
def residual_max_rms(law, r, u, mu, rho):
    """(max_i ||e_i||, sqrt(mean_i ||e_i||^2)) without a temporary array."""
    emax = 0.0
    esq = 0.0
    m = r.shape[0]
    for i in range(m):
        e = natural_map_norm(law, mu[i], rho[i], r[i, 0], r[i, 1], r[i, 2], u[i, 0], u[i, 1], u[i, 2])
        if e > emax:
            emax = e
        esq += e * e
    return emax, math.sqrt(esq / max(m, 1))


@njit(cache=True)
def _cone_violation(r, mu):
    v = 0.0
    for i in range(r.shape[0]):
        v = max(v, cone_excess(mu[i], r[i, 0], r[i, 1], r[i, 2]))
    return v


@njit(cache=True)
def _bogus_error(law, r, u, mu, trace):
    s = 0.0
    for i in range(r.shape[0]):
        sc = max(1.0, trace[i])
        s += fischer_burmeister_sq(law, mu[i], sc, r[i, 0], r[i, 1], r[i, 2], u[i, 0], u[i, 1], u[i, 2])
    return s / (1.0 + r.shape[0])


def rho_from_diagonal(diag_blocks: np.ndarray) -> np.ndarray:
    """rho_i = 3 / trace(W_ii) (1 where the trace is not positive)."""
    tr = np.einsum("kii->k", diag_blocks)
    out = np.ones_like(tr)
    pos = tr > 0
    out[pos] = 3.0 / tr[pos]
    return out


def residual_scale(b: np.ndarray, rho: np.ndarray) -> float:
    """max_i rho_i ||b_i|| (1.0 if that is 0, so the residual is then absolute)."""
    s = float(np.max(rho * np.linalg.norm(b.reshape(-1, 3), axis=1), initial=0.0))
    return s if s > 0 else 1.0


def residual(r, u, mu, rho, scale, law="soc", norm="max") -> float:
    """The scaled natural-map residual (module docstring) of (r, u); r, u: (3m,) or (m, 3)."""
    r = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, 3))
    u = np.ascontiguousarray(np.asarray(u, dtype=np.float64).reshape(-1, 3))
    emax, erms = residual_max_rms(law_code(law), r, u, np.ascontiguousarray(mu), np.ascontiguousarray(rho))
    if norm == "max":
        return emax / scale
    if norm == "rms":
        return erms / scale
    raise ValueError(f"norm must be 'max' or 'rms', not {norm!r}")


def cone_violation(r, mu) -> float:
    """max_i max(0, ||r_T,i|| - mu_i r_N,i)."""
    r = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, 3))
    return float(_cone_violation(r, np.ascontiguousarray(mu, dtype=np.float64)))


def bogus_error(r, u, mu, trace, law="soc") -> float:
    """so-bogus's own stopping figure (module docstring), for comparisons with that library."""
    r = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, 3))
    u = np.ascontiguousarray(np.asarray(u, dtype=np.float64).reshape(-1, 3))
    return float(_bogus_error(law_code(law), r, u, np.ascontiguousarray(mu), np.ascontiguousarray(trace)))
