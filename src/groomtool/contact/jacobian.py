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
from numba import njit

from ..rods import clothoid as cl
from ..rods import superhelix as sh

CLOTHOID_CHUNK = 4096  # contacts per batch of dense clothoid point Jacobians


def _setup(rod, contacts, kin):
    """What both forms of H start from: the kinematics (computed when not given), the flat dof offsets of the
    strands (elements of a Super-Helix, nodes of a Super Space Clothoid), the number of columns, and the
    contact frames (m, 3, 3), contiguous; None without contacts."""
    kin = kin if kin is not None else (cl if isinstance(rod, cl.SuperClothoid) else sh).kinematics(rod)
    offsets = rod.flat_offsets()
    m = len(contacts.strand_a)
    frames = np.ascontiguousarray(contacts.frame, dtype=np.float64).reshape(m, 3, 3) if m else None
    return kin, offsets, 3 * int(offsets[-1]), frames


def clothoid_contact_jacobian(rod: cl.SuperClothoid, contacts, kin: cl.Kinematics | None = None) -> sp.csr_matrix:
    """H for Super Space Clothoids, (3m, 3 n_nodes): H_i = F_i [J_a, -J_b] with J = dC/dq at the nodes
    (:func:`groomtool.rods.clothoid.point_jacobians`: blocks of nodes 0 .. elem + 1 of the point's strand),
    assembled in batches of contacts from the dense point Jacobians (a self-contact's blocks are summed)."""
    kin, node_offsets, n_dofs, frames = _setup(rod, contacts, kin)
    if frames is None:
        return sp.csr_matrix((0, n_dofs))
    m = len(frames)
    rows, cols, vals = [], [], []
    for side, strands, arcs, sign in (("a", contacts.strand_a, contacts.s_a, 1.0),
                                      ("b", contacts.strand_b, contacts.s_b, -1.0)):
        strands = np.asarray(strands, dtype=np.int64)
        arcs = np.asarray(arcs, dtype=np.float64)
        on = np.flatnonzero(strands >= 0)
        for start in range(0, len(on), CLOTHOID_CHUNK):
            idx = on[start:start + CLOTHOID_CHUNK]
            J, elem = cl.point_jacobians(rod, strands[idx], arcs[idx], kin)  # (P, N + 1, 3, 3)
            blk = sign * np.einsum("prk,pnkc->pnrc", frames[idx], J)  # (P, node, row, col)
            P, N1 = J.shape[:2]
            node = np.arange(N1)[None, :]
            keep = node <= (elem[:, None] + 1)
            p_i, n_i = np.nonzero(keep)
            r = 3 * idx[p_i][:, None, None] + np.arange(3)[None, :, None]
            c = 3 * (node_offsets[strands[idx]][p_i] + n_i)[:, None, None] + np.arange(3)[None, None, :]
            rows.append(np.broadcast_to(r, (len(p_i), 3, 3)).ravel())
            cols.append(np.broadcast_to(c, (len(p_i), 3, 3)).ravel())
            vals.append(blk[p_i, n_i].ravel())
    H = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * m, n_dofs))
    H = H.tocsr()
    H.sum_duplicates()
    H.sort_indices()
    return H


def clothoid_point_forces_generalized(rod: cl.SuperClothoid, kin: cl.Kinematics, strand, s, f) -> np.ndarray:
    """Q = sum_p (dC(s_p)/dq)^T f_p, (S, N + 1, 3), from the dense clothoid point Jacobians, in batches."""
    S, N1 = rod.curvatures.shape[:2]
    out = np.zeros((S, N1, 3))
    strand = np.asarray(strand, dtype=np.int64)
    s = np.asarray(s, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64).reshape(-1, 3)
    for start in range(0, len(strand), CLOTHOID_CHUNK):
        sl = slice(start, start + CLOTHOID_CHUNK)
        J, _ = cl.point_jacobians(rod, strand[sl], s[sl], kin)
        np.add.at(out, strand[sl], np.einsum("pnkc,pk->pnc", J, f[sl]))
    return out


def contact_jacobian(helix, contacts, kin=None) -> sp.csr_matrix:
    """H as a sparse (3m, 3E) matrix, E the number of real elements of all strands.

    Written directly in CSR form (sorted indices) by :func:`_fill_csr`: the 3 rows of contact i share
    the columns of elements 0..elem_a of strand a and 0..elem_b of strand b (one range, the union,
    for a self-contact, whose overlapping blocks are summed); memory O(nnz(H)).  A Super Space Clothoid
    (columns: its nodes) goes to :func:`clothoid_contact_jacobian`.
    """
    if isinstance(helix, cl.SuperClothoid):
        return clothoid_contact_jacobian(helix, contacts, kin)
    kin, dof_offsets, n_dofs, frames = _setup(helix, contacts, kin)
    if frames is None:
        return sp.csr_matrix((0, n_dofs))
    m = len(frames)
    strand_a = np.ascontiguousarray(contacts.strand_a, dtype=np.int64)
    strand_b = np.ascontiguousarray(contacts.strand_b, dtype=np.int64)
    elem_a, x_a, own_a = sh.point_jacobian_parts(helix, strand_a, np.asarray(contacts.s_a), kin)
    other = np.flatnonzero(strand_b >= 0)
    elem_b = np.full(m, -1, dtype=np.int64)
    x_b = np.zeros((m, 3))
    own_b = np.zeros((m, 3, 3))
    if len(other):
        elem_b[other], x_b[other], own_b[other] = sh.point_jacobian_parts(
            helix, strand_b[other], np.asarray(contacts.s_b)[other], kin)
    strand_b = np.where(strand_b >= 0, strand_b, -1)

    # blocks per contact (each block: 3 columns in each of the contact's 3 rows)
    same = strand_b == strand_a
    blocks = np.where(same, np.maximum(elem_a, elem_b) + 1, elem_a + 1 + (elem_b + 1))  # elem_b + 1 = 0: head
    row_len = np.repeat(3 * blocks, 3)
    nnz = int(row_len.sum())
    idx_dtype = np.int32 if max(nnz, n_dofs) < np.iinfo(np.int32).max else np.int64
    indptr = np.zeros(3 * m + 1, dtype=idx_dtype)
    np.cumsum(row_len, out=indptr[1:])
    data = np.empty(nnz)
    indices = np.empty(nnz, dtype=idx_dtype)
    B = np.ascontiguousarray(sh.upstream_jacobian_terms(kin))
    _fill_csr(strand_a, elem_a, np.ascontiguousarray(x_a), np.ascontiguousarray(own_a),
              strand_b, elem_b, x_b, own_b, frames, B, np.ascontiguousarray(kin.Theta),
              dof_offsets, indptr, data, indices)
    H = sp.csr_matrix((data, indices, indptr), shape=(3 * m, n_dofs), copy=False)
    H.has_sorted_indices = True  # by construction (strand ranges in dof order, elements increasing)
    return H


def contact_jacobian_part(part: sh.SuperHelix, part_kin: sh.Kinematics, contacts, strands, flat_offsets) -> sp.csr_matrix:
    """contact_jacobian's H of ``contacts`` whose strands are all among ``strands`` (sorted), computed on those
    strands alone: ``part`` = helix.subset(strands) with its kinematics (gathered from the whole groom's), the columns
    those of the whole groom (``flat_offsets`` (S + 1,) its elements' offsets).  The same entries as contact_jacobian
    on the whole groom, in O(the strands' elements) instead of the whole groom's upstream terms (a simulator's
    partial step: Simulator._partial_contacts)."""
    strands = np.asarray(strands, dtype=np.int64)
    flat_offsets = np.asarray(flat_offsets, dtype=np.int64)
    local = np.full(len(flat_offsets) - 1, -1, dtype=np.int64)
    local[strands] = np.arange(len(strands))
    mine = contacts.subset(np.arange(len(contacts.strand_a)))
    mine.strand_a = local[mine.strand_a]
    mine.strand_b = np.where(mine.strand_b >= 0, local[np.maximum(mine.strand_b, 0)], mine.strand_b)
    H = contact_jacobian(part, mine, part_kin)
    part_offsets = part.flat_offsets()
    dof_strand = np.repeat(np.arange(len(strands)), 3 * np.diff(part_offsets))
    shift = 3 * (flat_offsets[strands] - part_offsets[:-1])
    indices = H.indices.astype(np.int64) + shift[dof_strand[H.indices]]
    out = sp.csr_matrix((H.data, indices, H.indptr), shape=(H.shape[0], 3 * int(flat_offsets[-1])), copy=False)
    out.has_sorted_indices = True  # strands in the same order, shifted
    return out


@njit(cache=True)
def _add_side(F, sign, x, own, B, Theta, strand, elem, col0, pos0, start, row_len, accumulate, J, data, indices):
    """Write (or add, if ``accumulate``) sign F J_k for k = 0..elem (J_k = B_k - [x]x Theta_k,
    J_elem = own) at block positions pos0 + k of the 3 rows starting at data[start], row_len apart,
    columns 3 (col0 + k) + c."""
    for k in range(elem + 1):
        if k == elem:
            for a in range(3):
                for b in range(3):
                    J[a, b] = own[a, b]
        else:
            for b in range(3):
                t0, t1, t2 = Theta[strand, k, 0, b], Theta[strand, k, 1, b], Theta[strand, k, 2, b]
                J[0, b] = B[strand, k, 0, b] - (x[1] * t2 - x[2] * t1)
                J[1, b] = B[strand, k, 1, b] - (x[2] * t0 - x[0] * t2)
                J[2, b] = B[strand, k, 2, b] - (x[0] * t1 - x[1] * t0)
        base = start + 3 * (pos0 + k)
        col = 3 * (col0 + k)
        for r in range(3):
            at = base + r * row_len
            for c in range(3):
                v = sign * (F[r, 0] * J[0, c] + F[r, 1] * J[1, c] + F[r, 2] * J[2, c])
                if accumulate:
                    data[at + c] += v
                else:
                    data[at + c] = v
                    indices[at + c] = col + c


@njit(cache=True)
def _fill_csr(strand_a, elem_a, x_a, own_a, strand_b, elem_b, x_b, own_b, frames, B, Theta, offsets,
              indptr, data, indices):
    """Every entry of H, contact by contact: the blocks of the strand with the smaller dof offset
    first; a self-contact writes its longer range and adds the other side onto it."""
    J = np.empty((3, 3))
    for i in range(strand_a.shape[0]):
        start = indptr[3 * i]
        row_len = indptr[3 * i + 1] - start
        sa, sb, ea, eb = strand_a[i], strand_b[i], elem_a[i], elem_b[i]
        F = frames[i]
        if sb < 0:
            _add_side(F, 1.0, x_a[i], own_a[i], B, Theta, sa, ea, offsets[sa], 0, start, row_len, False, J,
                      data, indices)
        elif sb == sa:
            if ea >= eb:
                _add_side(F, 1.0, x_a[i], own_a[i], B, Theta, sa, ea, offsets[sa], 0, start, row_len, False, J,
                          data, indices)
                _add_side(F, -1.0, x_b[i], own_b[i], B, Theta, sb, eb, offsets[sb], 0, start, row_len, True, J,
                          data, indices)
            else:
                _add_side(F, -1.0, x_b[i], own_b[i], B, Theta, sb, eb, offsets[sb], 0, start, row_len, False, J,
                          data, indices)
                _add_side(F, 1.0, x_a[i], own_a[i], B, Theta, sa, ea, offsets[sa], 0, start, row_len, True, J,
                          data, indices)
        elif offsets[sa] <= offsets[sb]:
            _add_side(F, 1.0, x_a[i], own_a[i], B, Theta, sa, ea, offsets[sa], 0, start, row_len, False, J,
                      data, indices)
            _add_side(F, -1.0, x_b[i], own_b[i], B, Theta, sb, eb, offsets[sb], ea + 1, start, row_len, False, J,
                      data, indices)
        else:
            _add_side(F, -1.0, x_b[i], own_b[i], B, Theta, sb, eb, offsets[sb], 0, start, row_len, False, J,
                      data, indices)
            _add_side(F, 1.0, x_a[i], own_a[i], B, Theta, sa, ea, offsets[sa], eb + 1, start, row_len, False, J,
                      data, indices)


def generalized_contact_force(helix: sh.SuperHelix, contacts, forces: np.ndarray,
                              kin: sh.Kinematics | None = None, parts=None) -> np.ndarray:
    """H^T r from the point forces, without H: (S, N, 3), in O(S N + m) time and memory.

    The world force on strand a is f = F_i^T r_i at x = C(s_a), its opposite on strand b.  With
    dC/domega_k = B_k - [x]x Theta_k for a point beyond element k, B_k = R_k D_k + [C_{k+1}]x Theta_k,
    f contributes B_k^T f + Theta_k^T (x cross f) to element k, so per strand, with the suffix sums F_{>k}
    (forces on points beyond element k) and M_{>k} (their moments x cross f about the origin),

        Q_k = D_k^T R_k^T F_{>k} + Theta_k^T (M_{>k} - C_{k+1} x F_{>k}) + sum over the points p on
              element k of own_p^T f_p.

    (The equilibrium check uses this; it never builds H.  tests/reference/contact.py has the dense
    point-Jacobian version the tests compare with.)  ``parts``: point_jacobian_parts of the contact points on
    strands (:func:`contact_points` with strand >= 0) when already known (contact/operator.py).
    """
    if kin is None:
        kin = cl.kinematics(helix) if isinstance(helix, cl.SuperClothoid) else sh.kinematics(helix)
    frames = np.asarray(contacts.frame, dtype=np.float64).reshape(-1, 3, 3)
    world = np.einsum("pji,pj->pi", frames, np.asarray(forces, dtype=np.float64).reshape(-1, 3))
    strand, s = contact_points(contacts)
    keep = strand >= 0
    return point_forces_generalized(helix, kin, strand[keep], s[keep], np.concatenate([world, -world])[keep], parts)


def contact_points(contacts) -> tuple[np.ndarray, np.ndarray]:
    """Both sides of the contacts as one list of points (2m,): strands (-1: the head) and arc lengths, side a
    then side b."""
    strand = np.concatenate([np.asarray(contacts.strand_a, dtype=np.int64),
                             np.asarray(contacts.strand_b, dtype=np.int64)])
    s = np.concatenate([np.asarray(contacts.s_a, dtype=np.float64), np.asarray(contacts.s_b, dtype=np.float64)])
    return strand, s


def point_forces_generalized(helix: sh.SuperHelix, kin: sh.Kinematics, strand, s, f, parts=None) -> np.ndarray:
    """The generalised force of world point forces: Q = sum_p (dC(s_p)/dq)^T f_p, (S, N, 3), for forces f_p
    (P, 3) at arc lengths s_p on strands ``strand`` (P,), by the suffix sums of
    :func:`generalized_contact_force` in O(S N + P).  ``parts``: the points' superhelix.point_jacobian_parts when
    already known (contact/operator.py keeps them per configuration).  A Super Space Clothoid: (S, N + 1, 3), from
    its dense point Jacobians (:func:`clothoid_point_forces_generalized`)."""
    if isinstance(helix, cl.SuperClothoid):
        return clothoid_point_forces_generalized(helix, kin, strand, s, f)
    S, N = helix.curvatures.shape[:2]
    out = np.zeros((S, N, 3))
    if len(strand):
        strand = np.ascontiguousarray(strand, dtype=np.int64)
        elem, x, own = parts if parts is not None else sh.point_jacobian_parts(helix, strand, s, kin)
        _generalized_force_kernel(strand, elem, np.ascontiguousarray(x), np.ascontiguousarray(own),
                                  np.ascontiguousarray(f, dtype=np.float64), np.ascontiguousarray(kin.C),
                                  np.ascontiguousarray(kin.R), np.ascontiguousarray(kin.D),
                                  np.ascontiguousarray(kin.Theta), helix.n_elements, out)
    return out


@njit(cache=True)
def _generalized_force_kernel(strand, elem, x, own, f, C, R, D, Theta, n_elements, out):
    """Bin the forces, moments x cross f and own_p^T f_p per element, then one pass from each strand's tip
    (generalized_contact_force)."""
    S, N = out.shape[0], out.shape[1]
    force = np.zeros((S, N, 3))
    moment = np.zeros((S, N, 3))
    touched = np.zeros(S, dtype=np.bool_)
    for p in range(strand.shape[0]):
        k, e = strand[p], elem[p]
        if e >= n_elements[k]:  # a strand without elements
            continue
        touched[k] = True
        f0, f1, f2 = f[p, 0], f[p, 1], f[p, 2]
        for b in range(3):
            out[k, e, b] += own[p, 0, b] * f0 + own[p, 1, b] * f1 + own[p, 2, b] * f2
        force[k, e, 0] += f0
        force[k, e, 1] += f1
        force[k, e, 2] += f2
        moment[k, e, 0] += x[p, 1] * f2 - x[p, 2] * f1
        moment[k, e, 1] += x[p, 2] * f0 - x[p, 0] * f2
        moment[k, e, 2] += x[p, 0] * f1 - x[p, 1] * f0
    for k in range(S):
        if not touched[k]:
            continue
        F0 = F1 = F2 = 0.0  # forces beyond element j
        M0 = M1 = M2 = 0.0  # their moments
        for j in range(n_elements[k] - 1, -1, -1):
            # r = R_j^T F, m = M - C_{j+1} x F
            r0 = R[k, j, 0, 0] * F0 + R[k, j, 1, 0] * F1 + R[k, j, 2, 0] * F2
            r1 = R[k, j, 0, 1] * F0 + R[k, j, 1, 1] * F1 + R[k, j, 2, 1] * F2
            r2 = R[k, j, 0, 2] * F0 + R[k, j, 1, 2] * F1 + R[k, j, 2, 2] * F2
            c0, c1, c2 = C[k, j + 1, 0], C[k, j + 1, 1], C[k, j + 1, 2]
            m0 = M0 - (c1 * F2 - c2 * F1)
            m1 = M1 - (c2 * F0 - c0 * F2)
            m2 = M2 - (c0 * F1 - c1 * F0)
            for b in range(3):
                out[k, j, b] += (D[k, j, 0, b] * r0 + D[k, j, 1, b] * r1 + D[k, j, 2, b] * r2
                                 + Theta[k, j, 0, b] * m0 + Theta[k, j, 1, b] * m1 + Theta[k, j, 2, b] * m2)
            F0 += force[k, j, 0]
            F1 += force[k, j, 1]
            F2 += force[k, j, 2]
            M0 += moment[k, j, 0]
            M1 += moment[k, j, 1]
            M2 += moment[k, j, 2]
