"""Strand/head contacts and root snapping against a triangle mesh.

``HeadSurface`` prepares a mesh once: vertices welded (OBJ files often repeat them per face),
faces oriented outward (the signed volume must be positive), a bounding-volume hierarchy over the
triangles (queried in numba), and angle-weighted pseudo-normals (Baerentzen and Aanaes 2005) for
the sign.

Signed distance: the distance to the closest point c on the surface, negative when the point is on
the inner side of the pseudo-normal of the feature (face, edge, vertex) holding c.  Open meshes: a
point whose closest feature lies on a hole's rim counts as outside.  The contact normal is the
direction from c to the point, flipped for inside points, so it always points out of the head; it
falls back to the pseudo-normal when the point is on the surface.

Strand/head contacts (``detect_head_contacts``): the signed distance is evaluated at every vertex
inside the head's box (inflated by r_c plus the longest segment); each discrete local minimum of it
along a strand that could dip below r_c (1-Lipschitz bound over its two segments) is refined by a
golden-section search on those two segments, and kept when the refined distance is below r_c.
Minima closer than ``merge_arc`` along the strand are merged.  The first ``min_root_arc`` of a
strand (default pi r_c) is its attachment to the scalp, not a contact.
"""

from __future__ import annotations

import time

import numba as nb
import numpy as np

from .detect import HEAD, Contacts, check_strands, merge_close, strand_segments
from .frames import contact_frames

_GOLDEN = 0.5 * (np.sqrt(5.0) - 1.0)
_FACE, _VA, _VB, _VC, _EAB, _EBC, _ECA = range(7)  # closest-feature codes


# ---------------------------------------------------------------------------- mesh preparation
def _pseudo_normals(vertices: np.ndarray, faces: np.ndarray):
    """Per face (F, 7, 3) pseudo-normals and (F, 7) rim flags, in feature-code order."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    fn = cross / np.linalg.norm(cross, axis=1, keepdims=True)

    def angle(p, q, r):  # interior angle at p
        u, v = q - p, r - p
        return np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.sum(u * v, axis=1))

    vn = np.zeros_like(vertices)
    for k, (p, q, r) in enumerate(((a, b, c), (b, c, a), (c, a, b))):
        np.add.at(vn, faces[:, k], angle(p, q, r)[:, None] * fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)

    slots = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)  # (F, 3, 2)
    _, edge_id, edge_count = np.unique(np.sort(slots, axis=2).reshape(-1, 2), axis=0,
                                       return_inverse=True, return_counts=True)
    edge_id = edge_id.reshape(-1, 3)
    en = np.zeros((edge_count.size, 3))
    np.add.at(en, edge_id.ravel(), np.repeat(fn, 3, axis=0))
    en /= np.maximum(np.linalg.norm(en, axis=1, keepdims=True), 1e-300)
    edge_rim = edge_count[edge_id] == 1  # (F, 3)
    vertex_rim = np.zeros(len(vertices), dtype=bool)
    vertex_rim[slots[edge_rim].ravel()] = True

    normals = np.concatenate([fn[:, None], vn[faces], en[edge_id]], axis=1)
    rim = np.concatenate([np.zeros((len(faces), 1), bool), vertex_rim[faces], edge_rim], axis=1)
    return normals, rim


def _build_bvh(tri_lo, tri_hi, centroid, leaf_size):
    """Median-split BVH over triangle boxes, built level by level (vectorised).

    Every node's faces are split at the median of their centroids along the longest centroid
    extent, down to leaves of at most ``leaf_size`` faces; the tree is complete, stored as a heap
    (children of node i: 2i + 1, 2i + 2).  Returns node boxes (N, 6) as (lo, hi), children (N, 2)
    (-1 for leaves), face ranges (N, 2) into ``order``, and ``order``.
    """
    n = len(centroid)
    leaf_size = max(int(leaf_size), 2)
    depth = 0
    while -(-n // 2**depth) > leaf_size:
        depth += 1
    order = np.arange(n)
    starts, ends = np.array([0]), np.array([n])
    levels = [(starts, ends)]
    for _ in range(depth):
        c = centroid[order]
        extent = np.maximum.reduceat(c, starts) - np.minimum.reduceat(c, starts)
        axis = np.argmax(extent, axis=1)
        node_of = np.repeat(np.arange(len(starts)), ends - starts)
        order = order[np.lexsort((c[np.arange(n), axis[node_of]], node_of))]
        mids = (starts + ends) // 2
        starts, ends = np.column_stack([starts, mids]).ravel(), np.column_stack([mids, ends]).ravel()
        levels.append((starts, ends))
    lo, hi = tri_lo[order], tri_hi[order]
    boxes = np.concatenate([np.hstack([np.minimum.reduceat(lo, s), np.maximum.reduceat(hi, s)]) for s, _ in levels])
    span = np.concatenate([np.column_stack([s, e]) for s, e in levels]).astype(np.int64)
    child = np.full((len(span), 2), -1, dtype=np.int64)
    internal = np.arange(2**depth - 1)
    child[internal] = np.column_stack([2 * internal + 1, 2 * internal + 2])
    return np.ascontiguousarray(boxes), child, span, order


class HeadSurface:
    """A head mesh prepared for signed-distance queries (build once, query many times).

    ``mesh``: a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair, in the strands' units (metres).
    """

    def __init__(self, mesh, *, leaf_size: int = 8):
        if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            vertices, faces = mesh.vertices, mesh.faces
        else:
            vertices, faces = mesh
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if len(faces) == 0:
            raise ValueError("head mesh has no faces")
        vertices, inverse = np.unique(vertices, axis=0, return_inverse=True)
        faces = inverse.reshape(-1)[faces]
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        faces = faces[area2 > 0.0]  # a zero-area face adds no surface
        if len(faces) == 0:
            raise ValueError("head mesh has only degenerate faces")
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        self.flipped = bool(np.sum(a * np.cross(b, c)) < 0.0)  # signed volume < 0: inward faces
        if self.flipped:
            faces = faces[:, ::-1].copy()
        self.vertices, self.faces = vertices, faces
        normals, rim = _pseudo_normals(vertices, faces)

        tris = vertices[faces]  # (F, 3, 3)
        boxes, child, span, order = _build_bvh(tris.min(axis=1), tris.max(axis=1), tris.mean(axis=1),
                                               int(leaf_size))
        self.face_order = order
        tris = tris[order]
        self._bvh = (boxes, child, span, np.ascontiguousarray(tris.reshape(-1, 9)),
                     np.ascontiguousarray(normals[order]), np.ascontiguousarray(rim[order]))

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) bounding box."""
        return self._bvh[0][0].reshape(2, 3).copy()

    def query(self, points):
        """Signed distance (n,), closest surface point (n, 3), outward unit normal (n, 3) and face
        index (n,) into ``self.faces`` for every point (n, 3)."""
        points = np.ascontiguousarray(np.reshape(points, (-1, 3)), dtype=np.float64)
        dist, closest, normal, face = _query_kernel(points, self._bvh)
        return dist, closest, normal, self.face_order[face]


def as_head_surface(head) -> HeadSurface:
    """``head`` itself when already prepared, otherwise a ``HeadSurface`` built from it.

    For a trimesh.Trimesh the result is kept in the mesh's own cache, which trimesh clears when the
    mesh's vertices or faces change, so repeated calls on one mesh build it once.
    """
    if isinstance(head, HeadSurface):
        return head
    cache = getattr(head, "_cache", None)
    key = "groomtool_head_surface"
    if cache is not None:
        try:
            surface = cache[key]
            if surface is not None:
                return surface
        except Exception:  # noqa: BLE001 - any trimesh cache problem: just build it
            cache = None
    surface = HeadSurface(head)
    if cache is not None:
        try:
            cache[key] = surface
        except Exception:  # noqa: BLE001
            pass
    return surface


# ------------------------------------------------------------------------------------ queries
@nb.njit(cache=True)
def _closest_on_triangle(px, py, pz, tri, f):
    """Closest point of triangle ``tri[f]`` (a, b, c flattened) to p (Ericson 5.1.5) and its feature code."""
    ax, ay, az = tri[f, 0], tri[f, 1], tri[f, 2]
    bx, by, bz = tri[f, 3], tri[f, 4], tri[f, 5]
    cx, cy, cz = tri[f, 6], tri[f, 7], tri[f, 8]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, _VA
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, _VB
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz, _EAB
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, _VC
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz, _ECA
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), _EBC
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, _FACE


@nb.njit(cache=True)
def _axis_gap2(p, lo, hi):
    if p < lo:
        return (lo - p) * (lo - p)
    if p > hi:
        return (p - hi) * (p - hi)
    return 0.0


@nb.njit(cache=True)
def _box_dist2(box, node, px, py, pz):
    return (_axis_gap2(px, box[node, 0], box[node, 3]) + _axis_gap2(py, box[node, 1], box[node, 4])
            + _axis_gap2(pz, box[node, 2], box[node, 5]))


@nb.njit(cache=True)
def _nearest(px, py, pz, box, child, span, tri, best):
    """Closest triangle feature to p among those closer than sqrt(best): (d2, x, y, z, face, feature);
    face is -1 when none is."""
    stack = np.empty(64, np.int64)
    stack_d = np.empty(64)
    stack[0] = 0
    stack_d[0] = 0.0
    sp = 1
    bx = by = bz = 0.0
    bf = -1
    bfeat = 0
    while sp > 0:
        sp -= 1
        if stack_d[sp] >= best:
            continue
        node = stack[sp]
        left = child[node, 0]
        if left < 0:
            for f in range(span[node, 0], span[node, 1]):
                cx, cy, cz, feat = _closest_on_triangle(px, py, pz, tri, f)
                d2 = (px - cx) * (px - cx) + (py - cy) * (py - cy) + (pz - cz) * (pz - cz)
                if d2 < best:
                    best, bx, by, bz, bf, bfeat = d2, cx, cy, cz, f, feat
            continue
        right = child[node, 1]
        dl = _box_dist2(box, left, px, py, pz)
        dr = _box_dist2(box, right, px, py, pz)
        if dl > dr:
            left, right, dl, dr = right, left, dr, dl
        if dr < best:  # the farther child first, so the nearer one is searched first
            stack[sp] = right
            stack_d[sp] = dr
            sp += 1
        if dl < best:
            stack[sp] = left
            stack_d[sp] = dl
            sp += 1
    return best, bx, by, bz, bf, bfeat


@nb.njit(cache=True)
def _signed_point(px, py, pz, bvh, bound):
    """(signed distance, closest x, y, z, outward normal x, y, z, face slot) of one point.

    ``bound``: an upper bound of the unsigned distance (np.inf if none) that prunes the search.
    """
    box, child, span, tri, normals, rim = bvh
    best = np.inf if bound == np.inf else (bound * (1.0 + 1e-9) + 1e-300) ** 2
    d2, bx, by, bz, bf, bfeat = _nearest(px, py, pz, box, child, span, tri, best)
    if bf < 0:  # the bound was too tight (rounding): search again without it
        d2, bx, by, bz, bf, bfeat = _nearest(px, py, pz, box, child, span, tri, np.inf)
    dist = np.sqrt(d2)
    vx, vy, vz = px - bx, py - by, pz - bz
    n0, n1, n2 = normals[bf, bfeat, 0], normals[bf, bfeat, 1], normals[bf, bfeat, 2]
    sign = 1.0
    if not rim[bf, bfeat] and vx * n0 + vy * n1 + vz * n2 < 0.0:
        sign = -1.0
    if dist > 1e-12 * (1.0 + abs(px) + abs(py) + abs(pz)):
        n0, n1, n2 = sign * vx / dist, sign * vy / dist, sign * vz / dist
    return sign * dist, bx, by, bz, n0, n1, n2, bf


@nb.njit(cache=True)
def _query_kernel(points, bvh):
    n = points.shape[0]
    dist = np.empty(n)
    closest = np.empty((n, 3))
    normal = np.empty((n, 3))
    face = np.empty(n, np.int64)
    for q in range(n):
        r = _signed_point(points[q, 0], points[q, 1], points[q, 2], bvh, np.inf)
        dist[q] = r[0]
        closest[q, 0], closest[q, 1], closest[q, 2] = r[1], r[2], r[3]
        normal[q, 0], normal[q, 1], normal[q, 2] = r[4], r[5], r[6]
        face[q] = r[7]
    return dist, closest, normal, face


# ------------------------------------------------------------------------------- head contacts
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


def detect_head_contacts(points, offsets, arc, head, radius: float, *, min_root_arc: float | None = None,
                         merge_arc: float | None = None, stats: dict | None = None) -> Contacts:
    """Strand/head contacts: local minima along each strand of the signed axis-to-surface distance
    that are below ``radius`` (negative: the axis is inside the head; such contacts are reported).

    ``head``: a trimesh.Trimesh, (vertices, faces) or a prepared ``HeadSurface``.  See the module
    docstring for the rules; contacts are ordered by (strand_a, s_a).
    """
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


# -------------------------------------------------------------------------------- root helpers
def root_gaps(root_points, head) -> np.ndarray:
    """Signed distance (n,) of each root to the head surface (negative: inside the head)."""
    return as_head_surface(head).query(root_points)[0]


def snap_roots(root_points, head, *, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Roots projected onto the head surface, then moved ``offset`` along the outward normal (e.g.
    the fibre radius, so the fibre rests on the scalp instead of half inside it).

    Returns (snapped roots (n, 3), signed gaps (n,) of the roots before snapping).
    """
    gaps, closest, normal, _ = as_head_surface(head).query(root_points)
    return closest + offset * normal, gaps
