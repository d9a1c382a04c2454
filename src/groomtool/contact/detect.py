"""The ``Contacts`` record and strand/strand contact detection.

Each strand segment is a capsule of radius ``r_c`` around its axis; two capsules touch when the
axis-to-axis distance is below ``2 r_c``.  Pipeline (all numba, one core):

1. broad phase: runs of up to ``GROUP_SEGMENTS`` consecutive segments of one strand (at most
   ``GROUP_DIAMETERS`` contact diameters long, so long segments stay alone) form groups, each with
   the box of its segments inflated by ``r_c`` and a capsule (the chord from its first to its last
   vertex, and how far its vertices stray from it).  A sorted spatial hash finds the group pairs
   whose boxes overlap: every group box is inserted in every cell it overlaps (counting sort by
   cell, boxes by lower x inside a cell); each cell's entries are swept along x and tested pairwise;
   a pair is owned by the single cell holding the lower corner of the two boxes' intersection, so
   no pair is reported twice.  Group pairs whose capsules are at least ``2 r_c`` apart (plus a
   rounding margin) are skipped; in the others, segments whose box overlaps the other group's box
   are paired up, and pairs whose boxes overlap are tested, as are the pairs inside each group.
   Pairs whose infinite lines are at least ``2 r_c`` apart, and consecutive segments of a strand
   bent too little to touch themselves (a bound from the same-strand rule below), are rejected
   before the exact test.  The close pairs come out sorted by segment pair.
2. narrow phase: exact closest points between the two segments (clamped closest points; parallel,
   collinear and zero-length segments handled) -> contact when distance < ``2 r_c``.
3. same-strand rule: two points of one strand are neighbours, not a contact, when they are less
   than ``min_self_arc`` apart in arc length (default ``pi r_c``: a U-turn whose two arms touch has
   an arc of at least ``pi r_c`` between them, while points of a straight-ish strand closer than
   that in arc length are trivially within ``2 r_c``).  For two segments of one strand the closest
   points are sought under that constraint (exactly: a convex problem on a half-plane), so the
   result does not depend on how finely the strand is sampled.
4. one contact per local minimum of the polyline-to-polyline distance: the distance between two
   segments is convex in their parameters, so a segment pair's closest point is a local minimum
   of the distance between the two polylines unless it sits on a shared vertex where a neighbouring
   segment pair is closer (or equally close with a lower index).  Local minima of one strand pair
   closer than ``merge_arc`` (default ``4 r_c``) along both strands are then merged, keeping the
   closest (on a tie, the lower segment pair).

The segment-level spatial hash that step 1 replaced (every segment box in every cell it overlaps) is
kept as the tests' reference (tests/reference/contact.py); they check that both find the same pairs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from .frames import contact_frames

HEAD = -1  #: ``strand_b`` of a strand/head contact
DEFAULT_CONTACT_RADIUS = 50e-6  #: m: the 40 um fibre radius plus a 10 um margin (docs/contact.md)

_LEN2_EPS = 1e-30  # squared length below which a segment is a point
_PARALLEL_EPS = 1e-12  # relative (1 - cos^2) below which two segments are parallel


# ----------------------------------------------------------------------------------------- record
@dataclass
class Contacts:
    """m contacts as plain arrays.

    strand_a (m,) int64; s_a (m,) arc length on strand a; strand_b (m,) int64 or ``HEAD`` (-1);
    s_b (m,) arc length on strand b (nan for the head); point_a, point_b (m, 3) closest points on
    the axis of a and on the axis of b / the head surface; normal (m, 3) unit, from b towards a;
    frame (m, 3, 3) rows (e_N, e_T1, e_T2), e_N = normal; distance (m,) axis-to-axis distance, or
    signed axis-to-surface distance for the head (negative: the axis is inside the head).
    radius: the contact radius r_c used (m), or None.
    """

    strand_a: np.ndarray
    s_a: np.ndarray
    strand_b: np.ndarray
    s_b: np.ndarray
    point_a: np.ndarray
    point_b: np.ndarray
    normal: np.ndarray
    frame: np.ndarray
    distance: np.ndarray
    radius: float | None = None

    ARRAYS = ("strand_a", "s_a", "strand_b", "s_b", "point_a", "point_b", "normal", "frame", "distance")

    def __post_init__(self) -> None:
        self.strand_a = np.ascontiguousarray(self.strand_a, dtype=np.int64).reshape(-1)
        m = len(self.strand_a)
        self.strand_b = np.ascontiguousarray(self.strand_b, dtype=np.int64).reshape(m)
        for name in ("s_a", "s_b", "distance"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float64).reshape(m))
        for name in ("point_a", "point_b", "normal"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float64).reshape(m, 3))
        self.frame = np.ascontiguousarray(self.frame, dtype=np.float64).reshape(m, 3, 3)
        self.radius = None if self.radius is None else float(self.radius)

    def __len__(self) -> int:
        return len(self.strand_a)

    @property
    def is_head(self) -> np.ndarray:
        """(m,) bool, True for strand/head contacts."""
        return self.strand_b == HEAD

    @property
    def n_strand_strand(self) -> int:
        return int(np.count_nonzero(~self.is_head))

    @property
    def n_strand_head(self) -> int:
        return int(np.count_nonzero(self.is_head))

    @classmethod
    def empty(cls, radius: float | None = None) -> "Contacts":
        z = np.zeros(0)
        return cls(z, z, z, z, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), z,
                   radius)

    @classmethod
    def concatenate(cls, parts) -> "Contacts":
        """One record holding ``parts`` one after the other (their radii must agree, or be None)."""
        parts = list(parts)
        radii = {p.radius for p in parts if p.radius is not None}
        if len(radii) > 1:
            raise ValueError(f"cannot concatenate contacts found with different radii {sorted(radii)}")
        radius = radii.pop() if radii else None
        if not parts:
            return cls.empty()
        return cls(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in cls.ARRAYS},
                   radius=radius)

    def subset(self, mask) -> "Contacts":
        """The contacts selected by a boolean mask or an index array."""
        return Contacts(**{name: getattr(self, name)[mask] for name in self.ARRAYS}, radius=self.radius)

    def __repr__(self) -> str:
        return f"Contacts({len(self)}: {self.n_strand_strand} strand/strand, {self.n_strand_head} strand/head)"


# ------------------------------------------------------------------------------ input checking
def check_strands(points, offsets, arc) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and convert the ragged strand arrays (points (V,3), offsets (S+1,), arc (V,))."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    arc = np.ascontiguousarray(arc, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (V, 3), got {points.shape}")
    if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or offsets[-1] != len(points):
        raise ValueError("offsets must be (S + 1,), start at 0 and end at len(points)")
    if np.any(np.diff(offsets) < 0):
        raise ValueError("offsets must be non-decreasing")
    if arc.shape != (len(points),):
        raise ValueError(f"arc must be ({len(points)},), got {arc.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(arc))):
        raise ValueError("points and arc must be finite")
    step = np.diff(arc)
    within = np.ones(len(step), dtype=bool)
    within[offsets[1:-1][(offsets[1:-1] > 0) & (offsets[1:-1] < len(points))] - 1] = False
    if np.any(step[within] < 0.0):
        raise ValueError("arc must be non-decreasing along every strand")
    return points, offsets, arc


def strand_segments(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start vertex (n_seg,) and strand id (n_seg,) of every segment, strand after strand."""
    counts = np.diff(offsets)
    n_seg = np.maximum(counts - 1, 0)
    seg_strand = np.repeat(np.arange(len(counts), dtype=np.int64), n_seg)
    first_seg = np.concatenate([[0], np.cumsum(n_seg)])[:-1]
    v0 = np.arange(len(seg_strand), dtype=np.int64) - np.repeat(first_seg, n_seg) + np.repeat(offsets[:-1], n_seg)
    return v0, seg_strand


# --------------------------------------------------------------------- segment/segment distance
@nb.njit(cache=True)
def _segment_params(p0x, p0y, p0z, p1x, p1y, p1z, q0x, q0y, q0z, q1x, q1y, q1z):
    """Parameters (s, t) in [0, 1] of the closest points of [p0, p1] and [q0, q1] (Ericson 5.1.9)."""
    d1x, d1y, d1z = p1x - p0x, p1y - p0y, p1z - p0z
    d2x, d2y, d2z = q1x - q0x, q1y - q0y, q1z - q0z
    rx, ry, rz = p0x - q0x, p0y - q0y, p0z - q0z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    if a <= _LEN2_EPS and e <= _LEN2_EPS:
        return 0.0, 0.0
    if a <= _LEN2_EPS:
        return 0.0, min(max(f / e, 0.0), 1.0)
    c = d1x * rx + d1y * ry + d1z * rz
    if e <= _LEN2_EPS:
        return min(max(-c / a, 0.0), 1.0), 0.0
    b = d1x * d2x + d1y * d2y + d1z * d2z
    denom = a * e - b * b
    parallel = not denom > _PARALLEL_EPS * a * e
    s = 0.0
    if not parallel:
        s = min(max((b * f - c * e) / denom, 0.0), 1.0)
    t = (b * s + f) / e
    if t < 0.0:
        t = 0.0
        s = min(max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        t = 1.0
        s = min(max((b - c) / a, 0.0), 1.0)
    if not parallel:
        return s, t
    # (nearly) parallel: the pair above is a minimiser only if they are exactly parallel; the closest
    # pair has an endpoint of one segment, so take the best of the four endpoint projections where one
    # is clearly closer (|r + s d1 - t d2|^2 summed from its components: the expanded form cancels)
    best = _gap2(rx, ry, rz, d1x, d1y, d1z, d2x, d2y, d2z, s, t)
    for k in range(4):
        if k == 0:
            cs, ct = 0.0, min(max(f / e, 0.0), 1.0)
        elif k == 1:
            cs, ct = 1.0, min(max((b + f) / e, 0.0), 1.0)
        elif k == 2:
            cs, ct = min(max(-c / a, 0.0), 1.0), 0.0
        else:
            cs, ct = min(max((b - c) / a, 0.0), 1.0), 1.0
        d2 = _gap2(rx, ry, rz, d1x, d1y, d1z, d2x, d2y, d2z, cs, ct)
        if d2 < best * (1.0 - 1e-12):
            best, s, t = d2, cs, ct
    return s, t


@nb.njit(cache=True)
def _gap2(rx, ry, rz, d1x, d1y, d1z, d2x, d2y, d2z, s, t):
    """|r + s d1 - t d2|^2 from its components."""
    vx = rx + s * d1x - t * d2x
    vy = ry + s * d1y - t * d2y
    vz = rz + s * d1z - t * d2z
    return vx * vx + vy * vy + vz * vz


@nb.njit(cache=True)
def _segment_closest_points_kernel(p0, p1, q0, q1):
    n = p0.shape[0]
    s = np.empty(n)
    t = np.empty(n)
    for k in range(n):
        s[k], t[k] = _segment_params(p0[k, 0], p0[k, 1], p0[k, 2], p1[k, 0], p1[k, 1], p1[k, 2],
                                     q0[k, 0], q0[k, 1], q0[k, 2], q1[k, 0], q1[k, 1], q1[k, 2])
    return s, t


def segment_closest_points(p0, p1, q0, q1):
    """Closest points between segments [p0, p1] and [q0, q1], all (n, 3).

    Returns (s, t, c1, c2, distance): parameters in [0, 1], points c1 = p0 + s (p1 - p0) and
    c2 = q0 + t (q1 - q0), and |c1 - c2|.  Parallel and zero-length segments give one of the
    minimisers, chosen deterministically.
    """
    p0, p1, q0, q1 = (np.ascontiguousarray(np.reshape(x, (-1, 3)), dtype=np.float64) for x in (p0, p1, q0, q1))
    s, t = _segment_closest_points_kernel(p0, p1, q0, q1)
    c1 = p0 + s[:, None] * (p1 - p0)
    c2 = q0 + t[:, None] * (q1 - q0)
    return s, t, c1, c2, np.linalg.norm(c1 - c2, axis=1)


# ------------------------------------------------------------------------------- broad phase
GROUP_SEGMENTS = 4  #: most segments in a broad-phase group
GROUP_DIAMETERS = 32.0  #: most length of a group, in contact diameters (long segments stay alone)


@nb.njit(cache=True)
def _segment_box(points, v, radius, box, r):
    """Row r of box: the box of segment [points[v], points[v + 1]], inflated by radius."""
    for k in range(3):
        box[r, k] = min(points[v, k], points[v + 1, k]) - radius
        box[r, 3 + k] = max(points[v, k], points[v + 1, k]) + radius


@nb.njit(cache=True)
def _boxes_overlap(a, r, b, q):
    """Whether box row r of a and box row q of b (lower xyz, upper xyz) overlap (closed)."""
    return not (b[q, 0] > a[r, 3] or a[r, 0] > b[q, 3] or b[q, 1] > a[r, 4] or a[r, 1] > b[q, 4]
                or b[q, 2] > a[r, 5] or a[r, 2] > b[q, 5])


@nb.njit(cache=True)
def _segment_groups(points, seg_v0, seg_strand, seg_radius, max_segments, max_length):
    """Runs of consecutive segments of one strand, at most ``max_segments`` long and, past the first
    segment, at most ``max_length`` in total length.

    Returns first (n_groups + 1,): the first segment of each group, then n_seg; box (n_groups, 6):
    the union of the group's segment boxes, each inflated by its radius seg_radius (lower xyz, upper xyz); capsule
    (n_groups, 7): the chord from the group's first to its last vertex and the largest distance of
    the group's vertices (hence of its polyline) from that chord.
    """
    n = seg_v0.shape[0]
    first = np.empty(n + 1, np.int64)
    n_groups = 0
    length = 0.0
    for i in range(n):
        v = seg_v0[i]
        seg_len = np.sqrt((points[v + 1, 0] - points[v, 0]) ** 2 + (points[v + 1, 1] - points[v, 1]) ** 2
                          + (points[v + 1, 2] - points[v, 2]) ** 2)
        if (n_groups == 0 or seg_strand[i] != seg_strand[i - 1] or i - first[n_groups - 1] >= max_segments
                or length + seg_len > max_length):
            first[n_groups] = i
            n_groups += 1
            length = 0.0
        length += seg_len
    first[n_groups] = n
    first = first[: n_groups + 1].copy()
    box = np.empty((n_groups, 6))
    capsule = np.empty((n_groups, 7))
    seg_box = np.empty((1, 6))
    for g in range(n_groups):
        box[g, :3] = np.inf
        box[g, 3:] = -np.inf
        for i in range(first[g], first[g + 1]):
            _segment_box(points, seg_v0[i], seg_radius[i], seg_box, 0)
            for k in range(3):
                box[g, k] = min(box[g, k], seg_box[0, k])
                box[g, 3 + k] = max(box[g, 3 + k], seg_box[0, 3 + k])
        v0 = seg_v0[first[g]]
        v1 = seg_v0[first[g + 1] - 1] + 1
        chord2 = 0.0
        for k in range(3):
            capsule[g, k] = points[v0, k]
            capsule[g, 3 + k] = points[v1, k]
            chord2 += (points[v1, k] - points[v0, k]) ** 2
        dev = 0.0
        for v in range(v0 + 1, v1):
            t = 0.0
            if chord2 > 0.0:
                for k in range(3):
                    t += (points[v, k] - points[v0, k]) * (points[v1, k] - points[v0, k])
                t = min(max(t / chord2, 0.0), 1.0)
            d2 = 0.0
            for k in range(3):
                d2 += (points[v, k] - points[v0, k] - t * (points[v1, k] - points[v0, k])) ** 2
            dev = max(dev, np.sqrt(d2))
        capsule[g, 6] = dev
    return first, box, capsule


def default_cell_size(box: np.ndarray) -> float:
    """Hash cell edge: twice the mean edge of the group boxes (box (n, 6): lower xyz, upper xyz)."""
    if len(box) == 0:
        return 1.0
    return 2.0 * float(np.mean(box[:, 3:] - box[:, :3]))


@nb.njit(cache=True)
def _cell_entries(box, order, origin, h, nx, ny):
    """(cell key, box) for every cell overlapped by every box, the boxes taken in ``order``."""
    n = box.shape[0]
    rng = np.empty((n, 6), np.int64)
    total = 0
    for i in range(n):
        cnt = 1
        for k in range(3):
            a = np.int64(np.floor((box[i, k] - origin[k]) / h))
            b = np.int64(np.floor((box[i, 3 + k] - origin[k]) / h))
            rng[i, k] = a
            rng[i, 3 + k] = b
            cnt *= b - a + 1
        total += cnt
    keys = np.empty(total, np.int64)
    ids = np.empty(total, np.int64)
    m = 0
    for o in range(n):
        i = order[o]
        for iz in range(rng[i, 2], rng[i, 5] + 1):
            for iy in range(rng[i, 1], rng[i, 4] + 1):
                for ix in range(rng[i, 0], rng[i, 3] + 1):
                    keys[m] = ix + nx * (iy + ny * iz)
                    ids[m] = i
                    m += 1
    return keys, ids


@nb.njit(cache=True)
def _counting_sort(keys, n_keys):
    """Stable order of keys in [0, n_keys)."""
    start = np.zeros(n_keys + 1, np.int64)
    for key in keys:
        start[key + 1] += 1
    for c in range(n_keys):
        start[c + 1] += start[c]
    order = np.empty(keys.shape[0], np.int64)
    for x in range(keys.shape[0]):
        order[start[keys[x]]] = x
        start[keys[x]] += 1
    return order


@nb.njit(cache=True)
def _grow(arr, n):
    out = np.empty((max(2 * arr.shape[0], n),) + arr.shape[1:], arr.dtype)
    out[: arr.shape[0]] = arr
    return out


@nb.njit(cache=True)
def _self_params(points, arc, u, w, s, t, min_arc):
    """Closest points of two segments of one strand (u before w) under the constraint
    s_b - s_a >= min_arc on their arc lengths; returns (s, t, feasible).

    The distance is convex on the parameter square and the constraint a half-plane, so when the
    free minimiser (s, t) violates it the constrained one lies on the line s_b - s_a = min_arc.
    """
    a0, la = arc[u], arc[u + 1] - arc[u]
    b0, lb = arc[w], arc[w + 1] - arc[w]
    if (b0 + t * lb) - (a0 + s * la) >= min_arc:
        return s, t, True
    if lb <= 0.0:  # t does not move s_b: the constraint is s <= s_max, a sub-rectangle
        if la <= 0.0:
            return s, t, False
        s_max = (b0 - a0 - min_arc) / la
        if s_max < 0.0:
            return s, t, False
        s_max = min(s_max, 1.0)
        s, t = _segment_params(points[u, 0], points[u, 1], points[u, 2],
                               points[u, 0] + s_max * (points[u + 1, 0] - points[u, 0]),
                               points[u, 1] + s_max * (points[u + 1, 1] - points[u, 1]),
                               points[u, 2] + s_max * (points[u + 1, 2] - points[u, 2]),
                               points[w, 0], points[w, 1], points[w, 2],
                               points[w + 1, 0], points[w + 1, 1], points[w + 1, 2])
        return s * s_max, t, True
    alpha = (min_arc + a0 - b0) / lb  # on the line: t = alpha + beta s
    beta = la / lb
    s_lo, s_hi = 0.0, 1.0
    if beta > 0.0:
        s_lo = max(0.0, -alpha / beta)
        s_hi = min(1.0, (1.0 - alpha) / beta)
    elif alpha < 0.0 or alpha > 1.0:
        return s, t, False
    if s_lo > s_hi:
        return s, t, False
    # |r0 + s q|^2 along the line, r0 = p0 - q0 - alpha d2, q = d1 - beta d2
    rq = 0.0
    qq = 0.0
    for k in range(3):
        d1 = points[u + 1, k] - points[u, k]
        d2 = points[w + 1, k] - points[w, k]
        r0 = points[u, k] - points[w, k] - alpha * d2
        q = d1 - beta * d2
        rq += r0 * q
        qq += q * q
    s_new = s_lo if qq <= 0.0 else min(max(-rq / qq, s_lo), s_hi)
    t_new = min(max(alpha + beta * s_new, 0.0), 1.0)
    if t_new < 1e-12:
        t_new = 0.0
    elif t_new > 1.0 - 1e-12:
        t_new = 1.0
    return s_new, t_new, True


_ADJACENT_MARGIN = 1e-6  # relative margin of the adjacent-segment bound over rounding


@nb.njit(cache=True)
def _pair_test(i, j, points, arc, seg_v0, seg_strand, two_rc, min_self_arc):
    """Exact test of segments i < j whose inflated boxes overlap.

    Returns (stage, s, t, d): stage 0 when rejected without the exact test, 1 when the exact test
    finds them 2 r_c apart or more, 2 when they are closer, with their closest-point parameters
    and distance.
    """
    u = seg_v0[i]
    w = seg_v0[j]
    dxi = points[u + 1, 0] - points[u, 0]
    dyi = points[u + 1, 1] - points[u, 1]
    dzi = points[u + 1, 2] - points[u, 2]
    dxj = points[w + 1, 0] - points[w, 0]
    dyj = points[w + 1, 1] - points[w, 1]
    dzj = points[w + 1, 2] - points[w, 2]
    len2_i = 0.0 + dxi ** 2 + dyi ** 2 + dzi ** 2
    len2_j = 0.0 + dxj ** 2 + dyj ** 2 + dzj ** 2
    two_rc2 = two_rc * two_rc
    same = seg_strand[i] == seg_strand[j]
    if same and w == u + 1:
        # consecutive segments meeting at a vertex at angle cos = c: points P, Q at arc distances
        # (1 - s) l_i before it and t l_j after it with (1 - s) l_i + t l_j >= min_self_arc are at
        # least rho min_self_arc apart along the polyline, rho = min(|segment| / arc) <= 1, so
        # |P - Q|^2 >= (rho min_self_arc)^2 (1 + c) / 2: no contact when that exceeds (2 r_c)^2
        la = arc[u + 1] - arc[u]
        lb = arc[w + 1] - arc[w]
        if la > 0.0 and lb > 0.0 and len2_i > 0.0 and len2_j > 0.0:
            c = (dxi * dxj + dyi * dyj + dzi * dzj) / np.sqrt(len2_i * len2_j)
            rho2 = min(len2_i / (la * la), len2_j / (lb * lb))
            if rho2 * min_self_arc * min_self_arc * 0.5 * (1.0 + c) >= two_rc2 * (1.0 + _ADJACENT_MARGIN):
                return 0, 0.0, 0.0, 0.0
    # the infinite lines are no farther apart than the segments: reject when they are at least
    # 2 r_c apart (only where the lines are not nearly parallel)
    cx = dyi * dzj - dzi * dyj
    cy = dzi * dxj - dxi * dzj
    cz = dxi * dyj - dyi * dxj
    cc = cx * cx + cy * cy + cz * cz
    if cc > 1e-8 * len2_i * len2_j:
        r = ((0.5 * (points[u, 0] + points[u + 1, 0]) - 0.5 * (points[w, 0] + points[w + 1, 0])) * cx
             + (0.5 * (points[u, 1] + points[u + 1, 1]) - 0.5 * (points[w, 1] + points[w + 1, 1])) * cy
             + (0.5 * (points[u, 2] + points[u + 1, 2]) - 0.5 * (points[w, 2] + points[w + 1, 2])) * cz)
        if r * r >= two_rc2 * cc:
            return 0, 0.0, 0.0, 0.0
    s, t = _segment_params(points[u, 0], points[u, 1], points[u, 2],
                           points[u + 1, 0], points[u + 1, 1], points[u + 1, 2],
                           points[w, 0], points[w, 1], points[w, 2],
                           points[w + 1, 0], points[w + 1, 1], points[w + 1, 2])
    if same:
        s, t, feasible = _self_params(points, arc, u, w, s, t, min_self_arc)
        if not feasible:
            return 1, s, t, 0.0
    d2 = 0.0
    for k in range(3):
        ca = points[u, k] + s * (points[u + 1, k] - points[u, k])
        cb = points[w, k] + t * (points[w + 1, k] - points[w, k])
        d2 += (ca - cb) * (ca - cb)
    d = np.sqrt(d2)
    return (2 if d < two_rc else 1), s, t, d


@nb.njit(cache=True, inline="always")
def _capsules_apart(capsule, a, b, limit):
    """Whether the chords of capsule rows a and b are at least limit + both deviations apart (tested
    on the chords' lines first, then on the chords)."""
    reach = limit + capsule[a, 6] + capsule[b, 6]
    dxa = capsule[a, 3] - capsule[a, 0]
    dya = capsule[a, 4] - capsule[a, 1]
    dza = capsule[a, 5] - capsule[a, 2]
    dxb = capsule[b, 3] - capsule[b, 0]
    dyb = capsule[b, 4] - capsule[b, 1]
    dzb = capsule[b, 5] - capsule[b, 2]
    cx = dya * dzb - dza * dyb
    cy = dza * dxb - dxa * dzb
    cz = dxa * dyb - dya * dxb
    cc = cx * cx + cy * cy + cz * cz
    if cc > 1e-8 * (dxa * dxa + dya * dya + dza * dza) * (dxb * dxb + dyb * dyb + dzb * dzb):  # not nearly parallel
        r = ((capsule[a, 0] - capsule[b, 0]) * cx + (capsule[a, 1] - capsule[b, 1]) * cy
             + (capsule[a, 2] - capsule[b, 2]) * cz)
        if r * r >= reach * reach * cc:
            return True
    s, t = _segment_params(capsule[a, 0], capsule[a, 1], capsule[a, 2], capsule[a, 3], capsule[a, 4], capsule[a, 5],
                           capsule[b, 0], capsule[b, 1], capsule[b, 2], capsule[b, 3], capsule[b, 4], capsule[b, 5])
    d2 = 0.0
    for k in range(3):
        d2 += (capsule[a, k] + s * (capsule[a, 3 + k] - capsule[a, k])
               - capsule[b, k] - t * (capsule[b, 3 + k] - capsule[b, k])) ** 2
    return d2 >= reach * reach


@nb.njit(cache=True)
def _pair_test_other(p0x, p0y, p0z, p1x, p1y, p1z, q0x, q0y, q0z, q1x, q1y, q1z, two_rc, reject):
    """:func:`_pair_test` for segments [p0, p1] and [q0, q1] of two different strands, on their end
    points (scalars: the caller's loop does no array reference counting), with one more early out
    first: the separating axis through the midpoints.  The segments are at least
    |m| - (|d_p . m| + |d_q . m|) / (2 |m|) apart (m the midpoints' difference, d the directions);
    a pair whose separation is at least ``reject`` (2 r_c plus a margin far above rounding) cannot be
    closer than 2 r_c.  The same arithmetic as :func:`_pair_test` otherwise: the same (s, t, d)."""
    dxi = p1x - p0x
    dyi = p1y - p0y
    dzi = p1z - p0z
    dxj = q1x - q0x
    dyj = q1y - q0y
    dzj = q1z - q0z
    mx = 0.5 * (p0x + p1x) - 0.5 * (q0x + q1x)
    my = 0.5 * (p0y + p1y) - 0.5 * (q0y + q1y)
    mz = 0.5 * (p0z + p1z) - 0.5 * (q0z + q1z)
    mm = mx * mx + my * my + mz * mz
    half = 0.5 * (abs(dxi * mx + dyi * my + dzi * mz) + abs(dxj * mx + dyj * my + dzj * mz))
    if mm - half >= reject * np.sqrt(mm):
        return 0, 0.0, 0.0, 0.0
    len2_i = 0.0 + dxi * dxi + dyi * dyi + dzi * dzi
    len2_j = 0.0 + dxj * dxj + dyj * dyj + dzj * dzj
    # the infinite lines are no farther apart than the segments (as in _pair_test)
    cx = dyi * dzj - dzi * dyj
    cy = dzi * dxj - dxi * dzj
    cz = dxi * dyj - dyi * dxj
    cc = cx * cx + cy * cy + cz * cz
    if cc > 1e-8 * len2_i * len2_j:
        r = mx * cx + my * cy + mz * cz
        if r * r >= two_rc * two_rc * cc:
            return 0, 0.0, 0.0, 0.0
    s, t = _segment_params(p0x, p0y, p0z, p1x, p1y, p1z, q0x, q0y, q0z, q1x, q1y, q1z)
    ax = p0x + s * (p1x - p0x) - (q0x + t * (q1x - q0x))
    ay = p0y + s * (p1y - p0y) - (q0y + t * (q1y - q0y))
    az = p0z + s * (p1z - p0z) - (q0z + t * (q1z - q0z))
    d = np.sqrt(0.0 + ax * ax + ay * ay + az * az)
    return (2 if d < two_rc else 1), s, t, d


@nb.njit(cache=True)
def _segment_boxes(points, seg_v0, seg_radius):
    """(n_seg, 6) box of every segment inflated by its radius (``_segment_box``'s values)."""
    n = seg_v0.shape[0]
    sb = np.empty((n, 6))
    for i in range(n):
        v = seg_v0[i]
        r = seg_radius[i]
        for k in range(3):
            sb[i, k] = min(points[v, k], points[v + 1, k]) - r
            sb[i, 3 + k] = max(points[v, k], points[v + 1, k]) + r
    return sb


@nb.njit(cache=True, inline="always")
def _rows_overlap(a, r, b, q):
    """:func:`_boxes_overlap`, inlined."""
    return not (b[q, 0] > a[r, 3] or a[r, 0] > b[q, 3] or b[q, 1] > a[r, 4] or a[r, 1] > b[q, 4]
                or b[q, 2] > a[r, 5] or a[r, 2] > b[q, 5])


@nb.njit(cache=True)
def _pair_order(out_i, out_j, n_out, n_seg):
    """The order sorting distinct pairs (out_i, out_j)[:n_out] by (i, j): counting sort by i, then an
    insertion sort by j inside each row (rows are short)."""
    start = np.zeros(n_seg + 1, np.int64)
    for k in range(n_out):
        start[out_i[k] + 1] += 1
    for c in range(n_seg):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n_out, np.int64)
    for k in range(n_out):
        order[fill[out_i[k]]] = k
        fill[out_i[k]] += 1
    for c in range(n_seg):
        for x in range(start[c] + 1, start[c + 1]):
            o = order[x]
            key = out_j[o]
            y = x - 1
            while y >= start[c] and out_j[order[y]] > key:
                order[y + 1] = order[y]
                y -= 1
            order[y + 1] = o
    return order


@nb.njit(cache=True)
def _close_pairs_kernel(keys, ids, first, box, capsule, origin, h, nx, ny, points, arc, seg_v0, seg_strand,
                        seg_radius, min_self_arc, tol, out_i, out_j, out_s, out_t, out_d, n_out, g_start, e_start,
                        n_group_pairs, n_cand):
    """Exact close segment pairs, from the group cell entries sorted by (cell key, box lower x).

    Segment pairs inside each group are tested directly.  Pairs of groups come from a sweep along
    x inside each cell (boxes, capsules, strands and arc spans gathered in entry order); a group pair
    belongs to the single cell holding the lower corner of the two boxes' intersection (the cell of
    max(a, b) is the larger of the cells of a and b: floor is monotone).  Segments i and j are close
    when their axes are less than seg_radius[i] + seg_radius[j] apart (2 r_c for one radius; one
    radius per strand, so a group has its strand's).  Group pairs of one strand whose arc span is
    below ``min_self_arc`` and group pairs whose capsules are at least r_A + r_B + tol apart are
    skipped; otherwise each group's segments whose boxes overlap the other group's box are paired up
    and the pairs whose boxes overlap get :func:`_pair_test_other` (two strands) or
    :func:`_pair_test` (one strand, unless the two segments span less than ``min_self_arc``: no two
    of their points are that far apart along the strand).

    The pairs go to ``out_i, out_j, out_s, out_t, out_d`` from row ``n_out`` on, in the order found
    (:func:`_sorted_pairs` sorts them), starting with group ``g_start`` (the pairs inside groups)
    and, once all groups are done, with the cell whose entries start at ``e_start``.  When the
    arrays are full the kernel stops before the group or cell that does not fit, forgetting that
    group's or cell's pairs, and returns where to resume: (n_out, g_next, e_next, n_group_pairs,
    n_candidates), finished when g_next = n_groups and e_next = len(keys).  No array grows in its
    loops (arrays carried through a loop cost reference counting in every iteration).
    """
    n_groups = first.shape[0] - 1
    self_skip = min_self_arc * (1.0 - 1e-9)  # spans below this have no two points min_self_arc apart
    sb = _segment_boxes(points, seg_v0, seg_radius)
    capacity = out_i.shape[0]
    size = 1
    for g in range(n_groups):
        size = max(size, first[g + 1] - first[g])
    seg_a = np.empty(size, np.int64)
    seg_b = np.empty(size, np.int64)
    for g in range(g_start, n_groups):
        n_out0, n_cand0 = n_out, n_cand
        for a in range(first[g], first[g + 1]):
            for b in range(a + 1, first[g + 1]):
                if not _rows_overlap(sb, a, sb, b) or arc[seg_v0[b] + 1] - arc[seg_v0[a]] < self_skip:
                    continue
                stage, s, t, d = _pair_test(a, b, points, arc, seg_v0, seg_strand, seg_radius[a] + seg_radius[b],
                                            min_self_arc)
                n_cand += stage > 0
                if stage == 2:
                    if n_out == capacity:
                        return n_out0, g, 0, n_group_pairs, n_cand0
                    out_i[n_out], out_j[n_out], out_s[n_out], out_t[n_out], out_d[n_out] = a, b, s, t, d
                    n_out += 1

    n = keys.shape[0]
    eb = np.empty((n, 6))
    ec = np.empty((n, 7))
    ecell = np.empty((n, 3), np.int64)  # cell of the box's lower corner
    estrand = np.empty(n, np.int64)
    earc = np.empty((n, 2))  # arc length of the group's first and last vertex
    for x in range(n):
        g = ids[x]
        for k in range(6):
            eb[x, k] = box[g, k]
        for k in range(7):
            ec[x, k] = capsule[g, k]
        for k in range(3):
            ecell[x, k] = np.int64(np.floor((box[g, k] - origin[k]) / h))
        estrand[x] = seg_strand[first[g]]
        earc[x, 0] = arc[seg_v0[first[g]]]
        earc[x, 1] = arc[seg_v0[first[g + 1] - 1] + 1]
    start = e_start
    while start < n:
        n_out0, n_cand0, n_group_pairs0 = n_out, n_cand, n_group_pairs
        key = keys[start]
        end = start + 1
        while end < n and keys[end] == key:
            end += 1
        cz = key // (nx * ny)
        rem = key - cz * nx * ny
        cy = rem // nx
        cx = rem - cy * nx
        for x in range(start, end):
            ax1, ay0, ay1, az0, az1 = eb[x, 3], eb[x, 1], eb[x, 4], eb[x, 2], eb[x, 5]
            xcy, xcz = ecell[x, 1], ecell[x, 2]
            for y in range(x + 1, end):
                if eb[y, 0] > ax1:
                    break  # sorted by lower x: no later box overlaps along x
                if eb[y, 1] > ay1 or ay0 > eb[y, 4] or eb[y, 2] > az1 or az0 > eb[y, 5]:
                    continue
                # the pair belongs to the cell holding the lower corner of the boxes' intersection
                # (eb[y, 0] >= eb[x, 0] after the sort)
                if ecell[y, 0] != cx or max(xcy, ecell[y, 1]) != cy or max(xcz, ecell[y, 2]) != cz:
                    continue
                n_group_pairs += 1
                if estrand[x] == estrand[y] and max(earc[x, 1], earc[y, 1]) - min(earc[x, 0], earc[y, 0]) < self_skip:
                    continue  # one strand, no two points min_self_arc apart
                A = ids[x]
                B = ids[y]
                if _capsules_apart(ec, x, y, seg_radius[first[A]] + seg_radius[first[B]] + tol):
                    continue
                na = 0
                for a in range(first[A], first[A + 1]):
                    if _rows_overlap(sb, a, eb, y):
                        seg_a[na] = a
                        na += 1
                if na == 0:
                    continue
                nb_ = 0
                for b in range(first[B], first[B + 1]):
                    if _rows_overlap(sb, b, eb, x):
                        seg_b[nb_] = b
                        nb_ += 1
                for p in range(na):
                    for q in range(nb_):
                        if not _rows_overlap(sb, seg_a[p], sb, seg_b[q]):
                            continue
                        i = min(seg_a[p], seg_b[q])
                        j = max(seg_a[p], seg_b[q])
                        two_rc = seg_radius[i] + seg_radius[j]
                        u = seg_v0[i]
                        w = seg_v0[j]
                        if estrand[x] == estrand[y]:
                            if arc[w + 1] - arc[u] < self_skip:
                                continue
                            stage, s, t, d = _pair_test(i, j, points, arc, seg_v0, seg_strand, two_rc, min_self_arc)
                        else:
                            stage, s, t, d = _pair_test_other(
                                points[u, 0], points[u, 1], points[u, 2], points[u + 1, 0], points[u + 1, 1],
                                points[u + 1, 2], points[w, 0], points[w, 1], points[w, 2], points[w + 1, 0],
                                points[w + 1, 1], points[w + 1, 2], two_rc, two_rc + tol)
                        n_cand += stage > 0
                        if stage == 2:
                            if n_out == capacity:
                                return n_out0, n_groups, start, n_group_pairs0, n_cand0
                            out_i[n_out], out_j[n_out], out_s[n_out], out_t[n_out], out_d[n_out] = i, j, s, t, d
                            n_out += 1
        start = end
    return n_out, n_groups, n, n_group_pairs, n_cand


@nb.njit(cache=True)
def _sorted_pairs(out_i, out_j, out_s, out_t, out_d, n_out, n_seg):
    """The first n_out pairs sorted by (i, j): i, j, s, t, distance (n_out,) each."""
    order = _pair_order(out_i, out_j, n_out, n_seg)
    i, j = np.empty(n_out, np.int64), np.empty(n_out, np.int64)
    s, t, d = np.empty(n_out), np.empty(n_out), np.empty(n_out)
    for k in range(n_out):
        o = order[k]
        i[k], j[k], s[k], t[k], d[k] = out_i[o], out_j[o], out_s[o], out_t[o], out_d[o]
    return i, j, s, t, d


@dataclass
class SegmentPairs:
    """Close segment pairs (global segment ids i < j, sorted by (i, j)) with their closest-point
    parameters and distance."""

    i: np.ndarray
    j: np.ndarray
    s: np.ndarray
    t: np.ndarray
    distance: np.ndarray
    n_candidates: int  #: segment pairs given the exact test (boxes overlap, lines closer than 2 r_c)
    n_group_pairs: int = 0  #: pairs of segment groups whose inflated boxes overlap


def strand_radii(radius, n_strands: int) -> np.ndarray:
    """A contact radius per strand (S,) from a scalar or an (S,) array, checked positive."""
    r = np.asarray(radius, dtype=np.float64)
    if r.ndim == 0:
        r = np.full(n_strands, float(r))
    if r.shape != (n_strands,):
        raise ValueError(f"contact radius must be a number or one per strand ({n_strands},), got shape {r.shape}")
    if not np.all(r > 0):
        raise ValueError(f"contact radius must be positive, got {float(np.min(r)) if len(r) else radius}")
    return np.ascontiguousarray(r)


_PAIRS_PER_SEGMENT = [1.0]  # close pairs per segment of the last call (+25 %): the next call's capacity
_MIN_CAPACITY = 4096  # (the tests make it tiny to exercise the resumption)


def close_segment_pairs(points, offsets, arc, radius, *, min_self_arc: float | None = None,
                        cell_size: float | None = None) -> SegmentPairs:
    """All segment pairs whose axes are closer than ``r_a + r_b`` (same-strand rule applied), sorted
    by (i, j).  ``radius``: r_c (the threshold 2 r_c) or one radius per strand (S,) (the simulator's
    speculative margins, strand by strand).  ``min_self_arc`` default pi max(radius).
    ``cell_size``: the hash cell edge (default :func:`default_cell_size`)."""
    points, offsets, arc = check_strands(points, offsets, arc)
    out, n_out, n_cand, n_group_pairs = _find_pairs(points, offsets, arc, radius, min_self_arc, cell_size)
    return SegmentPairs(*_sorted_pairs(*out, n_out, len(strand_segments(offsets)[0])), int(n_cand),
                        int(n_group_pairs))


def _find_pairs(points, offsets, arc, radius, min_self_arc, cell_size):
    """:func:`close_segment_pairs`' pairs in the order the kernel found them: ([i, j, s, t, distance]
    arrays, of which the first n_pairs rows are the pairs, n_pairs, n_candidates, n_group_pairs)."""
    radii = strand_radii(radius, len(offsets) - 1)
    r_max = float(np.max(radii, initial=0.0))
    if min_self_arc is None:
        min_self_arc = np.pi * r_max
    seg_v0, seg_strand = strand_segments(offsets)
    if len(seg_v0) < 2:
        return [np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0)], 0, 0, 0
    seg_radius = np.ascontiguousarray(radii[seg_strand])
    first, box, capsule = _segment_groups(points, seg_v0, seg_strand, seg_radius, GROUP_SEGMENTS,
                                          GROUP_DIAMETERS * 2.0 * float(np.min(radii)))
    h = float(cell_size) if cell_size is not None else default_cell_size(box)
    origin = box[:, :3].min(axis=0)
    dims = np.floor((box[:, 3:].max(axis=0) - origin) / h).astype(np.int64) + 1
    n_cells = float(np.prod(dims.astype(np.float64)))
    if n_cells > 2.0**62:
        raise ValueError(f"hash cell size {h} is too small for the extent of the strands")
    keys, ids = _cell_entries(box, np.argsort(box[:, 0], kind="stable"), origin, h, dims[0], dims[1])
    if n_cells <= 4 * len(keys) + 65536:
        order = _counting_sort(keys, int(n_cells))
    else:
        order = np.argsort(keys, kind="stable")
    # distances are compared with a margin of rounding when groups are skipped by their capsules
    tol = 1e-9 * (2.0 * r_max + float(np.max(np.abs(points))))
    args = (keys[order], ids[order], first, box, capsule, origin, h, dims[0], dims[1], points, arc, seg_v0,
            seg_strand, seg_radius, float(min_self_arc), tol)
    # the kernel fills arrays of a given size and says where to resume when they are full: sized from
    # the last call's pairs per segment, doubled as needed (the result does not depend on it)
    capacity = int(_PAIRS_PER_SEGMENT[0] * len(seg_v0)) + _MIN_CAPACITY
    out = [np.empty(capacity, np.int64), np.empty(capacity, np.int64), np.empty(capacity), np.empty(capacity),
           np.empty(capacity)]
    n_out = g_next = e_next = n_group_pairs = n_cand = 0
    while True:
        n_out, g_next, e_next, n_group_pairs, n_cand = _close_pairs_kernel(
            *args, *out, n_out, g_next, e_next, n_group_pairs, n_cand)
        if g_next >= len(first) - 1 and e_next >= len(keys):
            break
        out = [np.concatenate([x[:n_out], np.empty(2 * len(x) - n_out, x.dtype)]) for x in out]
    _PAIRS_PER_SEGMENT[0] = 1.25 * n_out / len(seg_v0)
    return out, n_out, n_cand, n_group_pairs


# ------------------------------------------------------------------------------ deduplication
@nb.njit(cache=True)
def _local_minima_unsorted(pi, pj, ps, pt, pd, n, seg_strand, tol):
    """Keep the pairs whose closest point is a local minimum of the polyline/polyline distance: a pair whose
    closest point is a vertex (s or t at 0 or 1) is dropped when a neighbouring pair sharing that vertex is
    closer (ties: the smaller (i, j) wins).  The first n pairs in any order (distinct pairs i < j), the
    neighbours looked up in a hash table of the pairs: each decision depends on the set of pairs, their values
    and the (i, j) order of keys only (the sorted-pairs search of tests/reference/contact.py gives the same).
    Returns the indices of the kept pairs, sorted by (i, j)."""
    n_seg = seg_strand.shape[0]
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    mask = (1 << bits) - 1
    table = np.full((1 << bits, 2), -1, np.int64)  # (key, pair) per slot: one cache line per probe
    for k in range(n):
        key = pi[k] * n_seg + pj[k]
        slot = _pair_slot(key, bits)
        while table[slot, 1] >= 0:
            slot = (slot + 1) & mask
        table[slot, 0] = key
        table[slot, 1] = k
    keep = np.ones(n, np.bool_)
    ni = np.empty(2, np.int64)
    nj = np.empty(2, np.int64)
    n_keep = 0
    for k in range(n):
        i, j = pi[k], pj[k]
        if not (0.0 < ps[k] < 1.0 and 0.0 < pt[k] < 1.0):
            # segments sharing the closest point (vertex) with i, and with j
            ni[0] = i
            ni[1] = _vertex_neighbour(i, ps[k], seg_strand)
            ci = 1 if ni[1] < 0 else 2
            nj[0] = j
            nj[1] = _vertex_neighbour(j, pt[k], seg_strand)
            cj = 1 if nj[1] < 0 else 2
            for x in range(ci):
                for y in range(cj):
                    if x == 0 and y == 0:
                        continue
                    a = min(ni[x], nj[y])
                    b = max(ni[x], nj[y])
                    if a == b:
                        continue
                    key = a * n_seg + b
                    slot = _pair_slot(key, bits)
                    while table[slot, 1] >= 0:
                        if table[slot, 0] == key:
                            d_other = pd[table[slot, 1]]
                            if d_other < pd[k] - tol or (d_other <= pd[k] + tol and (a < i or (a == i and b < j))):
                                keep[k] = False
                            break
                        slot = (slot + 1) & mask
        n_keep += keep[k]
    kept = np.empty(n_keep, np.int64)
    keys = np.empty(n_keep, np.int64)
    c = 0
    for k in range(n):
        if keep[k]:
            kept[c] = k
            keys[c] = pi[k] * n_seg + pj[k]
            c += 1
    return kept[np.argsort(keys)]


@nb.njit(cache=True, inline="always")
def _vertex_neighbour(seg, param, seg_strand):
    """The segment of the same strand sharing the vertex at ``param`` (0: its start, 1: its end) of segment
    ``seg``, else -1 (an interior point, or the strand's first/last vertex)."""
    if param == 0.0 and seg > 0 and seg_strand[seg - 1] == seg_strand[seg]:
        return seg - 1
    if param == 1.0 and seg + 1 < seg_strand.shape[0] and seg_strand[seg + 1] == seg_strand[seg]:
        return seg + 1
    return -1


@nb.njit(cache=True, inline="always")
def _pair_slot(key, bits):
    """Slot of a pair key in a table of 2^bits slots (Fibonacci hashing)."""
    return np.int64((np.uint64(key) * np.uint64(11400714819323198485)) >> np.uint64(64 - bits))


@nb.njit(cache=True)
def _merge_kernel(group_a, group_b, s_a, s_b, dist, merge_arc):
    """Greedy: in each (group_a, group_b) run, sorted by distance, drop contacts within merge_arc
    of an already kept one along both strands."""
    m = group_a.shape[0]
    keep = np.zeros(m, np.bool_)
    start = 0
    while start < m:
        end = start + 1
        while end < m and group_a[end] == group_a[start] and group_b[end] == group_b[start]:
            end += 1
        for k in range(start, end):
            ok = True
            for q in range(start, k):
                if keep[q] and abs(s_a[q] - s_a[k]) < merge_arc and abs(s_b[q] - s_b[k]) < merge_arc:
                    ok = False
                    break
            keep[k] = ok
        start = end
    return keep


def merge_close(strand_a, strand_b, s_a, s_b, distance, merge_arc: float) -> np.ndarray:
    """Indices of the contacts kept after merging, per strand pair, those closer than ``merge_arc``
    along both strands (the closest wins; ties by input order)."""
    order = np.lexsort((np.arange(len(distance)), distance, strand_b, strand_a))
    keep = _merge_kernel(strand_a[order], strand_b[order], s_a[order], np.nan_to_num(s_b[order]),
                         distance[order], float(merge_arc))
    return np.sort(order[keep])


# ---------------------------------------------------------------------------------- normals
def _fallback_normals(dir_a: np.ndarray, dir_b: np.ndarray) -> np.ndarray:
    """A unit normal when the two axes touch: orthogonal to both directions (or to dir_a)."""
    n = np.cross(dir_a, dir_b)
    bad = np.linalg.norm(n, axis=1) <= 1e-12 * np.maximum(
        np.linalg.norm(dir_a, axis=1) * np.linalg.norm(dir_b, axis=1), 1e-300)
    if np.any(bad):
        axis = np.eye(3)[np.argmin(np.abs(dir_a[bad]), axis=1)]
        n[bad] = np.cross(dir_a[bad], axis)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # deterministic sign: the largest component positive
    big = np.take_along_axis(n, np.argmax(np.abs(n), axis=1)[:, None], axis=1)
    return n * np.where(big < 0.0, -1.0, 1.0)


def pair_normals(point_a, point_b, dir_a, dir_b, distance) -> np.ndarray:
    """Unit normals from b to a; when the axes touch (distance ~ 0), orthogonal to both axes."""
    scale = 1.0 + np.max(np.abs(point_a), axis=1) if len(point_a) else np.ones(0)
    tiny = distance <= 1e-12 * scale
    normal = np.empty_like(point_a)
    ok = ~tiny
    normal[ok] = (point_a[ok] - point_b[ok]) / distance[ok, None]
    if np.any(tiny):
        normal[tiny] = _fallback_normals(dir_a[tiny], dir_b[tiny])
    return normal


# ---------------------------------------------------------------------------- public detection
def detect_strand_contacts(points, offsets, arc, radius, *, min_self_arc: float | None = None,
                           merge_arc: float | None = None, cell_size: float | None = None,
                           stats: dict | None = None) -> Contacts:
    """Strand/strand contacts between capsules of radius ``radius`` around the strand polylines
    (a number, or one per strand (S,): capsules of strands a and b touch below r_a + r_b; min_self_arc,
    merge_arc and the result's ``radius`` then use the largest).

    points (V, 3), offsets (S + 1,), arc (V,): the sampled strands and the arc-length parameter of
    each vertex (s on a segment is interpolated linearly).  ``min_self_arc`` (default pi r_c):
    same-strand pairs closer than this in arc length are neighbours, not contacts.  ``merge_arc``
    (default 4 r_c): local minima of one strand pair closer than this along both strands are merged.
    ``stats``, if given, receives counts (candidates, close pairs, local minima, contacts).
    Contacts are ordered by (strand_a, s_a, strand_b, s_b); strand_a <= strand_b, and s_a < s_b
    for self-contacts.
    """
    points, offsets, arc = check_strands(points, offsets, arc)
    radii = radius  # a number or one per strand, for the pair thresholds
    radius = float(np.max(radius, initial=0.0)) if np.ndim(radius) else radius  # the largest, for the rest
    merge_arc = 4.0 * radius if merge_arc is None else float(merge_arc)
    t0 = time.perf_counter()
    (pi, pj, ps, pt, pd), n_pairs, n_cand, n_group_pairs = _find_pairs(points, offsets, arc, radii, min_self_arc,
                                                                        cell_size)
    seg_v0, seg_strand = strand_segments(offsets)
    t1 = time.perf_counter()

    # the local minima of the pairs (in (i, j) order), without sorting all of them
    keep = _local_minima_unsorted(pi, pj, ps, pt, pd, n_pairs, seg_strand, 1e-9 * radius)
    i, j, s, t, d = (x[keep] for x in (pi, pj, ps, pt, pd))
    va, vb = seg_v0[i], seg_v0[j]
    s_a = arc[va] + s * (arc[va + 1] - arc[va])
    s_b = arc[vb] + t * (arc[vb + 1] - arc[vb])
    strand_a, strand_b = seg_strand[i], seg_strand[j]
    kept = merge_close(strand_a, strand_b, s_a, s_b, d, merge_arc)
    t2 = time.perf_counter()

    n_minima = len(d)
    kept = kept[np.lexsort((s_b[kept], strand_b[kept], s_a[kept], strand_a[kept]))]
    strand_a, strand_b, s_a, s_b, s, t, d, va, vb = (
        x[kept] for x in (strand_a, strand_b, s_a, s_b, s, t, d, va, vb))
    dir_a = points[va + 1] - points[va]
    dir_b = points[vb + 1] - points[vb]
    point_a = points[va] + s[:, None] * dir_a
    point_b = points[vb] + t[:, None] * dir_b
    normal = pair_normals(point_a, point_b, dir_a, dir_b, d)
    frame = contact_frames(normal, dir_a) if len(d) else np.zeros((0, 3, 3))
    if stats is not None:
        stats.update(segments=len(seg_v0), group_pairs=int(n_group_pairs), candidates=int(n_cand),
                     close_pairs=int(n_pairs), local_minima=n_minima, strand_contacts=len(kept),
                     time_strand_pairs=t1 - t0,
                     time_strand_dedup=t2 - t1, time_strand_frames=time.perf_counter() - t2)
    return Contacts(strand_a, s_a, strand_b, s_b, point_a, point_b, normal, frame, d, radius)
