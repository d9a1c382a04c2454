"""A computable bound on how far a feasible point of the SOCQP is from the optimum, in the D-norm of H^T r.

The problem (problem.py):  min_r f(r) = 1/2 |A^T r|^2 + gamma |r|^2 + b^T r,  r_i in K_mu_i,  A = H D^1/2.
In the inversion D = K^-2 (scaled), so A^T r = K^-1 H^T r (scaled): the rest-curvature correction of the
contacts.  Its error against the optimum r* is what the user cares about (q0 = q0_guess + d - K^-1 H^T r).

Fenchel dual (writing 1/2 |A^T r|^2 = max_l l^T A^T r - 1/2 |l|^2 and minimising over the cones in closed
form, Moreau's decomposition):

    g(l) = -1/2 |l|^2 - |P_K(-(A l + b))|^2 / (4 gamma)            (1-strongly concave in l)

For r in the cones and any l, with y = A^T r and y* = A^T r* = l* (strong duality):

    f(r) - f*  >= 1/2 |y - y*|^2 + gamma |r - r*|^2     (optimality of r*: grad f(r*)^T (r - r*) >= 0)
    f* - g(l)  >= 1/2 |l - y*|^2                        (strong concavity of g, maximised at y*)

so the duality gap G(r, l) = f(r) - g(l) bounds both: with l = y, |y - y*| <= sqrt(G).  Per contact,
with a = 2 gamma r_i and v = c_i + 2 gamma r_i (c = A l + b; v = u_i = (W r + b)_i when l = y):

    G(r, l) = 1/2 |y - l|^2 + sum_i phi_i / (4 gamma),   phi_i = |P_K(a - v)|^2 - |a|^2 + 2 a^T v >= 0

(phi_i >= 0 by convexity of 1/2 |P_K z|^2, whose gradient is P_K z; phi_i = 0 exactly when contact i
satisfies its law), so the gap is a sum of non-negative terms without cancellation, and it is quadratic
in the local mismatch: a contact whose velocity is off by delta contributes about |delta|^2 / (4 gamma).
Cost with l = y: one pass over (r, u), which the solvers already have.

A better dual point than l = y: the gap is convex in l; ``line_search`` minimises it along
l = y + t (A^T r(y) - y), r(l) = P_K(-(A l + b)) / (2 gamma) the dual's own forces (two products with A
and a scalar search over per-contact terms).  Then |y - y*| <= (delta + sqrt(4 G - delta^2)) / 2,
delta = |y - l| (from |y - y*|^2 + |l - y*|^2 <= 2 G and |y - y*| <= |l - y*| + delta).

gamma = 0 has no such bound (the dual is not strongly concave then): inf is returned.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .cones import project_cone


@njit(cache=True)
def gap_terms(r, c, mu, gamma2, out):
    """out[i] = phi_i(a, v) with a = gamma2 r_i, v = c_i + gamma2 r_i (see the module docstring)."""
    for i in range(r.shape[0]):
        a0 = gamma2 * r[i, 0]
        a1 = gamma2 * r[i, 1]
        a2 = gamma2 * r[i, 2]
        v0 = c[i, 0] + a0
        v1 = c[i, 1] + a1
        v2 = c[i, 2] + a2
        p0, p1, p2 = project_cone(mu[i], a0 - v0, a1 - v1, a2 - v2)
        phi = (p0 * p0 + p1 * p1 + p2 * p2) - (a0 * a0 + a1 * a1 + a2 * a2) + 2.0 * (a0 * v0 + a1 * v1 + a2 * v2)
        out[i] = phi if phi > 0.0 else 0.0


@njit(cache=True)
def project_onto_cones(r, mu, out):
    """out_i = P_K(r_i) for every contact (r, out: (m, 3)); returns the largest |out_i - r_i|."""
    worst = 0.0
    for i in range(r.shape[0]):
        p0, p1, p2 = project_cone(mu[i], r[i, 0], r[i, 1], r[i, 2])
        d = math.sqrt((p0 - r[i, 0]) ** 2 + (p1 - r[i, 1]) ** 2 + (p2 - r[i, 2]) ** 2)
        worst = max(worst, d)
        out[i, 0] = p0
        out[i, 1] = p1
        out[i, 2] = p2
    return worst


def project_forces(r: np.ndarray, mu) -> tuple[np.ndarray, float]:
    """(P_K(r) per contact as (3m,), the largest per-contact move)."""
    r3 = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, 3))
    mu = np.ascontiguousarray(np.broadcast_to(np.asarray(mu, dtype=np.float64), (r3.shape[0],)))
    out = np.empty_like(r3)
    moved = project_onto_cones(r3, mu, out)
    return out.reshape(-1), float(moved)


def duality_gap(r, u, mu, gamma: float) -> float:
    """G(r, A^T r) = sum_i phi_i / (4 gamma) from r (in the cones) and u = W r + b; inf when gamma = 0."""
    if not gamma > 0:
        return math.inf
    r3 = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, 3))
    u3 = np.ascontiguousarray(np.asarray(u, dtype=np.float64).reshape(-1, 3))
    mu = np.ascontiguousarray(np.broadcast_to(np.asarray(mu, dtype=np.float64), (r3.shape[0],)))
    phi = np.empty(r3.shape[0])
    # c = A y + b = u - 2 gamma r, so v = c + 2 gamma r = u
    gap_terms(r3, u3 - 2.0 * gamma * r3, mu, 2.0 * gamma, phi)
    return float(phi.sum() / (4.0 * gamma))


def error_bound(problem, r, u=None, line_search: bool = True, HTr=None) -> dict:
    """Certified bound on |A^T (r - r*)| (= |D^1/2 H^T (r - r*)|) for r in the cones of ``problem``
    (a ContactProblem; r (3m,)).  Returns {"bound", "gap", "norm_y" (= |A^T r|), "line_search_t", "HTr"
    (H^T r, (n,))}.
    ``line_search`` (diagonal D only) tries better dual points along y + t (A^T r(y) - y).  ``u`` (W r + b) and
    ``HTr`` (H^T r): when already known."""
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    gamma = problem.gamma
    mu = problem.mu
    sqrt_d = np.sqrt(problem.D_data) if problem.is_diagonal else None
    Htr = problem.H.T @ r if HTr is None else np.asarray(HTr, dtype=np.float64).reshape(-1)
    out = {"gap": math.inf, "bound": math.inf, "norm_y": math.nan, "line_search_t": 0.0, "HTr": Htr}
    if sqrt_d is not None:
        y = sqrt_d * Htr
        out["norm_y"] = float(np.linalg.norm(y))
    else:
        out["norm_y"] = float(math.sqrt(max(0.0, Htr @ problem.D_apply(Htr))))
    if not gamma > 0:
        return out
    u = problem.velocity(r) if u is None else np.asarray(u, dtype=np.float64).reshape(-1)
    gap = duality_gap(r, u, mu, gamma)
    out["gap"] = gap
    out["bound"] = math.sqrt(gap)
    if not line_search or sqrt_d is None or not math.isfinite(gap) or gap == 0.0:
        return out
    m = problem.n_contacts
    r3 = r.reshape(m, 3)
    c0 = (u - 2.0 * gamma * r).reshape(m, 3)  # A y + b
    r_dual, _ = project_forces(-c0.reshape(-1), mu)
    direction = sqrt_d * (problem.H.T @ (r_dual / (2.0 * gamma))) - y
    dn2 = float(direction @ direction)
    if not dn2 > 0:
        return out
    Ad = (problem.H @ (sqrt_d * direction)).reshape(m, 3)
    phi = np.empty(m)
    mu_c = np.ascontiguousarray(mu)

    def gap_at(t):
        gap_terms(r3, np.ascontiguousarray(c0 + t * Ad), mu_c, 2.0 * gamma, phi)
        return 0.5 * t * t * dn2 + float(phi.sum()) / (4.0 * gamma)

    # golden-section search of the convex gap(t) on [0, 1] (t = 1: the dual's own point)
    lo, hi = 0.0, 1.0
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    g1, g2 = gap_at(x1), gap_at(x2)
    for _ in range(40):
        if g1 <= g2:
            hi, x2, g2 = x2, x1, g1
            x1 = hi - ratio * (hi - lo)
            g1 = gap_at(x1)
        else:
            lo, x1, g1 = x1, x2, g2
            x2 = lo + ratio * (hi - lo)
            g2 = gap_at(x2)
    t, g_t = (x1, g1) if g1 <= g2 else (x2, g2)
    delta = t * math.sqrt(dn2)
    if g_t < gap and 4.0 * g_t >= delta * delta:
        b_t = 0.5 * (delta + math.sqrt(4.0 * g_t - delta * delta))
        if b_t < out["bound"]:
            out.update(bound=b_t, gap=g_t, line_search_t=t)
    return out


def error_bound_with_dual(problem, r, lam) -> dict:
    """Certified bound on |A^T (r - r*)| from a primal point r (in the cones) and any dual point ``lam`` (n,)
    (diagonal D only): G = 1/2 |y - l|^2 + sum_i phi_i / (4 gamma) with c = A l + b, then
    |y - y*| <= (delta + sqrt(4 G - delta^2)) / 2, delta = |y - l|.  For a dual method's iterate q
    (q = D H^T r in the dof-space dual), l = D^-1/2 q and r = P_K(-(A l + b)) / (2 gamma)."""
    if not problem.gamma > 0 or not problem.is_diagonal:
        return {"gap": math.inf, "bound": math.inf}
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    lam = np.asarray(lam, dtype=np.float64).reshape(-1)
    sqrt_d = np.sqrt(problem.D_data)
    y = sqrt_d * (problem.H.T @ r)
    delta = float(np.linalg.norm(y - lam))
    gap, bound = _gap_and_bound(problem, r, problem.H @ (sqrt_d * lam) + problem.b, delta * delta)
    return {"gap": gap, "bound": bound}


def _gap_and_bound(problem, r, c, delta2: float) -> tuple[float, float]:
    """G = f(r) - g(l) = delta^2 / 2 + sum_i phi_i(2 gamma r_i, c_i + 2 gamma r_i) / (4 gamma) at a dual point l
    with c = A l + b (3m,) and delta^2 = |A^T r - l|^2, and the bound (delta + sqrt(4 G - delta^2)) / 2 on
    |A^T (r - r*)| (module docstring)."""
    m = problem.n_contacts
    phi = np.empty(m)
    mu = np.ascontiguousarray(np.broadcast_to(np.asarray(problem.mu, dtype=np.float64), (m,)))
    gap_terms(np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(m, 3)),
              np.ascontiguousarray(np.asarray(c, dtype=np.float64).reshape(m, 3)), mu, 2.0 * problem.gamma, phi)
    gap = 0.5 * delta2 + float(phi.sum()) / (4.0 * problem.gamma)
    return gap, 0.5 * (math.sqrt(delta2) + math.sqrt(max(4.0 * gap - delta2, 0.0)))


def error_bound_with_strands(problem, r, h, HTr=None, c=None) -> dict:
    """Certified bound on |A^T (r - r*)| (A = H D^1/2) from forces r (in the cones) and the dual point
    l = D^1/2 h of a dof-space vector h, e.g. the strand-split ADMM's strand solves h = sum_e J_e^T x_e
    (admm.StrandSplit.strand_sum: each strand's own H^T of its copies x of the forces).  Any D (diagonal or
    dense blocks): everything is written with D_apply, never D^1/2:

        delta^2 = |y - l|^2 = (H^T r - h)^T D (H^T r - h),      c = A l + b = H D h + b,
        G = f(r) - g(l) = delta^2 / 2 + sum_i phi_i(a_i = 2 gamma r_i, v_i = c_i + 2 gamma r_i) / (4 gamma),
        |A^T (r - r*)| <= (delta + sqrt(4 G - delta^2)) / 2.

    Why it is an upper bound: weak duality makes g(l) <= f* for EVERY l, and with y* = A^T r* (strong duality)
    f(r) - f* >= 1/2 |y - y*|^2 (r in the cones, r* optimal) and f* - g(l) >= 1/2 |l - y*|^2 (g is 1-strongly
    concave, maximised at y*).  So a = |y - y*| and |l - y*| >= |a - delta| satisfy a^2 + (a - delta)^2 <= 2 G,
    whose largest root is the bound above (4 G >= delta^2 always holds: a^2 + (a - delta)^2 >= delta^2 / 2).  It
    is the module docstring's bound with l = y replaced by another l; nothing about l is assumed, so a stale or
    unconverged h is still certified.  At ADMM's iterates the phi terms nearly vanish (c is about the velocity
    the s-step projected against) and G is about the strands' disagreement |D^1/2 (H^T r - h)|^2 / 2, with no
    1 / gamma factor (docs/solvers.md section 12).  ``HTr`` (H^T r) and ``c`` (H D h + b): when already known.
    Returns {"gap", "bound", "delta"}; inf without gamma."""
    if not problem.gamma > 0:
        return {"gap": math.inf, "bound": math.inf, "delta": math.nan}
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    h = np.asarray(h, dtype=np.float64).reshape(-1)
    Htr = problem.H.T @ r if HTr is None else np.asarray(HTr, dtype=np.float64).reshape(-1)
    e = Htr - h
    delta2 = max(float(e @ problem.D_apply(e)), 0.0)
    if c is None:
        c = problem.H @ problem.D_apply(h) + problem.b
    gap, bound = _gap_and_bound(problem, r, c, delta2)
    return {"gap": gap, "bound": bound, "delta": math.sqrt(delta2)}
