"""Distance from input vertices to the fitted curve (MATH.md section 3, "Quality").

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
"""

from __future__ import annotations

import numpy as np

from .kernels import cross
from .state import CurveTable

PRECHECK_STRIDE = 4      # vertex stride of the cheap first error check of a pass
CHUNK = 1 << 17          # vertices per batch of closest-point queries


class ElementRows:
    """Per-element rows (3, E): C_e, T_e, u1, u2; and w (E,), l (E,)."""

    def __init__(self, table: CurveTable):
        w = np.sqrt((table.Omega * table.Omega).sum(axis=1))
        a = table.Omega / np.where(w > 0, w, 1.0)[:, None]
        u1 = cross(a, table.T)
        u2 = cross(a, u1)
        self.rows = np.ascontiguousarray(np.concatenate([table.C, table.T, u1, u2], axis=1).T)  # (12, E)
        self.w = np.where(w > 0, w, 1.0)
        self.length = table.length


def _point(soa: ElementRows, e, t, want_derivatives=True):
    """C(t) (3, P) and, if asked, T(t), C''(t) on elements e at local parameters t."""
    rows = soa.rows[:, e]
    C0, T0, u1, u2 = rows[0:3], rows[3:6], rows[6:9], rows[9:12]
    w = soa.w[e]
    half = 0.5 * w * t
    sh, ch = np.sin(half), np.cos(half)
    sn = 2.0 * sh * ch                 # sin(theta)
    vc = 2.0 * sh * sh                 # 1 - cos(theta)
    C = C0 + t * T0 + (vc / w) * u1 + (t - sn / w) * u2
    if not want_derivatives:
        return C
    T = T0 + sn * u1 + vc * u2
    K = (w * (1.0 - vc)) * u1 + (w * sn) * u2
    return C, T, K


def locate(table: CurveTable, strand, s):
    """Element (global index) and local parameter of arc lengths s (clamped) on strands."""
    strand = np.asarray(strand, dtype=np.int64)
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, table.strand_length[strand])
    counts = np.diff(table.elem_offsets)
    base = np.concatenate([[0.0], np.cumsum(table.strand_length + 1.0)])[:-1]
    key = table.start + np.repeat(base, counts)
    e = np.searchsorted(key, s + base[strand], side="right") - 1
    e = np.clip(e, table.elem_offsets[strand], table.elem_offsets[strand + 1] - 1)
    return e, np.clip(s - table.start[e], 0.0, table.length[e])


def evaluate_table(table: CurveTable, strand, s):
    """Points (P, 3), unit tangents (P, 3) and C'' (P, 3) at arc lengths s on strands."""
    e, t = locate(table, strand, s)
    C, T, K = _point(ElementRows(table), e, t)
    return C.T, T.T, K.T


def closest_distances(table: CurveTable, points, strand, s_guess=None, elem=None, t=None,
                      iterations: int = 2, rows: ElementRows | None = None):
    """Distances (P,) from points to their strand's curve, with the foot points' (element, t).

    Start from arc lengths ``s_guess`` or directly from elements ``elem`` and local parameters ``t``;
    ``rows``: the table's :class:`ElementRows` when already built.
    """
    points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    strand = np.asarray(strand, dtype=np.int64)
    if elem is None:
        elem, t = locate(table, strand, s_guess)
    e = np.asarray(elem, dtype=np.int64).copy()
    t = np.asarray(t, dtype=np.float64).copy()
    first = table.elem_offsets[strand]
    last = table.elem_offsets[strand + 1] - 1
    soa = rows if rows is not None else ElementRows(table)
    for _ in range(iterations):
        C, T, K = _point(soa, e, t)
        r = C - points
        g = (r * T).sum(axis=0)
        dg = 1.0 + (r * K).sum(axis=0)
        t = t - np.where(dg > 0.2, g / np.maximum(dg, 0.2), g)
        back = (t < 0.0) & (e > first)
        e[back] -= 1
        t[back] += soa.length[e[back]]
        ahead = (t > soa.length[e]) & (e < last)
        t[ahead] -= soa.length[e[ahead]]
        e[ahead] += 1
        t = np.clip(t, 0.0, soa.length[e])
    C = _point(soa, e, t, want_derivatives=False)
    d = C - points
    return np.sqrt((d * d).sum(axis=0)), e, t


def strand_errors(table, offsets, vpoints, vfrac, active, n_act, tol, full, stride: int = PRECHECK_STRIDE):
    """Max and mean vertex distance (S',) of the strands ``active`` of the groom (offsets, vpoints,
    vfrac: vertex arc-length fractions) to their curves in ``table`` (fitted with n_act elements).

    A pre-check on every ``stride``-th vertex (and the tip) settles the strands above tolerance there
    (they will be refined); the others, and those marked ``full``, get their remaining vertices
    measured.
    """
    vidx, owner, vcount = _ranges(offsets, active)
    starts = np.cumsum(vcount) - vcount
    local = np.arange(len(vidx)) - starts[owner]
    sub = (local % stride == 0) | (local == vcount[owner] - 1)
    mx, mn = np.zeros(len(active)), np.zeros(len(active))
    rows = ElementRows(table)
    d = vertex_distances(table, rows, vpoints, vfrac, n_act, vidx[sub], owner[sub])
    sub_max = np.zeros(len(active))
    np.maximum.at(sub_max, owner[sub], d)
    mean_sub = np.bincount(owner[sub], d, minlength=len(active)) / np.bincount(owner[sub], minlength=len(active))
    again = (sub_max <= tol) | full
    mx[~again], mn[~again] = sub_max[~again], mean_sub[~again]
    rest = again[owner] & ~sub
    if np.any(again):
        d_all = np.zeros(len(vidx))
        d_all[sub] = d
        d_all[rest] = vertex_distances(table, rows, vpoints, vfrac, n_act, vidx[rest], owner[rest])
        ids = np.nonzero(again)[0]
        d_all = d_all[again[owner]]
        cnt = vcount[ids]
        st = np.cumsum(cnt) - cnt
        mx[ids] = np.maximum.reduceat(d_all, st)
        mn[ids] = np.add.reduceat(d_all, st) / cnt
    return mx, mn


def vertex_distances(table, rows, vpoints, vfrac, n_act, vidx, owner, iterations=2, chunk: int = CHUNK):
    """Distances of vertices vidx to their strand (owner: index in the pass), from the point that
    corresponds to them: sample interval i <-> element i at the same fraction.  In chunks of
    ``chunk`` vertices (bounded memory, better cache use)."""
    dist = np.empty(len(vidx))
    for a in range(0, len(vidx), chunk):
        v, o = vidx[a:a + chunk], owner[a:a + chunk]
        u = vfrac[v] * n_act[o]
        i = np.minimum(u.astype(np.int64), n_act[o] - 1)
        e = table.elem_offsets[o] + i
        dist[a:a + chunk], _, _ = closest_distances(table, vpoints[v], o, elem=e, t=(u - i) * table.length[e],
                                                    iterations=iterations, rows=rows)
    return dist


def _ranges(offsets, ids):
    """Concatenated index ranges offsets[i]:offsets[i+1] for i in ids, and their owner positions."""
    counts = offsets[ids + 1] - offsets[ids]
    owner = np.repeat(np.arange(len(ids)), counts)
    starts = np.repeat(offsets[ids], counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return starts + local, owner, counts
