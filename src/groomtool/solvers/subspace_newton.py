"""Subspace Newton steps for the SOCQP, between Gauss-Seidel sweeps (issue 22).

Gauss-Seidel identifies which contacts take off, stick or slip long before it converges: on the shared
generator's 30k problem fewer than 100 of 30,000 contacts are still misclassified after 140 sweeps, while the
forces themselves are still off by O(1) (the slow modes of W).  Given that classification, the SOCQP

    min f(r) = 1/2 r^T W r + b^T r,   r_i in K_mu_i = {||r_T|| <= mu r_N}

is, locally, a smooth problem on the face each r_i lies on:

* take-off (r_i = 0): r_i stays 0;
* stick (r_i inside the cone): r_i is free;
* slip (r_i on the cone's boundary, r_N > 0): g_i(r_i) = ||r_T,i|| - mu_i r_N,i = 0, multiplier
  lambda_i = ||u_T,i|| (u_i = W r + b = lambda_i (mu_i, -w_i), w_i = r_T,i / ||r_T,i||).

One SQP (Newton) step on that face solves, for d in the tangent space of the face,

    min_d 1/2 d^T (W + Lambda) d + u^T d,    d_i = 0 (take-off),  n_i . d_i = 0 (slip)

with the Lagrangian's curvature Lambda_i = lambda_i / ||r_T,i|| (I_T - w_i w_i^T) on the tangential block of
a slipping contact (the Hessian of lambda_i g_i), n_i = (-mu_i, w_i) / sqrt(1 + mu_i^2).  In an orthonormal basis
B of the faces' tangent spaces (two coordinates per slipping contact, three per sticking one, none for a take-off:
``face_bases``) this is the SPD system  B^T (W + Lambda) B y = -B^T u,  d = B y, assembled once per step as 2x2
blocks over "slots" (``reduced_slots``: take-off rows and columns dropped, so it holds about half of W's stored
numbers on the shared generator's problems) and solved inexactly by conjugate gradients preconditioned by the
slots' diagonal blocks (``slot_cg``).
The step is taken along the projected path r(alpha) = P_K(r + alpha d), alpha = 1, 1/2, ..., and accepted only
if it lowers f (a contact whose class was wrong is put back into its cone by the projection, and the following
sweeps correct the classification).  So a step never makes f worse, and the caller keeps the Gauss-Seidel
sweeps around it: every returned point is still a sweep's output.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


_FM = {"contract", "arcp", "nsz"}

TAKEOFF = 0
STICK = 1
SLIP = 2
SLIP_TOL = 1e-8  #: relative distance to the cone's boundary under which a contact counts as slipping


@njit(cache=True, fastmath=_FM)
def classify(r, u, mu, kind, curv):
    """Per contact: its face (kind: TAKEOFF, STICK or SLIP; a frictionless contact with r_N > 0 counts as SLIP,
    its face being the ray r_T = 0) and, for a slipping one with mu > 0, the curvature lambda_i / ||r_T,i|| of its
    constraint (curv; 0 otherwise), lambda_i = -(n_i . u_i) / sqrt(1 + mu_i^2) clipped at 0.
    Returns the counts (take-off, stick, slip)."""
    m = r.shape[0]
    n_take = 0
    n_stick = 0
    n_slip = 0
    for i in range(m):
        rn = r[i, 0]
        t1 = r[i, 1]
        t2 = r[i, 2]
        nt = math.sqrt(t1 * t1 + t2 * t2)
        mi = mu[i]
        curv[i] = 0.0
        if not (rn > 0.0):
            kind[i] = TAKEOFF
            n_take += 1
        elif mi == 0.0:
            kind[i] = SLIP
            n_slip += 1
        elif nt > 0.0 and nt >= mi * rn * (1.0 - SLIP_TOL):
            kind[i] = SLIP
            n_slip += 1
            # u = lambda (mu, -w) on the optimum's face
            lam = (mi * u[i, 0] - (t1 * u[i, 1] + t2 * u[i, 2]) / nt) / (1.0 + mi * mi)
            if lam > 0.0:
                curv[i] = lam / nt
        else:
            kind[i] = STICK
            n_stick += 1
    return n_take, n_stick, n_slip


@njit(cache=True, fastmath=_FM)
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return s


@njit(cache=True, fastmath=_FM)
def projected_point(mu, r, d, alpha, out):
    """out = P_K(r + alpha d), contact by contact."""
    for i in range(r.shape[0]):
        zn = r[i, 0] + alpha * d[i, 0]
        z1 = r[i, 1] + alpha * d[i, 1]
        z2 = r[i, 2] + alpha * d[i, 2]
        nt = math.sqrt(z1 * z1 + z2 * z2)
        mi = mu[i]
        if nt <= mi * zn and zn >= 0.0:
            out[i, 0] = zn
            out[i, 1] = z1
            out[i, 2] = z2
        elif mi * nt <= -zn:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0
        else:
            a = (zn + mi * nt) / (1.0 + mi * mi)
            s = a * mi / nt
            out[i, 0] = a
            out[i, 1] = s * z1
            out[i, 2] = s * z2



@njit(cache=True, fastmath=_FM)
def upper2_matvec(indptr, indices, blocks, x, out):
    """out = A x for a symmetric A stored as its upper triangle of 2x2 blocks (diagonal block first)."""
    n = indptr.shape[0] - 1
    for i in range(n):
        out[i, 0] = 0.0
        out[i, 1] = 0.0
    for i in range(n):
        y0 = x[i, 0]
        y1 = x[i, 1]
        p0 = indptr[i]
        u0 = blocks[p0, 0, 0] * y0 + blocks[p0, 0, 1] * y1
        u1 = blocks[p0, 1, 0] * y0 + blocks[p0, 1, 1] * y1
        for p in range(p0 + 1, indptr[i + 1]):
            j = indices[p]
            x0 = x[j, 0]
            x1 = x[j, 1]
            b00 = blocks[p, 0, 0]
            b01 = blocks[p, 0, 1]
            b10 = blocks[p, 1, 0]
            b11 = blocks[p, 1, 1]
            u0 += b00 * x0 + b01 * x1
            u1 += b10 * x0 + b11 * x1
            out[j, 0] += b00 * y0 + b10 * y1
            out[j, 1] += b01 * y0 + b11 * y1
        out[i, 0] += u0
        out[i, 1] += u1


@njit(cache=True, fastmath=_FM)
def face_bases(r, mu, kind):
    """Orthonormal bases of the faces' tangent spaces, two columns per slot: a slipping contact has one slot
    (e1 = (0, -w2, w1), e2 = (1, mu w) / sqrt(1 + mu^2)), a sticking one two ((e_N, e_T1) and (e_T2, 0)), a
    frictionless one one ((e_N, 0)), a take-off none.  Returns (slot_ptr (m + 1,), basis (slots, 3, 2))."""
    m = r.shape[0]
    ptr = np.zeros(m + 1, dtype=np.int64)
    for i in range(m):
        ns = 0
        if kind[i] == STICK:
            ns = 2
        elif kind[i] == SLIP:
            ns = 1
        ptr[i + 1] = ptr[i] + ns
    B = np.zeros((ptr[m], 3, 2))
    for i in range(m):
        q = ptr[i]
        if kind[i] == STICK:
            B[q, 0, 0] = 1.0
            B[q, 1, 1] = 1.0
            B[q + 1, 2, 0] = 1.0
        elif kind[i] == SLIP:
            mi = mu[i]
            if mi == 0.0:
                B[q, 0, 0] = 1.0
            else:
                t1 = r[i, 1]
                t2 = r[i, 2]
                nt = math.sqrt(t1 * t1 + t2 * t2)
                w1 = t1 / nt
                w2 = t2 / nt
                B[q, 1, 0] = -w2
                B[q, 2, 0] = w1
                s = 1.0 / math.sqrt(1.0 + mi * mi)
                B[q, 0, 1] = s
                B[q, 1, 1] = mi * w1 * s
                B[q, 2, 1] = mi * w2 * s
    return ptr, B


@njit(cache=True, inline="always", fastmath=_FM)
def _btab(Ba, Wb, Bb, out, q):
    """out[q] = Ba^T Wb Bb (Wb 3x3; Ba, Bb 3x2)."""
    for a in range(2):
        for c in range(2):
            acc = 0.0
            for k1 in range(3):
                ba = Ba[k1, a]
                if ba != 0.0:
                    t = 0.0
                    for k2 in range(3):
                        t += Wb[k1, k2] * Bb[k2, c]
                    acc += ba * t
            out[q, a, c] = acc


@njit(cache=True, fastmath=_FM)
def reduced_slots(indptr, indices, blocks, curv, slot_ptr, B):
    """The reduced Hessian B^T (W + Lambda) B over the slots, as an upper triangle of 2x2 blocks, the diagonal
    block first in each row (the slots of a contact are consecutive).  Lambda_i = curv_i (I_T - w w^T) adds
    curv_i to the (e1, e1) entry of a slipping contact's slot.  Returns (indptr, indices, blocks)."""
    m = indptr.shape[0] - 1
    S = slot_ptr[m]
    cptr = np.zeros(S + 1, dtype=np.int64)
    for i in range(m):
        ns = slot_ptr[i + 1] - slot_ptr[i]
        if ns == 0:
            continue
        other = 0
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j != i:
                other += slot_ptr[j + 1] - slot_ptr[j]
        for a in range(ns):
            q = slot_ptr[i] + a
            cptr[q + 1] = cptr[q] + (ns - a) + other  # the diagonal, the later slots of i, the slots of j > i
    nnz = cptr[S]
    cidx = np.empty(nnz, dtype=np.int32)
    cblk = np.empty((nnz, 2, 2))
    Wd = np.empty((3, 3))
    for i in range(m):
        s0 = slot_ptr[i]
        ns = slot_ptr[i + 1] - s0
        if ns == 0:
            continue
        for a in range(3):
            for c in range(3):
                Wd[a, c] = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            if indices[p] == i:
                for a in range(3):
                    for c in range(3):
                        Wd[a, c] += blocks[p, a, c]
        for a in range(ns):
            sa = s0 + a
            q = cptr[sa]
            for b2 in range(a, ns):
                cidx[q] = s0 + b2
                _btab(B[sa], Wd, B[s0 + b2], cblk, q)
                q += 1
            for p in range(indptr[i], indptr[i + 1]):
                j = indices[p]
                if j == i:
                    continue
                for sb in range(slot_ptr[j], slot_ptr[j + 1]):
                    cidx[q] = sb
                    _btab(B[sa], blocks[p], B[sb], cblk, q)
                    q += 1
        cblk[cptr[s0], 0, 0] += curv[i]
        # the padded column of a frictionless slot or of a stick's second slot: 1 on its diagonal (its
        # right-hand side is 0, so it stays 0)
        for a in range(ns):
            sa = s0 + a
            q = cptr[sa]
            if B[sa, 0, 1] == 0.0 and B[sa, 1, 1] == 0.0 and B[sa, 2, 1] == 0.0:
                cblk[q, 1, 1] = 1.0
    return cptr, cidx, cblk


@njit(cache=True, fastmath=_FM)
def slot_cg(cptr, cidx, cblk, slot_ptr, B, u, max_iter, rtol):
    """Block-Jacobi (2x2) preconditioned CG on the slots' system  A y = -B^T u; returns (d = B y on all
    contacts, iterations, ||residual|| / ||B^T u||)."""
    m = u.shape[0]
    S = slot_ptr[m]
    res = np.zeros((S, 2))
    for i in range(m):
        for q in range(slot_ptr[i], slot_ptr[i + 1]):
            for a in range(2):
                res[q, a] = -(B[q, 0, a] * u[i, 0] + B[q, 1, a] * u[i, 1] + B[q, 2, a] * u[i, 2])
    Mi = np.empty((S, 2, 2))
    for q in range(S):
        p = cptr[q]
        a = cblk[p, 0, 0]
        b = 0.5 * (cblk[p, 0, 1] + cblk[p, 1, 0])
        c = cblk[p, 1, 1]
        det = a * c - b * b
        if det > 0.0:
            Mi[q, 0, 0] = c / det
            Mi[q, 0, 1] = -b / det
            Mi[q, 1, 0] = -b / det
            Mi[q, 1, 1] = a / det
        else:
            Mi[q, 0, 0] = 1.0 / a if a > 0.0 else 0.0
            Mi[q, 0, 1] = 0.0
            Mi[q, 1, 0] = 0.0
            Mi[q, 1, 1] = 1.0 / c if c > 0.0 else 0.0
    y = np.zeros((S, 2))
    d = np.zeros((m, 3))
    r0 = 0.0
    for q in range(S):
        r0 += res[q, 0] * res[q, 0] + res[q, 1] * res[q, 1]
    r0 = math.sqrt(r0)
    if r0 == 0.0 or S == 0:
        return d, 0, 0.0
    z = np.empty((S, 2))
    qv = np.empty((S, 2))
    for q in range(S):
        z[q, 0] = Mi[q, 0, 0] * res[q, 0] + Mi[q, 0, 1] * res[q, 1]
        z[q, 1] = Mi[q, 1, 0] * res[q, 0] + Mi[q, 1, 1] * res[q, 1]
    p = z.copy()
    rz = 0.0
    for q in range(S):
        rz += res[q, 0] * z[q, 0] + res[q, 1] * z[q, 1]
    it = 0
    rn = r0
    while it < max_iter:
        upper2_matvec(cptr, cidx, cblk, p, qv)
        pq = 0.0
        for q in range(S):
            pq += p[q, 0] * qv[q, 0] + p[q, 1] * qv[q, 1]
        if not (pq > 0.0) or not (rz > 0.0):
            break
        al = rz / pq
        rr = 0.0
        for q in range(S):
            y[q, 0] += al * p[q, 0]
            y[q, 1] += al * p[q, 1]
            res[q, 0] -= al * qv[q, 0]
            res[q, 1] -= al * qv[q, 1]
            rr += res[q, 0] * res[q, 0] + res[q, 1] * res[q, 1]
        it += 1
        rn = math.sqrt(rr)
        if rn <= rtol * r0:
            break
        rz2 = 0.0
        for q in range(S):
            z0 = Mi[q, 0, 0] * res[q, 0] + Mi[q, 0, 1] * res[q, 1]
            z1 = Mi[q, 1, 0] * res[q, 0] + Mi[q, 1, 1] * res[q, 1]
            z[q, 0] = z0
            z[q, 1] = z1
            rz2 += res[q, 0] * z0 + res[q, 1] * z1
        be = rz2 / rz
        rz = rz2
        for q in range(S):
            p[q, 0] = z[q, 0] + be * p[q, 0]
            p[q, 1] = z[q, 1] + be * p[q, 1]
    for i in range(m):
        for q in range(slot_ptr[i], slot_ptr[i + 1]):
            for a in range(3):
                d[i, a] += B[q, a, 0] * y[q, 0] + B[q, a, 1] * y[q, 1]
    return d, it, rn / r0


def objective(r: np.ndarray, u: np.ndarray, b: np.ndarray) -> float:
    """f(r) = 1/2 r^T W r + b^T r = 1/2 r . (u + b) for u = W r + b."""
    return 0.5 * float(_dot(r, u) + _dot(r, b))


class SubspaceNewton:
    """Newton steps on the faces Gauss-Seidel has identified, for an AssembledOperator (W's upper blocks).

    cg_iter: (few, many) conjugate-gradient iterations per step: ``few`` while the last step had to be shortened
    (alpha < 1: the classification is still changing, a precise direction is wasted), ``many`` once a full step
    was accepted.  cg_rtol: CG stops earlier at this relative residual."""

    def __init__(self, op, cg_iter=(30, 200), cg_rtol: float = 1e-3, max_halvings: int = 5):
        m = op.b.shape[0]
        self.op = op
        few, many = (cg_iter, cg_iter) if np.isscalar(cg_iter) else cg_iter
        self.cg_few = int(few)
        self.cg_many = int(many)
        self.cg_rtol = float(cg_rtol)
        self.max_halvings = int(max_halvings)
        self.kind = np.empty(m, dtype=np.int64)
        self.curv = np.empty(m)
        self.steps = 0
        self.accepted = 0
        self.cg_iterations = 0
        self.last = None

    def step(self, r: np.ndarray, u: np.ndarray):
        """From r (m, 3) in the cones with u = W r + b: (P_K(r + alpha d), its u) for the first alpha in 1, 1/2,
        ... that lowers f, or None (r is then left as it is)."""
        op = self.op
        W = op.W
        counts = classify(r, u, op.mu, self.kind, self.curv)
        slot_ptr, B = face_bases(r, op.mu, self.kind)
        cptr, cidx, cblk = reduced_slots(W.indptr, W.indices, W.blocks, self.curv, slot_ptr, B)
        full = self.last is not None and self.last["alpha"] == 1.0
        d, its, rel = slot_cg(cptr, cidx, cblk, slot_ptr, B, u, self.cg_many if full else self.cg_few, self.cg_rtol)
        self.steps += 1
        self.cg_iterations += its
        f0 = objective(r, u, op.b)
        trial = np.empty_like(r)
        alpha = 1.0
        for _ in range(self.max_halvings + 1):
            projected_point(op.mu, r, d, alpha, trial)
            ut = op.velocity(trial)
            ft = objective(trial, ut, op.b)
            if ft < f0:
                self.accepted += 1
                self.last = dict(counts=counts, cg=its, cg_rel=rel, alpha=alpha, f0=f0, f1=ft)
                return trial, ut
            alpha *= 0.5
        self.last = dict(counts=counts, cg=its, cg_rel=rel, alpha=0.0, f0=f0, f1=f0)
        return None
