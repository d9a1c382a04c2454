"""Friction-cone primitives shared by the local and global solvers (numba, scalar, allocation-free).

Each contact has a 3-vector block ``[normal, tangent1, tangent2]``.  The friction cone and its dual:

    K_mu     = { r : ||r_T|| <= mu r_N }
    K_mu^*   = K_{1/mu} = { u : mu ||u_T|| <= u_N }

The two laws (docs/maths.md section 5) share one *natural map*
``e = r - P_K(r - rho * u_eff)``:

* ``SOC``     (the associated law, KKT of the SOCQP):  ``u_eff = u``
* ``COULOMB`` (De Saxcé's change of variable):        ``u_eff = u + mu ||u_T|| e_N``

``e = 0`` iff ``r in K_mu``, ``u_eff in K_mu^*`` and ``r . u_eff = 0`` (any ``rho > 0``).
All functions take and return plain floats so that numba keeps them in registers.
"""

from __future__ import annotations

import math

from numba import njit

SOC = 0
COULOMB = 1

LAW_CODES = {"soc": SOC, "coulomb": COULOMB}


def law_code(law: str) -> int:
    """'soc' -> SOC, 'coulomb' -> COULOMB (ValueError otherwise)."""
    try:
        return LAW_CODES[law.lower()]
    except (KeyError, AttributeError):
        raise ValueError(f"unknown contact law {law!r}: expected 'soc' or 'coulomb'") from None


@njit(cache=True, inline="always")
def project_cone(mu, zn, zt1, zt2):
    """Euclidean projection of z onto K_mu = {||z_T|| <= mu z_N}.

    interior (||z_T|| <= mu z_N and z_N >= 0; the second matters for mu = 0, z_T = 0): z;
    polar cone (mu ||z_T|| <= -z_N): 0;
    else:     a (1, mu z_T/||z_T||) with a = (z_N + mu ||z_T||) / (1 + mu^2).
    """
    nt = math.sqrt(zt1 * zt1 + zt2 * zt2)
    if nt <= mu * zn and zn >= 0.0:
        return zn, zt1, zt2
    if mu * nt <= -zn:
        return 0.0, 0.0, 0.0
    a = (zn + mu * nt) / (1.0 + mu * mu)
    s = a * mu / nt
    return a, s * zt1, s * zt2


@njit(cache=True, inline="always")
def effective_velocity(law, mu, un, ut1, ut2):
    """u_eff = u (SOC) or u + mu ||u_T|| e_N (Coulomb, De Saxcé)."""
    if law == COULOMB:
        return un + mu * math.sqrt(ut1 * ut1 + ut2 * ut2), ut1, ut2
    return un, ut1, ut2


@njit(cache=True, inline="always")
def natural_map_norm(law, mu, rho, rn, rt1, rt2, un, ut1, ut2):
    """||r - P_K(r - rho u_eff)|| for one contact."""
    en, et1, et2 = effective_velocity(law, mu, un, ut1, ut2)
    pn, pt1, pt2 = project_cone(mu, rn - rho * en, rt1 - rho * et1, rt2 - rho * et2)
    dn = rn - pn
    d1 = rt1 - pt1
    d2 = rt2 - pt2
    return math.sqrt(dn * dn + d1 * d1 + d2 * d2)


@njit(cache=True, inline="always")
def cone_excess(mu, rn, rt1, rt2):
    """max(0, ||r_T|| - mu r_N) (for mu = 0 also counts a negative r_N)."""
    v = math.sqrt(rt1 * rt1 + rt2 * rt2) - mu * rn
    if mu == 0.0 and rn < 0.0:
        v = max(v, -rn)
    return v if v > 0.0 else 0.0


@njit(cache=True)
def fischer_burmeister_sq(law, mu, scale, rn, rt1, rt2, un, ut1, ut2):
    """||phi_FB(x, y)||^2 with x = scale (mu r_N, r_T), y = (u_eff_N, mu u_eff_T) (Jordan algebra of the
    unit cone; as the so-bogus library measures its error).  Used only for a comparable error figure."""
    en, et1, et2 = effective_velocity(law, mu, un, ut1, ut2)
    if mu == 0.0:
        xn = scale * rn
        f0 = xn + en - math.sqrt(xn * xn + en * en)
        return f0 * f0 + (scale * rt1) ** 2 + (scale * rt2) ** 2
    x0 = scale * mu * rn
    x1 = scale * rt1
    x2 = scale * rt2
    y0 = en
    y1 = mu * et1
    y2 = mu * et2
    z0 = x0 * x0 + x1 * x1 + x2 * x2 + y0 * y0 + y1 * y1 + y2 * y2
    z1 = x0 * x1 + y0 * y1
    z2 = x0 * x2 + y0 * y2
    nz = math.sqrt(z1 * z1 + z2 * z2)
    if nz > 0.0:
        o1 = z1 / nz
        o2 = z2 / nz
    else:
        o1 = 1.0
        o2 = 0.0
    l1 = math.sqrt(max(0.0, z0 - 2.0 * nz))
    l2 = math.sqrt(z0 + 2.0 * nz)
    s0 = 0.5 * (l1 + l2)
    s1 = 0.5 * (l2 - l1) * o1
    s2 = 0.5 * (l2 - l1) * o2
    f0 = x0 + y0 - s0
    f1 = x1 + y1 - s1
    f2 = x2 + y2 - s2
    return f0 * f0 + f1 * f1 + f2 * f2
