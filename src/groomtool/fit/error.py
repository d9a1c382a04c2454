"""Distance from input vertices to the fitted curve (docs/maths.md section 4.5).

On element e (start C_e, tangent T_e, world Darboux vector Omega = w a, |a| = 1) let u1 = a x T_e,
u2 = a x u1 (so a x u2 = -u1).  At t = s - S_e, theta = w t, the Rodrigues rotation gives

    T(s)   = T_e + sin(theta) u1 + (1 - cos theta) u2
    C(s)   = C_e + t T_e + (1 - cos theta)/w u1 + (t - sin(theta)/w) u2
    C''(s) = Omega x T(s) = w (cos(theta) u1 + sin(theta) u2)

(1 - cos theta = 2 sin^2(theta/2), no cancellation; t - sin(theta)/w = (theta - sin theta)/w is exact
to round-off relative to t; w = 0 gives u1 = u2 = 0, a straight element).
The closest point to x is a root of g(t) = (C - x) . T, g' = 1 + (C - x) . C'': Newton in the element's
local parameter, hopping to the neighbouring element when t leaves [0, l_e], clamped at the strand's
ends; where g' is small (far from the curve, near a centre of curvature) a projection step t -= g is
taken instead.  Started from the point that corresponds to the vertex (its arc-length fraction), this
finds the local closest point: the one that corresponds to the vertex.

:func:`strand_errors` runs numba kernels, one vertex at a time (``_closest_s``), with the operations (and
summation orders) of the array versions ``closest_distances_numpy`` / ``strand_errors_numpy``, kept as the
tests' references in tests/reference/fit.py beside ``closest_distances`` (``_closest_s`` over any points:
the tests' entry to the kernel).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .state import CurveTable

PRECHECK_STRIDE = 4      # vertex stride of the cheap first error check of a pass


def _element_arrays(table: CurveTable):
    """(C, T, Omega, length), contiguous, for the kernels."""
    return tuple(np.ascontiguousarray(a, dtype=np.float64) for a in (table.C, table.T, table.Omega, table.length))


def strand_errors(table, offsets, vpoints, vfrac, active, n_act, tol, full, stride: int = PRECHECK_STRIDE):
    """Max and mean vertex distance (S',) of the strands ``active`` of the groom (offsets, vpoints,
    vfrac: vertex arc-length fractions) to their curves in ``table`` (fitted with n_act elements).

    A pre-check on every ``stride``-th vertex (and the tip) settles the strands above tolerance there
    (they will be refined); the others, and those marked ``full``, get their remaining vertices
    measured.
    """
    n_act = np.ascontiguousarray(n_act, dtype=np.int64)
    mx, mn = np.zeros(len(active)), np.zeros(len(active))
    _errors_kernel(*_element_arrays(table), table.elem_offsets, np.asarray(offsets, dtype=np.int64),
                   np.asarray(active, dtype=np.int64), n_act, np.ascontiguousarray(vpoints, dtype=np.float64),
                   np.ascontiguousarray(vfrac, dtype=np.float64),
                   np.ascontiguousarray(np.broadcast_to(tol, (len(active),)), dtype=np.float64),
                   np.ascontiguousarray(np.broadcast_to(full, (len(active),)), dtype=np.bool_), stride, 2, mx, mn)
    return mx, mn


# --------------------------------------------------------------------------- numba kernels
@njit(cache=True, error_model="numpy")
def _max_s(a, b):
    """np.maximum on scalars (NaN propagates)."""
    return a if (a >= b or a != a) else b


@njit(cache=True, error_model="numpy")
def _closest_s(C, T, Om, length, px, py, pz, e, t, first, last, iterations):
    """Distance from (px, py, pz) to the curve and the foot (e, t): the Newton steps of
    reference ``closest_distances_numpy`` on one point (its ``ElementRows`` and ``_point`` inline)."""
    for it in range(iterations + 1):
        O0, O1, O2 = Om[e, 0], Om[e, 1], Om[e, 2]
        w = np.sqrt(O0 * O0 + O1 * O1 + O2 * O2)
        w = w if w > 0 else 1.0
        a0, a1, a2 = O0 / w, O1 / w, O2 / w
        T0, T1, T2 = T[e, 0], T[e, 1], T[e, 2]
        u0, u1, u2 = a1 * T2 - a2 * T1, a2 * T0 - a0 * T2, a0 * T1 - a1 * T0       # a x T
        v0, v1, v2 = a1 * u2 - a2 * u1, a2 * u0 - a0 * u2, a0 * u1 - a1 * u0       # a x u1
        half = 0.5 * w * t
        sh, ch = np.sin(half), np.cos(half)
        sn = 2.0 * sh * ch
        vc = 2.0 * sh * sh
        cu, cv = vc / w, t - sn / w
        r0 = C[e, 0] + t * T0 + cu * u0 + cv * v0 - px
        r1 = C[e, 1] + t * T1 + cu * u1 + cv * v1 - py
        r2 = C[e, 2] + t * T2 + cu * u2 + cv * v2 - pz
        if it == iterations:
            return np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), e, t
        ku, kv = w * (1.0 - vc), w * sn
        g = r0 * (T0 + sn * u0 + vc * v0) + r1 * (T1 + sn * u1 + vc * v1) + r2 * (T2 + sn * u2 + vc * v2)
        dg = 1.0 + (r0 * (ku * u0 + kv * v0) + r1 * (ku * u1 + kv * v1) + r2 * (ku * u2 + kv * v2))
        t = t - (g / _max_s(dg, 0.2) if dg > 0.2 else g)
        if t < 0.0 and e > first:
            e -= 1
            t += length[e]
        if t > length[e] and e < last:
            t -= length[e]
            e += 1
        if t == t:                                                       # np.clip(t, 0, l_e)
            t = t if t > 0.0 else 0.0
            t = t if t < length[e] else length[e]
    return 0.0, e, t


@njit(cache=True, error_model="numpy")
def _pairwise_block(a, lo, n):
    """sum(a[lo:lo + n]), n <= 128, in numpy's order: 8 accumulators (a -0.0 start below 8 terms)."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r = a[lo:lo + 8].copy()
    i = 8
    while i < n - n % 8:
        for j in range(8):
            r[j] += a[lo + i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, error_model="numpy")
def _pairwise_sum(a, lo, n):
    """sum(a[lo:lo + n]) in numpy's pairwise order: halves (multiples of 8) down to blocks of 128.

    Without recursion (numba's cache cannot load recursive functions): a stack of halves."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    los, ns, right, left = np.empty(64, np.int64), np.empty(64, np.int64), np.zeros(64, np.bool_), np.empty(64)
    top = 0
    los[0], ns[0], right[0] = lo, n, False
    while True:
        if ns[top] > 128:                                   # split: push the left half
            n2 = ns[top] // 2
            n2 -= n2 % 8
            los[top + 1], ns[top + 1], right[top + 1] = los[top], n2, False
            top += 1
            continue
        res = _pairwise_block(a, los[top], ns[top])
        while True:                                         # hand the sum up
            top -= 1
            if top < 0:
                return res
            if not right[top]:                              # left half done: push the right half
                left[top] = res
                right[top] = True
                n2 = ns[top] // 2
                n2 -= n2 % 8
                los[top + 1], ns[top + 1], right[top + 1] = los[top] + n2, ns[top] - n2, False
                top += 1
                break
            res = left[top] + res


@njit(cache=True, error_model="numpy")
def _errors_kernel(C, T, Om, length, elem_offsets, offsets, active, n_act, vpoints, vfrac, tol, full, stride,
                   iterations, mx, mn):
    """:func:`strand_errors`, strand by strand: the pre-check on every stride-th vertex and the tip, then
    the other vertices where needed (max, and the mean summed as np.add.reduceat does)."""
    nmax = 0
    for j in range(len(active)):
        nmax = max(nmax, offsets[active[j] + 1] - offsets[active[j]])
    d = np.empty(nmax)
    for j in range(len(active)):
        v0, cnt = offsets[active[j]], offsets[active[j] + 1] - offsets[active[j]]
        n, first, last = n_act[j], elem_offsets[j], elem_offsets[j + 1] - 1
        for p in range(2):                                   # 0: the pre-check, 1: the other vertices
            for i in range(cnt):
                if ((i % stride == 0) or (i == cnt - 1)) != (p == 0):
                    continue
                v = v0 + i
                u = vfrac[v] * n
                k = min(np.int64(u), n - 1)
                e = first + k
                d[i], _, _ = _closest_s(C, T, Om, length, vpoints[v, 0], vpoints[v, 1], vpoints[v, 2], e,
                                        (u - k) * length[e], first, last, iterations)
            if p == 0:
                sub_max, sub_sum, sub_n = 0.0, 0.0, 0
                for i in range(cnt):
                    if (i % stride == 0) or (i == cnt - 1):
                        sub_max = _max_s(sub_max, d[i])
                        sub_sum += d[i]
                        sub_n += 1
                if not (sub_max <= tol[j] or full[j]):
                    mx[j], mn[j] = sub_max, sub_sum / sub_n
                    break
            else:
                m = d[0]
                for i in range(1, cnt):
                    m = _max_s(m, d[i])
                mx[j] = m
                mn[j] = (d[0] + _pairwise_sum(d, 1, cnt - 1)) / cnt
