"""H as an operator: H v and H^T r for Super-Helices in O(S N + m), without storing H.

H (contact/jacobian.py) has, for a contact on element e, the blocks dC(s)/domega_k = B_k - [x]x Theta_k of every
element k < e of its strand, so nnz(H) grows like contacts x elements (harolongo with all its contacts: 78M
entries, ~1 GB as CSR).  Both products only need per-element prefix (or suffix) sums along each strand:

    velocity of the point x = C(s) on element e:
        xdot = sum_{k<e} (B_k v_k - x cross Theta_k v_k) + own v_e = L_e - x cross A_e + own v_e,
        L_e = sum_{k<e} (R_k D_k v_k + C_{k+1} cross Theta_k v_k),   A_e = sum_{k<e} Theta_k v_k

(B_k = R_k D_k + [C_{k+1}]x Theta_k, superhelix.upstream_jacobian_terms), and u_i = F_i (xdot_a - xdot_b);
H^T r is :func:`groomtool.contact.jacobian.generalized_contact_force` (the suffix sums of the same blocks).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..rods import superhelix as sh
from .jacobian import contact_points, generalized_contact_force


def point_velocities(helix: sh.SuperHelix, kin: sh.Kinematics, strand, s, rates, parts=None) -> np.ndarray:
    """World velocities dC(s_p)/dt (P, 3) of the points at arc lengths s_p on strands ``strand`` (P,), for the
    curvature rates ``rates`` (S, N, 3): L_e - x cross A_e + own v_e (module docstring), one pass along each
    strand that has a point.  ``parts``: the points' superhelix.point_jacobian_parts when already known."""
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    out = np.zeros((len(strand), 3))
    if len(strand) == 0:
        return out
    elem, x, own = parts if parts is not None else sh.point_jacobian_parts(helix, strand, s, kin)
    S, N = helix.curvatures.shape[:2]
    touched = np.zeros(S, dtype=np.bool_)
    touched[strand] = True
    _point_velocity_kernel(strand, elem, np.ascontiguousarray(x), np.ascontiguousarray(own),
                           np.ascontiguousarray(rates, dtype=np.float64).reshape(S, N, 3), np.ascontiguousarray(kin.C),
                           np.ascontiguousarray(kin.R), np.ascontiguousarray(kin.D), np.ascontiguousarray(kin.Theta),
                           helix.n_elements, touched, out)
    return out


@njit(cache=True)
def _point_velocity_kernel(strand, elem, x, own, v, C, R, D, Theta, n_elements, touched, out):
    """Prefix sums L_e, A_e per element of the touched strands, then each point's L_e - x cross A_e + own v_e."""
    S, N = v.shape[0], v.shape[1]
    lin = np.zeros((S, N, 3))
    ang = np.zeros((S, N, 3))
    for k in range(S):
        if not touched[k]:
            continue
        L0 = L1 = L2 = 0.0
        A0 = A1 = A2 = 0.0
        for j in range(n_elements[k]):
            lin[k, j, 0], lin[k, j, 1], lin[k, j, 2] = L0, L1, L2
            ang[k, j, 0], ang[k, j, 1], ang[k, j, 2] = A0, A1, A2
            v0, v1, v2 = v[k, j, 0], v[k, j, 1], v[k, j, 2]
            d0 = D[k, j, 0, 0] * v0 + D[k, j, 0, 1] * v1 + D[k, j, 0, 2] * v2
            d1 = D[k, j, 1, 0] * v0 + D[k, j, 1, 1] * v1 + D[k, j, 1, 2] * v2
            d2 = D[k, j, 2, 0] * v0 + D[k, j, 2, 1] * v1 + D[k, j, 2, 2] * v2
            w0 = Theta[k, j, 0, 0] * v0 + Theta[k, j, 0, 1] * v1 + Theta[k, j, 0, 2] * v2
            w1 = Theta[k, j, 1, 0] * v0 + Theta[k, j, 1, 1] * v1 + Theta[k, j, 1, 2] * v2
            w2 = Theta[k, j, 2, 0] * v0 + Theta[k, j, 2, 1] * v1 + Theta[k, j, 2, 2] * v2
            c0, c1, c2 = C[k, j + 1, 0], C[k, j + 1, 1], C[k, j + 1, 2]
            L0 += R[k, j, 0, 0] * d0 + R[k, j, 0, 1] * d1 + R[k, j, 0, 2] * d2 + (c1 * w2 - c2 * w1)
            L1 += R[k, j, 1, 0] * d0 + R[k, j, 1, 1] * d1 + R[k, j, 1, 2] * d2 + (c2 * w0 - c0 * w2)
            L2 += R[k, j, 2, 0] * d0 + R[k, j, 2, 1] * d1 + R[k, j, 2, 2] * d2 + (c0 * w1 - c1 * w0)
            A0 += w0
            A1 += w1
            A2 += w2
    for p in range(strand.shape[0]):
        k, e = strand[p], elem[p]
        if e >= n_elements[k]:  # a strand without elements
            continue
        a0, a1, a2 = ang[k, e, 0], ang[k, e, 1], ang[k, e, 2]
        x0, x1, x2 = x[p, 0], x[p, 1], x[p, 2]
        v0, v1, v2 = v[k, e, 0], v[k, e, 1], v[k, e, 2]
        out[p, 0] = lin[k, e, 0] - (x1 * a2 - x2 * a1) + own[p, 0, 0] * v0 + own[p, 0, 1] * v1 + own[p, 0, 2] * v2
        out[p, 1] = lin[k, e, 1] - (x2 * a0 - x0 * a2) + own[p, 1, 0] * v0 + own[p, 1, 1] * v1 + own[p, 1, 2] * v2
        out[p, 2] = lin[k, e, 2] - (x0 * a1 - x1 * a0) + own[p, 2, 0] * v0 + own[p, 2, 1] * v1 + own[p, 2, 2] * v2


def contact_velocities(helix: sh.SuperHelix, contacts, rates, kin: sh.Kinematics | None = None,
                       parts=None) -> np.ndarray:
    """H v without H: u_i = F_i (xdot_a(s_a) - xdot_b(s_b)) (m, 3) in contact frames, for rates (S, N, 3) or flat
    (3E,) as H's columns (contact/jacobian.contact_jacobian); the head side (strand_b < 0) does not move.
    ``parts``: (on, point_jacobian_parts of the points on strands) when already known (ContactJacobianOperator)."""
    kin = kin if kin is not None else sh.kinematics(helix)
    m = len(contacts.strand_a)
    rates = np.asarray(rates, dtype=np.float64)
    if rates.ndim == 1:
        rates = helix.from_flat(rates.reshape(-1, 3))
    strand, s = contact_points(contacts)
    on = np.flatnonzero(strand >= 0) if parts is None else parts[0]
    xdot = np.zeros((2 * m, 3))
    xdot[on] = point_velocities(helix, kin, strand[on], s[on], rates, None if parts is None else parts[1])
    relative = xdot[:m] - xdot[m:]
    return np.einsum("mij,mj->mi", np.asarray(contacts.frame, dtype=np.float64).reshape(m, 3, 3), relative)


class ContactJacobianOperator:
    """H (3m, 3E) as an operator on one configuration: ``H @ v`` (flat rates, (3E,)) -> (3m,) and ``H.T @ r``
    ((3m,) or (m, 3) impulses in contact frames) -> (3E,), each in O(S N + m) (module docstring); the same
    columns and rows as contact/jacobian.contact_jacobian.  ``as_linear_operator()`` for scipy's solvers."""

    def __init__(self, helix: sh.SuperHelix, contacts, kin: sh.Kinematics | None = None):
        self.helix = helix
        self.contacts = contacts
        self.kin = kin if kin is not None else sh.kinematics(helix)
        self.shape = (3 * len(contacts.strand_a), 3 * int(helix.flat_offsets()[-1]))
        strand, s = contact_points(contacts)
        on = np.flatnonzero(strand >= 0)
        self._parts = (on, sh.point_jacobian_parts(helix, strand[on], s[on], self.kin))  # per configuration

    def matvec(self, v) -> np.ndarray:
        """H v, (3m,)."""
        return contact_velocities(self.helix, self.contacts, np.asarray(v).ravel(), self.kin, self._parts).ravel()

    def rmatvec(self, r) -> np.ndarray:
        """H^T r, (3E,): contact/jacobian.generalized_contact_force on the kept point parts."""
        Q = generalized_contact_force(self.helix, self.contacts, np.asarray(r).reshape(-1, 3), self.kin,
                                      self._parts[1])
        return self.helix.to_flat(Q).ravel()

    def __matmul__(self, v):
        return self.matvec(v)

    @property
    def T(self) -> "_Transposed":
        return _Transposed(self)


class _Transposed:
    """H^T of a ContactJacobianOperator: ``H.T @ r``."""

    def __init__(self, op: ContactJacobianOperator):
        self.op = op
        self.shape = op.shape[::-1]

    def __matmul__(self, r):
        return self.op.rmatvec(r)
