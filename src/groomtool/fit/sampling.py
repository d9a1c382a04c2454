"""Polylines as smooth curves: cleaning, arc length, and point + tangent samples (docs/maths.md section 4.2).

Tangent estimate: at arc length s on segment k (vertices k, k+1), the cubic through the 4 nearest
vertices k-1..k+2 (shifted inwards at the ends), parameterised by the polyline's vertex arc lengths
s_j, in Lagrange form

    x(s) = sum_j L_j(s) x_j,   L_j(s) = prod_{m != j} (s - s_m) / (s_j - s_m),

gives the sample point Q = x(s) and the tangent t = x'(s) / |x'(s)| from the same polynomial.  It
reproduces the vertices (Q = x_j at s = s_j), is exact for cubic curves and has an O(h^3) tangent
error on a smooth curve sampled at spacing h.  Strands of 2 or 3 vertices get extra vertices first
(on the longest segments), so every strand has at least 4.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def drop_repeated_vertices(points, offsets, relative: float = 1e-6, absolute: float = 1e-12):
    """Remove vertices closer to their predecessor than max(absolute, relative * strand length).

    The root is always kept.  Returns (points, offsets, kept), ``kept`` the kept input vertex ids.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    keep = np.ones(len(points), dtype=bool)
    if len(points) > 1:
        _, lengths = vertex_arc_lengths(points, offsets)
        _keep_kernel(points, offsets, lengths, float(relative), float(absolute), keep)
    return _kept(points, offsets, keep)


def _kept(points, offsets, keep):
    """(points, offsets, kept ids) keeping the vertices marked in ``keep`` and every root."""
    keep[offsets[:-1][offsets[:-1] < len(points)]] = True
    if keep.all():
        return points.copy(), offsets.copy(), np.arange(len(points))
    kept = np.nonzero(keep)[0]
    csum = np.concatenate([[0], np.cumsum(keep)])
    return points[kept], csum[offsets].astype(np.int64), kept


def ensure_four_vertices(points, offsets):
    """Strands of 2 or 3 vertices: insert points (halving the longest segments) to reach 4."""
    counts = np.diff(offsets)
    short = np.nonzero((counts >= 2) & (counts < 4))[0]
    if len(short) == 0:
        return points, offsets
    strands = [points[offsets[i]:offsets[i + 1]] for i in range(len(counts))]
    for i in short:
        p = strands[i]
        while len(p) < 4:
            k = int(np.argmax(np.linalg.norm(np.diff(p, axis=0), axis=1)))
            p = np.concatenate([p[:k + 1], 0.5 * (p[k:k + 1] + p[k + 1:k + 2]), p[k + 1:]])
        strands[i] = p
    new_counts = np.array([len(s) for s in strands], dtype=np.int64)
    return np.concatenate(strands), np.concatenate([[0], np.cumsum(new_counts)]).astype(np.int64)


def vertex_arc_lengths(points, offsets) -> tuple[np.ndarray, np.ndarray]:
    """Arc length of every vertex from its root (V,), and strand lengths (S,)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    s, lengths = np.empty(len(points)), np.zeros(len(offsets) - 1)
    _arc_kernel(points, offsets, s, lengths)
    return s, lengths


class PolylineCurves:
    """Strands (at least 4 distinct vertices each) evaluated as local cubics in arc length.

    The cubic of a sample's window x0..x3 (vertex arc lengths) in Newton form:
    x(s) = p0 + (s - x0) (d1 + (s - x1) (d2 + (s - x2) d3)), with divided differences built from the
    unit segment directions u_k = (p_{k+1} - p_k) / (x_{k+1} - x_k) (the first divided differences):
    d1 = u_0, d2 = (u_1 - u_0) / (x2 - x0), d3 = ((u_2 - u_1) / (x3 - x1) - d2) / (x3 - x0).
    """

    def __init__(self, points, offsets):
        self.points = np.asarray(points, dtype=np.float64)
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.counts = np.diff(self.offsets)
        self.arc, self.lengths = vertex_arc_lengths(self.points, self.offsets)
        # a global, increasing key: arc length shifted per strand so one searchsorted serves all
        self._base = np.concatenate([[0.0], np.cumsum(self.lengths + 1.0)])[:-1]
        self._key = self.arc + np.repeat(self._base, self.counts)
        seg = np.diff(self.points, axis=0)
        ds = np.diff(self.arc)
        ds[ds <= 0.0] = 1.0                                   # across strands: never used
        self._u = np.concatenate([seg / ds[:, None], np.zeros((1, 3))])

    def evaluate(self, strand, s):
        """Points (P, 3) and unit tangents (P, 3) of the local cubic at arc lengths s on strands."""
        strand = np.ascontiguousarray(strand, dtype=np.int64).ravel()
        s = np.ascontiguousarray(s, dtype=np.float64).ravel()
        pts, tan = np.empty((len(s), 3)), np.empty((len(s), 3))
        _evaluate_kernel(self.points, self.arc, self._key, self._base, self._u, self.offsets, self.lengths,
                         strand, s, pts, tan)
        return pts, tan


@njit(cache=True, error_model="numpy")
def _evaluate_kernel(points, arc, key, base, u, offsets, lengths, strand, s, pts, tan):
    """:meth:`PolylineCurves.evaluate`, one sample at a time (the same operations, the segment found
    by bisection in the strand's part of the key instead of np.searchsorted over all of it)."""
    for k in range(len(s)):
        st = strand[k]
        first, n = offsets[st], offsets[st + 1] - offsets[st]
        sk = s[k]
        if sk == sk:                                     # np.clip(s, 0, L)
            sk = sk if sk > 0.0 else 0.0
            sk = sk if sk < lengths[st] else lengths[st]
        q = sk + base[st]
        lo, hi = first, first + n                        # the last v with key[v] <= q
        while lo < hi:
            mid = (lo + hi) // 2
            if key[mid] <= q:
                lo = mid + 1
            else:
                hi = mid
        seg = min(max(lo - 1 - first, 0), n - 2)
        w = first + min(max(seg - 1, 0), n - 4)
        x0, x1, x2, x3 = arc[w], arc[w + 1], arc[w + 2], arc[w + 3]
        a0, a1, a2 = sk - x0, sk - x1, sk - x2
        for c in range(3):
            d2 = (u[w + 1, c] - u[w, c]) / (x2 - x0)
            d3 = ((u[w + 2, c] - u[w + 1, c]) / (x3 - x1) - d2) / (x3 - x0)
            q2 = d2 + a2 * d3
            q1 = u[w, c] + a1 * q2
            pts[k, c] = points[w, c] + a0 * q1
            tan[k, c] = q1 + a0 * (q2 + a1 * d3)
        nrm = np.sqrt(tan[k, 0] * tan[k, 0] + tan[k, 1] * tan[k, 1] + tan[k, 2] * tan[k, 2])
        for c in range(3):
            tan[k, c] /= nrm


@njit(cache=True, error_model="numpy")
def _arc_kernel(points, offsets, s, lengths):
    """:func:`vertex_arc_lengths`: segment lengths (0 at roots) summed over the whole groom, minus the
    sum at the strand's root (as the reference's global cumsum)."""
    V = points.shape[0]
    root = np.zeros(V, dtype=np.bool_)
    for k in range(len(offsets) - 1):
        if offsets[k + 1] > offsets[k]:
            root[offsets[k]] = True
    acc = 0.0
    for i in range(V):
        d = 0.0
        if i > 0 and not root[i]:
            d0, d1, d2 = (points[i, 0] - points[i - 1, 0], points[i, 1] - points[i - 1, 1],
                          points[i, 2] - points[i - 1, 2])
            d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        acc = d if i == 0 else acc + d
        s[i] = acc
    for k in range(len(offsets) - 1):
        a, b = offsets[k], offsets[k + 1]
        if b > a:
            c0 = s[a]
            for i in range(a, b):
                s[i] = s[i] - c0
            lengths[k] = s[b - 1]


@njit(cache=True, error_model="numpy")
def _keep_kernel(points, offsets, lengths, relative, absolute, keep):
    """keep[i] = |p_i - p_{i-1}| >= max(absolute, relative L) inside each strand (roots set by the caller)."""
    for k in range(len(offsets) - 1):
        lim = relative * lengths[k]
        lim = lim if (lim >= absolute or lim != lim) else absolute
        for i in range(max(offsets[k], 1), offsets[k + 1]):
            d0, d1, d2 = (points[i, 0] - points[i - 1, 0], points[i, 1] - points[i - 1, 1],
                          points[i, 2] - points[i - 1, 2])
            keep[i] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) >= lim
