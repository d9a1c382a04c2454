"""Shared discrete-rod helpers: resampling, twist-free frames and nodal loads, batched over strands.

Ragged layout (see :mod:`groomtool.groom`): ``points`` (V, 3), ``offsets`` (S + 1,).  A strand of
``n + 1`` vertices has ``n`` edges and ``n - 1`` interior vertices, so a groom has ``E = V - S`` edges
(``edge_offsets = offsets - arange(S + 1)``) and ``V - 2S`` interior vertices
(``interior_offsets = offsets - 2 arange(S + 1)``), each stored strand after strand, root first.
"""

from __future__ import annotations

import numba
import numpy as np


class RestDataError(ValueError):
    """Input that no discrete rod can represent (too few vertices, zero-length or folded edges)."""


# ---------------------------------------------------------------------------------------- row algebra
# Column-wise (N, 3) helpers: several times faster than np.cross / np.einsum for 3-vectors.
def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a . b, (N,)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b, (N, 3)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def matvec(Q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Q v for (N, 3, 3) Q: with director rows, the material-frame components of lab vector v."""
    return np.stack([dot(Q[:, 0], v), dot(Q[:, 1], v), dot(Q[:, 2], v)], axis=1)


def norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(dot(a, a))


# ---------------------------------------------------------------------------------------- layout
def edge_offsets(offsets: np.ndarray) -> np.ndarray:
    """(S + 1,) offsets of the per-edge arrays: strand i owns edges [eo[i], eo[i + 1])."""
    return np.asarray(offsets, np.int64) - np.arange(len(offsets), dtype=np.int64)


def interior_offsets(offsets: np.ndarray) -> np.ndarray:
    """(S + 1,) offsets of the per-interior-vertex arrays (V - 2S entries)."""
    return np.asarray(offsets, np.int64) - 2 * np.arange(len(offsets), dtype=np.int64)


def edge_start_vertices(offsets: np.ndarray) -> np.ndarray:
    """(E,) global index of the first vertex of every edge (every vertex but a strand's last)."""
    offsets = np.asarray(offsets, np.int64)
    keep = np.ones(offsets[-1], dtype=bool)
    keep[offsets[1:] - 1] = False
    return np.flatnonzero(keep)


def interior_vertices(offsets: np.ndarray) -> np.ndarray:
    """(V - 2S,) global index of every interior vertex (neither a root nor a tip)."""
    offsets = np.asarray(offsets, np.int64)
    keep = np.ones(offsets[-1], dtype=bool)
    keep[offsets[:-1]] = False
    keep[offsets[1:] - 1] = False
    return np.flatnonzero(keep)


def check_strands(points: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate and return (points float64 (V, 3), offsets int64); every strand needs >= 3 vertices."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    if offsets.ndim != 1 or offsets.size < 2 or offsets[0] != 0 or offsets[-1] != len(points):
        raise RestDataError("offsets must start at 0 and end at len(points), with at least one strand")
    counts = np.diff(offsets)
    if np.any(counts < 3):
        bad = np.flatnonzero(counts < 3)
        raise RestDataError(f"strands {bad[:10].tolist()} have fewer than 3 vertices (need 2 edges)")
    if not np.all(np.isfinite(points)):
        raise RestDataError("points contain NaN or inf")
    return points, offsets


def strand_stiffness_factors(stiffness_factor, n_strands: int) -> np.ndarray:
    """Per-strand stiffness factors f_s, (S,) float64: None gives all ones.

    Strand s then has Young's and shear moduli f_s E and f_s G, so every stiffness of the strand
    (bend, twist, shear, stretch) is multiplied by f_s.  Raises :class:`RestDataError` unless the
    input is an (S,) array of positive finite numbers.
    """
    if stiffness_factor is None:
        return np.ones(n_strands)
    f = np.asarray(stiffness_factor, dtype=np.float64)
    if f.shape != (n_strands,):
        raise RestDataError(f"stiffness_factor must have shape ({n_strands},) (one factor per strand), "
                            f"got shape {f.shape}")
    bad = np.flatnonzero(~(np.isfinite(f) & (f > 0.0)))
    if bad.size:
        raise RestDataError(f"stiffness_factor must be positive and finite: strands {bad[:10].tolist()} "
                            f"have {f[bad[:10]].tolist()}")
    return np.ascontiguousarray(f)


# ---------------------------------------------------------------------------------------- resampling
def arc_lengths(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(V,) polyline arc length s of every vertex from its strand's root."""
    d = np.concatenate([[0.0], norm(np.diff(points, axis=0))])
    d[offsets[:-1]] = 0.0
    c = np.cumsum(d)
    return c - np.repeat(c[offsets[:-1]], np.diff(offsets))


def resample(points: np.ndarray, offsets: np.ndarray, segments: int | None = None):
    """The rod polyline of every strand.

    ``segments=None`` keeps the input vertices.  ``segments=N`` places N + 1 vertices per strand at
    equal arc length s_j = j L / N along the input polyline (linear interpolation), so the rod's
    chords are slightly shorter than L / N where the strand bends.

    Returns (rod_points (V', 3), rod_offsets (S + 1,), rod_arc (V',)), where ``rod_arc`` is the
    input-polyline arc length of every rod vertex (the parameter that point-force positions use).
    """
    points, offsets = check_strands(points, offsets)
    s = arc_lengths(points, offsets)
    if segments is None:
        return points.copy(), offsets.copy(), s
    n = int(segments)
    if n < 2:
        raise RestDataError(f"segments must be >= 2, got {segments}")
    S = len(offsets) - 1
    lengths = s[offsets[1:] - 1]
    # one monotone key over the whole groom: strand i lives in [base[i], base[i] + L_i]
    base = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    key = s + np.repeat(base, np.diff(offsets))
    u = np.arange(n + 1) / n
    target_s = lengths[:, None] * u[None, :]                      # (S, N + 1)
    q = (base[:, None] + target_s).ravel()
    seg = np.searchsorted(key, q, side="right") - 1
    lo = np.repeat(offsets[:-1], n + 1)
    hi = np.repeat(offsets[1:] - 2, n + 1)
    seg = np.clip(seg, lo, hi)
    s0 = s[seg]
    ds = s[seg + 1] - s0
    t = np.divide(target_s.ravel() - s0, ds, out=np.zeros_like(s0), where=ds > 0)
    t = np.clip(t, 0.0, 1.0)[:, None]
    rod = (1.0 - t) * points[seg] + t * points[seg + 1]
    rod_offsets = np.arange(S + 1, dtype=np.int64) * (n + 1)
    return rod, rod_offsets, target_s.ravel()


# ---------------------------------------------------------------------------------------- frames
def edge_geometry(points: np.ndarray, offsets: np.ndarray):
    """Edges e_j = x_{j+1} - x_j, (E, 3); lengths |e_j|, (E,); unit tangents t_j = e_j / |e_j|."""
    e0 = edge_start_vertices(offsets)
    e = points[e0 + 1] - points[e0]
    length = norm(e)
    if np.any(length <= 0.0):
        strand = np.searchsorted(edge_offsets(offsets), np.flatnonzero(length <= 0.0), side="right") - 1
        raise RestDataError(f"{int(np.sum(length <= 0))} zero-length edges (repeated vertices) in strands "
                            f"{np.unique(strand)[:10].tolist()}: drop the repeats or resample (segments=N)")
    return e, length, e / length[:, None]


def default_root_normal(t_root: np.ndarray) -> np.ndarray:
    """d1 at the root, (S, 3): the world axis least aligned with the root tangent, made normal to it."""
    axis = np.argmin(np.abs(t_root), axis=1)
    a = np.zeros_like(t_root)
    a[np.arange(len(t_root)), axis] = 1.0
    n = a - dot(a, t_root)[:, None] * t_root
    return n / norm(n)[:, None]


@numba.njit(cache=True)
def _transport(t, eoff, d1_root, d1):
    """d1_{j+1} = P_j d1_j, P_j the minimal rotation t_j -> t_{j+1}:
    P v = c v + b x v + b (b.v) / (1 + c), with b = t_j x t_{j+1}, c = t_j . t_{j+1}."""
    for s in range(len(eoff) - 1):
        j0 = eoff[s]
        d1[j0] = d1_root[s]
        for j in range(j0, eoff[s + 1] - 1):
            a0, a1, a2 = t[j, 0], t[j, 1], t[j, 2]
            c0, c1, c2 = t[j + 1, 0], t[j + 1, 1], t[j + 1, 2]
            b0 = a1 * c2 - a2 * c1
            b1 = a2 * c0 - a0 * c2
            b2 = a0 * c1 - a1 * c0
            c = a0 * c0 + a1 * c1 + a2 * c2
            v0, v1, v2 = d1[j, 0], d1[j, 1], d1[j, 2]
            bv = (b0 * v0 + b1 * v1 + b2 * v2) / (1.0 + c)
            w0 = c * v0 + (b1 * v2 - b2 * v1) + b0 * bv
            w1 = c * v1 + (b2 * v0 - b0 * v2) + b1 * bv
            w2 = c * v2 + (b0 * v1 - b1 * v0) + b2 * bv
            # remove round-off drift: project out t_{j+1}, renormalise
            p = w0 * c0 + w1 * c1 + w2 * c2
            w0 -= p * c0
            w1 -= p * c1
            w2 -= p * c2
            nrm = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            d1[j + 1, 0] = w0 / nrm
            d1[j + 1, 1] = w1 / nrm
            d1[j + 1, 2] = w2 / nrm


def bishop_frames(points: np.ndarray, offsets: np.ndarray, root_normal=None, geometry=None) -> np.ndarray:
    """Twist-free (parallel-transported) edge frames, (E, 3, 3) with rows d1, d2, d3.

    d3 = unit edge tangent; d1 at the root edge is ``root_normal`` ((3,) or (S, 3), projected normal
    to the tangent) or :func:`default_root_normal`; d1 is carried edge to edge by the minimal
    rotation taking t_j to t_{j+1}; d2 = d3 x d1 (right-handed: d1 x d2 = d3).
    Raises if two consecutive edges fold back on each other (t_j . t_{j+1} = -1).
    ``geometry``: :func:`edge_geometry` of ``points``, if already computed.
    """
    _, _, t = edge_geometry(points, offsets) if geometry is None else geometry
    eoff = edge_offsets(offsets)
    S = len(offsets) - 1
    c = dot(t[:-1], t[1:])
    c[eoff[1:-1] - 1] = 0.0  # pairs across strands are not bends
    if np.any(c <= -1.0 + 1e-12):
        raise RestDataError("consecutive edges fold back on themselves (180 degree kink)")
    t_root = t[eoff[:-1]]
    if root_normal is None:
        d1_root = default_root_normal(t_root)
    else:
        r = np.broadcast_to(np.asarray(root_normal, np.float64), (S, 3))
        r = r - np.sum(r * t_root, axis=1)[:, None] * t_root
        nr = np.linalg.norm(r, axis=1)
        if np.any(nr < 1e-12):
            raise RestDataError("root_normal is parallel to a root tangent")
        d1_root = r / nr[:, None]
    d1 = np.empty_like(t)
    _transport(t, eoff, np.ascontiguousarray(d1_root), d1)
    frames = np.empty((len(t), 3, 3))
    frames[:, 0] = d1
    frames[:, 1] = cross(t, d1)
    frames[:, 2] = t
    return frames


def prepare_rods(points, offsets, segments: int | None = None, root_normal=None) -> dict:
    """Everything both exporters derive from the groom alone, computed once: rod_points, rod_offsets,
    rod_arc (:func:`resample`), geometry = (edges, lengths, tangents) (:func:`edge_geometry`) and the
    twist-free frames (:func:`bishop_frames`).  Pass it as ``rod=`` to the exporters to share it."""
    rod_points, rod_offsets, rod_arc = resample(points, offsets, segments)
    rod_points, rod_offsets = check_strands(rod_points, rod_offsets)
    geometry = edge_geometry(rod_points, rod_offsets)
    frames = bishop_frames(rod_points, rod_offsets, root_normal, geometry)
    return {"rod_points": rod_points, "rod_offsets": rod_offsets, "rod_arc": rod_arc, "geometry": geometry,
            "frames": frames}


# ---------------------------------------------------------------------------------------- loads
def lumped_masses(rest_lengths: np.ndarray, offsets: np.ndarray, linear_density: float) -> np.ndarray:
    """(V,) node masses m_v = rho S (l_{v-1} + l_v) / 2 (half of each adjacent edge, as PyElastica)."""
    e0 = edge_start_vertices(offsets)
    half = 0.5 * linear_density * rest_lengths
    m = np.zeros(offsets[-1])
    m[e0] += half          # e0 has no repeats, so fancy += is exact here
    m[e0 + 1] += half
    return m


def point_force_nodes(point_forces, rod_offsets: np.ndarray, rod_arc: np.ndarray, at: str = "arc_length"):
    """Map point forces onto rod nodes: returns (V, 3) nodal forces.

    ``point_forces = (strand (K,), where (K,), force (K, 3))``.  With ``at="node"`` ``where`` is a
    vertex index local to the strand's rod polyline.  With ``at="arc_length"`` it is an arc length (m)
    along the *input* polyline (the resampling parameter ``rod_arc``); a force at s between rod
    nodes j and j+1 (s_j <= s <= s_{j+1}) is split linearly, (1 - u) F on j and u F on j + 1 with
    u = (s - s_j) / (s_{j+1} - s_j): this keeps the total force and its moment about any point
    (the two shares act at the chord point (1 - u) x_j + u x_{j+1}).
    """
    F = np.zeros((rod_offsets[-1], 3))
    if point_forces is None:
        return F
    strand, where, force = point_forces
    strand = np.asarray(strand, np.int64).ravel()
    force = np.asarray(force, np.float64).reshape(-1, 3)
    S = len(rod_offsets) - 1
    if len(strand) != len(force) or np.size(where) != len(strand):
        raise RestDataError("point_forces arrays (strand, where, force) must have the same length")
    if len(strand) == 0:
        return F
    if strand.min() < 0 or strand.max() >= S:
        raise RestDataError(f"point_forces strand index out of range [0, {S})")
    first = rod_offsets[strand]
    count = rod_offsets[strand + 1] - first
    if at == "node":
        idx = np.asarray(where, np.int64).ravel()
        if np.any(idx < 0) or np.any(idx >= count):
            raise RestDataError("point_forces node index out of range for its strand")
        np.add.at(F, first + idx, force)
        return F
    if at != "arc_length":
        raise RestDataError(f"point_force_at must be 'arc_length' or 'node', got {at!r}")
    s = np.asarray(where, np.float64).ravel()
    lengths = rod_arc[rod_offsets[1:] - 1]
    L = lengths[strand]
    if np.any(s < -1e-12 * L) or np.any(s > L * (1 + 1e-12)):
        raise RestDataError("point_forces arc length outside [0, strand length]")
    base = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    key = rod_arc + np.repeat(base, np.diff(rod_offsets))
    j = np.searchsorted(key, base[strand] + s, side="right") - 1
    j = np.clip(j, first, first + count - 2)
    s0, s1 = rod_arc[j], rod_arc[j + 1]
    u = np.clip((s - s0) / (s1 - s0), 0.0, 1.0)[:, None]
    np.add.at(F, j, (1.0 - u) * force)
    np.add.at(F, j + 1, u * force)
    return F


def node_forces(rod_points, rod_offsets, rod_arc, rest_lengths, material, gravity, point_forces=None,
                point_force_at: str = "arc_length"):
    """External nodal forces F_v = m_v g + point forces, (V, 3), and the lumped masses m_v, (V,),
    computed from ``rest_lengths`` (:func:`lumped_masses`)."""
    g = np.asarray(gravity, np.float64).reshape(3)
    m = lumped_masses(rest_lengths, rod_offsets, material.linear_density)
    return m[:, None] * g[None, :] + point_force_nodes(point_forces, rod_offsets, rod_arc, point_force_at), m


