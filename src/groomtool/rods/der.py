"""Rest data for Discrete Elastic Rods (Bergou et al. 2008, 2010), solved so grad E = f_ext exactly.

Per strand: vertices x_0..x_n, edges e^j = x_{j+1} - x_j, material frames (m1^j, m2^j, t^j) per edge
(here: the twist-free parallel-transport frame of :func:`discrete.bishop_frames`, twist angles
theta^j = 0 at the groom), interior vertices i = 1..n-1.  With chi_i = 1 + t^{i-1} . t^i:

* curvature binormal  (kb)_i = 2 e^{i-1} x e^i / (|e^{i-1}| |e^i| + e^{i-1} . e^i)   (|kb| = 2 tan(phi/2))
* material curvature  kappa_i = 1/2 sum_{j=i-1,i} (kb_i . m2^j, -kb_i . m1^j)   (dimensionless)
* twist               m_i = angle from P_i m1^{i-1} to m1^i about t^i (P_i: t^{i-1} -> t^i), which
                      is theta^i - theta^{i-1} + reference twist (0 for the groom's transport frame)
* Voronoi length      D_i = (|e~^{i-1}| + |e~^i|) / 2 from the *rest* lengths e~
* energy  E = sum_j EA/2 (|e^j|/e~_j - 1)^2 e~_j
            + sum_i [ (kappa_i - kappa~_i)^T B (kappa_i - kappa~_i) + GJ (m_i - m~_i)^2 ] / (2 D_i)

The gradient is grad E = J^T s with the strains' Jacobian J (:func:`der_strain_jacobian`, formulas
of Bergou 2010 for frames that are time-parallel transported) and the stresses
s = (w_j = EA (|e^j|/e~_j - 1), y_i = B (kappa_i - kappa~_i) / D_i, z_i = GJ (m_i - m~_i) / D_i).
The inverse problem grad E = f_ext is linear in s.  With a clamped root (x_0, x_1, theta^0 fixed)
its free equations (x_2..x_n, theta^1..theta^{n-1}: 4(n-1)) and unknowns (w_1.., y, z: 4(n-1)) form
a square block-triangular system, solved exactly from the tip; then
e~_j = |e^j| / (1 + w_j / EA), D_i from e~, kappa~_i = kappa_i - D_i B^-1 y_i, m~_i = m_i - D_i z_i / GJ.
"""

from __future__ import annotations

import numba
import numpy as np

from .discrete import (
    RestDataError,
    cross,
    edge_geometry,
    edge_offsets,
    edge_start_vertices,
    interior_offsets,
    interior_vertices,
    lumped_masses,
    point_force_nodes,
    prepare_rods,
    strand_stiffness_factors,
)


def der_stiffness(material):
    """(EA, EI, GJ) with J = 2I (circular section)."""
    return (material.young_modulus * material.area, material.bending_stiffness, material.twist_stiffness)


def _factor_arrays(offsets, stiffness_factor):
    """The strand factors f_s (validated; None: ones) repeated per edge (E,) and per interior vertex."""
    fac = strand_stiffness_factors(stiffness_factor, len(offsets) - 1)
    counts = np.diff(offsets)
    return np.repeat(fac, counts - 1), np.repeat(fac, counts - 2)


def der_stiffness_arrays(material, offsets, stiffness_factor=None):
    """Per-strand stiffnesses spread over the ragged layout: EA per edge (E,), EI and GJ per interior
    vertex (V - 2S,), each the material's value times its strand's factor f_s (None: all ones)."""
    EA, EI, GJ = der_stiffness(material)
    fe, fi = _factor_arrays(offsets, stiffness_factor)
    return EA * fe, EI * fi, GJ * fi


def _pairs(offsets):
    """Global edge indices (a, b) = (i - 1, i) of every interior vertex i, and the vertex index."""
    iv = interior_vertices(offsets)
    strand = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets) - 2)
    b = iv - strand
    return b - 1, b, iv


@numba.njit(cache=True)
def _jacobian_kernel(t, length, m1, m2, ia, kappa, twist, kb, A, C, a, c, gm, gp):
    """Per interior vertex p between edges ia[p] and ia[p] + 1: the formulas of der_strain_jacobian."""
    for p in range(len(ia)):
        ea = ia[p]
        eb = ea + 1
        ta = t[ea]
        tb = t[eb]
        chi = 1.0 + ta[0] * tb[0] + ta[1] * tb[1] + ta[2] * tb[2]
        bx = ta[1] * tb[2] - ta[2] * tb[1]
        by = ta[2] * tb[0] - ta[0] * tb[2]
        bz = ta[0] * tb[1] - ta[1] * tb[0]
        k0, k1, k2 = 2.0 * bx / chi, 2.0 * by / chi, 2.0 * bz / chi
        kb[p, 0], kb[p, 1], kb[p, 2] = k0, k1, k2
        kd1a = k0 * m1[ea, 0] + k1 * m1[ea, 1] + k2 * m1[ea, 2]
        kd1b = k0 * m1[eb, 0] + k1 * m1[eb, 1] + k2 * m1[eb, 2]
        kd2a = k0 * m2[ea, 0] + k1 * m2[ea, 1] + k2 * m2[ea, 2]
        kd2b = k0 * m2[eb, 0] + k1 * m2[eb, 1] + k2 * m2[eb, 2]
        kap1 = 0.5 * (kd2a + kd2b)
        kap2 = -0.5 * (kd1a + kd1b)
        kappa[p, 0] = kap1
        kappa[p, 1] = kap2
        gm[p, 0], gm[p, 1] = -0.5 * kd1a, -0.5 * kd2a
        gp[p, 0], gp[p, 1] = -0.5 * kd1b, -0.5 * kd2b
        ila = 1.0 / length[ea]
        ilb = 1.0 / length[eb]
        for q in range(3):
            a[p, q] = 0.5 * kb[p, q] * ila
            c[p, q] = 0.5 * kb[p, q] * ilb
        for q in range(3):
            q1 = (q + 1) % 3
            q2 = (q + 2) % 3
            tt = (ta[q] + tb[q]) / chi
            # t x m~ with m~ = (m^a + m^b) / chi, for t = tb (into A) and t = ta (into C)
            tb_m2 = (tb[q1] * (m2[ea, q2] + m2[eb, q2]) - tb[q2] * (m2[ea, q1] + m2[eb, q1])) / chi
            tb_m1 = (tb[q1] * (m1[ea, q2] + m1[eb, q2]) - tb[q2] * (m1[ea, q1] + m1[eb, q1])) / chi
            ta_m2 = (ta[q1] * (m2[ea, q2] + m2[eb, q2]) - ta[q2] * (m2[ea, q1] + m2[eb, q1])) / chi
            ta_m1 = (ta[q1] * (m1[ea, q2] + m1[eb, q2]) - ta[q2] * (m1[ea, q1] + m1[eb, q1])) / chi
            A[p, 0, q] = (-kap1 * tt + tb_m2) * ila
            A[p, 1, q] = (-kap2 * tt - tb_m1) * ila
            C[p, 0, q] = (-kap1 * tt - ta_m2) * ilb
            C[p, 1, q] = (-kap2 * tt + ta_m1) * ilb
        # twist: u = P m1^a (transport ta -> tb), angle(u, m1^b) about tb
        cab = chi - 1.0
        v0, v1, v2 = m1[ea, 0], m1[ea, 1], m1[ea, 2]
        bv = (bx * v0 + by * v1 + bz * v2) / chi
        u0 = cab * v0 + (by * v2 - bz * v1) + bx * bv
        u1 = cab * v1 + (bz * v0 - bx * v2) + by * bv
        u2 = cab * v2 + (bx * v1 - by * v0) + bz * bv
        w0, w1, w2 = m1[eb, 0], m1[eb, 1], m1[eb, 2]
        sn = (u1 * w2 - u2 * w1) * tb[0] + (u2 * w0 - u0 * w2) * tb[1] + (u0 * w1 - u1 * w0) * tb[2]
        cs = u0 * w0 + u1 * w1 + u2 * w2
        twist[p] = np.arctan2(sn, cs)


def der_strain_jacobian(points, offsets, m1, geometry=None):
    """Strains and their derivatives at every interior vertex (Bergou et al. 2010).

    m1 (E, 3): material d1 per edge (m2 = t x m1).  Returns a dict with
    kappa (I, 2), twist (I,), lengths (E,), t (E, 3), kb (I, 3) and
    A = d kappa / d e^{i-1}, C = d kappa / d e^i (I, 2, 3):
        d k1/d e^{i-1} = (-k1 t~ + t^i x m2~) / |e^{i-1}|,   d k1/d e^i = (-k1 t~ - t^{i-1} x m2~) / |e^i|
        d k2/d e^{i-1} = (-k2 t~ - t^i x m1~) / |e^{i-1}|,   d k2/d e^i = (-k2 t~ + t^{i-1} x m1~) / |e^i|
        with t~ = (t^{i-1} + t^i) / chi, m~ = (m^{i-1} + m^i) / chi;
    a = d m_i / d e^{i-1} = kb / (2 |e^{i-1}|), c = d m_i / d e^i = kb / (2 |e^i|) (I, 3);
    gm, gp = d kappa_i / d theta^{i-1}, d kappa_i / d theta^i = -1/2 (kb . m1^j, kb . m2^j) (I, 2).
    ``geometry``: :func:`discrete.edge_geometry` of ``points``, if already computed.
    """
    _, length, t = edge_geometry(points, offsets) if geometry is None else geometry
    m1 = np.ascontiguousarray(m1, dtype=np.float64)
    m2 = cross(t, m1)
    ia, _, _ = _pairs(offsets)
    n = len(ia)
    out = {"kappa": np.empty((n, 2)), "twist": np.empty(n), "kb": np.empty((n, 3)),
           "A": np.empty((n, 2, 3)), "C": np.empty((n, 2, 3)), "a": np.empty((n, 3)), "c": np.empty((n, 3)),
           "gm": np.empty((n, 2)), "gp": np.empty((n, 2))}
    _jacobian_kernel(t, length, m1, m2, ia, out["kappa"], out["twist"], out["kb"], out["A"], out["C"],
                     out["a"], out["c"], out["gm"], out["gp"])
    out["lengths"] = length
    out["t"] = t
    return out


def der_voronoi(rest_lengths, offsets):
    """D_i = (e~_{i-1} + e~_i) / 2, (V - 2S,)."""
    a, b, _ = _pairs(offsets)
    return 0.5 * (rest_lengths[a] + rest_lengths[b])


def der_energy(points, offsets, m1, rest_lengths, rest_kappa, rest_twist, material, *,
               stiffness_factor=None) -> float:
    """E = stretching + bending + twisting (module docstring), J.  ``stiffness_factor`` (S,): strand s
    has EA, EI, GJ multiplied by f_s (None: all ones)."""
    EA, EI, GJ = der_stiffness(material)
    fe, fi = _factor_arrays(offsets, stiffness_factor)
    J = der_strain_jacobian(points, offsets, m1)
    D = der_voronoi(rest_lengths, offsets)
    strain = J["lengths"] / rest_lengths - 1.0
    dk = J["kappa"] - rest_kappa
    dm = J["twist"] - rest_twist
    return float(0.5 * EA * np.sum(fe * strain**2 * rest_lengths)
                 + np.sum(fi * (EI * np.sum(dk**2, axis=1) + GJ * dm**2) / (2.0 * D)))


@numba.njit(cache=True)
def _assemble_kernel(t, A, C, a, c, gm, gp, e0, iv, ia, w, y, z, gx, gt):
    for j in range(len(e0)):
        for q in range(3):
            gx[e0[j] + 1, q] += w[j] * t[j, q]
            gx[e0[j], q] -= w[j] * t[j, q]
    for p in range(len(iv)):
        v = iv[p]
        for q in range(3):
            ga = A[p, 0, q] * y[p, 0] + A[p, 1, q] * y[p, 1] + a[p, q] * z[p]
            gc = C[p, 0, q] * y[p, 0] + C[p, 1, q] * y[p, 1] + c[p, q] * z[p]
            gx[v - 1, q] -= ga
            gx[v, q] += ga - gc
            gx[v + 1, q] += gc
        gt[ia[p]] += gm[p, 0] * y[p, 0] + gm[p, 1] * y[p, 1] - z[p]
        gt[ia[p] + 1] += gp[p, 0] * y[p, 0] + gp[p, 1] * y[p, 1] + z[p]


def der_assemble_gradient(J, offsets, w, y, z):
    """grad E = J^T s for stresses w (E,), y (I, 2), z (I,): returns (grad_x (V, 3), grad_theta (E,)).

    Edge j adds -w_j t^j to x_j and +w_j t^j to x_{j+1}; interior vertex i adds, with
    G_A = A_i^T y_i + a_i z_i and G_C = C_i^T y_i + c_i z_i, -G_A to x_{i-1}, G_A - G_C to x_i, G_C to
    x_{i+1}, gm_i . y_i - z_i to theta^{i-1} and gp_i . y_i + z_i to theta^i.
    """
    ia, _, iv = _pairs(offsets)
    gx = np.zeros((offsets[-1], 3))
    gt = np.zeros(len(w))
    _assemble_kernel(J["t"], J["A"], J["C"], J["a"], J["c"], J["gm"], J["gp"], edge_start_vertices(offsets),
                     iv, ia, np.ascontiguousarray(w, dtype=np.float64), np.ascontiguousarray(y, dtype=np.float64),
                     np.ascontiguousarray(z, dtype=np.float64), gx, gt)
    return gx, gt


def der_gradient(points, offsets, m1, rest_lengths, rest_kappa, rest_twist, material, J=None, *,
                 stiffness_factor=None):
    """(dE/dx (V, 3) N, dE/dtheta (E,) N m) of :func:`der_energy` (frames time-parallel transported).
    ``J``: a :func:`der_strain_jacobian` of the same state, to skip recomputing it;
    ``stiffness_factor`` (S,): per-strand factors on EA, EI, GJ (None: all ones)."""
    EA, EI, GJ = der_stiffness_arrays(material, offsets, stiffness_factor)
    J = der_strain_jacobian(points, offsets, m1) if J is None else J
    D = der_voronoi(rest_lengths, offsets)
    w = EA * (J["lengths"] / rest_lengths - 1.0)
    y = EI[:, None] * (J["kappa"] - rest_kappa) / D[:, None]
    z = GJ * (J["twist"] - rest_twist) / D
    return der_assemble_gradient(J, offsets, w, y, z)


@numba.njit(cache=True)
def _der_solve(f, tq, t, A, C, a, c, gm, gp, voff, eoff, ioff, w, y, z):
    """Back-substitution from the tip of the block-triangular system grad E = (f, tq) (module doc).

    Step k (vertex x_k and edge theta^{k-1}, k = n..2) solves for (w_{k-1}, y_{k-1}, z_{k-1}):
      w t^{k-1} + C_{k-1}^T y + c_{k-1} z = f_k + w_k t^k - (A_k - C_k)^T y_k - (a_k - c_k) z_k
                                            + A_{k+1}^T y_{k+1} + a_{k+1} z_{k+1}
      gp_{k-1} . y + z                    = tq_{k-1} - gm_k . y_k + z_k
    by eliminating z = r2 - gp . y and a 3x3 Cramer solve of [t | C_0 - c gp_0 | C_1 - c gp_1].
    Returns the smallest normalised pivot |det| / (|u1| |u2|) met (0 = singular).
    """
    mindet = np.inf
    r = np.empty(3)
    u0 = np.empty(3)
    u1 = np.empty(3)
    u2 = np.empty(3)
    for s in range(len(voff) - 1):
        v0, e0, i0 = voff[s], eoff[s], ioff[s]
        n = eoff[s + 1] - e0
        w[e0] = 0.0
        for k in range(n, 1, -1):
            for q in range(3):
                r[q] = f[v0 + k, q]
            r2 = tq[e0 + k - 1]
            if k < n:
                p = i0 + k - 1          # interior vertex k
                for q in range(3):
                    r[q] += (w[e0 + k] * t[e0 + k, q]
                             - (A[p, 0, q] - C[p, 0, q]) * y[p, 0] - (A[p, 1, q] - C[p, 1, q]) * y[p, 1]
                             - (a[p, q] - c[p, q]) * z[p])
                r2 += z[p] - gm[p, 0] * y[p, 0] - gm[p, 1] * y[p, 1]
            if k + 1 < n:
                p = i0 + k              # interior vertex k + 1
                for q in range(3):
                    r[q] += A[p, 0, q] * y[p, 0] + A[p, 1, q] * y[p, 1] + a[p, q] * z[p]
            p = i0 + k - 2              # interior vertex k - 1 carries the unknowns
            je = e0 + k - 1
            for q in range(3):
                u0[q] = t[je, q]
                u1[q] = C[p, 0, q] - c[p, q] * gp[p, 0]
                u2[q] = C[p, 1, q] - c[p, q] * gp[p, 1]
                r[q] -= c[p, q] * r2
            x0 = u1[1] * u2[2] - u1[2] * u2[1]      # u1 x u2
            x1 = u1[2] * u2[0] - u1[0] * u2[2]
            x2 = u1[0] * u2[1] - u1[1] * u2[0]
            y0 = u2[1] * u0[2] - u2[2] * u0[1]      # u2 x u0
            y1 = u2[2] * u0[0] - u2[0] * u0[2]
            y2 = u2[0] * u0[1] - u2[1] * u0[0]
            z0 = u0[1] * u1[2] - u0[2] * u1[1]      # u0 x u1
            z1 = u0[2] * u1[0] - u0[0] * u1[2]
            z2 = u0[0] * u1[1] - u0[1] * u1[0]
            det = u0[0] * x0 + u0[1] * x1 + u0[2] * x2
            scale = np.sqrt((u1[0] ** 2 + u1[1] ** 2 + u1[2] ** 2) * (u2[0] ** 2 + u2[1] ** 2 + u2[2] ** 2))
            mindet = min(mindet, abs(det) / scale)
            w[je] = (r[0] * x0 + r[1] * x1 + r[2] * x2) / det
            y[p, 0] = (r[0] * y0 + r[1] * y1 + r[2] * y2) / det
            y[p, 1] = (r[0] * z0 + r[1] * z1 + r[2] * z2) / det
            z[p] = r2 - gp[p, 0] * y[p, 0] - gp[p, 1] * y[p, 1]
    return mindet


def der_residual(points, offsets, m1, rest_lengths, rest_kappa, rest_twist, material, f, tq=None,
                 tension=None, J=None, *, stiffness_factor=None):
    """Free-dof residual of grad E = f_ext (clamped root: x_0, x_1, theta^0 excluded).

    ``tension`` (E,) adds constraint forces sum_j tension_j d|e^j|/dx (inextensible rods);
    ``stiffness_factor`` (S,): per-strand factors on EA, EI, GJ (None: all ones).

    Returns {"force_rel": ||dE/dx - f|| / ||f||, "torque_rel": ||dE/dtheta - tq|| / (||f|| L_mean),
    "per_strand_max": max over strands of the per-strand force_rel}.
    """
    gx, gt = der_gradient(points, offsets, m1, rest_lengths, rest_kappa, rest_twist, material, J,
                          stiffness_factor=stiffness_factor)
    if tension is not None:
        e0 = edge_start_vertices(offsets)
        wt = tension[:, None] * (points[e0 + 1] - points[e0]) / np.linalg.norm(
            points[e0 + 1] - points[e0], axis=1)[:, None]
        np.add.at(gx, e0 + 1, wt)
        np.add.at(gx, e0, -wt)
    tq = np.zeros(len(gt)) if tq is None else tq
    free_v = np.ones(offsets[-1], dtype=bool)
    free_v[offsets[:-1]] = False
    free_v[offsets[:-1] + 1] = False
    eoff = edge_offsets(offsets)
    free_e = np.ones(len(gt), dtype=bool)
    free_e[eoff[:-1]] = False
    rx = np.where(free_v[:, None], gx - f, 0.0)
    rt = np.where(free_e, gt - tq, 0.0)
    fn = np.linalg.norm(f[free_v])
    lmean = float(np.mean(rest_lengths))
    S = len(offsets) - 1
    sid = np.repeat(np.arange(S), np.diff(offsets))
    num = np.bincount(sid, np.sum(rx**2, axis=1), S)
    den = np.bincount(sid, np.where(free_v, np.sum(f**2, axis=1), 0.0), S)
    per = np.sqrt(num / np.maximum(den, 1e-300))
    return {
        "force_rel": float(np.linalg.norm(rx) / max(fn, 1e-300)),
        "torque_rel": float(np.linalg.norm(rt) / max(fn * lmean, 1e-300)),
        "per_strand_max": float(per.max()),
    }


def der_rest_data(points, offsets, material, gravity, point_forces=None, segments=None, *,
                  point_force_at: str = "arc_length", root_normal=None, stretching: str = "stiff",
                  mass_iterations: int = 3, rod: dict | None = None, stiffness_factor=None) -> dict:
    """Rest lengths, rest material curvatures and rest twists making the groom a DER equilibrium.

    Arguments as :func:`groomtool.rods.cosserat.cosserat_rest_data`.  ``stretching="stiff"`` solves
    the rest lengths (stretch energy EA/2 (|e|/e~ - 1)^2 e~) and computes vertex masses
    rho S (e~_{i-1} + e~_i) / 2 from them (a fixed point, ``mass_iterations`` passes; the change is
    ~1e-6 relative); ``"inextensible"`` keeps e~ = groomed lengths and reports the edge tensions
    ``der_tension`` (the constraint forces) instead.  ``stiffness_factor``: None, or (S,) positive
    finite factors f_s: strand s is solved with moduli f_s E, f_s G (EA, EI, GJ times f_s, so
    e~ = |e| / (1 + w / (f_s EA)), kappa~ = kappa - D y / (f_s EI), m~ = m - D z / (f_s GJ)).

    Returns rod_points (V', 3), rod_offsets (S + 1,), der_rest_lengths (E,) m, der_rest_kappa
    (V' - 2S, 2) (dimensionless, integrated over D_i), der_rest_twist (V' - 2S,) rad (integrated),
    der_voronoi_lengths (V' - 2S,) m, der_frames (E, 3, 3) rows m1, m2, t (theta = 0), der_tension
    (E,) N, der_vertex_mass (V',) kg, node_forces (V', 3) N, and a ``der_residual`` dict.
    """
    if stretching not in ("stiff", "inextensible"):
        raise ValueError(f"stretching must be 'stiff' or 'inextensible', got {stretching!r}")
    rod = prepare_rods(points, offsets, segments, root_normal) if rod is None else rod
    rod_points, rod_offsets, rod_arc = rod["rod_points"], rod["rod_offsets"], rod["rod_arc"]
    geometry, frames = rod["geometry"], rod["frames"]
    EA, EI, GJ = der_stiffness_arrays(material, rod_offsets, stiffness_factor)   # per edge / interior vertex
    m1 = np.ascontiguousarray(frames[:, 0])
    J = der_strain_jacobian(rod_points, rod_offsets, m1, geometry)
    length = J["lengths"]
    g = np.asarray(gravity, np.float64).reshape(3)
    Fp = point_force_nodes(point_forces, rod_offsets, rod_arc, point_force_at)
    eoff, ioff = edge_offsets(rod_offsets), interior_offsets(rod_offsets)
    w = np.zeros(len(length))
    y = np.zeros((len(J["kappa"]), 2))
    z = np.zeros(len(J["kappa"]))
    tq = np.zeros(len(length))
    rest_len = length.copy()
    args = [np.ascontiguousarray(J[k]) for k in ("t", "A", "C", "a", "c", "gm", "gp")]
    for _ in range(max(1, mass_iterations) if stretching == "stiff" else 1):
        mass = lumped_masses(rest_len, rod_offsets, material.linear_density)
        F = mass[:, None] * g + Fp
        mindet = _der_solve(F, tq, *args, rod_offsets, eoff, ioff, w, y, z)
        if stretching == "stiff":
            rest_len = length / (1.0 + w / EA)
            rest_len[eoff[:-1]] = length[eoff[:-1]]   # the clamped first edge carries no stretch
    if not (mindet > 1e-12 and np.all(np.isfinite(w)) and np.all(np.isfinite(y))):
        raise RestDataError(f"DER system singular (smallest normalised pivot {mindet:.1e}): a near-folded edge pair")
    D = der_voronoi(rest_len, rod_offsets)
    rest_kappa = J["kappa"] - D[:, None] * y / EI[:, None]
    rest_twist = J["twist"] - D * z / GJ
    mass = lumped_masses(rest_len, rod_offsets, material.linear_density)
    F = mass[:, None] * g + Fp
    residual = der_residual(rod_points, rod_offsets, m1, rest_len, rest_kappa, rest_twist, material, F,
                            tension=None if stretching == "stiff" else w, J=J, stiffness_factor=stiffness_factor)
    residual["min_pivot"] = float(mindet)
    return {
        "rod_points": rod_points,
        "rod_offsets": rod_offsets,
        "der_rest_lengths": rest_len,
        "der_rest_kappa": rest_kappa,
        "der_rest_twist": rest_twist,
        "der_voronoi_lengths": D,
        "der_frames": frames,
        "der_tension": w,
        "der_vertex_mass": mass,
        "node_forces": F,
        "der_residual": residual,
    }

