"""References for groomtool.contact: the slower implementations the fast ones replaced, kept for the
tests that compare them (bit for bit).

* :func:`close_segment_pairs_reference`: :func:`groomtool.contact.detect.close_segment_pairs` by the
  segment-level spatial hash it replaced (every segment box in every cell it overlaps): the same
  pairs, in hash order.
* :func:`detect_strand_contacts_reference`: :func:`groomtool.contact.detect.detect_strand_contacts` as
  it was before the unsorted local minima: the reference's pairs (one radius per strand: those of the
  largest below r_a + r_b), sorted by (i, j), the local minima by a binary search over all pairs.
* :func:`detect_head_contacts_reference`: :func:`groomtool.contact.head.detect_head_contacts` as it
  was before the distance bounds (every vertex in the head's inflated box queried).
* :func:`contact_jacobian_reference`: :func:`groomtool.contact.jacobian.contact_jacobian` built from the
  dense point Jacobians (:func:`groomtool.rods.superhelix.point_jacobians`) and filtered (O(m N) memory).
* :func:`generalized_contact_force_reference`: :func:`groomtool.contact.jacobian.generalized_contact_force`
  (H^T r) with the same dense point Jacobians.
"""

from __future__ import annotations

import time

import numba as nb
import numpy as np
import scipy.sparse as sp

from groomtool.contact.detect import (HEAD, Contacts, SegmentPairs, _grow, _segment_params, _self_params,
                                      pair_normals, strand_radii,
                                      check_strands, merge_close, strand_segments)
from groomtool.contact.frames import contact_frames
from groomtool.contact.head import _GOLDEN, HeadSurface, _signed_point, as_head_surface
from groomtool.rods import superhelix as sh


# ------------------------------------------------------- strand/strand: segment-level spatial hash
@nb.njit(cache=True)
def _cell_entries(lo, hi, origin, h, nx, ny):
    """(cell key, segment) for every cell overlapped by every box."""
    n = lo.shape[0]
    rng = np.empty((n, 6), np.int64)
    total = 0
    for i in range(n):
        cnt = 1
        for k in range(3):
            a = np.int64(np.floor((lo[i, k] - origin[k]) / h))
            b = np.int64(np.floor((hi[i, k] - origin[k]) / h))
            rng[i, k] = a
            rng[i, 3 + k] = b
            cnt *= b - a + 1
        total += cnt
    keys = np.empty(total, np.int64)
    ids = np.empty(total, np.int64)
    m = 0
    for i in range(n):
        for iz in range(rng[i, 2], rng[i, 5] + 1):
            for iy in range(rng[i, 1], rng[i, 4] + 1):
                for ix in range(rng[i, 0], rng[i, 3] + 1):
                    keys[m] = ix + nx * (iy + ny * iz)
                    ids[m] = i
                    m += 1
    return keys, ids


@nb.njit(cache=True)
def _close_pairs_kernel(keys, ids, lo, hi, origin, h, nx, ny, points, arc, seg_v0, seg_strand,
                        two_rc, min_self_arc):
    """Exact close segment pairs from the cell entries sorted by (cell key, box lower x).

    Returns (n_box_pairs, n_candidates, i, j, s, t, d).  Boxes are gathered in entry order so the
    sweep along x inside each cell reads memory linearly.  Candidates: pairs whose inflated boxes
    overlap and whose infinite lines are closer than 2 r_c; they get the exact segment test.
    """
    n = keys.shape[0]
    elo = np.empty((3, n))
    ehi = np.empty((3, n))
    geo = np.empty((7, n))  # per entry: segment midpoint, direction, squared length
    for x in range(n):
        v = seg_v0[ids[x]]
        geo[6, x] = 0.0
        for k in range(3):
            elo[k, x] = lo[ids[x], k]
            ehi[k, x] = hi[ids[x], k]
            geo[k, x] = 0.5 * (points[v, k] + points[v + 1, k])
            geo[3 + k, x] = points[v + 1, k] - points[v, k]
            geo[6, x] += geo[3 + k, x] ** 2
    two_rc2 = two_rc * two_rc
    cap = 1024
    out_i = np.empty(cap, np.int64)
    out_j = np.empty(cap, np.int64)
    out_s = np.empty(cap)
    out_t = np.empty(cap)
    out_d = np.empty(cap)
    n_out = 0
    n_box = 0
    n_cand = 0
    start = 0
    while start < n:
        key = keys[start]
        end = start + 1
        while end < n and keys[end] == key:
            end += 1
        cz = key // (nx * ny)
        rem = key - cz * nx * ny
        cy = rem // nx
        cx = rem - cy * nx
        for x in range(start, end):
            a = ids[x]
            ax1, ay0, ay1, az0, az1 = ehi[0, x], elo[1, x], ehi[1, x], elo[2, x], ehi[2, x]
            for y in range(x + 1, end):
                if elo[0, y] > ax1:
                    break  # sorted by lower x: no later box overlaps along x
                if elo[1, y] > ay1 or ay0 > ehi[1, y] or elo[2, y] > az1 or az0 > ehi[2, y]:
                    continue
                # the pair belongs to the cell holding the lower corner of the boxes' intersection
                # (elo[0, y] >= elo[0, x] after the sort)
                if np.int64(np.floor((elo[0, y] - origin[0]) / h)) != cx:
                    continue
                if np.int64(np.floor((max(ay0, elo[1, y]) - origin[1]) / h)) != cy:
                    continue
                if np.int64(np.floor((max(az0, elo[2, y]) - origin[2]) / h)) != cz:
                    continue
                n_box += 1
                # the infinite lines are no farther apart than the segments: reject when they are
                # at least 2 r_c apart (only where the lines are not nearly parallel)
                cx_ = geo[4, x] * geo[5, y] - geo[5, x] * geo[4, y]
                cy_ = geo[5, x] * geo[3, y] - geo[3, x] * geo[5, y]
                cz_ = geo[3, x] * geo[4, y] - geo[4, x] * geo[3, y]
                cc = cx_ * cx_ + cy_ * cy_ + cz_ * cz_
                if cc > 1e-8 * geo[6, x] * geo[6, y]:
                    rc_ = ((geo[0, x] - geo[0, y]) * cx_ + (geo[1, x] - geo[1, y]) * cy_
                           + (geo[2, x] - geo[2, y]) * cz_)
                    if rc_ * rc_ >= two_rc2 * cc:
                        continue
                b = ids[y]
                i = min(a, b)
                j = max(a, b)
                n_cand += 1
                u = seg_v0[i]
                w = seg_v0[j]
                s, t = _segment_params(points[u, 0], points[u, 1], points[u, 2],
                                       points[u + 1, 0], points[u + 1, 1], points[u + 1, 2],
                                       points[w, 0], points[w, 1], points[w, 2],
                                       points[w + 1, 0], points[w + 1, 1], points[w + 1, 2])
                if seg_strand[i] == seg_strand[j]:
                    s, t, feasible = _self_params(points, arc, u, w, s, t, min_self_arc)
                    if not feasible:
                        continue
                d2 = 0.0
                for k in range(3):
                    ca = points[u, k] + s * (points[u + 1, k] - points[u, k])
                    cb = points[w, k] + t * (points[w + 1, k] - points[w, k])
                    d2 += (ca - cb) * (ca - cb)
                d = np.sqrt(d2)
                if d >= two_rc:
                    continue
                if n_out == out_i.shape[0]:
                    out_i = _grow(out_i, n_out + 1)
                    out_j = _grow(out_j, n_out + 1)
                    out_s = _grow(out_s, n_out + 1)
                    out_t = _grow(out_t, n_out + 1)
                    out_d = _grow(out_d, n_out + 1)
                out_i[n_out] = i
                out_j[n_out] = j
                out_s[n_out] = s
                out_t[n_out] = t
                out_d[n_out] = d
                n_out += 1
        start = end
    return n_box, n_cand, out_i[:n_out], out_j[:n_out], out_s[:n_out], out_t[:n_out], out_d[:n_out]


def _cell_size(points, seg_v0, radius: float) -> float:
    """Hash cell edge: the mean segment length plus the contact diameter."""
    if len(seg_v0) == 0:
        return 1.0
    mean_len = float(np.mean(np.linalg.norm(points[seg_v0 + 1] - points[seg_v0], axis=1)))
    return mean_len + 2.0 * radius


def close_segment_pairs_reference(points, offsets, arc, radius: float, *, min_self_arc: float | None = None,
                                  cell_size: float | None = None) -> SegmentPairs:
    """:func:`close_segment_pairs` by the segment-level spatial hash it replaced, kept as the
    reference the tests compare against: the same pairs, in hash order."""
    points, offsets, arc = check_strands(points, offsets, arc)
    if not radius > 0:
        raise ValueError(f"contact radius must be positive, got {radius}")
    if min_self_arc is None:
        min_self_arc = np.pi * radius
    seg_v0, seg_strand = strand_segments(offsets)
    if len(seg_v0) < 2:
        e = np.zeros(0)
        return SegmentPairs(e.astype(np.int64), e.astype(np.int64), e, e, e, 0)
    h = float(cell_size) if cell_size is not None else _cell_size(points, seg_v0, radius)
    p0, p1 = points[seg_v0], points[seg_v0 + 1]
    lo = np.minimum(p0, p1) - radius
    hi = np.maximum(p0, p1) + radius
    origin = lo.min(axis=0)
    dims = np.floor((hi.max(axis=0) - origin) / h).astype(np.int64) + 1
    if float(np.prod(dims.astype(np.float64))) > 2.0**62:
        raise ValueError(f"hash cell size {h} is too small for the extent of the strands")
    keys, ids = _cell_entries(lo, hi, origin, h, dims[0], dims[1])
    order = np.lexsort((ids, lo[ids, 0], keys))
    n_box, n_cand, i, j, s, t, d = _close_pairs_kernel(
        keys[order], ids[order], lo, hi, origin, h, dims[0], dims[1], points, arc, seg_v0, seg_strand,
        2.0 * radius, float(min_self_arc))
    return SegmentPairs(i, j, s, t, d, int(n_cand))


# ------------------------------------------------- strand/strand contacts: all pairs sorted, then minima
@nb.njit(cache=True)
def _local_minima_searchsorted(pi, pj, ps, pt, pd, seg_strand, tol):
    """Keep pairs whose closest point is a local minimum of the polyline/polyline distance (pairs
    sorted by (i, j)); neighbours found by a binary search over all pair keys."""
    m = pi.shape[0]
    n_seg = seg_strand.shape[0]
    keys = pi * n_seg + pj
    keep = np.ones(m, np.bool_)
    ni = np.empty(2, np.int64)
    nj = np.empty(2, np.int64)
    for k in range(m):
        i, j = pi[k], pj[k]
        if 0.0 < ps[k] < 1.0 and 0.0 < pt[k] < 1.0:
            continue
        ni[0] = i
        ci = 1
        if ps[k] == 0.0 and i > 0 and seg_strand[i - 1] == seg_strand[i]:
            ni[1] = i - 1
            ci = 2
        elif ps[k] == 1.0 and i + 1 < n_seg and seg_strand[i + 1] == seg_strand[i]:
            ni[1] = i + 1
            ci = 2
        nj[0] = j
        cj = 1
        if pt[k] == 0.0 and j > 0 and seg_strand[j - 1] == seg_strand[j]:
            nj[1] = j - 1
            cj = 2
        elif pt[k] == 1.0 and j + 1 < n_seg and seg_strand[j + 1] == seg_strand[j]:
            nj[1] = j + 1
            cj = 2
        for x in range(ci):
            for y in range(cj):
                if x == 0 and y == 0:
                    continue
                a = min(ni[x], nj[y])
                b = max(ni[x], nj[y])
                if a == b:
                    continue
                other = a * n_seg + b
                pos = np.searchsorted(keys, other)
                if pos < m and keys[pos] == other:
                    d_other = pd[pos]
                    if d_other < pd[k] - tol or (d_other <= pd[k] + tol and other < keys[k]):
                        keep[k] = False
    return keep


def close_segment_pairs_per_strand_reference(points, offsets, arc, radius, *,
                                             min_self_arc: float | None = None) -> SegmentPairs:
    """Close pairs with one radius per strand (or one for all), sorted by (i, j): the segment-level
    reference's pairs at the largest radius whose distance is below r_a + r_b."""
    points, offsets, arc = check_strands(points, offsets, arc)
    radii = strand_radii(radius, len(offsets) - 1)
    r_max = float(np.max(radii, initial=0.0))
    min_self_arc = np.pi * r_max if min_self_arc is None else float(min_self_arc)
    _, seg_strand = strand_segments(offsets)
    ref = close_segment_pairs_reference(points, offsets, arc, r_max, min_self_arc=min_self_arc)
    order = np.lexsort((ref.j, ref.i))
    i, j, s, t, d = (getattr(ref, name)[order] for name in ("i", "j", "s", "t", "distance"))
    keep = d < radii[seg_strand[i]] + radii[seg_strand[j]]
    return SegmentPairs(i[keep], j[keep], s[keep], t[keep], d[keep], ref.n_candidates)


def detect_strand_contacts_reference(points, offsets, arc, radius, *, min_self_arc: float | None = None,
                                     merge_arc: float | None = None) -> Contacts:
    """``detect_strand_contacts`` from the reference's sorted pairs (the pipeline before the unsorted
    local minima): the same contacts, bit for bit."""
    points, offsets, arc = check_strands(points, offsets, arc)
    r_max = float(np.max(radius, initial=0.0)) if np.ndim(radius) else float(radius)
    merge_arc = 4.0 * r_max if merge_arc is None else float(merge_arc)
    pairs = close_segment_pairs_per_strand_reference(points, offsets, arc, radius, min_self_arc=min_self_arc)
    seg_v0, seg_strand = strand_segments(offsets)
    keep = _local_minima_searchsorted(pairs.i, pairs.j, pairs.s, pairs.t, pairs.distance, seg_strand, 1e-9 * r_max)
    i, j, s, t, d = (x[keep] for x in (pairs.i, pairs.j, pairs.s, pairs.t, pairs.distance))
    va, vb = seg_v0[i], seg_v0[j]
    s_a = arc[va] + s * (arc[va + 1] - arc[va])
    s_b = arc[vb] + t * (arc[vb + 1] - arc[vb])
    strand_a, strand_b = seg_strand[i], seg_strand[j]
    kept = merge_close(strand_a, strand_b, s_a, s_b, d, merge_arc)
    kept = kept[np.lexsort((s_b[kept], strand_b[kept], s_a[kept], strand_a[kept]))]
    strand_a, strand_b, s_a, s_b, s, t, d, va, vb = (
        x[kept] for x in (strand_a, strand_b, s_a, s_b, s, t, d, va, vb))
    dir_a = points[va + 1] - points[va]
    dir_b = points[vb + 1] - points[vb]
    point_a = points[va] + s[:, None] * dir_a
    point_b = points[vb] + t[:, None] * dir_b
    normal = pair_normals(point_a, point_b, dir_a, dir_b, d)
    frame = contact_frames(normal, dir_a) if len(d) else np.zeros((0, 3, 3))
    return Contacts(strand_a, s_a, strand_b, s_b, point_a, point_b, normal, frame, d, r_max)


# ---------------------------------------------------------------- strand/head: every vertex queried
@nb.njit(cache=True)
def _signed_on_segment(p, q, x, dp, dq, length, bvh):
    """Signed distance at p + x (q - p); |dp|, |dq| (the ends' distances) bound the search."""
    bound = min(abs(dp) + x * length, abs(dq) + (1.0 - x) * length)
    return _signed_point(p[0] + x * (q[0] - p[0]), p[1] + x * (q[1] - p[1]), p[2] + x * (q[2] - p[2]),
                         bvh, bound)[0]


@nb.njit(cache=True)
def _golden_on_segment(p, q, dp, dq, t_lo, bvh, tol):
    """Minimise the signed distance over p + t (q - p), t in [t_lo, 1]; returns (t, distance).

    dp, dq: the signed distances at p and q.
    """
    length = np.sqrt((q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 + (q[2] - p[2]) ** 2)
    lo, hi = t_lo, 1.0
    x1 = hi - _GOLDEN * (hi - lo)
    x2 = lo + _GOLDEN * (hi - lo)
    f1 = _signed_on_segment(p, q, x1, dp, dq, length, bvh)
    f2 = _signed_on_segment(p, q, x2, dp, dq, length, bvh)
    while hi - lo > tol:
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - _GOLDEN * (hi - lo)
            f1 = _signed_on_segment(p, q, x1, dp, dq, length, bvh)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + _GOLDEN * (hi - lo)
            f2 = _signed_on_segment(p, q, x2, dp, dq, length, bvh)
    return (x1, f1) if f1 <= f2 else (x2, f2)


@nb.njit(cache=True)
def _head_minima_kernel(points, arc, offsets, vdist, bvh, radius, min_root_arc, rel_tol):
    """Per strand: refined local minima of the signed distance below ``radius``.

    Returns (vertex index of the segment start, segment parameter, distance) per minimum, and the
    number of refined candidates.
    """
    out_v = np.empty(1024, np.int64)
    out_t = np.empty(1024)
    out_d = np.empty(1024)
    n_out = 0
    n_refined = 0
    for st in range(offsets.shape[0] - 1):
        v_first, v_last = offsets[st], offsets[st + 1] - 1
        if v_last <= v_first:  # a strand without segments has no contact
            continue
        for k in range(v_first, v_last + 1):
            dk = vdist[k]
            if arc[k] - arc[v_first] < min_root_arc:
                continue
            if k > v_first and vdist[k - 1] < dk:
                continue
            if k < v_last and vdist[k + 1] <= dk:
                continue
            # 1-Lipschitz lower bound of the distance over the two segments around k
            side_lower = np.full(2, np.inf)
            for side, nb_ in enumerate((k - 1, k + 1)):
                if v_first <= nb_ <= v_last:
                    seg = np.sqrt((points[nb_, 0] - points[k, 0]) ** 2
                                  + (points[nb_, 1] - points[k, 1]) ** 2
                                  + (points[nb_, 2] - points[k, 2]) ** 2)
                    side_lower[side] = 0.5 * (dk + vdist[nb_] - seg)
            if min(dk, side_lower[0], side_lower[1]) >= radius:
                continue
            n_refined += 1
            best_v, best_t, best_d = k, 0.0, dk
            if k == v_last:  # express the vertex as the end of its segment
                best_v, best_t = k - 1, 1.0
            if k > v_first and side_lower[0] < radius:  # segment (k - 1, k), outside the attachment
                a0, a1 = arc[k - 1] - arc[v_first], arc[k] - arc[v_first]
                t_lo = 0.0
                if a0 < min_root_arc:
                    t_lo = (min_root_arc - a0) / (a1 - a0) if a1 > a0 else 1.0
                t, d = _golden_on_segment(points[k - 1], points[k], vdist[k - 1], dk, t_lo, bvh, rel_tol)
                if d < best_d and t > t_lo + rel_tol:
                    best_v, best_t, best_d = k - 1, t, d
            if k < v_last and side_lower[1] < radius:  # segment (k, k + 1)
                t, d = _golden_on_segment(points[k], points[k + 1], dk, vdist[k + 1], 0.0, bvh, rel_tol)
                if d < best_d:
                    best_v, best_t, best_d = k, t, d
            if best_d >= radius:
                continue
            if n_out == out_v.shape[0]:
                out_v = np.concatenate((out_v, np.empty(n_out, np.int64)))
                out_t = np.concatenate((out_t, np.empty(n_out)))
                out_d = np.concatenate((out_d, np.empty(n_out)))
            out_v[n_out], out_t[n_out], out_d[n_out] = best_v, best_t, best_d
            n_out += 1
    return out_v[:n_out], out_t[:n_out], out_d[:n_out], n_refined


@nb.njit(cache=True)
def _strand_distances_kernel(points, offsets, in_box, bvh):
    """Signed distance of every vertex in the box (+inf elsewhere); along a strand the previous
    vertex's distance plus the segment length bounds the search (1-Lipschitz)."""
    dist = np.full(points.shape[0], np.inf)
    for st in range(offsets.shape[0] - 1):
        for k in range(offsets[st], offsets[st + 1]):
            if not in_box[k]:
                continue
            bound = np.inf
            if k > offsets[st] and in_box[k - 1]:
                step = np.sqrt((points[k, 0] - points[k - 1, 0]) ** 2
                               + (points[k, 1] - points[k - 1, 1]) ** 2
                               + (points[k, 2] - points[k - 1, 2]) ** 2)
                bound = abs(dist[k - 1]) + step
            dist[k] = _signed_point(points[k, 0], points[k, 1], points[k, 2], bvh, bound)[0]
    return dist


def vertex_signed_distances(points, offsets, head: HeadSurface, margin: float) -> np.ndarray:
    """Signed distance of every strand vertex; +inf outside the head box inflated by ``margin``."""
    lo, hi = head.bounds
    in_box = np.all((points >= lo - margin) & (points <= hi + margin), axis=1)
    return _strand_distances_kernel(points, offsets, in_box, head._bvh)


def detect_head_contacts_reference(points, offsets, arc, head, radius: float, *,
                                   min_root_arc: float | None = None, merge_arc: float | None = None,
                                   stats: dict | None = None) -> Contacts:
    """``detect_head_contacts`` as it was before the bounds (every vertex in the box queried):
    the reference the tests compare it with, bit for bit."""
    points, offsets, arc = check_strands(points, offsets, arc)
    if not radius > 0:
        raise ValueError(f"contact radius must be positive, got {radius}")
    t0 = time.perf_counter()
    head = as_head_surface(head)
    min_root_arc = np.pi * radius if min_root_arc is None else float(min_root_arc)
    merge_arc = 4.0 * radius if merge_arc is None else float(merge_arc)
    seg_v0, _ = strand_segments(offsets)
    seg_len = np.linalg.norm(points[seg_v0 + 1] - points[seg_v0], axis=1)
    max_seg = float(np.max(seg_len)) if len(seg_len) else 0.0
    t1 = time.perf_counter()

    vdist = vertex_signed_distances(points, offsets, head, radius + max_seg)
    t2 = time.perf_counter()
    v, t, d, n_refined = _head_minima_kernel(points, arc, offsets, vdist, head._bvh, float(radius),
                                             min_root_arc, 1e-3)
    strand = np.searchsorted(offsets, v, side="right") - 1
    s_a = arc[v] + t * (arc[v + 1] - arc[v])
    kept = merge_close(strand, np.full(len(v), HEAD), s_a, np.zeros(len(v)), d, merge_arc)
    t3 = time.perf_counter()

    n_minima = len(v)
    v, t, strand, s_a = v[kept], t[kept], strand[kept], s_a[kept]
    direction = points[v + 1] - points[v]
    point_a = points[v] + t[:, None] * direction
    dist, closest, normal, _ = head.query(point_a)
    frame = contact_frames(normal, direction) if len(v) else np.zeros((0, 3, 3))
    if stats is not None:
        stats.update(head_vertices_queried=int(np.isfinite(vdist).sum()),
                     head_vertices_inside=int(np.sum(vdist < 0.0)),
                     head_candidates=int(n_refined), head_minima=n_minima, head_contacts=len(kept),
                     time_head_prepare=t1 - t0, time_head_vertices=t2 - t1, time_head_refine=t3 - t2,
                     time_head_frames=time.perf_counter() - t3)
    return Contacts(strand, s_a, np.full(len(v), HEAD), np.full(len(v), np.nan), point_a, closest, normal, frame,
                    dist, radius)


# ------------------------------------------------------- H and H^T r by dense point Jacobians
def _side_entries(helix, kin, strand, s, frames, sign, dof_offsets):
    """(rows, columns, values) of one side's blocks sign F_i J_k, k <= the element of the point."""
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


def contact_jacobian_reference(helix: sh.SuperHelix, contacts, kin: sh.Kinematics | None = None) -> sp.csr_matrix:
    """The original dense-then-filter H (via :func:`sh.point_jacobians`, O(m N) memory)."""
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


def generalized_contact_force_reference(helix: sh.SuperHelix, contacts, forces: np.ndarray,
                                         kin: sh.Kinematics | None = None) -> np.ndarray:
    """H^T r with the dense (P, N, 3, 3) point Jacobians of sh.point_jacobians."""
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
