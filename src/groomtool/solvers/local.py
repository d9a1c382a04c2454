"""The 3x3 local contact problem, exactly, under either law.

Find r (3,) such that, with u = A r + c (A symmetric PSD 3x3, normally SPD),

* SOC law:      r in K_mu, u in K_mu^*, r . u = 0       (the KKT of min 1/2 r^T A r + c^T r, r in K_mu)
* Coulomb law:  take-off (r = 0, u_N >= 0) | stick (r in K_mu, u = 0) |
                slip (||r_T|| = mu r_N > 0, u_N = 0, u_T = -alpha r_T, alpha >= 0)

Strategy (after normalising the problem to tr(A) = 3 and ||c|| = 1, so that one tolerance fits all):

1. take-off test, then the frictionless case (mu = 0), then stick r = -A^{-1} c (closed forms; for a
   singular A of rank 2 the stick set r_p + t n is intersected with the cone by a quadratic in t);
2. slip: non-smooth Newton on the natural map F(r) = r - P_K(r - u_eff(r)) (rho = 1 after the
   normalisation), Armijo line search on ||F||, warm-started;
3. if Newton fails, the exact enumerative slip solver: on the slip branch A r + c = -nu G r with
   G = diag(-mu^2, 1, 1) (SOC, u = nu J r) or G = diag(0, 1, 1) (Coulomb, u_N = 0, u_T = -nu r_T), so
   r(nu) = -M(nu)^{-1} c, M(nu) = A + nu G, and the cone boundary mu^2 r_N^2 = ||r_T||^2 becomes the
   quartic  mu^2 x_N(nu)^2 - ||x_T(nu)||^2 = 0  with x = adj(M(nu)) c.  Its real roots nu >= 0 are
   isolated by the derivative cascade (quadratic -> cubic -> quartic, bisection-safeguarded
   Newton on each monotone piece); every root with r_N > 0 is a slip solution; the best is
   polished by Newton;
4. SOC only, last resort: accelerated projected gradient on the 3D convex problem.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .cones import COULOMB, SOC, effective_velocity, project_cone

# numba fastmath flags: fused multiply-add only (IEEE semantics otherwise)
_FM = {"contract"}

TAKEOFF = 0
STICK = 1
SLIP_NEWTON = 2
SLIP_ENUMERATIVE = 3
FRICTIONLESS = 4
SLIP_GRADIENT = 5
FAILED = -1

STATUS_NAMES = {
    TAKEOFF: "take-off",
    STICK: "stick",
    SLIP_NEWTON: "slip (Newton)",
    SLIP_ENUMERATIVE: "slip (enumerative)",
    FRICTIONLESS: "frictionless",
    SLIP_GRADIENT: "slip (projected gradient)",
    FAILED: "failed",
}

LOCAL_TOL = 1e-13
NEWTON_MAX_ITER = 30
_PIVOT_TOL = 1e-14


# ----------------------------------------------------------------------------------------------
# 3x3 helpers on 9-tuples (row-major), so nothing is allocated
# ----------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", fastmath=_FM)
def _mv(A, x0, x1, x2):
    """A x for a row-major 9-tuple A."""
    return (
        A[0] * x0 + A[1] * x1 + A[2] * x2,
        A[3] * x0 + A[4] * x1 + A[5] * x2,
        A[6] * x0 + A[7] * x1 + A[8] * x2,
    )


@njit(cache=True, fastmath=_FM)
def solve3(M, b0, b1, b2):
    """Solve M x = b (Gaussian elimination, partial pivoting). Returns (ok, x0, x1, x2)."""
    scale = 0.0
    for k in range(9):
        scale = max(scale, abs(M[k]))
    if scale == 0.0:
        return False, 0.0, 0.0, 0.0
    # rows as tuples (m0, m1, m2, rhs)
    ra = (M[0], M[1], M[2], b0)
    rb = (M[3], M[4], M[5], b1)
    rc = (M[6], M[7], M[8], b2)
    if abs(rb[0]) > abs(ra[0]) and abs(rb[0]) >= abs(rc[0]):
        ra, rb = rb, ra
    elif abs(rc[0]) > abs(ra[0]):
        ra, rc = rc, ra
    if abs(ra[0]) <= _PIVOT_TOL * scale:
        return False, 0.0, 0.0, 0.0
    fb = rb[0] / ra[0]
    fc = rc[0] / ra[0]
    b11 = rb[1] - fb * ra[1]
    b12 = rb[2] - fb * ra[2]
    b13 = rb[3] - fb * ra[3]
    c11 = rc[1] - fc * ra[1]
    c12 = rc[2] - fc * ra[2]
    c13 = rc[3] - fc * ra[3]
    if abs(c11) > abs(b11):
        b11, c11 = c11, b11
        b12, c12 = c12, b12
        b13, c13 = c13, b13
    if abs(b11) <= _PIVOT_TOL * scale:
        return False, 0.0, 0.0, 0.0
    f = c11 / b11
    c22 = c12 - f * b12
    c23 = c13 - f * b13
    if abs(c22) <= _PIVOT_TOL * scale:
        return False, 0.0, 0.0, 0.0
    x2 = c23 / c22
    x1 = (b13 - b12 * x2) / b11
    x0 = (ra[3] - ra[1] * x1 - ra[2] * x2) / ra[0]
    return True, x0, x1, x2


@njit(cache=True, fastmath=_FM)
def solve3_cramer(M, b0, b1, b2):
    """Solve M x = b by the adjugate (branch-free) when M is well conditioned; else the pivoted
    elimination.  Returns (ok, x0, x1, x2)."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = M
    k00 = a11 * a22 - a12 * a21
    k01 = a02 * a21 - a01 * a22
    k02 = a01 * a12 - a02 * a11
    det = a00 * k00 + a10 * k01 + a20 * k02
    n2 = 0.0
    for k in range(9):
        n2 += M[k] * M[k]
    # |det| against ||M||_F^3: a cheap condition test (1e-8 ~ condition number 1e8)
    if det * det > 1e-16 * n2 * n2 * n2:
        k10 = a12 * a20 - a10 * a22
        k11 = a00 * a22 - a02 * a20
        k12 = a02 * a10 - a00 * a12
        k20 = a10 * a21 - a11 * a20
        k21 = a01 * a20 - a00 * a21
        k22 = a00 * a11 - a01 * a10
        inv = 1.0 / det
        return (
            True,
            (k00 * b0 + k01 * b1 + k02 * b2) * inv,
            (k10 * b0 + k11 * b1 + k12 * b2) * inv,
            (k20 * b0 + k21 * b1 + k22 * b2) * inv,
        )
    return solve3(M, b0, b1, b2)


@njit(cache=True, fastmath=_FM)
def inverse3(M):
    """(ok, M^{-1} as a 9-tuple) for a 3x3 row-major 9-tuple, via the pivoted solve."""
    ok0, a0, a1, a2 = solve3(M, 1.0, 0.0, 0.0)
    ok1, b0, b1, b2 = solve3(M, 0.0, 1.0, 0.0)
    ok2, c0, c1, c2 = solve3(M, 0.0, 0.0, 1.0)
    return ok0 and ok1 and ok2, (a0, b0, c0, a1, b1, c1, a2, b2, c2)


@njit(cache=True, inline="always", fastmath=_FM)
def _norm3(x0, x1, x2):
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


# ----------------------------------------------------------------------------------------------
# natural map and its Newton
# ----------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", fastmath=_FM)
def _natural_map(law, mu, A, c0, c1, c2, r0, r1, r2):
    """F(r) = r - P_K(r - u_eff(A r + c))  (rho = 1 in normalised units)."""
    u0, u1, u2 = _mv(A, r0, r1, r2)
    e0, e1, e2 = effective_velocity(law, mu, u0 + c0, u1 + c1, u2 + c2)
    p0, p1, p2 = project_cone(mu, r0 - e0, r1 - e1, r2 - e2)
    return r0 - p0, r1 - p1, r2 - p2


@njit(cache=True, fastmath=_FM)
def _newton_step(law, mu, A, c0, c1, c2, r0, r1, r2, F0, F1, F2):
    """Newton direction d = -J_F^{-1} F, J_F = I - J_P (I - dU), dU = d u_eff / d r.
    Falls back to a Levenberg-Marquardt step when J_F is singular."""
    u0, u1, u2 = _mv(A, r0, r1, r2)
    u0 += c0
    u1 += c1
    u2 += c2
    # dU = A (+ e_N (mu / ||u_T||) (u_T1 A[1,:] + u_T2 A[2,:]) for Coulomb)
    d00, d01, d02 = A[0], A[1], A[2]
    e0 = u0
    if law == COULOMB:
        nt = math.sqrt(u1 * u1 + u2 * u2)
        e0 = u0 + mu * nt
        if nt > 0.0:
            g = mu / nt
            d00 += g * (u1 * A[3] + u2 * A[6])
            d01 += g * (u1 * A[4] + u2 * A[7])
            d02 += g * (u1 * A[5] + u2 * A[8])
    # I - dU
    m00 = 1.0 - d00
    m01 = -d01
    m02 = -d02
    m10 = -A[3]
    m11 = 1.0 - A[4]
    m12 = -A[5]
    m20 = -A[6]
    m21 = -A[7]
    m22 = 1.0 - A[8]
    # projection Jacobian at z = r - u_eff
    zn = r0 - e0
    zt1 = r1 - u1
    zt2 = r2 - u2
    nt = math.sqrt(zt1 * zt1 + zt2 * zt2)
    if nt <= mu * zn and zn >= 0.0:
        # J_P = I:  J_F = dU
        J = (d00, d01, d02, A[3], A[4], A[5], A[6], A[7], A[8])
    elif mu * nt <= -zn:
        # J_P = 0:  J_F = I
        return True, -F0, -F1, -F2
    else:
        a = (zn + mu * nt) / (1.0 + mu * mu)
        w1 = zt1 / nt
        w2 = zt2 / nt
        inv = 1.0 / (1.0 + mu * mu)
        dd1 = mu * w1
        dd2 = mu * w2
        g = a * mu / nt
        p00 = inv
        p01 = dd1 * inv
        p02 = dd2 * inv
        p11 = dd1 * dd1 * inv + g * (1.0 - w1 * w1)
        p12 = dd1 * dd2 * inv - g * w1 * w2
        p22 = dd2 * dd2 * inv + g * (1.0 - w2 * w2)
        # J_F = I - P M  (P symmetric)
        J = (
            1.0 - (p00 * m00 + p01 * m10 + p02 * m20),
            -(p00 * m01 + p01 * m11 + p02 * m21),
            -(p00 * m02 + p01 * m12 + p02 * m22),
            -(p01 * m00 + p11 * m10 + p12 * m20),
            1.0 - (p01 * m01 + p11 * m11 + p12 * m21),
            -(p01 * m02 + p11 * m12 + p12 * m22),
            -(p02 * m00 + p12 * m10 + p22 * m20),
            -(p02 * m01 + p12 * m11 + p22 * m21),
            1.0 - (p02 * m02 + p12 * m12 + p22 * m22),
        )
    ok, x0, x1, x2 = solve3_cramer(J, -F0, -F1, -F2)
    if ok:
        return True, x0, x1, x2
    # Levenberg-Marquardt: (J^T J + lam I) d = -J^T F
    jn = 0.0
    for k in range(9):
        jn += J[k] * J[k]
    lam = 1e-10 * jn + 1e-300
    n00 = J[0] * J[0] + J[3] * J[3] + J[6] * J[6] + lam
    n01 = J[0] * J[1] + J[3] * J[4] + J[6] * J[7]
    n02 = J[0] * J[2] + J[3] * J[5] + J[6] * J[8]
    n11 = J[1] * J[1] + J[4] * J[4] + J[7] * J[7] + lam
    n12 = J[1] * J[2] + J[4] * J[5] + J[7] * J[8]
    n22 = J[2] * J[2] + J[5] * J[5] + J[8] * J[8] + lam
    g0 = -(J[0] * F0 + J[3] * F1 + J[6] * F2)
    g1 = -(J[1] * F0 + J[4] * F1 + J[7] * F2)
    g2 = -(J[2] * F0 + J[5] * F1 + J[8] * F2)
    return solve3((n00, n01, n02, n01, n11, n12, n02, n12, n22), g0, g1, g2)


@njit(cache=True, fastmath=_FM)
def newton(law, mu, A, c0, c1, c2, r0, r1, r2, tol, max_iter, atol=0.0):
    """Non-smooth Newton on F(r) = r - P_K(r - u_eff) with an Armijo line search on ||F||.
    Converged when ||F|| <= max(tol * max(1, ||r||), atol).  Returns (converged, r0, r1, r2, ||F||,
    iterations).  (Squared norms throughout: no square roots on the hot path.)"""
    F0, F1, F2 = _natural_map(law, mu, A, c0, c1, c2, r0, r1, r2)
    f2 = F0 * F0 + F1 * F1 + F2 * F2
    tol2 = tol * tol
    atol2 = atol * atol
    for it in range(max_iter):
        if f2 <= max(tol2 * max(1.0, r0 * r0 + r1 * r1 + r2 * r2), atol2):
            return True, r0, r1, r2, math.sqrt(f2), it
        ok, d0, d1, d2 = _newton_step(law, mu, A, c0, c1, c2, r0, r1, r2, F0, F1, F2)
        if not ok:
            return False, r0, r1, r2, math.sqrt(f2), it
        t = 1.0
        accepted = False
        for _ in range(40):
            s0 = r0 + t * d0
            s1 = r1 + t * d1
            s2 = r2 + t * d2
            G0, G1, G2 = _natural_map(law, mu, A, c0, c1, c2, s0, s1, s2)
            g2 = G0 * G0 + G1 * G1 + G2 * G2
            q = 1.0 - 1e-4 * t
            if g2 <= q * q * f2:
                accepted = True
                break
            t *= 0.5
        if not accepted:
            return f2 <= max(tol2 * max(1.0, r0 * r0 + r1 * r1 + r2 * r2), atol2), r0, r1, r2, math.sqrt(f2), it
        r0, r1, r2 = s0, s1, s2
        F0, F1, F2 = G0, G1, G2
        f2 = g2
    return f2 <= max(tol2 * max(1.0, r0 * r0 + r1 * r1 + r2 * r2), atol2), r0, r1, r2, math.sqrt(f2), max_iter


# ----------------------------------------------------------------------------------------------
# real roots of a polynomial of degree <= 4 on an interval (derivative cascade)
# ----------------------------------------------------------------------------------------------
@njit(cache=True, inline="always", fastmath=_FM)
def _horner(c, deg, x):
    v = c[deg]
    for k in range(deg - 1, -1, -1):
        v = v * x + c[k]
    return v


@njit(cache=True, fastmath=_FM)
def _refine_root(c, deg, a, b, fa, fb):
    """Root of the monotone polynomial piece on [a, b] with fa fb <= 0: Newton safeguarded by bisection."""
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    x = 0.5 * (a + b)
    for _ in range(200):
        fx = _horner(c, deg, x)
        if fx == 0.0:
            return x
        if (fx < 0.0) == (fa < 0.0):
            a = x
            fa = fx
        else:
            b = x
            fb = fx
        # derivative
        dv = deg * c[deg]
        for k in range(deg - 1, 0, -1):
            dv = dv * x + k * c[k]
        xn = x - fx / dv if dv != 0.0 else 0.5 * (a + b)
        if not (a < xn < b):
            xn = 0.5 * (a + b)
        if abs(xn - x) <= 4e-16 * max(abs(x), 1e-300) or b - a <= 4e-16 * max(abs(a), abs(b)):
            return xn
        x = xn
    return x


@njit(cache=True, fastmath=_FM)
def _roots_between(c, deg, pts, npts, out):
    """Roots of the polynomial c (degree deg) that is monotone between consecutive pts[0..npts-1]
    (sorted; pts[0], pts[-1] the interval's ends), plus near-double roots at interior points.
    Writes them sorted into out; returns their number."""
    n = 0
    fprev = _horner(c, deg, pts[0])
    for k in range(npts - 1):
        a = pts[k]
        b = pts[k + 1]
        fb = _horner(c, deg, b)
        if b > a and ((fprev <= 0.0 and fb >= 0.0) or (fprev >= 0.0 and fb <= 0.0)):
            x = _refine_root(c, deg, a, b, fprev, fb)
            if n == 0 or abs(x - out[n - 1]) > 1e-14 * max(1.0, abs(x)):
                out[n] = x
                n += 1
        elif k + 1 < npts - 1:
            # a touching (double) root at a critical point: keep it if |p| is at rounding level
            xs = abs(b)
            size = 0.0
            pw = 1.0
            for j in range(deg + 1):
                size += abs(c[j]) * pw
                pw *= xs
            if abs(fb) <= 1e-12 * size:
                out[n] = b
                n += 1
        fprev = fb
    return n


@njit(cache=True, fastmath=_FM)
def real_roots(coeffs, lo, hi):
    """Real roots in [lo, hi] of sum_k coeffs[k] x^k (degree <= 4), sorted, plus near-double roots.

    Derivative cascade: the roots of p^(k+1) split [lo, hi] into pieces where p^(k) is monotone, so
    each piece holds at most one root of p^(k) (found by safeguarded Newton); from the linear
    p^(deg-1) up to p itself."""
    deg = coeffs.shape[0] - 1
    while deg > 0 and coeffs[deg] == 0.0:
        deg -= 1
    if deg == 0:
        return np.empty(0)
    # derivatives: der[k] = coefficients of p^(k), degree deg - k
    der = np.zeros((deg + 1, deg + 1))
    for j in range(deg + 1):
        der[0, j] = coeffs[j]
    for k in range(1, deg + 1):
        for j in range(deg - k + 1):
            der[k, j] = (j + 1) * der[k - 1, j + 1]
    crit = np.empty(2 * deg + 2)
    ncrit = 0
    pts = np.empty(2 * deg + 4)
    for k in range(deg - 1, -1, -1):
        pts[0] = lo
        for j in range(ncrit):
            pts[j + 1] = min(max(crit[j], lo), hi)
        pts[ncrit + 1] = hi
        ncrit = _roots_between(der[k], deg - k, pts, ncrit + 2, crit)
    return np.sort(crit[:ncrit])


# ----------------------------------------------------------------------------------------------
# enumerative slip solver
# ----------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=_FM)
def _poly_mul(p, q):
    out = np.zeros(p.shape[0] + q.shape[0] - 1)
    for i in range(p.shape[0]):
        for j in range(q.shape[0]):
            out[i + j] += p[i] * q[j]
    return out


@njit(cache=True, fastmath=_FM)
def slip_quartic(law, mu, A, c0, c1, c2):
    """Coefficients (ascending) of q(nu) = mu^2 x_N^2 - ||x_T||^2, x(nu) = adj(A + nu G) c."""
    g0 = -mu * mu if law == SOC else 0.0
    g1 = 1.0
    g2 = 1.0
    a00, a01, a02 = A[0], 0.5 * (A[1] + A[3]), 0.5 * (A[2] + A[6])
    a11, a12, a22 = A[4], 0.5 * (A[5] + A[7]), A[8]
    # adjugate entries as polynomials in nu (ascending, degree <= 2)
    adj00 = np.array([a11 * a22 - a12 * a12, a11 * g2 + a22 * g1, g1 * g2])
    adj11 = np.array([a00 * a22 - a02 * a02, a00 * g2 + a22 * g0, g0 * g2])
    adj22 = np.array([a00 * a11 - a01 * a01, a00 * g1 + a11 * g0, g0 * g1])
    adj01 = np.array([a02 * a12 - a01 * a22, -a01 * g2, 0.0])
    adj02 = np.array([a01 * a12 - a02 * a11, -a02 * g1, 0.0])
    adj12 = np.array([a01 * a02 - a12 * a00, -a12 * g0, 0.0])
    xn = adj00 * c0 + adj01 * c1 + adj02 * c2
    xt1 = adj01 * c0 + adj11 * c1 + adj12 * c2
    xt2 = adj02 * c0 + adj12 * c1 + adj22 * c2
    return mu * mu * _poly_mul(xn, xn) - _poly_mul(xt1, xt1) - _poly_mul(xt2, xt2)


@njit(cache=True, fastmath=_FM)
def _snap_to_boundary(mu, r0, r1, r2):
    """Put a slip candidate exactly on the cone boundary ||r_T|| = mu r_N (keeps the larger part)."""
    nt = math.sqrt(r1 * r1 + r2 * r2)
    if nt == 0.0:
        return r0, r1, r2
    if mu <= 1.0:
        s = mu * r0 / nt
        return r0, r1 * s, r2 * s
    return nt / mu, r1, r2


@njit(cache=True, fastmath=_FM)
def enumerative_slip(law, mu, A, c0, c1, c2, w0, w1, w2, tol):
    """Exact slip solution from the quartic (see module docstring), polished by Newton.
    (w0, w1, w2) is a warm start used to choose among several valid roots (Coulomb) and as a
    fallback.  Returns (found, r0, r1, r2, ||F||)."""
    coeffs = slip_quartic(law, mu, A, c0, c1, c2)
    cmax = 0.0
    for k in range(5):
        cmax = max(cmax, abs(coeffs[k]))
    if cmax == 0.0:
        return False, w0, w1, w2, np.inf
    deg = 4
    while deg > 0 and abs(coeffs[deg]) == 0.0:
        deg -= 1
    hi = 1.0
    if deg > 0:
        lead = abs(coeffs[deg])
        for k in range(deg):
            hi = max(hi, 1.0 + abs(coeffs[k]) / lead)
        hi = min(hi, 1e300)
    roots = real_roots(coeffs / cmax, 0.0, hi)
    g0 = -mu * mu if law == SOC else 0.0
    best_f = np.inf
    best_d = np.inf
    b0, b1, b2 = w0, w1, w2
    found = False
    for k in range(roots.shape[0]):
        nu = roots[k]
        M = (A[0] + nu * g0, A[1], A[2], A[3], A[4] + nu, A[5], A[6], A[7], A[8] + nu)
        ok, r0, r1, r2 = solve3(M, -c0, -c1, -c2)
        if not ok or not (r0 > 0.0):
            continue
        r0, r1, r2 = _snap_to_boundary(mu, r0, r1, r2)
        conv, r0, r1, r2, f, _ = newton(law, mu, A, c0, c1, c2, r0, r1, r2, tol, 8)
        dist = _norm3(r0 - w0, r1 - w1, r2 - w2)
        # prefer converged candidates, then the one closest to the warm start
        scale = tol * max(1.0, _norm3(r0, r1, r2))
        if f <= scale:
            if not found or best_f > scale or dist < best_d:
                best_f, best_d = f, dist
                b0, b1, b2 = r0, r1, r2
                found = True
        elif not found and f < best_f:
            best_f, best_d = f, dist
            b0, b1, b2 = r0, r1, r2
    return found, b0, b1, b2, best_f


@njit(cache=True, fastmath=_FM)
def projected_gradient_soc(mu, A, c0, c1, c2, r0, r1, r2, tol, max_iter):
    """FISTA with restart on min 1/2 r^T A r + c^T r, r in K_mu (3D, convex; last resort)."""
    L = 0.0
    for k in range(9):
        L += A[k] * A[k]
    L = math.sqrt(L) + 1e-300
    t = 1.0 / L
    x0, x1, x2 = project_cone(mu, r0, r1, r2)
    y0, y1, y2 = x0, x1, x2
    th = 1.0
    for _ in range(max_iter):
        g0, g1, g2 = _mv(A, y0, y1, y2)
        n0, n1, n2 = project_cone(mu, y0 - t * (g0 + c0), y1 - t * (g1 + c1), y2 - t * (g2 + c2))
        th_n = 0.5 * (-th * th + th * math.sqrt(th * th + 4.0))
        beta = th * (1.0 - th) / (th * th + th_n)
        gx0, gx1, gx2 = _mv(A, n0, n1, n2)
        if (gx0 + c0) * (n0 - x0) + (gx1 + c1) * (n1 - x1) + (gx2 + c2) * (n2 - x2) > 0.0:
            th_n = 1.0
            beta = 0.0
        y0 = n0 + beta * (n0 - x0)
        y1 = n1 + beta * (n1 - x1)
        y2 = n2 + beta * (n2 - x2)
        x0, x1, x2 = n0, n1, n2
        th = th_n
        F0, F1, F2 = _natural_map(SOC, mu, A, c0, c1, c2, x0, x1, x2)
        if _norm3(F0, F1, F2) <= tol * max(1.0, _norm3(x0, x1, x2)):
            break
    F0, F1, F2 = _natural_map(SOC, mu, A, c0, c1, c2, x0, x1, x2)
    return x0, x1, x2, _norm3(F0, F1, F2)


@njit(cache=True, fastmath=_FM)
def singular_stick(mu, A, c0, c1, c2):
    """Stick (u = 0) for a singular A of rank 2: r = r_p + t n with n spanning null(A) (the largest cross
    product of two rows), r_p = -(A + n n^T)^{-1} c (so A r_p = -c when c is orthogonal to n);
    t is the point closest to 0 of {t : ||r_T|| <= mu r_N} (its ends solve a quadratic).
    Returns (found, r0, r1, r2)."""
    rows = ((A[0], A[1], A[2]), (A[3], A[4], A[5]), (A[6], A[7], A[8]))
    best = 0.0
    n0 = n1 = n2 = 0.0
    for i in range(3):
        for j in range(i + 1, 3):
            a = rows[i]
            b = rows[j]
            x0 = a[1] * b[2] - a[2] * b[1]
            x1 = a[2] * b[0] - a[0] * b[2]
            x2 = a[0] * b[1] - a[1] * b[0]
            nn = x0 * x0 + x1 * x1 + x2 * x2
            if nn > best:
                best = nn
                n0, n1, n2 = x0, x1, x2
    anorm2 = 0.0
    for k in range(9):
        anorm2 += A[k] * A[k]
    if best <= 1e-20 * anorm2 * anorm2:  # rank <= 1
        return False, 0.0, 0.0, 0.0
    inv = 1.0 / math.sqrt(best)
    n0 *= inv
    n1 *= inv
    n2 *= inv
    q0, q1, q2 = _mv(A, n0, n1, n2)
    if q0 * q0 + q1 * q1 + q2 * q2 > 1e-16 * anorm2:  # n is not a null vector: A is not singular
        return False, 0.0, 0.0, 0.0
    s = math.sqrt(anorm2)
    M = (A[0] + s * n0 * n0, A[1] + s * n0 * n1, A[2] + s * n0 * n2,
         A[3] + s * n1 * n0, A[4] + s * n1 * n1, A[5] + s * n1 * n2,
         A[6] + s * n2 * n0, A[7] + s * n2 * n1, A[8] + s * n2 * n2)
    ok, p0, p1, p2 = solve3(M, -c0, -c1, -c2)
    if not ok:
        return False, 0.0, 0.0, 0.0
    # consistency: A p + c = 0 (else u = 0 is impossible)
    q0, q1, q2 = _mv(A, p0, p1, p2)
    if _norm3(q0 + c0, q1 + c1, q2 + c2) > 1e-9 * max(1.0, _norm3(c0, c1, c2)):
        return False, 0.0, 0.0, 0.0
    p = (p0, p1, p2)
    a = p[0]
    b = n0

    def g(t):
        return mu * (a + t * b) - math.sqrt((p[1] + t * n1) ** 2 + (p[2] + t * n2) ** 2)

    if g(0.0) >= 0.0:
        return True, p[0], p[1], p[2]
    qa = mu * mu * b * b - n1 * n1 - n2 * n2
    qb = 2.0 * (mu * mu * a * b - p[1] * n1 - p[2] * n2)
    qc = mu * mu * a * a - p[1] * p[1] - p[2] * p[2]
    best = np.inf
    ts = np.empty(2)
    nt = 0
    if abs(qa) > 1e-300:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            sq = math.sqrt(disc)
            ts[0] = (-qb - sq) / (2.0 * qa)
            ts[1] = (-qb + sq) / (2.0 * qa)
            nt = 2
    elif abs(qb) > 1e-300:
        ts[0] = -qc / qb
        nt = 1
    for k in range(nt):
        t = ts[k]
        if a + t * b >= 0.0 and g(t) >= -1e-12 * max(1.0, abs(a) + abs(t)) and abs(t) < abs(best):
            best = t
    if best == np.inf:
        return False, 0.0, 0.0, 0.0
    return True, p[0] + best * n0, p[1] + best * n1, p[2] + best * n2


# ----------------------------------------------------------------------------------------------
# the local solver
# ----------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=_FM)
def solve_normalized(law, mu, A, Ainv, has_inv, c0, c1, c2, w0, w1, w2, tol, max_newton, atol=0.0):
    """Local solve in normalised units (tr A = 3, ||c|| = 1; Ainv = A^{-1} if has_inv).
    (w0, w1, w2): warm start.  Slip is solved to ||F|| <= max(tol max(1, ||r||), atol).
    Returns (status, r0, r1, r2)."""
    cn = math.sqrt(c1 * c1 + c2 * c2)
    # 1. take-off: r = 0 and u = c satisfies the law
    if law == SOC:
        if mu * cn <= c0:
            return TAKEOFF, 0.0, 0.0, 0.0
    elif c0 >= 0.0:
        return TAKEOFF, 0.0, 0.0, 0.0
    # frictionless: r_T = 0 (u_T free), r_N = -c_N / A_NN
    if mu == 0.0:
        if A[0] > _PIVOT_TOL:
            return FRICTIONLESS, -c0 / A[0], 0.0, 0.0
        return FAILED, 0.0, 0.0, 0.0
    # 2. stick: u = 0
    s0 = s1 = s2 = 0.0
    if has_inv:
        s0, s1, s2 = _mv(Ainv, -c0, -c1, -c2)
        if math.sqrt(s1 * s1 + s2 * s2) <= mu * s0:
            return STICK, s0, s1, s2
    else:
        found, s0, s1, s2 = singular_stick(mu, A, c0, c1, c2)
        if found:
            return STICK, s0, s1, s2
    # 3. slip by Newton, from the warm start if it is usable, else from the projected stick point
    if w0 == 0.0 and w1 == 0.0 and w2 == 0.0:
        if has_inv:
            w0, w1, w2 = project_cone(mu, s0, s1, s2)
        if w0 == 0.0 and w1 == 0.0 and w2 == 0.0:
            w0, w1, w2 = project_cone(mu, -c0, -c1, -c2)
    conv, r0, r1, r2, f, _ = newton(law, mu, A, c0, c1, c2, w0, w1, w2, tol, max_newton, atol)
    if conv:
        return SLIP_NEWTON, r0, r1, r2
    # 4. exact enumerative slip
    found, e0, e1, e2, fe = enumerative_slip(law, mu, A, c0, c1, c2, r0, r1, r2, tol)
    if found:
        return SLIP_ENUMERATIVE, e0, e1, e2
    if fe < f:
        r0, r1, r2, f = e0, e1, e2, fe
    # 5. SOC: the problem is convex, a first-order method cannot fail (only be slow)
    if law == SOC:
        g0, g1, g2, fg = projected_gradient_soc(mu, A, c0, c1, c2, r0, r1, r2, tol, 20000)
        if fg < f:
            r0, r1, r2, f = g0, g1, g2, fg
        conv, r0, r1, r2, f, _ = newton(law, mu, A, c0, c1, c2, r0, r1, r2, tol, max_newton)
        if f <= 1e3 * tol * max(1.0, _norm3(r0, r1, r2)):
            return SLIP_GRADIENT, r0, r1, r2
    return FAILED, r0, r1, r2


@njit(cache=True, fastmath=_FM)
def normalize_block(A):
    """(s = tr(A)/3, A/s as a 9-tuple, (A/s)^{-1}, invertible) for a 3x3 array A."""
    s = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    if not (s > 0.0):
        s = 1.0
    An = (
        A[0, 0] / s, A[0, 1] / s, A[0, 2] / s,
        A[1, 0] / s, A[1, 1] / s, A[1, 2] / s,
        A[2, 0] / s, A[2, 1] / s, A[2, 2] / s,
    )
    ok, Ainv = inverse3(An)
    if ok:
        big = 0.0
        for k in range(9):
            big = max(big, abs(Ainv[k]))
        ok = big <= 1e12
    return s, An, Ainv, ok


@njit(cache=True, fastmath=_FM)
def solve_block(law, mu, s, An, Ainv, has_inv, c0, c1, c2, r0, r1, r2, tol, max_newton, atol=0.0):
    """Local solve in physical units for a pre-normalised block (s, An = A/s, Ainv = An^{-1}):
    scales c to unit norm, solves, scales back.  (r0, r1, r2) is the warm start.
    atol: an absolute bound on the natural map e = r - P_K(r - u_eff / s) (units of r) that is good
    enough (Gauss-Seidel passes a fraction of its global tolerance: a contact whose forces are tiny
    next to the largest ones needs no 1e-13 relative accuracy).  Returns (status, r0, r1, r2)."""
    cm = max(abs(c0), max(abs(c1), abs(c2)))
    if cm == 0.0:
        return TAKEOFF, 0.0, 0.0, 0.0
    if 1e-150 < cm < 1e150:
        cn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    else:  # avoid under/overflow of the squares
        cn = cm * math.sqrt((c0 / cm) ** 2 + (c1 / cm) ** 2 + (c2 / cm) ** 2)
    ic = 1.0 / cn
    k = s * ic
    st, x0, x1, x2 = solve_normalized(
        law, mu, An, Ainv, has_inv, c0 * ic, c1 * ic, c2 * ic, r0 * k, r1 * k, r2 * k, tol, max_newton, atol * k
    )
    back = cn / s
    return st, x0 * back, x1 * back, x2 * back
