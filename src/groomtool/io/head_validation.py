"""Checks of a head (collision) mesh, alone and against the groom it should carry.

``validate_head`` (called by ``load_head``): non-finite vertices, absurd coordinates and meshes whose
every face is degenerate are errors; faces wound against their neighbours are reversed to match
(a ``HeadWarning`` says how many).  ``check_head_fits_groom``: a head whose size is far from the
groom's (other units) is an error; roots far outside or deep inside the surface (another frame) are
a warning.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from ..groom import GroomError

MAX_COORDINATE_M = 1e4  # beyond 10 km from the origin: not a head in metres
SIZE_RATIO_LIMIT = 10.0  # head size / groom size beyond this (or below its inverse): other units
FAR_FRACTION = 0.05  # median root gap beyond this fraction of the head's size: a warning


class HeadWarning(UserWarning):
    """A head mesh was repaired, or does not sit where the groom's roots are."""


def _face_graph(faces: np.ndarray):
    """Pairs of faces sharing a manifold edge and whether they traverse it the same way."""
    n = len(faces)
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    face_of = np.repeat(np.arange(n), 3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    forward = a < b
    order = np.lexsort((hi, lo))
    lo, hi, forward, face_of = lo[order], hi[order], forward[order], face_of[order]
    same_edge = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1])
    # manifold edges only: exactly two faces on the edge
    start = np.flatnonzero(same_edge)
    alone = np.ones(len(start), dtype=bool)
    if len(start):
        before = np.concatenate([[False], same_edge])[start]
        after = np.concatenate([same_edge, [False]])[start + 1]
        alone = ~before & ~after
    start = start[alone]
    f1, f2 = face_of[start], face_of[start + 1]
    same_direction = forward[start] == forward[start + 1]
    return f1, f2, same_direction


def consistent_winding(faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Faces reversed where needed so neighbours across every manifold edge agree; returns (faces,
    number reversed).  Each connected piece keeps the orientation most of its faces have."""
    faces = np.asarray(faces, dtype=np.int64)
    n = len(faces)
    f1, f2, same = _face_graph(faces)
    if not same.any():
        return faces, 0
    graph = coo_matrix((np.ones(2 * len(f1)), (np.concatenate([f1, f2]), np.concatenate([f2, f1]))),
                       shape=(n, n)).tocsr()
    _, part = connected_components(graph, directed=False)
    parent = np.arange(n)
    for seed in np.unique(part, return_index=True)[1]:  # a BFS tree per connected piece
        order, pred = breadth_first_order(graph, int(seed), directed=False, return_predecessors=True)
        parent[order[1:]] = pred[order[1:]]
    # does each face turn against its tree parent?  Look its tree edge up among the shared edges.
    key = np.minimum(f1, f2) * n + np.maximum(f1, f2)
    sort = np.argsort(key)
    tree = parent != np.arange(n)
    tree_key = np.minimum(parent, np.arange(n)) * n + np.maximum(parent, np.arange(n))
    flip = np.zeros(n, dtype=bool)
    flip[tree] = same[sort[np.searchsorted(key[sort], tree_key[tree])]]
    for _ in range(int(np.ceil(np.log2(max(n, 2)))) + 1):  # parity to the root by pointer jumping
        flip = flip ^ flip[parent]
        parent = parent[parent]
    flipped_per_part = np.bincount(part, weights=flip, minlength=part.max() + 1)
    size = np.bincount(part)
    flip ^= (2 * flipped_per_part > size)[part]  # each piece keeps its majority orientation
    flipped = int(flip.sum())
    if flipped:
        faces = faces.copy()
        faces[flip] = faces[flip][:, ::-1]
    return faces, flipped


def validate_head(vertices, faces, source: str):
    """(vertices, faces) checked and, for inconsistent winding, repaired with a ``HeadWarning``."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        raise GroomError(f"{source}: no triangles: not a mesh (a groom of lines, or an empty file?)")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise GroomError(f"{source}: not a triangle mesh in 3D (vertices {vertices.shape}, faces {faces.shape})")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise GroomError(f"{source}: vertex {first} has a non-finite coordinate {tuple(vertices[first].tolist())} "
                         f"({int(bad.sum())} such vertices); fix the mesh (dropping them would make holes)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise GroomError(f"{source}: a face refers to vertex {int(faces.max())} but there are {len(vertices)}")
    big = float(np.abs(vertices).max()) if len(vertices) else 0.0
    if big > MAX_COORDINATE_M:
        raise GroomError(f"{source}: a coordinate is {big:.3g} m from the origin: not a head in metres "
                         "(wrong --units?)")
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if not np.any(area2 > 0):
        raise GroomError(f"{source}: all {len(faces)} faces are degenerate (zero area): no surface")
    faces, flipped = consistent_winding(faces)
    if flipped:
        warnings.warn(f"{source}: {flipped} of {len(faces)} faces were wound against their neighbours; "
                      "reversed them to match", HeadWarning, stacklevel=2)
    return vertices, faces


def check_head_fits_groom(head, groom) -> None:
    """GroomError when the head's size is far from the groom's (units); ``HeadWarning`` when the
    roots are far outside or deep inside the head surface (another frame or a scaled mesh)."""
    from ..contact.head import root_gaps

    vertices = np.asarray(head.vertices, dtype=np.float64)
    head_size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    lo, hi = groom.bounds()
    groom_size = float(np.linalg.norm(hi - lo))
    source = head.metadata.get("source", "head") if hasattr(head, "metadata") else "head"
    if groom_size > 0 and head_size > 0:
        ratio = head_size / groom_size
        if ratio > SIZE_RATIO_LIMIT or ratio < 1 / SIZE_RATIO_LIMIT:
            raise GroomError(
                f"{source}: the head is {head_size:.3g} m across but the groom {groom.source} {groom_size:.3g} m "
                f"({ratio:.3g}x): different units? (--units applies to both files)")
    roots = groom.points[groom.offsets[:-1]]
    gaps = root_gaps(roots, head)
    median = float(np.median(gaps))
    if abs(median) > FAR_FRACTION * head_size:
        where = "outside" if median > 0 else "inside"
        warnings.warn(
            f"{source}: the roots of {groom.source} lie a median {abs(median) * 1e3:.1f} mm {where} the head "
            f"surface ({abs(median) / head_size:.0%} of its size): is the groom in the head's frame and units?",
            HeadWarning, stacklevel=2)
