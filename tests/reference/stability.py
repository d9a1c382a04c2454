"""References for groomtool.stability that only the tests use.

* :func:`contact_load_hessians_reference`: ``stability.contact_load_hessians`` as it was before the analytic
  Super-Helix Hessian (superhelix.point_load_hessian_parts): central differences of the exact generalized
  force contact.jacobian.point_forces_generalized, 2n perturbed copies of each strand, symmetrised; about
  1e-10 relative error.  For Super Space Clothoids it is still what the package does.
"""

from __future__ import annotations

import numpy as np

from groomtool.contact.jacobian import point_forces_generalized
from groomtool.rods import clothoid as cl
from groomtool.rods import superhelix as sh


def contact_load_hessians_reference(helix, strands, point_strand, point_s, point_force,
                                    rotation_step: float = 1e-6, chunk_dofs: int = 6000) -> list:
    """d(J^T f)/dq per listed strand (dense n x n, n = 3 N_s): the stiffness of the world point loads
    f_p at arc lengths s_p held fixed (dead loads), i.e. the Hessian of sum_p f_p . C(s_p; q).

    Central differences of the exact generalized force (contact.jacobian.point_forces_generalized) with
    a step of ``rotation_step`` radians per element (dq_j = rotation_step / l_j): truncation O(step^2) and
    round-off O(eps / step), about 1e-10 relative; symmetrised (it is a Hessian).  Strands are batched so
    that at most ``chunk_dofs`` perturbed copies are built at once."""
    clothoid = isinstance(helix, cl.SuperClothoid)
    mod = cl if clothoid else sh
    extra = 1 if clothoid else 0  # a clothoid's dofs are its N + 1 nodes
    strands = np.asarray(strands, dtype=np.int64)
    point_strand = np.asarray(point_strand, dtype=np.int64)
    order = np.argsort(point_strand, kind="stable")
    ps, pss, pf = point_strand[order], np.asarray(point_s, float)[order], np.asarray(point_force, float)[order]
    out = [None] * len(strands)
    start = 0
    while start < len(strands):
        stop, copies = start, 0
        while stop < len(strands) and (copies == 0 or copies + 6 * (helix.n_elements[strands[stop]] + extra)
                                       <= chunk_dofs):
            copies += 6 * (int(helix.n_elements[strands[stop]]) + extra)
            stop += 1
        ids = strands[start:stop]
        sub = helix.subset(ids)
        N = sub.max_elements + extra
        owner, signs, dofs = [], [], []
        for i in range(len(ids)):
            n = 3 * (int(sub.n_elements[i]) + extra)
            owner.append(np.full(2 * n, i))
            signs.append(np.repeat([1.0, -1.0], n))
            dofs.append(np.tile(np.arange(n), 2))
        owner, signs, dofs = np.concatenate(owner), np.concatenate(signs), np.concatenate(dofs)
        elem, comp = dofs // 3, dofs % 3
        if clothoid:  # node i: the mean length of its (one or two) elements
            lpad = np.concatenate([np.zeros((len(ids), 1)), sub.lengths, np.zeros((len(ids), 1))], axis=1)
            both = lpad[:, :-1] + lpad[:, 1:]
            nadj = (lpad[:, :-1] > 0).astype(float) + (lpad[:, 1:] > 0)
            step = rotation_step / (both / np.maximum(nadj, 1.0))[owner, elem]
        else:
            step = rotation_step / sub.lengths[owner, elem]
        q = sub.curvatures[owner].copy()
        q[np.arange(len(owner)), elem, comp] += signs * step
        copies_helix = type(sub)(sub.root_positions[owner], sub.root_frames[owner], sub.lengths[owner], q,
                                 sub.n_elements[owner])
        # every copy carries the loads of its strand
        lo = np.searchsorted(ps, ids, "left")
        hi = np.searchsorted(ps, ids, "right")
        count = (hi - lo)[owner]
        copy_of_point = np.repeat(np.arange(len(owner)), count)
        first = np.repeat(lo[owner], count)
        within = np.arange(len(copy_of_point)) - np.repeat(np.cumsum(count) - count, count)
        pidx = first + within
        g = point_forces_generalized(copies_helix, mod.kinematics(copies_helix), copy_of_point, pss[pidx], pf[pidx])
        g = g.reshape(len(owner), 3 * N)
        pos = 0
        for i in range(len(ids)):
            n = 3 * (int(sub.n_elements[i]) + extra)
            plus, minus = g[pos:pos + n, :n], g[pos + n:pos + 2 * n, :n]
            h = step[pos:pos + n]
            D = ((plus - minus) / (2.0 * h[:, None])).T  # column k: d g / d q_k
            out[start + i] = 0.5 * (D + D.T)
            pos += 2 * n
        start = stop
    return out
