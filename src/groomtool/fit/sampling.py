"""Polylines as smooth curves: cleaning, arc length, and point + tangent samples (MATH.md section 3.2).

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

from .kernels import dot


def drop_repeated_vertices(points, offsets, relative: float = 1e-6, absolute: float = 1e-12):
    """Remove vertices closer to their predecessor than max(absolute, relative * strand length).

    The root is always kept.  Returns (points, offsets, kept), ``kept`` the kept input vertex ids.
    """
    points = np.asarray(points, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    V = len(points)
    keep = np.ones(V, dtype=bool)
    if V > 1:
        _, lengths = vertex_arc_lengths(points, offsets)
        strand = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep[1:] = seg >= np.maximum(absolute, relative * lengths[strand[1:]])
    keep[offsets[:-1][offsets[:-1] < V]] = True
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
    counts = np.diff(offsets)
    d = np.zeros(len(points))
    if len(points) > 1:
        d[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1)
    d[offsets[:-1][counts > 0]] = 0.0
    csum = np.cumsum(d)
    start = np.repeat(csum[offsets[:-1][counts > 0]], counts[counts > 0])
    s = csum - start
    last = np.maximum(offsets[1:] - 1, 0)
    lengths = np.where(counts > 0, s[last], 0.0)
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
        strand = np.asarray(strand, dtype=np.int64)
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.lengths[strand])
        first = self.offsets[strand]
        n = self.counts[strand]
        v = np.searchsorted(self._key, s + self._base[strand], side="right") - 1
        seg = np.clip(v - first, 0, n - 2)
        w = first + np.clip(seg - 1, 0, n - 4)                # window start: vertices w..w+3
        x0, x1, x2, x3 = (self.arc[w + j] for j in range(4))
        u0, u1, u2 = self._u[w], self._u[w + 1], self._u[w + 2]
        d2 = (u1 - u0) / (x2 - x0)[:, None]
        d3 = ((u2 - u1) / (x3 - x1)[:, None] - d2) / (x3 - x0)[:, None]
        a0 = (s - x0)[:, None]
        a1 = (s - x1)[:, None]
        a2 = (s - x2)[:, None]
        q2 = d2 + a2 * d3
        q1 = u0 + a1 * q2
        pts = self.points[w] + a0 * q1
        tan = q1 + a0 * (q2 + a1 * d3)
        tan /= np.sqrt(dot(tan, tan))[:, None]
        return pts, tan
