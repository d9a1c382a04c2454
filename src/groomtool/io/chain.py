"""Strands from line segments (OBJ ``l`` records, PLY edges) or from fixed-length vertex runs.

Segments are directed root -> tip.  Segments sharing an end vertex join into one strand whatever
their order in the file (``l 1 2`` + ``l 2 3`` is the strand 1-2-3); a vertex may have at most one
successor and one predecessor.  Strands come out in the order of their first segment in the file.
"""

from __future__ import annotations

import numpy as np

from ..groom import GroomError


def chain_segments(starts, ends, n_vertices: int, label, source: str, base: int = 0):
    """Order vertices into strands.

    starts, ends: (E,) 0-based vertex indices of each segment (already range-checked).
    label:        segment index -> where it is in the file, for messages (e.g. "line 12").
    base:         how the file numbers vertices in messages (1 for OBJ, 0 for PLY).
    Returns (order, offsets): vertex ids strand after strand (root first) and (S + 1,) offsets.
    Vertices in no segment are not part of any strand.
    """
    a = np.asarray(starts, dtype=np.int64)
    b = np.asarray(ends, dtype=np.int64)
    _check_degrees(a, b, n_vertices, label, source, base)

    ids = np.arange(n_vertices)
    parent = ids.copy()  # pointer towards the root; roots and unused vertices point to themselves
    parent[b] = a
    used = np.zeros(n_vertices, dtype=bool)
    used[a] = used[b] = True
    is_root = used & (parent == ids)
    depth = (parent != ids).astype(np.int64)
    for _ in range(int(np.ceil(np.log2(max(n_vertices, 2)))) + 1):  # pointer jumping
        depth = depth + depth[parent]
        parent = parent[parent]
    looped = used & ~is_root[parent]  # never reached a root: on a cycle
    if looped.any():
        vertex = int(np.flatnonzero(looped)[0])
        seg = int(np.flatnonzero(a == vertex)[0])
        raise GroomError(f"{source}: {label(seg)}: segments form a closed loop through vertex {vertex + base}")

    # strands in the file order of each root's outgoing segment
    rank = np.zeros(n_vertices, dtype=np.int64)
    root_segments = np.flatnonzero(is_root[a])
    rank[a[root_segments]] = root_segments
    verts = np.flatnonzero(used)
    order = verts[np.lexsort((depth[verts], rank[parent[verts]]))]
    _, counts = np.unique(rank[parent[order]], return_counts=True)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return order, offsets


def _check_degrees(a, b, n_vertices, label, source, base) -> None:
    loops = np.flatnonzero(a == b)
    if len(loops):
        raise GroomError(f"{source}: {label(int(loops[0]))}: segment from vertex {int(a[loops[0]]) + base} to itself")
    for arr, what in ((a, "starts"), (b, "ends")):
        seen = np.bincount(arr, minlength=n_vertices)
        if np.any(seen > 1):
            vertex = int(np.flatnonzero(seen > 1)[0])
            second = int(np.flatnonzero(arr == vertex)[1])
            branch = "continues in two directions" if what == "starts" else "is reached from two vertices"
            raise GroomError(
                f"{source}: {label(second)}: vertex {vertex + base} {branch} (strands must not branch or merge)"
            )


def split_fixed(n_vertices: int, strand_length: int, source: str) -> np.ndarray:
    """Offsets of consecutive runs of ``strand_length`` vertices (for files of bare vertices)."""
    strand_length = int(strand_length)
    if strand_length < 2:
        raise GroomError(f"{source}: strand_length must be at least 2, got {strand_length}")
    if n_vertices % strand_length:
        raise GroomError(
            f"{source}: {n_vertices} vertices is not a whole number of strands of "
            f"strand_length={strand_length} ({n_vertices % strand_length} left over)"
        )
    return np.arange(0, n_vertices + 1, strand_length, dtype=np.int64)
