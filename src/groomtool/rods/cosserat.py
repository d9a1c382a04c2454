"""Rest data for Cosserat rods in PyElastica's (1.0) discretisation, solved at the rod's own nodes.

PyElastica's discrete rod (Gazzola et al. 2018, ``elastica/rod/cosserat_rod.py``), n elements,
n + 1 nodes, n - 1 Voronoi nodes, everything static (velocities zero, dilatations e = eps = 1):

* directors Q_k (rows d1, d2, d3) per element; strains are in the material frame;
* shear/stretch sigma_k = e_k Q_k t_k - e3, internal stress n_k = S (sigma_k - sigma0_k),
  S = diag(alpha G A, alpha G A, E A), alpha = 27/28; nodal internal force = Delta(Q^T n / e);
* curvature kappa_j = log(Q_{j+1} Q_j^T)-axis / D^_j, with PyElastica's sign: the rotation vector
  taking frame j to frame j + 1, in frame j's components, over the *rest* Voronoi length
  D^_j = (l^_j + l^_{j+1}) / 2; internal couple tau_j = B (kappa_j - kappa0_j), B = diag(EI, EI, GJ)
  (length-weighted average of the two elements' B, no Voronoi length inside);
* element torque  Delta(tau)_k + A(kappa x tau D^)_k + (Q_k t_k x n_k) l^_k + external = 0, where
  Delta(a)_k = a_k - a_{k-1} and A(a)_k = (a_k + a_{k-1}) / 2 with a_{-1} = a_{n-1} = 0.

Inverse problem (clamped root: node 0 and element 0 fixed).  Force balance at nodes 1..n gives
N_k = Q_k^T n_k = sum_{v > k} F_v (the load beyond element k).  With d3 = unit chord and rest
lengths = groomed lengths, sigma_k = 0, so the transverse part of N_k can only be carried by a rest
shear: sigma0_k = -S^-1 Q_k N_k (exported as ``cosserat_rest_sigma``, a few 1e-6 for hair).
Torque balance of elements n-1..1, solved from the tip:

    (I - [w_{k-1}]x) tau_{k-1} = tau_k + (D^_k / 2) kappa_k x tau_k + (e3 x n_k) l^_k,
    w_{k-1} = (D^_{k-1} / 2) kappa_{k-1},   (I - [w]x)^-1 r = (r + w x r + w (w . r)) / (1 + |w|^2)

and kappa0_j = kappa_j - B^-1 tau_j.  This is exact for PyElastica's equations (residual at round-off).
The continuum shortcut kappa0 = kappa - B^-1 m(moment of the loads beyond) differs at O(edge length).
"""

from __future__ import annotations

import numba
import numpy as np

from .discrete import edge_offsets, interior_offsets, matvec, node_forces, prepare_rods, strand_stiffness_factors

SHEAR_ALPHA = 27.0 / 28.0  # PyElastica's Timoshenko shear correction (Kaneko 1975, nu = 0.5)


def cosserat_stiffness(material):
    """(B (3,), S (3,)): bend/twist diag(EI, EI, GJ) and shear/stretch diag(aGA, aGA, EA), J = 2I."""
    A, I = material.area, material.second_moment
    B = np.array([material.young_modulus * I, material.young_modulus * I, material.G * 2.0 * I])
    S = np.array([SHEAR_ALPHA * material.G * A, SHEAR_ALPHA * material.G * A, material.young_modulus * A])
    return B, S


@numba.njit(cache=True)
def _inv_rotate_pairs(Q, ia, rest_vor, kappa):
    """PyElastica's ``_inv_rotate`` for the element pairs (ia[p], ia[p] + 1), over D^_p."""
    R = np.empty((3, 3))
    for p in range(len(ia)):
        qa = Q[ia[p]]
        qb = Q[ia[p] + 1]
        for i in range(3):
            for j in range(3):
                R[i, j] = qb[i, 0] * qa[j, 0] + qb[i, 1] * qa[j, 1] + qb[i, 2] * qa[j, 2]
        trace = min(max(R[0, 0] + R[1, 1] + R[2, 2], -1.0), 3.0)
        theta = np.arccos(0.5 * trace - 0.5) + 1e-14
        mag = -0.5 * theta / np.sin(theta) / rest_vor[p]
        kappa[p, 0] = (R[2, 1] - R[1, 2]) * mag
        kappa[p, 1] = (R[0, 2] - R[2, 0]) * mag
        kappa[p, 2] = (R[1, 0] - R[0, 1]) * mag


def pyelastica_kappa(directors: np.ndarray, rest_voronoi: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """kappa_j = -theta / (2 sin theta) axial(R - R^T) / D^_j with R = Q_{j+1} Q_j^T and
    theta = arccos((tr R - 1) / 2) + 1e-14: PyElastica's ``_inv_rotate`` (same floating-point path),
    i.e. the rotation vector from frame j to frame j + 1 in frame j's components.  Returns (I, 3)."""
    ia = _interior_edge_pairs(offsets)
    kappa = np.empty((len(ia), 3))
    _inv_rotate_pairs(np.ascontiguousarray(directors), ia, np.ascontiguousarray(rest_voronoi), kappa)
    return kappa


def _interior_edge_pairs(offsets: np.ndarray) -> np.ndarray:
    """Global index a of the root-side edge of every interior vertex (its edges are a, a + 1)."""
    eoff = edge_offsets(offsets)
    keep = np.ones(eoff[-1], dtype=bool)
    keep[eoff[1:] - 1] = False
    return np.flatnonzero(keep)


def voronoi_lengths(lengths: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """D_i = (l_{i-1} + l_i) / 2 at every interior vertex, (V - 2S,)."""
    idx = _interior_edge_pairs(offsets)
    return 0.5 * (lengths[idx] + lengths[idx + 1])


@numba.njit(cache=True)
def _cosserat_statics(F, Q, kappa, rest_len, rest_vor, voff, eoff, ioff, n_out, tau_out):
    """Per strand, from the tip: n_k = Q_k sum_{v > k} F_v, then the torque recurrence (module doc)."""
    for s in range(len(voff) - 1):
        v0, e0, i0 = voff[s], eoff[s], ioff[s]
        ne = eoff[s + 1] - e0
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for k in range(ne - 1, -1, -1):
            a0 += F[v0 + k + 1, 0]
            a1 += F[v0 + k + 1, 1]
            a2 += F[v0 + k + 1, 2]
            for r in range(3):
                n_out[e0 + k, r] = Q[e0 + k, r, 0] * a0 + Q[e0 + k, r, 1] * a1 + Q[e0 + k, r, 2] * a2
        for k in range(ne - 1, 0, -1):
            r0 = 0.0
            r1 = 0.0
            r2 = 0.0
            if k <= ne - 2:
                j = i0 + k
                t0, t1, t2 = tau_out[j, 0], tau_out[j, 1], tau_out[j, 2]
                h = 0.5 * rest_vor[j]
                k0, k1, k2 = kappa[j, 0], kappa[j, 1], kappa[j, 2]
                r0 = t0 + h * (k1 * t2 - k2 * t1)
                r1 = t1 + h * (k2 * t0 - k0 * t2)
                r2 = t2 + h * (k0 * t1 - k1 * t0)
            lk = rest_len[e0 + k]
            r0 -= n_out[e0 + k, 1] * lk          # e3 x n = (-n_y, n_x, 0)
            r1 += n_out[e0 + k, 0] * lk
            j = i0 + k - 1
            h = 0.5 * rest_vor[j]
            w0, w1, w2 = h * kappa[j, 0], h * kappa[j, 1], h * kappa[j, 2]
            wr = w0 * r0 + w1 * r1 + w2 * r2
            den = 1.0 + w0 * w0 + w1 * w1 + w2 * w2
            tau_out[j, 0] = (r0 + (w1 * r2 - w2 * r1) + w0 * wr) / den
            tau_out[j, 1] = (r1 + (w2 * r0 - w0 * r2) + w1 * wr) / den
            tau_out[j, 2] = (r2 + (w0 * r1 - w1 * r0) + w2 * wr) / den


@numba.njit(cache=True)
def _residual_kernel(x, Q, kappa, rest_kappa, rest_sigma, rest_len, rest_vor, B, Sd, fac, voff, eoff, ioff,
                     fres, tres):
    """B (3,), Sd (3,): the material's stiffnesses; strand s uses fac[s] B and fac[s] Sd."""
    e = np.empty(3)
    bs = np.empty(3)
    ss = np.empty(3)
    n = np.empty(3)
    qt = np.empty(3)
    ta = np.empty(3)
    v = np.empty(3)
    for s in range(len(voff) - 1):
        v0, e0, i0 = voff[s], eoff[s], ioff[s]
        ne = eoff[s + 1] - e0
        for r in range(3):
            bs[r] = B[r] * fac[s]
            ss[r] = Sd[r] * fac[s]
        for k in range(ne):
            je = e0 + k
            va = v0 + k
            for r in range(3):
                e[r] = x[va + 1, r] - x[va, r]
            le = np.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2)
            for r in range(3):
                qe = Q[je, r, 0] * e[0] + Q[je, r, 1] * e[1] + Q[je, r, 2] * e[2]
                sig = qe / rest_len[je] - (1.0 if r == 2 else 0.0)      # sigma = Q e / l^ - e3
                n[r] = ss[r] * (sig - rest_sigma[je, r])                # n = S (sigma - sigma0)
                qt[r] = qe / le
            for c in range(3):
                Nc = Q[je, 0, c] * n[0] + Q[je, 1, c] * n[1] + Q[je, 2, c] * n[2]   # Q^T n
                fres[va, c] += Nc                                       # Delta(Q^T n)
                fres[va + 1, c] -= Nc
            tres[je, 0] += (qt[1] * n[2] - qt[2] * n[1]) * rest_len[je]  # (Q t x n) l^
            tres[je, 1] += (qt[2] * n[0] - qt[0] * n[2]) * rest_len[je]
            tres[je, 2] += (qt[0] * n[1] - qt[1] * n[0]) * rest_len[je]
        for k in range(ne - 1):
            j = i0 + k
            for r in range(3):
                ta[r] = bs[r] * (kappa[j, r] - rest_kappa[j, r])       # tau = B (kappa - kappa0)
            h = 0.5 * rest_vor[j]
            v[0] = h * (kappa[j, 1] * ta[2] - kappa[j, 2] * ta[1])      # (kappa x tau) D^ / 2
            v[1] = h * (kappa[j, 2] * ta[0] - kappa[j, 0] * ta[2])
            v[2] = h * (kappa[j, 0] * ta[1] - kappa[j, 1] * ta[0])
            for r in range(3):
                tres[e0 + k, r] += ta[r] + v[r]                          # Delta(tau), A(.)
                tres[e0 + k + 1, r] += -ta[r] + v[r]
        for c in range(3):
            fres[v0, c] = 0.0
            tres[e0, c] = 0.0


def cosserat_static_residual(rod_points, rod_offsets, directors, rest_kappa, rest_sigma, rest_lengths,
                             forces, material, kappa=None, *, stiffness_factor=None):
    """PyElastica's static force and torque balance, re-evaluated term by term (independent of the
    solve; ``kappa`` = :func:`pyelastica_kappa` of the same directors, to skip recomputing it):

        force on node v:      F_v + Delta(Q^T n)_v,             n = S (Q e / l^ - e3 - sigma0)
        torque on element k:  Delta(tau)_k + A(kappa x tau D^)_k + (Q_k t_k x n_k) l^_k

    ``stiffness_factor`` (S,): strand s has moduli f_s E, f_s G, i.e. B and S multiplied by f_s
    (None: all ones, see :func:`cosserat_rest_data`).

    Returns (force residual (V, 3), torque residual (E, 3)) with the clamped node 0 and element 0 of
    every strand zeroed; a solved export makes both vanish to round-off.
    """
    B, Sd = cosserat_stiffness(material)
    fac = strand_stiffness_factors(stiffness_factor, len(rod_offsets) - 1)
    rest_vor = voronoi_lengths(rest_lengths, rod_offsets)
    kappa = pyelastica_kappa(directors, rest_vor, rod_offsets) if kappa is None else kappa
    fres = np.array(forces, dtype=np.float64, copy=True)
    tres = np.zeros((len(rest_lengths), 3))
    _residual_kernel(np.ascontiguousarray(rod_points), np.ascontiguousarray(directors), kappa,
                     np.ascontiguousarray(rest_kappa), np.ascontiguousarray(rest_sigma), rest_lengths, rest_vor,
                     B, Sd, fac, rod_offsets, edge_offsets(rod_offsets), interior_offsets(rod_offsets), fres, tres)
    return fres, tres


def cosserat_rest_data(points, offsets, material, gravity, point_forces=None, segments=None, *,
                       point_force_at: str = "arc_length", root_normal=None, rod: dict | None = None,
                       stiffness_factor=None) -> dict:
    """Rest data making the groomed polyline an exact static equilibrium of PyElastica's rod.

    points (V, 3) m, offsets (S + 1,); gravity (3,) m/s^2; point_forces = (strand (K,), where (K,),
    force (K, 3) N) with ``where`` an arc length along the input polyline (``point_force_at=
    "arc_length"``) or a rod-node index (``"node"``), see :func:`discrete.point_force_nodes`;
    segments: None keeps the input vertices, N resamples every strand to N equal-arc-length edges.
    stiffness_factor: None, or (S,) positive finite factors f_s: strand s is solved with Young's and
    shear moduli f_s E and f_s G (B and S multiplied by f_s, so its rest strains follow from
    kappa0 = kappa - (f_s B)^-1 tau and sigma0 = sigma - (f_s S)^-1 n); None = all ones.

    Returns rod_points (V', 3), rod_offsets (S + 1,), cosserat_directors (E, 3, 3) rows d1 d2 d3,
    cosserat_rest_kappa (V' - 2S, 3) 1/m, cosserat_rest_sigma (E, 3), cosserat_rest_lengths (E,) m,
    cosserat_rest_voronoi_lengths (V' - 2S,) m, node_forces (V', 3) N (the loads solved for, gravity
    on lumped masses + point loads), node_mass (V',) kg, cosserat_internal_stress (E, 3) N and
    cosserat_internal_couple (V' - 2S, 3) N m (material frame), cosserat_stiffness_factor (S,) (the
    factors solved with, read by :func:`pyelastica_rod`) and a ``cosserat_residual`` dict.
    """
    rod = prepare_rods(points, offsets, segments, root_normal) if rod is None else rod
    rod_points, rod_offsets, rod_arc = rod["rod_points"], rod["rod_offsets"], rod["rod_arc"]
    e, rest_len, _ = rod["geometry"]
    Q = rod["frames"]
    fac = strand_stiffness_factors(stiffness_factor, len(rod_offsets) - 1)
    B, Sd = cosserat_stiffness(material)
    rest_vor = voronoi_lengths(rest_len, rod_offsets)
    kappa = pyelastica_kappa(Q, rest_vor, rod_offsets)
    F, mass = node_forces(rod_points, rod_offsets, rod_arc, rest_len, material, gravity, point_forces,
                          point_force_at)
    eoff, ioff = edge_offsets(rod_offsets), interior_offsets(rod_offsets)
    n = np.zeros((len(rest_len), 3))
    tau = np.zeros((len(kappa), 3))
    _cosserat_statics(F, Q, kappa, rest_len, rest_vor, rod_offsets, eoff, ioff, n, tau)
    sigma = matvec(Q, e) / rest_len[:, None] - np.array([0.0, 0.0, 1.0])
    # strand s: B_s = f_s B at its Voronoi nodes, S_s = f_s S at its elements
    Sd_e = Sd[None, :] * np.repeat(fac, np.diff(eoff))[:, None]
    B_i = B[None, :] * np.repeat(fac, np.diff(ioff))[:, None]
    rest_sigma = sigma - n / Sd_e
    rest_kappa = kappa - tau / B_i
    fres, tres = cosserat_static_residual(rod_points, rod_offsets, Q, rest_kappa, rest_sigma, rest_len,
                                          F, material, kappa, stiffness_factor=fac)
    free = np.ones(len(F), dtype=bool)
    free[rod_offsets[:-1]] = False
    moment_scale = np.linalg.norm(n[:, :2] * rest_len[:, None])     # |e3 x n| l^
    residual = {
        "force_rel": float(np.linalg.norm(fres) / max(np.linalg.norm(F[free]), 1e-300)),
        "torque_rel": float(np.linalg.norm(tres) / max(moment_scale, 1e-300)),
        "max_rest_sigma": float(np.abs(rest_sigma).max()),
    }
    return {
        "rod_points": rod_points,
        "rod_offsets": rod_offsets,
        "cosserat_directors": Q,
        "cosserat_rest_kappa": rest_kappa,
        "cosserat_rest_sigma": rest_sigma,
        "cosserat_rest_lengths": rest_len,
        "cosserat_rest_voronoi_lengths": rest_vor,
        "node_forces": F,
        "node_mass": mass,
        "cosserat_internal_stress": n,
        "cosserat_internal_couple": tau,
        "cosserat_stiffness_factor": fac,
        "cosserat_residual": residual,
    }


def pyelastica_rod(data: dict, strand: int, material, *, inertia_scale: float = 1.0,
                   rest_sigma: bool = True, stiffness_factor: float | None = None):
    """Build ``elastica.CosseratRod`` for one strand of :func:`cosserat_rest_data` output.

    Positions, directors, rest_kappa, rest_sigma (zero if ``rest_sigma=False``) go in as given; the
    rest lengths follow from the positions (PyElastica computes them).  Young's and shear moduli are
    f material.young_modulus and f material.G, with f = ``stiffness_factor`` if given, else the
    strand's ``data["cosserat_stiffness_factor"]`` (the factor its rest data was solved with), else 1.
    ``inertia_scale`` multiplies the mass second moment of inertia: it changes the rotational
    dynamics only (not the equilibrium) and lifts the explicit-step limit set by shear-rotation
    modes, omega^2 ~ 4 alpha G / (rho r^2 inertia_scale).
    """
    import elastica as ea

    if stiffness_factor is None:
        stored = data.get("cosserat_stiffness_factor")
        stiffness_factor = 1.0 if stored is None else float(stored[strand])
    f = float(stiffness_factor)
    if not (np.isfinite(f) and f > 0.0):
        raise ValueError(f"stiffness_factor must be positive and finite, got {stiffness_factor}")
    off = data["rod_offsets"]
    v0, v1 = int(off[strand]), int(off[strand + 1])
    e0, e1 = v0 - strand, v1 - strand - 1
    i0, i1 = v0 - 2 * strand, v1 - 2 * strand - 2
    pos = np.ascontiguousarray(data["rod_points"][v0:v1].T)
    dirs = np.ascontiguousarray(np.moveaxis(data["cosserat_directors"][e0:e1], 0, -1))
    kappa0 = np.ascontiguousarray(data["cosserat_rest_kappa"][i0:i1].T)
    sigma0 = np.ascontiguousarray(data["cosserat_rest_sigma"][e0:e1].T)
    if not rest_sigma:
        sigma0 = np.zeros_like(sigma0)
    n = e1 - e0
    length = float(np.sum(data["cosserat_rest_lengths"][e0:e1]))
    rod = ea.CosseratRod.straight_rod(
        n, pos[:, 0].copy(), dirs[2, :, 0].copy(), dirs[0, :, 0].copy(), length, material.radius,
        material.density, youngs_modulus=f * material.young_modulus, shear_modulus=f * material.G,
        position=pos, directors=dirs, rest_kappa=kappa0, rest_sigma=sigma0,
    )
    if inertia_scale != 1.0:
        rod.mass_second_moment_of_inertia *= inertia_scale
        rod.inv_mass_second_moment_of_inertia /= inertia_scale
    return rod
