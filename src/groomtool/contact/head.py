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

Strand/head contacts (``detect_head_contacts``): the signed distance of the vertices inside the
head's box (inflated by r_c plus the longest segment); each discrete local minimum of it along a
strand that could dip below r_c (1-Lipschitz bound over its two segments) is refined by a
golden-section search on those two segments, and kept when the refined distance is below r_c.
Minima closer than ``merge_arc`` along the strand are merged.  The first ``min_root_arc`` of a
strand (default pi r_c) is its attachment to the scalp, not a contact.

Only the vertices that matter are queried: along a strand, the last exact query (unsigned distance
u) bounds the next vertices' distance by u -/+ the arc since it (1-Lipschitz), and a vertex whose
lower bound already rules it out as a candidate keeps the bound, when its sign is known to be
outside (``_sign_propagation``: a consistently oriented, one-component manifold mesh, the path
away from the surface and from the holes' guard boxes).  The minima pass replaces a bound by the
exact distance wherever a decision needs it, so the result is that of the reference that queries
every vertex (``detect_head_contacts_reference`` in tests/reference/contact.py) bit for bit; the tests
compare them.
"""

from __future__ import annotations

import time

import numba as nb
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .detect import HEAD, Contacts, check_strands, merge_close, strand_radii
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


def _sign_propagation(vertices: np.ndarray, faces: np.ndarray):
    """Whether the sign of the distance may be carried along a strand, and the guard boxes of the holes.

    The pseudo-normal sign is the side of the surface (Baerentzen and Aanaes) when the mesh is an
    embedded, consistently oriented 2-manifold: then a path that stays away from the surface keeps its
    sign.  Checked here: every edge in at most two faces, used once in each direction (consistent
    orientation), every vertex's faces one fan (no sheets pinched at a vertex), and one component
    (faces joined by edges; no eyeballs or teeth inside the head).
    Self-intersections are not checked (assumed absent).  On an open mesh a point whose closest
    feature is on a hole's rim counts as outside whatever its side, and a point can see the inner
    side of the surface through the hole; both need the point to be at least as close to the hole's
    rim loop (hence to any cap of the hole inside the loop's convex hull) as to the surface, so each
    rim loop gets a guard: an oriented box (PCA axes) holding the loop's vertices.

    Returns (ok, guard): guard (G, 15) rows of box centre (3), axes (3 rows of 3) and half extents (3).
    """
    none = np.zeros((0, 15))
    n_vert, n_face = len(vertices), len(faces)
    a, b = faces.ravel(), faces[:, [1, 2, 0]].ravel()  # directed edges (0, 1), (1, 2), (2, 0) per face
    directed = a * n_vert + b
    if np.unique(directed).size != directed.size:  # two faces use an edge in the same direction
        return False, none
    keys, inverse, count = np.unique(np.minimum(a, b) * n_vert + np.maximum(a, b), return_inverse=True,
                                     return_counts=True)
    if count.max() > 2:  # an edge shared by three faces or more
        return False, none
    face = np.repeat(np.arange(n_face), 3)
    order = np.argsort(inverse.ravel(), kind="stable")
    shared = inverse.ravel()[order][1:] == inverse.ravel()[order][:-1]
    s1, s2 = order[:-1][shared], order[1:][shared]  # the two slots (3 f + k: edge k of face f) of an edge
    f1, f2 = face[s1], face[s2]
    adjacency = sp.coo_matrix((np.ones(len(f1)), (f1, f2)), shape=(n_face, n_face))
    if connected_components(adjacency, directed=False)[0] != 1:
        return False, none
    # every vertex's faces form one fan (no two sheets pinched at a vertex): join the corners
    # (3 f + k: corner k of face f) of a vertex across each edge its faces share; one group per vertex
    other = (np.arange(3 * n_face) // 3) * 3 + (np.arange(3 * n_face) % 3 + 1) % 3  # the edge's 2nd corner
    s1_end, s2_end = other[s1], other[s2]  # edge slot k joins corners k and k+1; opposite directions
    corners = sp.coo_matrix((np.ones(2 * len(s1)), (np.concatenate([s1, s1_end]), np.concatenate([s2_end, s2]))),
                            shape=(3 * n_face, 3 * n_face))
    if connected_components(corners, directed=False)[0] != np.unique(faces).size:
        return False, none
    rim = keys[count == 1]
    if len(rim) == 0:
        return True, none
    ra, rb = rim // n_vert, rim % n_vert
    _, loop = connected_components(sp.coo_matrix((np.ones(len(rim)), (ra, rb)), shape=(n_vert, n_vert)),
                                   directed=False)
    rim_vertices = np.unique(np.concatenate([ra, rb]))
    scale = 1.0 + float(np.max(np.abs(vertices)))
    rows = []
    for lab in np.unique(loop[rim_vertices]):
        pts = vertices[rim_vertices[loop[rim_vertices] == lab]]
        centre = pts.mean(axis=0)
        axes = np.linalg.eigh(np.cov((pts - centre).T))[1] if len(pts) >= 3 else np.eye(3)
        local = (pts - centre) @ axes
        lo, hi = local.min(axis=0), local.max(axis=0)
        half = 0.5 * (hi - lo) + 1e-9 * (float(np.max(hi - lo)) + scale)  # holds the loop despite rounding
        rows.append(np.concatenate([centre + axes @ (0.5 * (lo + hi)), axes.T.ravel(), half]))
    return True, np.ascontiguousarray(rows, dtype=np.float64)


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

    def _triangle_boxes(self) -> np.ndarray:
        """(F, 6) box (lo, hi) of every triangle in BVH order, computed on first use."""
        boxes = getattr(self, "_tri_box_cache", None)
        if boxes is None:
            tri = self._bvh[3].reshape(-1, 3, 3)
            boxes = self._tri_box_cache = np.ascontiguousarray(np.hstack([tri.min(axis=1), tri.max(axis=1)]))
        return boxes

    def _sign_info(self):
        """(ok, guard) of ``_sign_propagation``, computed on first use."""
        info = getattr(self, "_sign_cache", None)
        if info is None:
            info = self._sign_cache = _sign_propagation(self.vertices, self.faces)
        return info

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
def _box_gap2(box, i, px, py, pz):
    """``_box_dist2`` without branches (the same value)."""
    gx = max(box[i, 0] - px, px - box[i, 3], 0.0)
    gy = max(box[i, 1] - py, py - box[i, 4], 0.0)
    gz = max(box[i, 2] - pz, pz - box[i, 5], 0.0)
    return gx * gx + gy * gy + gz * gz


@nb.njit(cache=True)
def _nearest_fast(px, py, pz, box, child, span, tri, tri_box, best):
    """``_nearest`` with a triangle's own box tested before its closest point (skipped when clearly
    farther than the best so far, so no triangle that ``_nearest`` would take is skipped): the same
    traversal order, the same triangles accepted, the same result."""
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
                if _box_gap2(tri_box, f, px, py, pz) > best * (1.0 + 1e-9) + 1e-20:
                    continue
                cx, cy, cz, feat = _closest_on_triangle(px, py, pz, tri, f)
                d2 = (px - cx) * (px - cx) + (py - cy) * (py - cy) + (pz - cz) * (pz - cz)
                if d2 < best:
                    best, bx, by, bz, bf, bfeat = d2, cx, cy, cz, f, feat
            continue
        right = child[node, 1]
        dl = _box_gap2(box, left, px, py, pz)
        dr = _box_gap2(box, right, px, py, pz)
        if dl > dr:
            left, right, dl, dr = right, left, dr, dl
        if dr < best:
            stack[sp] = right
            stack_d[sp] = dr
            sp += 1
        if dl < best:
            stack[sp] = left
            stack_d[sp] = dl
            sp += 1
    return best, bx, by, bz, bf, bfeat


@nb.njit(cache=True)
def _face_sign(px, py, pz, cx, cy, cz, f, feat, normals, rim):
    """``_signed_point``'s sign for p whose closest point is c, on feature ``feat`` of face slot f."""
    if not rim[f, feat] and ((px - cx) * normals[f, feat, 0] + (py - cy) * normals[f, feat, 1]
                             + (pz - cz) * normals[f, feat, 2]) < 0.0:
        return -1.0
    return 1.0


@nb.njit(cache=True)
def _signed_fast(px, py, pz, bvh, tri_box, bound):
    """The signed distance of ``_signed_point`` (``_nearest_fast`` instead of ``_nearest``).  Its
    result does not depend on ``bound`` (an upper bound of the distance, or inf): a triangle holding
    the minimum is never pruned (its boxes are no farther than it), so the search ends with the
    same triangle, the first in the tree's order that reaches the minimum."""
    box, child, span, tri, normals, rim = bvh
    best = np.inf if bound == np.inf else (bound * (1.0 + 1e-9) + 1e-300) ** 2
    d2, bx, by, bz, bf, bfeat = _nearest_fast(px, py, pz, box, child, span, tri, tri_box, best)
    if bf < 0:  # the bound was too tight (rounding): search again without it
        d2, bx, by, bz, bf, bfeat = _nearest_fast(px, py, pz, box, child, span, tri, tri_box, np.inf)
    return _face_sign(px, py, pz, bx, by, bz, bf, bfeat, normals, rim) * np.sqrt(d2)


@nb.njit(cache=True)
def _segment_candidates(p, q, reach, box, child, span, tri_box, out):
    """Face slots whose box is within ``reach`` of the box of segment pq (written to ``out``, grown
    as needed): every face that can be closest to a point x of the segment whose distance is at most
    ``reach``.  Returns (out, count)."""
    lo0, lo1, lo2 = min(p[0], q[0]), min(p[1], q[1]), min(p[2], q[2])
    hi0, hi1, hi2 = max(p[0], q[0]), max(p[1], q[1]), max(p[2], q[2])
    lim = reach * reach * (1.0 + 1e-9) + 1e-20
    stack = np.empty(64, np.int64)
    stack[0] = 0
    sp = 1
    n = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        gx = max(box[node, 0] - hi0, lo0 - box[node, 3], 0.0)
        gy = max(box[node, 1] - hi1, lo1 - box[node, 4], 0.0)
        gz = max(box[node, 2] - hi2, lo2 - box[node, 5], 0.0)
        if gx * gx + gy * gy + gz * gz > lim:
            continue
        if child[node, 0] >= 0:
            stack[sp] = child[node, 0]
            stack[sp + 1] = child[node, 1]
            sp += 2
            continue
        for f in range(span[node, 0], span[node, 1]):
            gx = max(tri_box[f, 0] - hi0, lo0 - tri_box[f, 3], 0.0)
            gy = max(tri_box[f, 1] - hi1, lo1 - tri_box[f, 4], 0.0)
            gz = max(tri_box[f, 2] - hi2, lo2 - tri_box[f, 5], 0.0)
            if gx * gx + gy * gy + gz * gz > lim:
                continue
            if n == out.shape[0]:
                out = np.concatenate((out, np.empty(n, np.int64)))
            out[n] = f
            n += 1
    return out, n


@nb.njit(cache=True)
def _signed_among(px, py, pz, bvh, tri_box, bound, cand, n_cand):
    """``_signed_point``'s signed distance when the closest face is among ``cand[:n_cand]`` (it is
    when every face within ``bound`` of p is there): the smallest squared distance is the same
    whatever the order the faces are tried in; the search keeps the first face reaching it, which
    only matters for the sign when several faces tie exactly, so then (if their signs differ) the
    point is queried again with ``_signed_fast``, in the tree's order."""
    box, child, span, tri, normals, rim = bvh
    best = np.inf if bound == np.inf else (bound * (1.0 + 1e-9) + 1e-300) ** 2
    bx = by = bz = 0.0
    bf = -1
    bfeat = 0
    conflict = False
    for i in range(n_cand):
        f = cand[i]
        if _box_gap2(tri_box, f, px, py, pz) > best * (1.0 + 1e-9) + 1e-20:
            continue
        cx, cy, cz, feat = _closest_on_triangle(px, py, pz, tri, f)
        d2 = (px - cx) * (px - cx) + (py - cy) * (py - cy) + (pz - cz) * (pz - cz)
        if d2 < best:
            best, bx, by, bz, bf, bfeat = d2, cx, cy, cz, f, feat
            conflict = False
        elif d2 == best and bf >= 0 and not conflict:
            conflict = (_face_sign(px, py, pz, cx, cy, cz, f, feat, normals, rim)
                        != _face_sign(px, py, pz, bx, by, bz, bf, bfeat, normals, rim))
    if bf < 0 or conflict:
        return _signed_fast(px, py, pz, bvh, tri_box, bound)
    return _face_sign(px, py, pz, bx, by, bz, bf, bfeat, normals, rim) * np.sqrt(best)


@nb.njit(cache=True)
def _golden_cand(p, q, dp, dq, t_lo, bvh, tri_box, tol, cand):
    """The golden-section search of the reference (``_golden_on_segment``, tests/reference/contact.py)
    with every evaluation searched among the faces near the segment (``_segment_candidates``, reach:
    the largest distance bound of the evaluations): the same evaluations, values and result.  Returns
    (t, distance, cand)."""
    box, child, span, tri, normals, rim = bvh
    length = np.sqrt((q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 + (q[2] - p[2]) ** 2)
    reach = 0.5 * (abs(dp) + abs(dq) + length)  # >= min(|dp| + x l, |dq| + (1 - x) l) for every x
    cand, n = _segment_candidates(p, q, reach, box, child, span, tri_box, cand)
    lo, hi = t_lo, 1.0
    x1 = hi - _GOLDEN * (hi - lo)
    x2 = lo + _GOLDEN * (hi - lo)
    f1 = _signed_among(p[0] + x1 * (q[0] - p[0]), p[1] + x1 * (q[1] - p[1]), p[2] + x1 * (q[2] - p[2]), bvh,
                       tri_box, min(abs(dp) + x1 * length, abs(dq) + (1.0 - x1) * length), cand, n)
    f2 = _signed_among(p[0] + x2 * (q[0] - p[0]), p[1] + x2 * (q[1] - p[1]), p[2] + x2 * (q[2] - p[2]), bvh,
                       tri_box, min(abs(dp) + x2 * length, abs(dq) + (1.0 - x2) * length), cand, n)
    while hi - lo > tol:
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - _GOLDEN * (hi - lo)
            f1 = _signed_among(p[0] + x1 * (q[0] - p[0]), p[1] + x1 * (q[1] - p[1]), p[2] + x1 * (q[2] - p[2]),
                               bvh, tri_box, min(abs(dp) + x1 * length, abs(dq) + (1.0 - x1) * length), cand, n)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + _GOLDEN * (hi - lo)
            f2 = _signed_among(p[0] + x2 * (q[0] - p[0]), p[1] + x2 * (q[1] - p[1]), p[2] + x2 * (q[2] - p[2]),
                               bvh, tri_box, min(abs(dp) + x2 * length, abs(dq) + (1.0 - x2) * length), cand, n)
    if f1 <= f2:
        return x1, f1, cand
    return x2, f2, cand


@nb.njit(cache=True)
def _seg_len(points, i, j):
    """|points[j] - points[i]| (the same rounding as the side bounds of the reference's ``_head_minima_kernel``)."""
    return np.sqrt((points[j, 0] - points[i, 0]) ** 2 + (points[j, 1] - points[i, 1]) ** 2
                   + (points[j, 2] - points[i, 2]) ** 2)


@nb.njit(cache=True)
def _guard_dist2(px, py, pz, guard):
    """Squared distance from p to the nearest guard box (rows of ``_sign_propagation``); inf if none."""
    best = np.inf
    for g in range(guard.shape[0]):
        dx, dy, dz = px - guard[g, 0], py - guard[g, 1], pz - guard[g, 2]
        s = 0.0
        for a in range(3):
            t = abs(guard[g, 3 + 3 * a] * dx + guard[g, 4 + 3 * a] * dy + guard[g, 5 + 3 * a] * dz) - guard[g, 12 + a]
            if t > 0.0:
                s += t * t
        best = min(best, s)
    return best


@nb.njit(cache=True)
def _never_refined(q, radius, s_prev, s_next, has_prev, has_next):
    """True when a vertex whose signed distance is at least ``q`` is no candidate of the
    reference's ``_head_minima_kernel`` whatever its neighbours: a candidate is a discrete local minimum (no
    neighbour below it) with min(d, side bounds) < radius, and its side bound 0.5 (d + d_neighbour -
    seg) is then at least 0.5 (q + q - seg), in floating point too (rounding is monotone).  The same
    expressions as there, so the test is exact, not approximately so."""
    if not q >= radius:
        return False
    if has_prev and not 0.5 * (q + q - s_prev) >= radius:
        return False
    if has_next and not 0.5 * (q + q - s_next) >= radius:
        return False
    return True


@nb.njit(cache=True)
def _in_box_kernel(points, lo, hi):
    """The reference's ``vertex_signed_distances``' box test (lo, hi: the inflated box corners)."""
    out = np.empty(points.shape[0], np.bool_)
    for k in range(points.shape[0]):
        out[k] = (points[k, 0] >= lo[0] and points[k, 1] >= lo[1] and points[k, 2] >= lo[2]
                  and points[k, 0] <= hi[0] and points[k, 1] <= hi[1] and points[k, 2] <= hi[2])
    return out


@nb.njit(cache=True)
def _strand_bounds_kernel(points, offsets, in_box, bvh, tri_box, radii, max_seg, propagate, guard, tol_abs):
    """Signed distance of the vertices in the box, or a lower bound of it where that already shows
    the vertex is no candidate (``_never_refined``); +inf outside the box.

    Along a strand the last exact query (the anchor: unsigned distance u, arc ``run`` since it)
    gives u - run <= |distance| <= u + run (1-Lipschitz).  The upper bound prunes the next exact
    query (as the previous vertex's distance plus the step did); the lower bound replaces the query
    when the sign is known: the anchor is outside and the path since it stayed farther from every
    hole's guard box than the upper bound (``_sign_propagation``).  Returns (value, exact flag,
    exact queries, bounded vertices).  radii: the contact radius of each strand.
    """
    n = points.shape[0]
    val = np.full(n, np.inf)
    exact = np.ones(n, np.bool_)
    n_exact = 0
    n_bounded = 0
    guarded = guard.shape[0] > 0
    for st in range(offsets.shape[0] - 1):
        v0, v1 = offsets[st], offsets[st + 1]
        radius = radii[st]
        ua = -1.0  # the anchor's unsigned distance (< 0: no anchor yet)
        run = 0.0  # arc length since the anchor
        positive = False  # the anchor is outside and its sign holds up to here
        step = 0.0
        for k in range(v0, v1):
            px, py, pz = points[k, 0], points[k, 1], points[k, 2]
            if k > v0:
                step = _seg_len(points, k - 1, k)
                run += step
            if positive and guarded:
                reach = ua + run + 1e-9 * (ua + run) + tol_abs
                if not _guard_dist2(px, py, pz, guard) > reach * reach:
                    positive = False
            if not in_box[k]:
                continue
            if positive:
                lb = ua - run - 1e-9 * (ua + run) - tol_abs
                if (lb >= radius and 0.5 * (lb + lb - max_seg) >= radius) or _never_refined(
                        lb, radius, step, _seg_len(points, k, k + 1) if k + 1 < v1 else 0.0, k > v0, k + 1 < v1):
                    val[k] = lb
                    exact[k] = False
                    n_bounded += 1
                    continue
            d = _signed_fast(px, py, pz, bvh, tri_box, np.inf if ua < 0.0 else ua + run)
            val[k] = d
            n_exact += 1
            ua, run = abs(d), 0.0
            positive = propagate and d > 0.0
            if positive and guarded:
                reach = ua + 1e-9 * ua + tol_abs
                if not _guard_dist2(px, py, pz, guard) > reach * reach:
                    positive = False
    return val, exact, n_exact, n_bounded


@nb.njit(cache=True)
def _make_exact(points, k, val, exact, bvh, tri_box):
    """Replace a lower bound by the signed distance; returns 1 if that took a query."""
    if exact[k]:
        return 0
    val[k] = _signed_fast(points[k, 0], points[k, 1], points[k, 2], bvh, tri_box, np.inf)
    exact[k] = True
    return 1


@nb.njit(cache=True)
def _head_minima_bounded_kernel(points, arc, offsets, val, exact, bvh, tri_box, radii, min_root_arc, rel_tol,
                                max_seg):
    """The reference's ``_head_minima_kernel`` (tests/reference/contact.py) on values that are exact
    or lower bounds (``_strand_bounds_kernel``): a bound is replaced by the exact distance (in place)
    wherever a decision needs it, so the candidates, the values used and the results are those of
    ``_head_minima_kernel`` on the exact distances.  ``max_seg``: the longest segment (a quick first
    test); radii: the contact radius of each strand.  Returns its four outputs and the number of late
    exact queries."""
    out_v = np.empty(1024, np.int64)
    out_t = np.empty(1024)
    out_d = np.empty(1024)
    n_out = 0
    n_refined = 0
    n_late = 0
    cand = np.empty(256, np.int64)  # candidate faces of a refined segment (``_golden_cand``)
    for st in range(offsets.shape[0] - 1):
        v_first, v_last = offsets[st], offsets[st + 1] - 1
        if v_last <= v_first:  # a strand without segments has no contact
            continue
        radius = radii[st]
        for k in range(v_first, v_last + 1):
            if arc[k] - arc[v_first] < min_root_arc:
                continue
            q = val[k]
            if q >= radius and 0.5 * (q + q - max_seg) >= radius:  # every segment is at most max_seg
                continue
            s_prev = _seg_len(points, k, k - 1) if k > v_first else 0.0
            s_next = _seg_len(points, k, k + 1) if k < v_last else 0.0
            if _never_refined(q, radius, s_prev, s_next, k > v_first, k < v_last):
                continue
            n_late += _make_exact(points, k, val, exact, bvh, tri_box)
            dk = val[k]
            if k > v_first and val[k - 1] < dk:  # a bound below dk: decide on the exact value
                n_late += _make_exact(points, k - 1, val, exact, bvh, tri_box)
                if val[k - 1] < dk:
                    continue
            if k < v_last and val[k + 1] <= dk:
                n_late += _make_exact(points, k + 1, val, exact, bvh, tri_box)
                if val[k + 1] <= dk:
                    continue
            # the side bounds from the neighbours' values (bounds or exact): when they rule k out,
            # so would the exact ones; otherwise take the exact values
            side_lower = np.full(2, np.inf)
            if k > v_first:
                side_lower[0] = 0.5 * (dk + val[k - 1] - s_prev)
            if k < v_last:
                side_lower[1] = 0.5 * (dk + val[k + 1] - s_next)
            if min(dk, side_lower[0], side_lower[1]) >= radius:
                continue
            if k > v_first and not exact[k - 1]:
                n_late += _make_exact(points, k - 1, val, exact, bvh, tri_box)
                side_lower[0] = 0.5 * (dk + val[k - 1] - s_prev)
            if k < v_last and not exact[k + 1]:
                n_late += _make_exact(points, k + 1, val, exact, bvh, tri_box)
                side_lower[1] = 0.5 * (dk + val[k + 1] - s_next)
            if min(dk, side_lower[0], side_lower[1]) >= radius:
                continue
            # from here on: _head_minima_kernel's refinement, on exact values
            n_refined += 1
            best_v, best_t, best_d = k, 0.0, dk
            if k == v_last:  # express the vertex as the end of its segment
                best_v, best_t = k - 1, 1.0
            if k > v_first and side_lower[0] < radius:  # segment (k - 1, k), outside the attachment
                a0, a1 = arc[k - 1] - arc[v_first], arc[k] - arc[v_first]
                t_lo = 0.0
                if a0 < min_root_arc:
                    t_lo = (min_root_arc - a0) / (a1 - a0) if a1 > a0 else 1.0
                t, d, cand = _golden_cand(points[k - 1], points[k], val[k - 1], dk, t_lo, bvh, tri_box, rel_tol, cand)
                if d < best_d and t > t_lo + rel_tol:
                    best_v, best_t, best_d = k - 1, t, d
            if k < v_last and side_lower[1] < radius:  # segment (k, k + 1)
                t, d, cand = _golden_cand(points[k], points[k + 1], dk, val[k + 1], 0.0, bvh, tri_box, rel_tol, cand)
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
    return out_v[:n_out], out_t[:n_out], out_d[:n_out], n_refined, n_late


@nb.njit(cache=True)
def _max_segment(points, offsets):
    """Longest segment (the rounding of ``np.linalg.norm(..., axis=1)``); 0 if none."""
    best = 0.0
    for st in range(offsets.shape[0] - 1):
        for k in range(offsets[st] + 1, offsets[st + 1]):
            best = max(best, _seg_len(points, k - 1, k))
    return best


def detect_head_contacts(points, offsets, arc, head, radius, *, min_root_arc: float | None = None,
                         merge_arc: float | None = None, stats: dict | None = None) -> Contacts:
    """Strand/head contacts: local minima along each strand of the signed axis-to-surface distance
    that are below ``radius`` (negative: the axis is inside the head; such contacts are reported).
    ``radius``: a number or one per strand (S,) (min_root_arc, merge_arc and the result's ``radius``
    then use the largest).

    ``head``: a trimesh.Trimesh, (vertices, faces) or a prepared ``HeadSurface``.  See the module
    docstring for the rules; contacts are ordered by (strand_a, s_a).  The result is that of the
    reference ``detect_head_contacts_reference`` (tests/reference/contact.py: every vertex queried);
    this one queries only the vertices whose distance bounds cannot rule them out.
    """
    points, offsets, arc = check_strands(points, offsets, arc)
    radii = strand_radii(radius, len(offsets) - 1)
    radius = float(np.max(radius))
    t0 = time.perf_counter()
    head = as_head_surface(head)
    min_root_arc = np.pi * radius if min_root_arc is None else float(min_root_arc)
    merge_arc = 4.0 * radius if merge_arc is None else float(merge_arc)
    max_seg = float(_max_segment(points, offsets))
    margin = radius + max_seg
    lo, hi = head.bounds
    in_box = _in_box_kernel(points, lo - margin, hi + margin)
    propagate, guard = head._sign_info()
    tri_box = head._triangle_boxes()
    tol_abs = 1e-12 * (1.0 + float(np.max(np.abs(head.bounds))))
    t1 = time.perf_counter()

    val, exact, n_exact, n_bounded = _strand_bounds_kernel(points, offsets, in_box, head._bvh, tri_box, radii,
                                                           max_seg, bool(propagate), guard, tol_abs)
    t2 = time.perf_counter()
    v, t, d, n_refined, n_late = _head_minima_bounded_kernel(points, arc, offsets, val, exact, head._bvh, tri_box,
                                                             radii, min_root_arc, 1e-3, max_seg)
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
        stats.update(head_vertices_in_box=int(np.count_nonzero(in_box)), head_vertices_queried=int(n_exact + n_late),
                     head_vertices_bounded=int(n_bounded - n_late), head_vertices_late=int(n_late),
                     head_vertices_inside=int(np.count_nonzero(val < 0.0)),
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
