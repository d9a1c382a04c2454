"""H: generalised velocities of the strands -> relative velocity at each contact, in its frame.

For contact i between the axis point of strand a at s_a and strand b at s_b (or the head), with
frame rows (e_N, e_T1, e_T2) and e_N pointing from b towards a,

    u_i = F_i (J_a(s_a) qdot_a - J_b(s_b) qdot_b),     H_i = F_i [J_a, -J_b]

(J = dC/dq of :func:`groomtool.rods.superhelix.point_jacobians`), so u_N > 0 separates and the
generalised force of the contact reactions r (in contact frames) is H^T r.  The dofs are the flat
(unpadded) curvatures of all strands: strand s owns columns 3 * flat_offsets[s] ... .
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..rods import superhelix as sh


def _side_entries(helix, kin, strand, s, frames, sign, dof_offsets):
    J, elem = sh.point_jacobians(helix, strand, s, kin)  # (P, N, 3, 3)
    blocks = sign * np.einsum("pij,pkjb->pkib", frames, J)  # (P, N, 3 rows, 3 dofs)
    P, N = J.shape[:2]
    k = np.arange(N)
    keep = k[None, :] <= elem[:, None]  # only upstream elements move the point
    pi, ki = np.nonzero(keep)
    vals = blocks[pi, ki]  # (nnzb, 3, 3)
    rows = 3 * pi[:, None, None] + np.arange(3)[None, :, None]
    cols = 3 * (dof_offsets[strand[pi]] + ki)[:, None, None] + np.arange(3)[None, None, :]
    rows, cols = np.broadcast_arrays(rows, cols)
    return rows.ravel(), cols.ravel(), vals.ravel()


def contact_jacobian(helix: sh.SuperHelix, contacts, kin: sh.Kinematics | None = None) -> sp.csr_matrix:
    """H as a sparse (3m, 3E) matrix, E the number of real elements of all strands."""
    kin = kin if kin is not None else sh.kinematics(helix)
    dof_offsets = helix.flat_offsets()
    n_dofs = 3 * int(dof_offsets[-1])
    m = len(contacts.strand_a)
    if m == 0:
        return sp.csr_matrix((0, n_dofs))
    frames = np.asarray(contacts.frame, dtype=np.float64)
    r_a, c_a, v_a = _side_entries(helix, kin, np.asarray(contacts.strand_a), np.asarray(contacts.s_a),
                                  frames, 1.0, dof_offsets)
    other = np.flatnonzero(np.asarray(contacts.strand_b) >= 0)
    parts_r, parts_c, parts_v = [r_a], [c_a], [v_a]
    if len(other):
        r_b, c_b, v_b = _side_entries(helix, kin, np.asarray(contacts.strand_b)[other],
                                      np.asarray(contacts.s_b)[other], frames[other], -1.0, dof_offsets)
        # rows were numbered within the subset: map back to the contact's own rows
        r_b = 3 * other[r_b // 3] + r_b % 3
        parts_r.append(r_b)
        parts_c.append(c_b)
        parts_v.append(v_b)
    H = sp.coo_matrix((np.concatenate(parts_v), (np.concatenate(parts_r), np.concatenate(parts_c))),
                      shape=(3 * m, n_dofs))
    return H.tocsr()


def generalized_contact_force(helix: sh.SuperHelix, contacts, forces: np.ndarray,
                              kin: sh.Kinematics | None = None) -> np.ndarray:
    """H^T r computed point by point (independently of the assembled H): (S, N, 3).

    The world force on strand a is F_i^T r_i at C(s_a), its opposite on strand b.
    """
    kin = kin if kin is not None else sh.kinematics(helix)
    out = np.zeros(helix.curvatures.shape)
    frames = np.asarray(contacts.frame, dtype=np.float64)
    world = np.einsum("pji,pj->pi", frames, np.asarray(forces, dtype=np.float64))
    for strand, s, f in ((contacts.strand_a, contacts.s_a, world),
                         (contacts.strand_b, contacts.s_b, -world)):
        strand = np.asarray(strand)
        mask = strand >= 0
        if not np.any(mask):
            continue
        J, _ = sh.point_jacobians(helix, strand[mask], np.asarray(s)[mask], kin)
        gen = np.einsum("pkab,pa->pkb", J, f[mask])
        np.add.at(out, strand[mask], gen)
    return out
