"""The strand-split ADMM's strand systems for Super-Helices in O(elements + ends) (issue 16; docs/solvers.md
section 12): the x-step of admm.py without a dense n_s x n_s factor per strand.

An end e is one side of a contact on a strand: the point x_e = C(s_e) on element b = b(e) of strand s, the
contact frame F_e (rows e_N, e_T1, e_T2) and sigma_e = +1 on side a, -1 on side b (a self-contact gives two
ends, one per point).  Its rows of H over the elements k of its strand are (contact/operator.py)

    J_e,k = P_e G_k (k < b),     J_e,b = O_e = sigma_e F_e R_b D_b(t_e),     J_e,k = 0 (k > b),
    P_e = sigma_e F_e [-[x_e - c_s]x, I]  (3 x 6),     G_k = [Theta_k; B_k - [c_s]x Theta_k]  (6 x 3),

B_k = R_k D_k + [C_{k+1}]x Theta_k (superhelix.upstream_jacobian_terms), c_s the strand's root (an origin that
keeps both factors of the size of the strand).  So M_s = D_s^-1 + sum_e J_e^T J_e / rho_e has the block form of
groomtool.semiseparable with r = 6:

    M_kj = later_k^T earlier_j (k > j),   earlier_j = G_j,
    later_k = S_{>k} G_k + sum_{b(e)=k} P_e^T O_e / rho_e,     S_{>k} = sum_{b(e)>k} P_e^T P_e / rho_e  (6 x 6),
    M_kk = D_k^-1 + G_k^T S_{>k} G_k + sum_{b(e)=k} O_e^T O_e / rho_e,

factored in O(E r^2) (semiseparable.factor_strand) and solved in O(E r).  The gather J_s^T w and the scatter
J_e t are contact/jacobian.point_forces_generalized and contact/operator.point_velocities on the ends' points
(their suffix and prefix sums along the strand).  The contacts' W_ii = H_i D H_i^T + 2 gamma I (for rho) come
from the prefix sums Pi_k = sum_{j<k} G_j D_j G_j^T: J_e D J_e^T = P_e Pi_b P_e^T + O_e D_b O_e^T, and for the
two ends of a self-contact (b(e1) <= b(e2)) the cross term J_e2 D J_e1^T = P_e2 V_e1 when b(e2) > b(e1), with
V_e1 = Pi_b1 P_e1^T + G_b1 D_b1 O_e1^T, else P_e2 Pi_b P_e1^T + O_e2 D_b O_e1^T.

Memory: 72 numbers per element (G, later, diag, the factor's L and W) and ~50 per end, instead of n_s^2 per strand
(harolongo with all contacts: ~0.2 GB against 1.25 GB of dense factors).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..contact.jacobian import point_forces_generalized
from ..contact.operator import point_velocities
from ..rods import superhelix as sh
from ..semiseparable import factor_strand, solve_strand


@dataclass
class HelixContacts:
    """What the structured x-step needs beyond a ContactProblem: the Super-Helix groom, its contacts (those H was
    built from: contact/jacobian.contact_jacobian(helix, contacts, kin)) and the kinematics (computed when None)."""

    helix: sh.SuperHelix
    contacts: object
    kin: sh.Kinematics | None = None


def applies(problem, geometry: HelixContacts | None) -> bool:
    """Whether the structured split serves ``problem``: a Super-Helix geometry whose strands and contacts are the
    problem's, and a diagonal D (the clothoid's dense D blocks keep admm.StrandSplit)."""
    if geometry is None or not isinstance(geometry.helix, sh.SuperHelix) or not np.all(problem.D_is_diag):
        return False
    helix = geometry.helix
    return (problem.n_strands == helix.n_strands and problem.n_contacts == len(geometry.contacts.strand_a)
            and np.array_equal(np.asarray(problem.dof_offsets, dtype=np.int64), 3 * helix.flat_offsets()))


def helix_ends(helix: sh.SuperHelix, contacts):
    """The ends, contact-major and by strand within a contact (admm.StrandSplit's order for contacts on two
    strands; a self-contact: side a, then side b): (cend_ptr (m + 1,), end_contact, end_strand, end_arc, sign)
    (E,) each.  A side on the head or on a strand without elements has no end."""
    sa = np.asarray(contacts.strand_a, dtype=np.int64)
    sb = np.asarray(contacts.strand_b, dtype=np.int64)
    m = len(sa)
    n_el = helix.n_elements
    has_a = n_el[sa] > 0
    has_b = (sb >= 0) & (n_el[np.maximum(sb, 0)] > 0)
    first_a = has_a & ~(has_b & (sb < sa))
    count = has_a.astype(np.int64) + has_b
    cend_ptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(count, out=cend_ptr[1:])
    end_contact = np.repeat(np.arange(m, dtype=np.int64), count)
    second = np.arange(len(end_contact)) > cend_ptr[end_contact]
    is_a = np.where(second, ~first_a[end_contact], first_a[end_contact])
    end_strand = np.ascontiguousarray(np.where(is_a, sa[end_contact], sb[end_contact]))
    end_arc = np.where(is_a, np.asarray(contacts.s_a)[end_contact], np.asarray(contacts.s_b)[end_contact])
    return cend_ptr, end_contact, end_strand, np.ascontiguousarray(end_arc, dtype=np.float64), \
        np.where(is_a, 1.0, -1.0)


@njit(cache=True)
def _rigid_rows(sF, x, root, P):
    """P_e = sF_e [-[x_e - c]x, I] (3 x 6) per end, c its strand's root (root (E, 3))."""
    for e in range(sF.shape[0]):
        d0 = x[e, 0] - root[e, 0]
        d1 = x[e, 1] - root[e, 1]
        d2 = x[e, 2] - root[e, 2]
        for a in range(3):
            f0, f1, f2 = sF[e, a, 0], sF[e, a, 1], sF[e, a, 2]
            # row a of sF times -[d]x: f^T (-(d x u)) = u . (d x f)
            P[e, a, 0] = d1 * f2 - d2 * f1
            P[e, a, 1] = d2 * f0 - d0 * f2
            P[e, a, 2] = d0 * f1 - d1 * f0
            P[e, a, 3] = f0
            P[e, a, 4] = f1
            P[e, a, 5] = f2


@njit(cache=True)
def _generators(strands, offsets, strand_ptr, elem, P, O, rho, G, d_inv, diag, later):
    """diag_k and later_k (module docstring) of the elements of ``strands``, from the tip: S_{>k} (6 x 6) summed
    over the ends beyond element k (the ends' elem, P, O, rho in strand order: by strand, then element)."""
    S6 = np.zeros((6, 6))
    SG = np.zeros((6, 3))
    for q in range(strands.shape[0]):
        s = strands[q]
        e0 = offsets[s]
        S6[:] = 0.0
        p = strand_ptr[s + 1] - 1
        for k in range(offsets[s + 1] - e0 - 1, -1, -1):
            j = e0 + k
            for a in range(6):
                for c in range(3):
                    acc = 0.0
                    for b in range(6):
                        acc += S6[a, b] * G[j, b, c]
                    SG[a, c] = acc
                    later[j, a, c] = acc
            for c in range(3):
                for d in range(3):
                    acc = d_inv[j, c] if c == d else 0.0
                    for a in range(6):
                        acc += G[j, a, c] * SG[a, d]
                    diag[j, c, d] = acc
            while p >= strand_ptr[s] and elem[p] == k:
                e = p
                ir = 1.0 / rho[e]
                for a in range(6):
                    for c in range(3):
                        later[j, a, c] += ir * (P[e, 0, a] * O[e, 0, c] + P[e, 1, a] * O[e, 1, c]
                                                + P[e, 2, a] * O[e, 2, c])
                    for b in range(6):
                        S6[a, b] += ir * (P[e, 0, a] * P[e, 0, b] + P[e, 1, a] * P[e, 1, b] + P[e, 2, a] * P[e, 2, b])
                for c in range(3):
                    for d in range(3):
                        diag[j, c, d] += ir * (O[e, 0, c] * O[e, 0, d] + O[e, 1, c] * O[e, 1, d]
                                               + O[e, 2, c] * O[e, 2, d])
                p -= 1


@njit(cache=True)
def _factor_strands(strands, offsets, diag, later, earlier, L, W):
    """semiseparable.factor_strand for each of ``strands``; the first that is not positive definite, or -1."""
    for q in range(strands.shape[0]):
        s = strands[q]
        if not factor_strand(diag, later, earlier, offsets[s], offsets[s + 1], L, W):
            return s
    return -1


@njit(cache=True)
def _cross(Pe, Pi, Pf, Oe, d, Of, out):
    """out = Pe Pi Pf^T + Oe diag(d) Of^T (3 x 3)."""
    for a in range(3):
        for b in range(3):
            acc = 0.0
            for c in range(6):
                t = 0.0
                for g in range(6):
                    t += Pi[c, g] * Pf[b, g]
                acc += Pe[a, c] * t
            for c in range(3):
                acc += Oe[a, c] * d[c] * Of[b, c]
            out[a, b] = acc


@njit(cache=True)
def _end_delassus(strands, offsets, strand_ptr, elem, P, O, G, D, partner, own, cross):
    """own_e = J_e D J_e^T per end and, for the later end e of a self-contact (its partner f on the same strand
    comes first in strand order: by element, then index), cross_e = J_e D J_f^T (module docstring); the ends in
    strand order (partner: positions in it); one pass from each strand's root with the prefix sums
    Pi_k = sum_{j<k} G_j D_j G_j^T (D (E_el, 3) per element)."""
    Pi = np.zeros((6, 6))
    V = np.zeros((elem.shape[0], 6, 3))  # V_f of the first end of each self-contact
    for q in range(strands.shape[0]):
        s = strands[q]
        e0 = offsets[s]
        Pi[:] = 0.0
        p = strand_ptr[s]
        for k in range(offsets[s + 1] - e0):
            j = e0 + k
            while p < strand_ptr[s + 1] and elem[p] == k:
                e = p
                _cross(P[e], Pi, P[e], O[e], D[j], O[e], own[e])
                f = partner[e]
                if f >= 0 and elem[f] < k:  # the later end, its partner on an earlier element
                    for a in range(3):
                        for b in range(3):
                            acc = 0.0
                            for c in range(6):
                                acc += P[e, a, c] * V[f, c, b]
                            cross[e, a, b] = acc
                elif f >= 0 and elem[f] == k and f < e:  # the later end on the same element
                    _cross(P[e], Pi, P[f], O[e], D[j], O[f], cross[e])
                elif f >= 0:  # the first end: V_e = Pi_k P_e^T + G_k D_k O_e^T
                    for c in range(6):
                        for b in range(3):
                            acc = 0.0
                            for g in range(6):
                                acc += Pi[c, g] * P[e, b, g]
                            for g in range(3):
                                acc += G[j, c, g] * D[j, g] * O[e, b, g]
                            V[e, c, b] = acc
                p += 1
            for a in range(6):  # Pi += G_k D_k G_k^T
                for b in range(6):
                    Pi[a, b] += G[j, a, 0] * D[j, 0] * G[j, b, 0] + G[j, a, 1] * D[j, 1] * G[j, b, 1] \
                        + G[j, a, 2] * D[j, 2] * G[j, b, 2]


@njit(cache=True)
def _x_step_strands(strands, offsets, strand_ptr, elem, P, O, G, L, W, later, rho, w, x, y):
    """x_e = w_e - J_e M_s^-1 (sum_{e' on s} J_e'^T w_e') / rho_e, strand by strand in one pass each (its data stays
    in cache): the gather by suffix sums from the tip, t_k = G_k^T sum_{b(e)>k} P_e^T w_e + sum_{b(e)=k} O_e^T w_e,
    the semiseparable solve, the scatter by prefix sums from the root, J_e t = P_e sum_{k<b(e)} G_k t_k + O_e t_b.
    Every per-end array in strand order (contiguous per strand: harolongo's x-step 73 ms CPU against 175 ms
    through the ends' random order)."""
    acc = np.zeros(6)
    for q in range(strands.shape[0]):
        s = strands[q]
        e0, e1 = offsets[s], offsets[s + 1]
        n = e1 - e0
        acc[:] = 0.0
        p = strand_ptr[s + 1] - 1
        for k in range(n - 1, -1, -1):
            j = e0 + k
            for c in range(3):
                t = 0.0
                for a in range(6):
                    t += G[j, a, c] * acc[a]
                y[3 * k + c] = t
            while p >= strand_ptr[s] and elem[p] == k:
                w0, w1, w2 = w[p, 0], w[p, 1], w[p, 2]
                for c in range(3):
                    y[3 * k + c] += O[p, 0, c] * w0 + O[p, 1, c] * w1 + O[p, 2, c] * w2
                for a in range(6):
                    acc[a] += P[p, 0, a] * w0 + P[p, 1, a] * w1 + P[p, 2, a] * w2
                p -= 1
        solve_strand(L, W, later, e0, e1, y[:3 * n])
        acc[:] = 0.0
        p = strand_ptr[s]
        for k in range(n):
            j = e0 + k
            t0, t1, t2 = y[3 * k], y[3 * k + 1], y[3 * k + 2]
            while p < strand_ptr[s + 1] and elem[p] == k:
                inv = 1.0 / rho[p]
                for a in range(3):
                    v = O[p, a, 0] * t0 + O[p, a, 1] * t1 + O[p, a, 2] * t2
                    for b in range(6):
                        v += P[p, a, b] * acc[b]
                    x[p, a] = w[p, a] - v * inv
                p += 1
            for a in range(6):
                acc[a] += G[j, a, 0] * t0 + G[j, a, 1] * t1 + G[j, a, 2] * t2


@njit(cache=True)
def _gather_two(strands, offsets, strand_ptr, elem, P, O, G, y1, y2, out1, out2):
    """out_j = sum_e J_e^T y_j,e (j = 1, 2) as flat dof vectors (element k of the groom: dofs 3k..3k+2), the ends'
    y in strand order: per strand the suffix sums from the tip, t_k = G_k^T sum_{b(e)>k} P_e^T y_e +
    sum_{b(e)=k} O_e^T y_e (the x-step's gather; dofs of strands without ends are left alone)."""
    a1 = np.zeros(6)
    a2 = np.zeros(6)
    for q in range(strands.shape[0]):
        s = strands[q]
        e0, e1 = offsets[s], offsets[s + 1]
        a1[:] = 0.0
        a2[:] = 0.0
        p = strand_ptr[s + 1] - 1
        for k in range(e1 - e0 - 1, -1, -1):
            j = e0 + k
            for c in range(3):
                t1 = 0.0
                t2 = 0.0
                for a in range(6):
                    t1 += G[j, a, c] * a1[a]
                    t2 += G[j, a, c] * a2[a]
                out1[3 * j + c] = t1
                out2[3 * j + c] = t2
            while p >= strand_ptr[s] and elem[p] == k:
                u0, u1, u2 = y1[p, 0], y1[p, 1], y1[p, 2]
                v0, v1, v2 = y2[p, 0], y2[p, 1], y2[p, 2]
                for c in range(3):
                    out1[3 * j + c] += O[p, 0, c] * u0 + O[p, 1, c] * u1 + O[p, 2, c] * u2
                    out2[3 * j + c] += O[p, 0, c] * v0 + O[p, 1, c] * v1 + O[p, 2, c] * v2
                for a in range(6):
                    a1[a] += P[p, 0, a] * u0 + P[p, 1, a] * u1 + P[p, 2, a] * u2
                    a2[a] += P[p, 0, a] * v0 + P[p, 1, a] * v1 + P[p, 2, a] * v2
                p -= 1


@njit(cache=True)
def _scatter_two(strands, offsets, strand_ptr, elem, P, O, G, t1, t2, out1, out2):
    """out_j,e = J_e t_j (j = 1, 2) per end in strand order for flat dof vectors t_j: per strand the prefix sums
    from the root, J_e t = P_e sum_{k<b(e)} G_k t_k + O_e t_b (the x-step's scatter)."""
    a1 = np.zeros(6)
    a2 = np.zeros(6)
    for q in range(strands.shape[0]):
        s = strands[q]
        e0, e1 = offsets[s], offsets[s + 1]
        a1[:] = 0.0
        a2[:] = 0.0
        p = strand_ptr[s]
        for k in range(e1 - e0):
            j = e0 + k
            u0, u1, u2 = t1[3 * j], t1[3 * j + 1], t1[3 * j + 2]
            v0, v1, v2 = t2[3 * j], t2[3 * j + 1], t2[3 * j + 2]
            while p < strand_ptr[s + 1] and elem[p] == k:
                for a in range(3):
                    f1 = O[p, a, 0] * u0 + O[p, a, 1] * u1 + O[p, a, 2] * u2
                    f2 = O[p, a, 0] * v0 + O[p, a, 1] * v1 + O[p, a, 2] * v2
                    for b in range(6):
                        f1 += P[p, a, b] * a1[b]
                        f2 += P[p, a, b] * a2[b]
                    out1[p, a] = f1
                    out2[p, a] = f2
                p += 1
            for a in range(6):
                a1[a] += G[j, a, 0] * u0 + G[j, a, 1] * u1 + G[j, a, 2] * u2
                a2[a] += G[j, a, 0] * v0 + G[j, a, 1] * v1 + G[j, a, 2] * v2


@njit(cache=True)
def _contact_rows_in_order(contact_sorted, s, out):
    """out[p] = s[contact_sorted[p]] (each end's contact force, the ends in strand order)."""
    for p in range(contact_sorted.shape[0]):
        i = contact_sorted[p]
        out[p, 0], out[p, 1], out[p, 2] = s[i, 0], s[i, 1], s[i, 2]


@njit(cache=True)
def _contact_sums(contact_sorted, v1, v2, out1, out2):
    """out_j,i += sum of v_j over the ends of contact i (v_j in strand order, contact_sorted their contacts)."""
    for p in range(contact_sorted.shape[0]):
        i = contact_sorted[p]
        for a in range(3):
            out1[i, a] += v1[p, a]
            out2[i, a] += v2[p, a]


@njit(cache=True)
def _permute_rows(a, order, out, inverse):
    """out[p] = a[order[p]] (inverse False: ends to strand order) or out[order[p]] = a[p] (inverse True); numpy's
    fancy assignment of the (E, 3) rows took 15 ms on harolongo, this 2.5 ms."""
    for p in range(order.shape[0]):
        e = order[p]
        if inverse:
            out[e, 0], out[e, 1], out[e, 2] = a[p, 0], a[p, 1], a[p, 2]
        else:
            out[p, 0], out[p, 1], out[p, 2] = a[e, 0], a[e, 1], a[e, 2]


@njit(cache=True)
def _frame_transpose_times(sF, y, out):
    """out_e = sF_e^T y_e (the world point force of an end's force copy)."""
    for e in range(sF.shape[0]):
        y0, y1, y2 = y[e, 0], y[e, 1], y[e, 2]
        for c in range(3):
            out[e, c] = sF[e, 0, c] * y0 + sF[e, 1, c] * y1 + sF[e, 2, c] * y2


@njit(cache=True)
def _minus_frame_times(w, sF, v, rho_end, x):
    """x_e = w_e - sF_e v_e / rho_e."""
    for e in range(sF.shape[0]):
        v0, v1, v2 = v[e, 0], v[e, 1], v[e, 2]
        inv = 1.0 / rho_end[e]
        for a in range(3):
            x[e, a] = w[e, a] - (sF[e, a, 0] * v0 + sF[e, a, 1] * v1 + sF[e, a, 2] * v2) * inv


class StructuredSplit:
    """admm.StrandSplit's interface (the ends, rho, x_step, strand_sum, strand_velocity) for a Super-Helix groom,
    with the semiseparable factors of M_s = D_s^-1 + J_s^T J_s / rho (module docstring) instead of dense ones.
    Built from the geometry (HelixContacts) and the problem's D, with the contacts' W_ii (``diag``, in
    O(elements + ends)); rho (from W_ii: admm.py's rule) is given to ``set_rho``, which factors the strands."""

    def __init__(self, problem, geometry: HelixContacts):
        helix, contacts = geometry.helix, geometry.contacts
        kin = geometry.kin if geometry.kin is not None else sh.kinematics(helix)
        self.helix, self.kin = helix, kin
        self.cend_ptr, self.end_contact, self.end_strand, self.end_arc, sign = helix_ends(helix, contacts)
        E = len(self.end_contact)
        self.n_ends = E
        elem, x, own = sh.point_jacobian_parts(helix, self.end_strand, self.end_arc, kin)
        self.parts = (elem, x, own)
        frames = np.asarray(contacts.frame, dtype=np.float64).reshape(-1, 3, 3)
        self.sF = np.ascontiguousarray(sign[:, None, None] * frames[self.end_contact])
        P = np.empty((E, 3, 6))
        _rigid_rows(self.sF, np.ascontiguousarray(x), np.ascontiguousarray(kin.C[self.end_strand, 0]), P)
        mask = helix.element_mask
        root = kin.C[:, 0]
        Bc = sh.upstream_jacobian_terms(kin) - sh.skew(root)[:, None] @ kin.Theta
        self.G = np.ascontiguousarray(np.concatenate([kin.Theta[mask], Bc[mask]], axis=1))  # (E_el, 6, 3)
        self.offsets = helix.flat_offsets()
        S = helix.n_strands
        # strand order: the ends by strand, then element (then index); the kernels' per-end data in that order
        order = np.lexsort((elem, self.end_strand)).astype(np.int64)
        self.ends_sorted = order
        self.strand_ptr = np.zeros(S + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.end_strand, minlength=S), out=self.strand_ptr[1:])
        self.active = np.flatnonzero(np.diff(self.strand_ptr) > 0).astype(np.int64)
        self.elem = np.ascontiguousarray(elem[order], dtype=np.int64)
        self.P = np.ascontiguousarray(P[order])
        self.O = np.ascontiguousarray((self.sF @ own)[order])
        partner = np.full(E, -1, dtype=np.int64)  # a self-contact's other end
        two = np.flatnonzero((np.diff(self.cend_ptr) == 2))
        two = two[self.end_strand[self.cend_ptr[two]] == self.end_strand[self.cend_ptr[two] + 1]]
        partner[self.cend_ptr[two]] = self.cend_ptr[two] + 1
        partner[self.cend_ptr[two] + 1] = self.cend_ptr[two]
        position = np.empty(E, dtype=np.int64)
        position[order] = np.arange(E)
        self.partner = np.where(partner[order] >= 0, position[np.maximum(partner[order], 0)], -1)
        self.H_source = (problem.H.indptr, problem.H.indices, problem.H.data, problem.H.shape)
        self._attach(problem)
        self.diag = self.contact_diagonal(problem)
        self.beta = None  # the beta of rho (admm.run_admm)
        self.rho_c = self.rho_end = self.L = self.W = self.later = self.diag_M = None

    def _attach(self, problem):
        self.problem = problem
        self.D_data, self.D_ptr = problem.D_data, problem.D_ptr
        self.n_dofs = problem.n_dofs
        self.gamma = problem.gamma
        self.D_el = problem.D_data.reshape(-1, 3)  # diagonal D: one entry per dof, strand after strand

    def contact_diagonal(self, problem) -> np.ndarray:
        """W_ii = H_i D H_i^T + 2 gamma I (m, 3, 3) of ``problem`` (this split's H, its D), in O(elements + ends)."""
        own = np.zeros((self.n_ends, 3, 3))
        cross = np.zeros((self.n_ends, 3, 3))
        _end_delassus(self.active, self.offsets, self.strand_ptr, self.elem, self.P, self.O, self.G, self.D_el,
                      self.partner, own, cross)
        own += cross + cross.transpose(0, 2, 1)
        m = len(self.cend_ptr) - 1
        out = np.zeros((m, 3, 3))
        np.add.at(out, self.end_contact[self.ends_sorted], own)
        out = 0.5 * (out + out.transpose(0, 2, 1))
        out += 2.0 * problem.gamma * np.eye(3)
        return out

    def set_rho(self, rho_c: np.ndarray) -> None:
        """Fix rho per contact and (re)factor every strand that carries an end."""
        self.rho_c = np.ascontiguousarray(rho_c, dtype=np.float64)
        self.rho_end = np.ascontiguousarray(self.rho_c[self.end_contact])
        rho_sorted = np.ascontiguousarray(self.rho_end[self.ends_sorted])
        E_el = self.G.shape[0]
        self.diag_M = np.zeros((E_el, 3, 3))
        self.later = np.zeros((E_el, 6, 3))
        _generators(self.active, self.offsets, self.strand_ptr, self.elem, self.P, self.O, rho_sorted, self.G,
                    1.0 / self.D_el, self.diag_M, self.later)
        self.L = np.zeros((E_el, 3, 3))
        self.W = np.zeros((E_el, 6, 3))
        bad = _factor_strands(self.active, self.offsets, self.diag_M, self.later, self.G, self.L, self.W)
        if bad >= 0:
            raise np.linalg.LinAlgError(f"strand {bad}: M_s = D_s^-1 + J_s^T J_s / rho is not positive definite")
        self.refactored = len(self.active)
        self._y = np.empty(3 * int(np.diff(self.offsets).max(initial=0)))
        self._rho_sorted = rho_sorted
        self._in_order = (np.empty((self.n_ends, 3)), np.empty((self.n_ends, 3)))  # w and x in strand order

    def detached(self) -> "StructuredSplit":
        """A copy sharing every array but not the problem (for admm.ADMMState)."""
        out = copy.copy(self)
        out.problem = None
        return out

    def rebind(self, problem) -> "StructuredSplit":
        """This split on ``problem`` (the same H, another diagonal D, e.g. the next stiffening round): the ends and
        generators G, P, O kept, W_ii (``diag``) from the new D; rho and the factors are set_rho's."""
        out = copy.copy(self)
        out._attach(problem)
        out.diag = out.contact_diagonal(problem)
        out.rho_c = out.rho_end = out.L = out.W = out.later = out.diag_M = out._rho_sorted = out._in_order = None
        return out

    def _gather(self, y) -> np.ndarray:
        """sum_e J_e^T y_e per strand, padded (S, N, 3): the generalised force of the point forces sF_e^T y_e."""
        f = np.empty((self.n_ends, 3))
        _frame_transpose_times(self.sF, np.ascontiguousarray(y), f)
        return point_forces_generalized(self.helix, self.kin, self.end_strand, self.end_arc, f, self.parts)

    def _scatter(self, t, w, scale, out) -> np.ndarray:
        """out_e = w_e - J_e t / scale_e per end for strand dofs t padded (S, N, 3): J_e t is sF_e times the end's
        point velocity."""
        v = point_velocities(self.helix, self.kin, self.end_strand, self.end_arc, t, self.parts)
        _minus_frame_times(w, self.sF, v, scale, out)
        return out

    def x_step(self, w, x):
        """x_e = w_e - J_e M_s^-1 (sum_{e' on s} J_e'^T w_e') / rho_e (admm.py's x-step), in strand order."""
        ws, xs = self._in_order
        _permute_rows(np.ascontiguousarray(w), self.ends_sorted, ws, False)
        _x_step_strands(self.active, self.offsets, self.strand_ptr, self.elem, self.P, self.O, self.G, self.L, self.W,
                        self.later, self._rho_sorted, ws, xs, self._y)
        _permute_rows(xs, self.ends_sorted, x, True)

    def check_products(self, s, x, b):
        """What a check of the ADMM run needs, through the generators instead of the CSR H (equal to round-off; two
        passes over the ends and elements, no product with H): for the forces s (m, 3), the last x-step's copies
        x (E, 3) and b (m, 3)

            HTs = H^T s = sum_e J_e^T s_c(e),   h = sum_e J_e^T x_e (the strand sum),
            u = H D HTs + 2 gamma s + b (= W s + b),   c = H D h + b  (the strand certificate's A l + b).

        Returns (HTs, h, u, c): (n,), (n,), (3m,), (3m,).  Dofs of strands without ends: 0 in HTs and h."""
        E = self.n_ends
        m = s.shape[0]
        se = np.empty((E, 3))
        if getattr(self, "_contact_sorted", None) is None:
            self._contact_sorted = np.ascontiguousarray(self.end_contact[self.ends_sorted])
        _contact_rows_in_order(self._contact_sorted, np.ascontiguousarray(s), se)
        xs = self._in_order[1]
        _permute_rows(np.ascontiguousarray(x), self.ends_sorted, xs, False)
        HTs = np.zeros(self.n_dofs)
        h = np.zeros(self.n_dofs)
        _gather_two(self.active, self.offsets, self.strand_ptr, self.elem, self.P, self.O, self.G, se, xs, HTs, h)
        d = self.D_data
        v1 = np.empty((E, 3))
        v2 = np.empty((E, 3))
        _scatter_two(self.active, self.offsets, self.strand_ptr, self.elem, self.P, self.O, self.G, d * HTs, d * h,
                     v1, v2)
        u = 2.0 * self.gamma * s + b
        c = np.array(b, dtype=np.float64, copy=True).reshape(m, 3)
        _contact_sums(self._contact_sorted, v1, v2, u, c)
        return HTs, h, u.reshape(-1), c.reshape(-1)

    def strand_sum(self, x) -> np.ndarray:
        """h = sum_e J_e^T x_e (n,) (admm.StrandSplit.strand_sum)."""
        return self.helix.to_flat(self._gather(x)).reshape(-1)

    def strand_velocity(self, x):
        """out_e = J_e D_s sum_{e' on s} J_e'^T x_e' (admm.StrandSplit.strand_velocity)."""
        t = self._gather(x)
        t[self.helix.element_mask] *= self.D_el
        out = np.empty((self.n_ends, 3))
        return -self._scatter(t, np.zeros_like(out), np.ones(self.n_ends), out)
