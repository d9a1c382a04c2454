"""Strand-split (consensus) ADMM for the SOCQP of a ContactProblem (issue 16; docs/solvers.md section 12).

    min_r 1/2 r^T W r + b^T r,  r_i in K_mu_i,   W = H D H^T + 2 gamma I

Contact i acts on the strands its rows touch (two for a strand/strand contact, one against the head): its
Jacobian H_i = sum_e J_e over its *ends* e, J_e holding strand s(e)'s columns only.  Then
1/2 |D^1/2 H^T r|^2 = sum_s 1/2 |D_s^1/2 sum_{e on s} J_e^T r_i(e)|^2 splits by strand, and ADMM on the copies
x_e = s_i(e) of each contact's force (Boyd et al. 2011, consensus form, over-relaxed) alternates

    s-step (per contact):  s_i = P_K( (rho_i sum_e z_e - b_i) / (2 gamma + n_i rho_i) ),   n_i: ends of contact i
    x-step (per strand):   (J_s D_s J_s^T + rho) x_s = rho w_s,  w_e = 2 s_i(e) - z_e,  by Woodbury
                           x_s = w_s - J_s M_s^-1 J_s^T w_s / rho,   M_s = D_s^-1 + J_s^T J_s / rho  (n_s x n_s,
                           Cholesky factored ONCE: rho is fixed; a run from a previous run's state on the same H
                           keeps the factors of the strands whose D_s changed by a scalar: StrandSplit.reusing)
    update:                z_e += alpha (x_e - s_i(e))        (over-relaxed; z = x^ + lam, the scaled multiplier)

(the Douglas-Rachford form of the consensus ADMM: x^ = alpha x + (1 - alpha) s, lam += x^ - s),
with rho_i = beta tr(W_ii) / 3 per contact, and Anderson mixing (anderson.py) of the state z (3 per end).  Each
strand's exact solve sees all of its contacts at once: the directions that Gauss-Seidel corrects one contact at
a time by ~2 gamma / W_ii per sweep (redundant contacts, docs/solvers.md section 9) are solved in one step, and
what is left is the consensus between the two strands of each contact.  One iteration costs about two
products with H (per end: its panel of packed H) and one triangular solve pair per strand: ~ a Gauss-Seidel sweep.

For Super-Helices (run_admm's ``geometry``: the groom and its contacts) M_s is block-semiseparable of rank 6 and the
x-step runs through its O(n_s) factor (admm_structured.py: harolongo's x-step 443 -> 73 ms CPU, no dense factors);
without the geometry or with dense D blocks (Super Space Clothoids) through the dense Cholesky factors here.

s is always in the cones (an exact equilibrium in the inversion), so the caller's ``stop`` rule (certificate.py's
bound) can certify it at any check.  With ``stop_strands`` the rule also gets the strand solves'
h = sum_e J_e^T x_e: l = D^1/2 h is a dual point whose gap is about the strands' disagreement
1/2 |D^1/2 (H^T s - h)|^2, without the 1 / (4 gamma) that the dual point A^T s puts on the velocity mismatch of s
(certificate.error_bound_with_strands).  Measured on example_groom(1000) with all contacts (67,805): the certified
rest-curvature bound 1e-3 where Gauss-Seidel stalls, after 290 iterations with the strand certificate (840 with
A^T s alone; docs/solvers.md section 12).  SOC law only.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import residual as _res
from .admm_structured import HelixContacts, StructuredSplit, applies
from .anderson import AndersonMixer
from .blocks import symmetrize_add_diagonal
from .cones import SOC, project_cone

_FM = {"contract", "arcp", "nsz"}
_FM_SOLVE = _FM | {"reassoc"}  #: _x_step's triangular solves (the sums vectorised)

BETA = 0.03  #: rho_i = BETA tr(W_ii) / 3 (example_groom(300) with all contacts: 0.01 slower, 0.1 / 0.3 slower)
ALPHA = 1.6  #: over-relaxation
ANDERSON = 8  #: memory of the Anderson mixing of (x^, lam); 0 = plain ADMM
FACTOR_BLOCKS = 6  #: _factor_strands: a strand's ends in this many blocks by the columns they reach (BLAS per block)
WARM_SWEEPS = 20  #: Gauss-Seidel sweeps before the first ADMM iteration (cold starts only)


# ----------------------------------------------------------------------------------------------
# set-up: ends and the strand systems
# ----------------------------------------------------------------------------------------------
@njit(cache=True)
def _count_ends(ptr, cols, dof_offsets):
    """Ends per contact: the distinct strands among its (sorted) panel columns."""
    m = ptr.shape[0] - 1
    out = np.zeros(m, dtype=np.int64)
    for i in range(m):
        last = -1
        for p in range(ptr[i], ptr[i + 1]):
            s = np.searchsorted(dof_offsets, cols[p], side="right") - 1
            if s != last:
                out[i] += 1
                last = s
    return out


@njit(cache=True)
def _fill_ends(ptr, cols, dof_offsets, cend_ptr, end_contact, end_strand, end_p0, end_p1):
    """Per end (contact-major here): its contact, strand and panel range [p0, p1) of packed H."""
    m = ptr.shape[0] - 1
    for i in range(m):
        k = cend_ptr[i] - 1
        last = -1
        for p in range(ptr[i], ptr[i + 1]):
            s = np.searchsorted(dof_offsets, cols[p], side="right") - 1
            if s != last:
                k += 1
                end_contact[k] = i
                end_strand[k] = s
                end_p0[k] = p
                last = s
            end_p1[k] = p + 1


@njit(cache=True)
def _factor_strands(strands, strand_ptr, ends_sorted, end_p0, end_p1, cols, vals, rho_end, dof_offsets, D_data,
                    D_ptr, D_is_diag, D_inv, L_ptr, L):
    """For each strand s of ``strands``: M_s = D_s^-1 + J_s^T J_s (J_s: the rows J_e / sqrt(rho_e) of its ends,
    dense; the ends sorted by the columns they reach and taken in FACTOR_BLOCKS blocks, one BLAS product per block
    over its columns only: a Super-Helix contact reaches the dofs up to its element; D_s^-1 from D_data when
    diagonal, from D_inv (laid out like D_data) when dense), symmetrised, then its Cholesky factor
    (np.linalg.cholesky: LAPACK), row-major at L[L_ptr[s]:] (lower, the upper triangle zeroed).  Returns the first
    strand whose M_s has a diagonal entry <= 0, or -1 (an M_s that is not positive definite otherwise raises
    numpy's LinAlgError)."""
    for q in range(strands.shape[0]):
        s = strands[q]
        o = dof_offsets[s]
        n = dof_offsets[s + 1] - o
        base = L_ptr[s]
        q0 = strand_ptr[s]
        k = strand_ptr[s + 1] - q0
        width = np.zeros(k, dtype=np.int64)  # the columns an end reaches
        for qq in range(k):
            e = ends_sorted[q0 + qq]
            for p in range(end_p0[e], end_p1[e]):
                width[qq] = max(width[qq], cols[p] - o + 1)
        order = np.argsort(width)
        M = np.zeros((n, n))
        n_blocks = min(FACTOR_BLOCKS, k)
        for b in range(n_blocks):  # ends by width, in blocks: each block's product only over the columns it reaches
            lo = b * k // n_blocks
            hi = (b + 1) * k // n_blocks
            c = width[order[hi - 1]]
            if hi == lo or c == 0:
                continue
            J = np.zeros((3 * (hi - lo), c))
            for qq in range(lo, hi):
                e = ends_sorted[q0 + order[qq]]
                w = 1.0 / math.sqrt(rho_end[e])
                r = 3 * (qq - lo)
                for p in range(end_p0[e], end_p1[e]):
                    a = cols[p] - o
                    J[r, a] = vals[p, 0] * w
                    J[r + 1, a] = vals[p, 1] * w
                    J[r + 2, a] = vals[p, 2] * w
            P = np.dot(J.T, J)
            for i in range(c):
                for j in range(c):
                    M[i, j] += P[i, j]
        d0 = D_ptr[s]
        if D_is_diag[s]:
            for i in range(n):
                M[i, i] += 1.0 / D_data[d0 + i]
        else:
            for i in range(n):
                for j in range(n):
                    M[i, j] += D_inv[d0 + i * n + j]
        for i in range(n):  # 0.5 (M + M^T)
            for j in range(i):
                t = 0.5 * (M[i, j] + M[j, i])
                M[i, j] = t
                M[j, i] = t
        for i in range(n):  # a cheap test first: LAPACK's failure would raise from inside the kernel
            if not M[i, i] > 0.0:
                return s
        C = np.linalg.cholesky(M)
        for i in range(n):
            row = base + i * n
            for j in range(n):
                L[row + j] = C[i, j]
    return -1


@njit(cache=True)
def _strand_ratios(old, new, ptr, rtol, out):
    """out[s] = g with new_s = g old_s to round-off (max |new - g old| <= rtol max |new| over strand s's block, g the
    least-squares ratio, > 0), else NaN."""
    for s in range(ptr.shape[0] - 1):
        a = 0.0
        b = 0.0
        big = 0.0
        for k in range(ptr[s], ptr[s + 1]):
            a += new[k] * old[k]
            b += old[k] * old[k]
            big = max(big, abs(new[k]))
        g = a / b if b > 0.0 else math.nan
        if not g > 0.0:
            out[s] = math.nan
            continue
        dev = 0.0
        for k in range(ptr[s], ptr[s + 1]):
            dev = max(dev, abs(new[k] - g * old[k]))
        out[s] = g if dev <= rtol * big else math.nan


@njit(cache=True)
def _carried(cend_ptr, end_strand, g, rtol, out):
    """out[i] = the common ratio g of contact i's strands when they all have one (equal within rtol), else NaN."""
    for i in range(cend_ptr.shape[0] - 1):
        gi = math.nan
        for e in range(cend_ptr[i], cend_ptr[i + 1]):
            ge = g[end_strand[e]]
            if not ge > 0.0:
                gi = math.nan
                break
            if e == cend_ptr[i]:
                gi = ge
            elif abs(ge - gi) > rtol * gi:
                gi = math.nan
                break
        out[i] = gi


@njit(cache=True)
def _reusable(strand_ptr, ends_sorted, end_contact, g, g_contact, out):
    """out[s]: strand s carries contacts, has a ratio g_s and every contact on it carries its rho over (its factor
    then is the old one / sqrt(g_s))."""
    for s in range(strand_ptr.shape[0] - 1):
        ok = strand_ptr[s + 1] > strand_ptr[s] and g[s] > 0.0
        for q in range(strand_ptr[s], strand_ptr[s + 1]):
            if not ok:
                break
            ok = g_contact[end_contact[ends_sorted[q]]] > 0.0
        out[s] = ok


@njit(cache=True, fastmath=_FM)
def _contact_diagonal(contacts, cend_ptr, end_strand, end_p0, end_p1, cols, vals, dof_offsets, D_data, D_ptr,
                      D_is_diag, gamma2, out):
    """out_i = sum_{e of i} J_e D_s(e) J_e^T + 2 gamma I (symmetrised) for the contacts listed."""
    for q in range(contacts.shape[0]):
        i = contacts[q]
        for x in range(3):
            for y in range(3):
                out[i, x, y] = 0.0
        for e in range(cend_ptr[i], cend_ptr[i + 1]):
            s = end_strand[e]
            o = dof_offsets[s]
            n = dof_offsets[s + 1] - o
            d0 = D_ptr[s]
            for p in range(end_p0[e], end_p1[e]):
                a = cols[p] - o
                if D_is_diag[s]:
                    d = D_data[d0 + a]
                    for x in range(3):
                        for y in range(3):
                            out[i, x, y] += vals[p, x] * d * vals[p, y]
                else:
                    for p2 in range(end_p0[e], end_p1[e]):
                        d = D_data[d0 + a * n + cols[p2] - o]
                        for x in range(3):
                            for y in range(3):
                                out[i, x, y] += vals[p, x] * d * vals[p2, y]
        symmetrize_add_diagonal(out, i, gamma2)


@njit(cache=True, fastmath=_FM)
def _gather_strand(q0, q1, o, n, ends_sorted, end_p0, end_p1, cols, vals, y, t):
    """t = sum_{e on the strand} J_e^T y_e (the strand's ends q0..q1 of ends_sorted, its dofs o..o + n)."""
    for k in range(n):
        t[k] = 0.0
    for q in range(q0, q1):
        e = ends_sorted[q]
        y0 = y[e, 0]
        y1 = y[e, 1]
        y2 = y[e, 2]
        for p in range(end_p0[e], end_p1[e]):
            t[cols[p] - o] += vals[p, 0] * y0 + vals[p, 1] * y1 + vals[p, 2] * y2


@njit(cache=True, fastmath=_FM)
def _end_times(e, o, end_p0, end_p1, cols, vals, z):
    """J_e z (3,) for the strand dofs z (indexed from the strand's first dof o)."""
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    for p in range(end_p0[e], end_p1[e]):
        zp = z[cols[p] - o]
        a0 += vals[p, 0] * zp
        a1 += vals[p, 1] * zp
        a2 += vals[p, 2] * zp
    return a0, a1, a2


@njit(cache=True, fastmath=_FM_SOLVE)
def _x_step(strand_ptr, ends_sorted, end_p0, end_p1, cols, vals, rho_end, dof_offsets, L_ptr, L, L_scale, w, x, t):
    """x_e = w_e - J_e M_s^-1 (sum_{e' on s} J_e'^T w_e') / rho_e for every strand s (M_s = c_s^2 L L^T, L lower,
    row-major, c_s = L_scale[s]: a factor kept from an earlier run, StrandSplit.reusing); t: scratch of the
    largest n_s.  The forward solve in dot form (rows of L, vectorised: _FM_SOLVE allows reassociation), the
    backward one in axpy form over the rows of L (contiguous, instead of its columns): 25 % less time per x-step
    than both in dot form with strided columns (n_s = 128)."""
    S = strand_ptr.shape[0] - 1
    for s in range(S):
        q0 = strand_ptr[s]
        q1 = strand_ptr[s + 1]
        if q0 == q1:
            continue
        o = dof_offsets[s]
        n = dof_offsets[s + 1] - o
        _gather_strand(q0, q1, o, n, ends_sorted, end_p0, end_p1, cols, vals, w, t)
        base = L_ptr[s]
        for k in range(n):  # L y = t
            acc = 0.0
            row = base + k * n
            for j in range(k):
                acc += L[row + j] * t[j]
            t[k] = (t[k] - acc) / L[row + k]
        for k in range(n - 1, -1, -1):  # L^T z = y: z_k, then its column of L^T (row k of L) out of the rest
            row = base + k * n
            zk = t[k] / L[row + k]
            t[k] = zk
            for j in range(k):
                t[j] -= L[row + j] * zk
        c = L_scale[s]
        if c != 1.0:
            c = 1.0 / (c * c)
            for k in range(n):
                t[k] *= c
        for q in range(q0, q1):
            e = ends_sorted[q]
            a0, a1, a2 = _end_times(e, o, end_p0, end_p1, cols, vals, t)
            inv = 1.0 / rho_end[e]
            x[e, 0] = w[e, 0] - a0 * inv
            x[e, 1] = w[e, 1] - a1 * inv
            x[e, 2] = w[e, 2] - a2 * inv


@njit(cache=True, fastmath=_FM)
def _s_step(cend_ptr, z, b, mu, gamma2, rho_c, s, w):
    """s_i = P_K((rho_i sum_e z_e - b_i) / (2 gamma + n_i rho_i)) and w_e = 2 s_i(e) - z_e (z = x^ + lam)."""
    m = b.shape[0]
    for i in range(m):
        r = rho_c[i]
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for e in range(cend_ptr[i], cend_ptr[i + 1]):
            a0 += z[e, 0]
            a1 += z[e, 1]
            a2 += z[e, 2]
        d = 1.0 / (gamma2 + (cend_ptr[i + 1] - cend_ptr[i]) * r)
        p0, p1, p2 = project_cone(mu[i], (r * a0 - b[i, 0]) * d, (r * a1 - b[i, 1]) * d, (r * a2 - b[i, 2]) * d)
        s[i, 0] = p0
        s[i, 1] = p1
        s[i, 2] = p2
        for e in range(cend_ptr[i], cend_ptr[i + 1]):
            w[e, 0] = 2.0 * p0 - z[e, 0]
            w[e, 1] = 2.0 * p1 - z[e, 1]
            w[e, 2] = 2.0 * p2 - z[e, 2]


@njit(cache=True, fastmath=_FM)
def _dr_update(cend_ptr, z, x, s, alpha, out):
    """out_e = z_e + alpha (x_e - s_i(e))  (= x^_e + lam_e after the dual update)."""
    for i in range(cend_ptr.shape[0] - 1):
        for e in range(cend_ptr[i], cend_ptr[i + 1]):
            for a in range(3):
                out[e, a] = z[e, a] + alpha * (x[e, a] - s[i, a])


@njit(cache=True, fastmath=_FM)
def _strand_velocity(strand_ptr, ends_sorted, end_p0, end_p1, cols, vals, dof_offsets, D_data, D_ptr, D_is_diag,
                     x, out, t, t2):
    """out_e = J_e D_s sum_{e' on s} J_e'^T x_e'  (strand s's part of contact i(e)'s velocity)."""
    S = strand_ptr.shape[0] - 1
    for s in range(S):
        q0 = strand_ptr[s]
        q1 = strand_ptr[s + 1]
        if q0 == q1:
            continue
        o = dof_offsets[s]
        n = dof_offsets[s + 1] - o
        _gather_strand(q0, q1, o, n, ends_sorted, end_p0, end_p1, cols, vals, x, t)
        d0 = D_ptr[s]
        if D_is_diag[s]:
            for k in range(n):
                t2[k] = D_data[d0 + k] * t[k]
        else:
            for k in range(n):
                acc = 0.0
                for j in range(n):
                    acc += D_data[d0 + k * n + j] * t[j]
                t2[k] = acc
        for q in range(q0, q1):
            e = ends_sorted[q]
            out[e, 0], out[e, 1], out[e, 2] = _end_times(e, o, end_p0, end_p1, cols, vals, t2)


@njit(cache=True, fastmath=_FM)
def _strand_sum(end_p0, end_p1, cols, vals, x, out):
    """out = sum_e J_e^T x_e over all ends (out: (n,), zeroed here): each strand's H^T of its own force copies."""
    for k in range(out.shape[0]):
        out[k] = 0.0
    for e in range(end_p0.shape[0]):
        x0 = x[e, 0]
        x1 = x[e, 1]
        x2 = x[e, 2]
        for p in range(end_p0[e], end_p1[e]):
            out[cols[p]] += vals[p, 0] * x0 + vals[p, 1] * x1 + vals[p, 2] * x2


#: StrandSplit.reusing keeps a contact's rho scaled, g rho_i, only within RHO_RTOL of the rule's beta tr(W'_ii) / 3
#: (else the rule's, and its strands are refactored).  Without this limit (every contact of one g kept) the
#: contacts whose W_ii is mostly 2 gamma I (their rule's rho barely moves with g) got rho off by up to |g - 1|, and
#: example_groom(1000)'s re-solves took 220, 70, 40, 40, 20, 10 iterations instead of 210, 60, 30, 20, 20, 10;
#: with 1e-2 (or 1e-3) they take exactly the fresh set-up's counts
RHO_RTOL = 1e-2
RATIO_RTOL = 1e-13  #: D'_s = g D_s "exactly" (StrandSplit.reusing): max |D'_s - g D_s| <= RATIO_RTOL max |D'_s|


def _same_array(a, b) -> bool:
    """a and b hold the same values: the same memory (views of one array, as the inversion's rounds share H), or
    equal entries."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    ia, ib = a.__array_interface__, b.__array_interface__
    if ia["data"][0] == ib["data"][0] and ia["strides"] == ib["strides"]:
        return True
    return bool(np.array_equal(a, b))


def same_H(H_source, problem, dof_offsets) -> bool:
    """Whether ``problem``'s H is the one H_source = (indptr, indices, data, shape) was taken from (the same arrays,
    or equal ones) on the same strands (dof_offsets)."""
    H = problem.H
    indptr, indices, data, shape = H_source
    return (H.shape == shape and problem.n_strands == len(dof_offsets) - 1
            and _same_array(np.asarray(problem.dof_offsets, dtype=np.int64), np.asarray(dof_offsets, dtype=np.int64))
            and _same_array(H.indptr, indptr) and _same_array(H.indices, indices) and _same_array(H.data, data))


def contact_ratios(old_D_data, problem, cend_ptr, end_strand):
    """(g (S,), g_contact (m,)): g_s with D'_s = g_s D_s to round-off (RATIO_RTOL; NaN where there is none, D' the
    problem's, D laid out alike in old_D_data) and per contact its strands' common g (NaN where they differ)."""
    g = np.empty(problem.n_strands)
    _strand_ratios(old_D_data, problem.D_data, problem.D_ptr, RATIO_RTOL, g)
    gc = np.empty(problem.n_contacts)
    _carried(cend_ptr, end_strand, g, RATIO_RTOL, gc)
    return g, gc


def carried_rho(gc, previous_rho, diag, beta):
    """(rho', kept): rho'_i = g_i rho_i (g_i: contact_ratios) where that is within RHO_RTOL of the rule's
    beta tr(W'_ii) / 3 (diag: W'_ii), else the rule's; kept marks the former."""
    fresh = contact_rho(diag, beta)
    carried = gc * previous_rho
    kept = (gc > 0.0) & (np.abs(carried - fresh) <= RHO_RTOL * fresh)
    return np.ascontiguousarray(np.where(kept, carried, fresh)), kept


class StrandSplit:
    """The ends of a ContactProblem's contacts and the Cholesky factors of M_s = D_s^-1 + J_s^T J_s / rho, for a
    per-contact rho (fixed for the whole run).  Strand s's factor is L_scale[s] times its block of L (L_scale = 1
    for a fresh set-up; see ``reusing``)."""

    def __init__(self, problem, rho_c: np.ndarray):
        H = problem.packed_H()
        off = np.ascontiguousarray(problem.dof_offsets, dtype=np.int64)
        m = problem.n_contacts
        per = _count_ends(H.ptr, H.cols, off)
        cend_ptr = np.zeros(m + 1, dtype=np.int64)
        np.cumsum(per, out=cend_ptr[1:])
        E = int(cend_ptr[-1])
        end_contact = np.empty(E, dtype=np.int64)
        end_strand = np.empty(E, dtype=np.int64)
        end_p0 = np.empty(E, dtype=np.int64)
        end_p1 = np.empty(E, dtype=np.int64)
        _fill_ends(H.ptr, H.cols, off, cend_ptr, end_contact, end_strand, end_p0, end_p1)
        S = problem.n_strands
        self.ends_sorted = np.argsort(end_strand, kind="stable").astype(np.int64)
        self.strand_ptr = np.zeros(S + 1, dtype=np.int64)
        np.cumsum(np.bincount(end_strand, minlength=S), out=self.strand_ptr[1:])
        self.cend_ptr, self.end_contact, self.end_p0, self.end_p1 = cend_ptr, end_contact, end_p0, end_p1
        self.end_strand = end_strand
        self.H, self.off = H, off
        self.H_source = (problem.H.indptr, problem.H.indices, problem.H.data, problem.H.shape)
        sizes = np.diff(off)
        used = np.diff(self.strand_ptr) > 0
        self.L_ptr = np.zeros(S + 1, dtype=np.int64)
        np.cumsum(np.where(used, sizes * sizes, 0), out=self.L_ptr[1:])
        self.t = np.zeros(int(sizes.max()) if S else 0)
        self.t2 = np.zeros_like(self.t)
        self.n_ends = E
        self._attach(problem)
        self.rho_c = np.ascontiguousarray(rho_c, dtype=np.float64)
        self.rho_end = np.ascontiguousarray(self.rho_c[end_contact])
        self.L = np.empty(int(self.L_ptr[-1]))
        self.L_scale = np.ones(S)
        self.diag = None  # W_ii (m, 3, 3) that rho came from (run_admm; StrandSplit.reusing scales it)
        self.beta = None  # the beta of rho_c = beta tr(W_ii) / 3 (run_admm)
        self.refactored = self._factor(np.flatnonzero(used))

    def _attach(self, problem):
        self.problem = problem
        self.D_data, self.D_ptr, self.D_is_diag = problem.D_data, problem.D_ptr, problem.D_is_diag
        self.n_dofs = problem.n_dofs
        self.gamma = problem.gamma

    def _factor(self, strands) -> int:
        """(Re)build the factors of ``strands`` (int array) in place (one compiled pass; D_s^-1 of dense blocks by
        np.linalg.inv).  Returns their number."""
        strands = np.ascontiguousarray(strands, dtype=np.int64)
        D_inv = np.zeros(0)
        dense = strands[~self.D_is_diag[strands]]
        if len(dense):
            D_inv = np.zeros_like(self.D_data)
            sizes = np.diff(self.off)
            for s in dense:
                n = int(sizes[s])
                a = self.D_ptr[s]
                D_inv[a:a + n * n] = np.linalg.inv(self.D_data[a:a + n * n].reshape(n, n)).reshape(-1)
        self.L_scale[strands] = 1.0
        bad = _factor_strands(strands, self.strand_ptr, self.ends_sorted, self.end_p0, self.end_p1, self.H.cols,
                              self.H.vals, self.rho_end, self.off, self.D_data, self.D_ptr, self.D_is_diag, D_inv,
                              self.L_ptr, self.L)
        if bad >= 0:
            raise np.linalg.LinAlgError(f"strand {bad}: M_s = D_s^-1 + J_s^T J_s / rho is not positive definite")
        return len(strands)

    def factor(self, s: int) -> np.ndarray:
        """Strand s's Cholesky factor of M_s (n_s x n_s, lower; empty for a strand without contacts)."""
        blk = self.L[self.L_ptr[s]:self.L_ptr[s + 1]]
        n = int(math.isqrt(blk.shape[0]))
        return self.L_scale[s] * blk.reshape(n, n)

    def same_H(self, problem) -> bool:
        """Whether ``problem`` has this split's H (the same columns and values: its ends and packed H hold)."""
        return same_H(self.H_source, problem, self.off)

    def detached(self) -> "StrandSplit":
        """A copy sharing every array but not the problem (for ADMMState: the problem's caches are not kept)."""
        out = copy.copy(self)
        out.problem = None
        return out

    @classmethod
    def reusing(cls, problem, previous: "StrandSplit", beta: float):
        """The split of ``problem`` built from ``previous`` (a detached split of an earlier run on the same H, e.g.
        the inversion's previous stiffening round), or None when H, D's layout or beta differ.  Each strand gets
        g_s with D'_s = g_s D_s to round-off (RATIO_RTOL; NaN when there is none).  A contact whose strands share
        one g keeps its rho scaled, rho'_i = g rho_i, and its W_ii is scaled likewise, W'_ii = g (W_ii - 2 gamma I)
        + 2 gamma' I; the other contacts get theirs afresh (W'_ii from their ends, rho'_i = beta tr(W'_ii) / 3).  A
        strand with a g whose contacts all kept their rho keeps its factor: M'_s = D_s^-1 / g + J_s^T J_s /
        (g rho) = M_s / g exactly, so L'_s = L_s / sqrt(g) (L_scale, no pass over L); the others are refactored.
        The inversion's stiffening rounds scale every D_s by the new w_scale and the raised strands' by their
        factor too, so all but the strands touching a raised strand keep their factors.  ``previous`` is consumed:
        its L is updated in place (the factors of harolongo hold 1.25 GB)."""
        if previous.L is None or previous.diag is None or previous.beta != beta or not previous.same_H(problem):
            return None
        if not (np.array_equal(previous.D_ptr, problem.D_ptr) and np.array_equal(previous.D_is_diag,
                                                                                   problem.D_is_diag)):
            return None
        out = previous.detached()
        cache = problem._cache  # the same package's ContactProblem: its packed H is previous's, W_ii is below
        cache.setdefault("packed_H", previous.H)
        out._attach(problem)
        S, m = problem.n_strands, problem.n_contacts
        g, gc = contact_ratios(previous.D_data, problem, out.cend_ptr, out.end_strand)
        kept = gc > 0.0
        eye = np.eye(3)
        if "diag" in cache:
            diag = cache["diag"]
        else:
            diag = np.empty((m, 3, 3))
            diag[kept] = (gc[kept, None, None] * (previous.diag[kept] - 2.0 * previous.gamma * eye)
                          + 2.0 * problem.gamma * eye)
            _contact_diagonal(np.flatnonzero(~kept), out.cend_ptr, out.end_strand, out.end_p0, out.end_p1,
                              out.H.cols, out.H.vals, out.off, problem.D_data, problem.D_ptr, problem.D_is_diag,
                              2.0 * problem.gamma, diag)
            cache["diag"] = diag
        out.diag = diag
        out.rho_c, kept = carried_rho(gc, previous.rho_c, diag, beta)
        out.rho_end = np.ascontiguousarray(out.rho_c[out.end_contact])
        reuse = np.empty(S, dtype=np.bool_)
        _reusable(out.strand_ptr, out.ends_sorted, out.end_contact, g, np.where(kept, gc, np.nan), reuse)
        previous.L = None  # consumed: out.L is updated in place
        out.L_scale = np.where(reuse, previous.L_scale / np.sqrt(np.where(reuse, g, 1.0)), 1.0)
        out.refactored = out._factor(np.flatnonzero(~reuse & (np.diff(out.strand_ptr) > 0)))
        out.t = np.zeros_like(previous.t)
        out.t2 = np.zeros_like(previous.t2)
        return out

    @property
    def nbytes(self) -> int:
        return self.L.nbytes + 8 * 6 * self.n_ends

    def x_step(self, w, x):
        H = self.H
        _x_step(self.strand_ptr, self.ends_sorted, self.end_p0, self.end_p1, H.cols, H.vals, self.rho_end, self.off,
                self.L_ptr, self.L, self.L_scale, w, x, self.t)

    def strand_sum(self, x) -> np.ndarray:
        """h = sum_e J_e^T x_e (n,) for copies x (E, 3) of the forces per end: with x_e = r_i(e) it is H^T r; with
        ADMM's strand solves, the dual point l = D^1/2 h of certificate.error_bound_with_strands."""
        out = np.empty(self.n_dofs)
        _strand_sum(self.end_p0, self.end_p1, self.H.cols, self.H.vals, np.ascontiguousarray(x), out)
        return out

    def strand_velocity(self, x):
        H = self.H
        out = np.empty_like(x)
        _strand_velocity(self.strand_ptr, self.ends_sorted, self.end_p0, self.end_p1, H.cols, H.vals, self.off,
                         self.D_data, self.D_ptr, self.D_is_diag, x, out, self.t, self.t2)
        return out


def _reusing_structured(problem, previous: StructuredSplit, beta: float):
    """The structured split of ``problem`` from an earlier run's on the same H (StructuredSplit.rebind), with rho
    carried over as StrandSplit.reusing does (carried_rho) and every strand refactored (O(elements) here), or None
    when H, beta or a diagonal D are not there."""
    if (previous.beta != beta or not np.all(problem.D_is_diag)
            or not same_H(previous.H_source, problem, 3 * previous.offsets)):
        return None
    out = previous.rebind(problem)
    _, gc = contact_ratios(previous.D_data, problem, out.cend_ptr, out.end_strand)
    out.beta = beta
    out.set_rho(carried_rho(gc, previous.rho_c, out.diag, beta)[0])
    problem._cache.setdefault("diag", out.diag)
    return out


def contact_rho(diag: np.ndarray, beta: float = BETA) -> np.ndarray:
    """rho_i = beta tr(W_ii) / 3 per contact (1 where that is not positive)."""
    rho_c = beta * np.einsum("kii->k", diag) / 3.0
    return np.where(rho_c > 0, rho_c, 1.0)


@njit(cache=True)
def _used_strands(indices, dof_offsets, out):
    """out[s]: some entry of H (column indices ``indices``) lies in strand s's columns (a flag per column, no
    search: example_groom(1000)'s 13M entries in 0.01 s CPU instead of 0.24 with np.searchsorted; solver_choice
    asks before every solve of the inversion)."""
    hit = np.zeros(dof_offsets[-1], dtype=np.bool_)
    for p in range(indices.shape[0]):
        hit[indices[p]] = True
    for s in range(out.shape[0]):
        for k in range(dof_offsets[s], dof_offsets[s + 1]):
            if hit[k]:
                out[s] = True
                break


def strand_split_bytes(problem, anderson: int = ANDERSON, structured: bool = False) -> int:
    """Memory of run_admm on ``problem`` beyond the problem itself, estimated from H's columns alone: a dense
    n_s x n_s factor per strand that carries a contact (``structured``: the semiseparable generators and factors
    of admm_structured.StructuredSplit instead, 72 numbers per element, and ~50 numbers of geometry per end), and
    per contact end (at most the strands a contact's columns touch, bounded by 2 per contact for strand/strand
    contacts) its indices, three state vectors and the Anderson history (float32)."""
    ends = 2 * problem.n_contacts
    per_end = 4 * 8 + 5 * 3 * 8 + 2 * anderson * 3 * 4
    if structured:
        return int(8 * 72 * (problem.n_dofs // 3) + ends * (per_end + 8 * 50))
    used = np.zeros(problem.n_strands, dtype=np.bool_)
    _used_strands(problem.H.indices, np.ascontiguousarray(problem.dof_offsets, dtype=np.int64), used)
    sizes = np.diff(problem.dof_offsets)
    return int(8 * np.sum(sizes[used].astype(np.int64) ** 2) + ends * per_end)


def strand_traces(problem) -> np.ndarray:
    """tr(D_s) per strand of a ContactProblem (how much each strand's D changed between two runs)."""
    out = np.empty(problem.n_strands)
    for s, d in enumerate(problem.D_blocks):
        out[s] = float(np.sum(d)) if d.ndim == 1 else float(np.trace(d))
    return out


@dataclass
class ADMMState:
    """run_admm's state at the end of a run, to start a later run on a problem with the same contacts and strands
    (the same H: the same ends) but another D and b, e.g. the inversion's next stabilisation round (K raised on
    some strands).  Opaque to callers: pass it back as ``initial_state``.

    What carries over when D changes: the iteration's state is z_e = x^_e + lam_e per end (lam = y / rho, y the
    unscaled multiplier of the consensus x_e = s_i(e)).  At the fixed point x^_e = s_i and
    y_e = -J_e D_s J_s^T x_s (minus strand s's part of contact i's velocity): the forces carry over unchanged, and
    y_e, at the same forces, scales with D_s.  So the new run starts from
    z_e = s_i + (z_e - s_i) g_s rho_i / rho'_i, g_s = tr(D'_s) / tr(D_s) (exact for D'_s = g_s D_s, as a stiffness
    factor gives: K^-2 / w_scale), rho' the new run's rho (StrandSplit.reusing: g rho where that is within RHO_RTOL
    of the rule's beta tr(W'_ii) / 3, else the rule's).  For a converged
    state that is the start the forces alone give.  Measured on example_groom(1000)'s stiffening re-solves: with the
    primal certificate (runs stopped late, nearly converged) no gain; since the inversion stops on the strand
    certificate (runs stopped early, at the q0 tolerance) the later re-solves take 10-60 iterations from the state
    against 90-110 from the forces (docs/solvers.md section 12)."""

    z: np.ndarray  # (E, 3) the Douglas-Rachford variable per end
    s: np.ndarray  # (m, 3) the forces (in the cones) of the last iteration
    rho_c: np.ndarray  # (m,) rho per contact
    d_trace: np.ndarray  # (S,) tr(D_s) per strand
    end_strand: np.ndarray  # (E,) ends' strands (contact-major): the structure the state belongs to
    cend_ptr: np.ndarray  # (m + 1,)
    # the run's StrandSplit (detached from its problem), whose ends, W_ii, rho and factors the next run on the same H
    # reuses where D did not change but by a scalar (StrandSplit.reusing); consumed by that run (then None)
    split: object = field(default=None, repr=False, compare=False)

    def fits(self, split) -> bool:
        """Whether the state belongs to the same contact ends as ``split`` (a StrandSplit)."""
        return (self.z.shape[0] == split.n_ends and self.cend_ptr.shape == split.cend_ptr.shape
                and np.array_equal(self.cend_ptr, split.cend_ptr) and np.array_equal(self.end_strand, split.end_strand)
                and self.d_trace.shape[0] == len(split.strand_ptr) - 1)


def _start_from_state(state: ADMMState, split, rho_c: np.ndarray, d_trace: np.ndarray):
    """z (E, 3) and s (m, 3) for a new run from ``state`` on the problem of ``split`` (rho_c: its rho, d_trace: its
    strand_traces): the forces kept, each end's multiplier rescaled for the new D and rho (ADMMState)."""
    s = np.array(state.s, dtype=np.float64)
    se = s[split.end_contact]
    g = np.divide(d_trace, state.d_trace, out=np.ones_like(d_trace), where=state.d_trace > 0)
    f = g[split.end_strand] * state.rho_c[split.end_contact] / split.rho_end
    return se + (state.z - se) * f[:, None], s


@dataclass
class ADMMOutcome:
    r: np.ndarray  # (3m,) the last s (in the cones)
    residual: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)  # [(iteration, residual, seconds)]
    solve_s: float = 0.0
    setup_s: float = 0.0
    stopped_by_rule: bool = False
    anderson_restarts: int = 0
    warm_sweeps: int = 0
    state: ADMMState | None = None  # the end state, for a later run's initial_state
    from_state: bool = False  # whether this run started from an initial_state


def run_admm(
    problem,
    *,
    tol: float = 1e-8,
    max_iter: int = 5000,
    r0: np.ndarray | None = None,
    beta: float = BETA,
    alpha: float = ALPHA,
    anderson: int = ANDERSON,
    warm_sweeps: int = WARM_SWEEPS,
    check_every: int = 10,
    scale: float | None = None,
    time_limit: float | None = None,
    callback=None,
    stop=None,
    stop_strands: bool = False,
    initial_state: ADMMState | None = None,
    state_out: dict | None = None,
    geometry: HelixContacts | None = None,
    stop_products: bool = False,
) -> ADMMOutcome:
    """Strand-split ADMM (module docstring) on a ContactProblem, SOC law.  Starts from r0 (projected onto the
    cones) or, without one, from ``warm_sweeps`` Gauss-Seidel sweeps.  Every ``check_every`` iterations: the
    residual of residual.py on s (stop at tol), callback(iterations, residual), stop(r, u) -> bool (the caller's
    rule, e.g. the certified rest-curvature bound: True ends the run, outcome.stopped_by_rule), time_limit.
    ``stop_strands``: call stop(r, u, h) instead, h = sum_e J_e^T x_e (n,) from the last x-step
    (StrandSplit.strand_sum), the dual point of certificate.error_bound_with_strands (a certificate from ADMM's
    strand solves that needs no 1 / gamma on the velocity mismatch of s; docs/solvers.md section 12).
    ``initial_state``: a previous run's outcome.state (ADMMState) on a problem with the same H (another D and b):
    the run starts from it (r0 and the Gauss-Seidel sweeps are then not used; a state of other contacts is
    ignored).  ``state_out`` (a dict): gets the end state under "state" (for callers that reach run_admm through
    solve_contact_problem, whose result does not carry it).  ``geometry`` (admm_structured.HelixContacts: the
    Super-Helix groom and the contacts H was built from): the strand systems are solved through their
    semiseparable factors (admm_structured.StructuredSplit, O(elements + ends) per x-step) instead of dense
    Cholesky factors, where D is diagonal (else, or without it, the dense StrandSplit).
    ``stop_products`` (with ``stop_strands``; used where the split is the structured one): the checks' products
    come from the split's generators (StructuredSplit.check_products: H^T s, h, W s + b and H D h + b in two passes
    over ends and elements, equal to the CSR H's to round-off, instead of four products with H) and stop is called
    stop(r, u, h, HTr=H^T r, c=H D h + b).  A check that would end the run is redone on the same forces with the
    CSR H: the residual from u = W s + b through H (the run stops at tol only on that), and stop(r, u, h) again
    (no products given: the caller computes its own from H); the run stops by the rule only if that call says so.
    So no run stops on a number not computed with H on its returned forces."""
    from .certificate import project_forces

    if not 0.0 < alpha < 2.0:
        raise ValueError("alpha must be in (0, 2)")
    if not beta > 0.0:
        raise ValueError("beta must be > 0")
    t0 = time.perf_counter()
    m = problem.n_contacts
    split = None
    if initial_state is not None and initial_state.split is not None:  # the previous run's set-up, on the same H
        previous, initial_state.split = initial_state.split, None
        split = (_reusing_structured(problem, previous, beta) if isinstance(previous, StructuredSplit)
                 else StrandSplit.reusing(problem, previous, beta))
    if split is None and applies(problem, geometry):
        split = StructuredSplit(problem, geometry)
        split.beta = beta
        split.set_rho(contact_rho(split.diag, beta))
        problem._cache.setdefault("diag", split.diag)  # W_ii without packing H (problem.rho() reads it)
    if split is None:
        diag = problem.diagonal_blocks()
        split = StrandSplit(problem, contact_rho(diag, beta))
        split.diag, split.beta = diag, beta
    rho_c = split.rho_c
    b = np.ascontiguousarray(problem.b.reshape(m, 3))
    mu = problem.mu
    rho = problem.rho()
    if scale is None:
        scale = _res.residual_scale(problem.b, rho)
    warm = 0
    d_trace = strand_traces(problem)
    if initial_state is not None and not initial_state.fits(split):
        initial_state = None
    if initial_state is None and r0 is None and warm_sweeps > 0:
        from .gauss_seidel import MatrixFreeOperator, run_gauss_seidel

        out = run_gauss_seidel(MatrixFreeOperator(problem), "soc", tol=tol, max_sweeps=warm_sweeps, scale=scale)
        r0, warm = out.r, out.sweeps
    E = split.n_ends
    if initial_state is not None:
        z, s = _start_from_state(initial_state, split, rho_c, d_trace)
    else:
        s = np.zeros((m, 3)) if r0 is None else project_forces(r0, mu)[0].reshape(m, 3)
        # the ADMM fixed point's multipliers for s: lam_e = -(strand s(e)'s part of u_i) / rho_i, z = x^ + lam
        xh = np.ascontiguousarray(s[split.end_contact])
        z = xh - split.strand_velocity(xh) / split.rho_end[:, None]
    setup_s = time.perf_counter() - t0

    def measure(r):
        u = problem.velocity(r.reshape(-1))
        emax, _ = _res.residual_max_rms(SOC, r, u.reshape(m, 3), mu, rho)
        return emax / scale, u

    fast = bool(stop_products and stop_strands and hasattr(split, "check_products"))

    def check(x):
        """(residual, u, h, HTs, c) of s after the x-step that gave x: through the split's generators where
        ``fast`` (residual then confirmed with H where it is within tol), else with H (h, HTs, c: None)."""
        if fast:
            HTs, h, uf, c = split.check_products(s, x, b)
            emax, _ = _res.residual_max_rms(SOC, s, uf.reshape(m, 3), mu, rho)
            if not emax / scale <= tol:
                return emax / scale, uf, h, HTs, c
        res_, u_ = measure(s)
        return res_, u_, None, None, None

    x = np.zeros((split.n_ends, 3))
    res, u, *_ = check(x)
    history = [(0, res, time.perf_counter() - t0)]
    nxt = np.empty_like(z)
    f = np.empty(3 * E)
    mixer = AndersonMixer(3 * E, anderson) if anderson > 0 else None
    w = np.empty((E, 3))
    gamma2 = 2.0 * problem.gamma
    restarts = 0
    k = 0
    by_rule = False
    while res > tol and k < max_iter:
        _s_step(split.cend_ptr, z, b, mu, gamma2, rho_c, s, w)
        split.x_step(w, x)
        _dr_update(split.cend_ptr, z, x, s, alpha, nxt)
        k += 1
        if mixer is None:
            z, nxt = nxt, z
        else:
            zf = z.reshape(-1)
            np.subtract(nxt.reshape(-1), zf, out=f)
            restarts += mixer.guarded_step(zf, f, zf)
        if k % check_every == 0 or k >= max_iter:
            res, u, h, HTs, c = check(x)
            history.append((k, res, time.perf_counter() - t0))
            if callback is not None:
                callback(k, res)
            if res <= tol or not math.isfinite(res):
                break
            if stop is not None:
                r_now = s.reshape(-1).copy()
                if not stop_strands:
                    hit = stop(r_now, u)
                elif HTs is not None:  # the generators' products; a stop is confirmed with H's
                    hit = stop(r_now, u, h, HTr=HTs, c=c)
                    if hit:
                        res, u = measure(s)
                        history[-1] = (k, res, time.perf_counter() - t0)
                        hit = res <= tol or stop(r_now, u, h)
                else:
                    hit = stop(r_now, u, split.strand_sum(x))
                if hit:
                    by_rule = res > tol
                    break
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                break
    if history[-1][0] != k:
        res, u = measure(s)
        history.append((k, res, time.perf_counter() - t0))
    state = ADMMState(z=z.copy(), s=s.copy(), rho_c=rho_c.copy(), d_trace=d_trace, end_strand=split.end_strand,
                      cend_ptr=split.cend_ptr, split=split.detached())
    if state_out is not None:
        state_out["state"] = state
    return ADMMOutcome(s.reshape(-1).copy(), float(res), k, bool(res <= tol), history, time.perf_counter() - t0,
                       setup_s, by_rule, restarts, warm, state, initial_state is not None)
