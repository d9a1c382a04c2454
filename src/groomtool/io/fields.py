"""Fields of an inversion result, for export (VTP, USD, Alembic) and display (the viewer).

Everything here works on the dict of rest.npz arrays (:func:`groomtool.io.results.load_arrays` reads
it from an ``InversionResult``, an output directory of ``groom invert`` or its ``rest.npz``), in SI
units.  The strands are shown as the fitted Super-Helices sampled ``per_element`` times per element;
the rest shape is sampled at the same arc lengths, so the two polylines correspond vertex by vertex.
No pyvista import here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..groom import GroomError
from ..rods import superhelix as sh
from .results import result_helix


# ------------------------------------------------------------------------------------- sampling
@dataclass
class Samples:
    """The fitted and rest shapes sampled at the same arc lengths.

    points, rest_points (V, 3) m; offsets (S + 1,); strand (V,) strand id; arc (V,) arc length (m);
    element (V,) index of the vertex's helix element in the flat element list (a node belongs to
    the element it starts).
    """

    points: np.ndarray
    rest_points: np.ndarray
    offsets: np.ndarray
    strand: np.ndarray
    arc: np.ndarray
    element: np.ndarray
    per_element: int

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


def sample(arrays: dict, per_element: int = 8) -> Samples:
    """Sample the fitted and the rest helices ``per_element`` times per element (nodes included)."""
    h = result_helix(arrays)
    points, offsets, strand, arc = sh.sample(h, per_element)
    rest_points, _, _, _ = sh.sample(result_helix(arrays, rest=True), per_element)
    local = np.arange(len(strand)) - offsets[strand]
    elem = np.minimum(local // per_element, np.maximum(h.n_elements[strand] - 1, 0))
    element = h.flat_offsets()[strand] + elem
    return Samples(points, rest_points, offsets, strand, arc, element, per_element)


def nearest_samples(samples: Samples, strand, s) -> np.ndarray:
    """Global index of the sample nearest to arc length ``s`` on ``strand`` (both (m,))."""
    strand = np.asarray(strand, dtype=np.int64).reshape(-1)
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    if len(strand) == 0:
        return np.zeros(0, dtype=np.int64)
    first, last = samples.offsets[:-1], samples.offsets[1:] - 1
    lengths = samples.arc[last]
    base = np.concatenate([[0.0], np.cumsum(lengths + 1.0)])[:-1]  # strands 1 m apart on one key
    key = samples.arc + base[samples.strand]
    q = base[strand] + np.clip(s, 0.0, lengths[strand])
    hi = np.clip(np.searchsorted(key, q), first[strand], last[strand])
    lo = np.maximum(hi - 1, first[strand])
    return np.where(np.abs(key[lo] - q) <= np.abs(key[hi] - q), lo, hi)


# ------------------------------------------------------------------------------------- fields
def contact_forces_world(arrays: dict) -> np.ndarray:
    """(m, 3) contact forces on strand a in world coordinates (N): frame rows (N, T1, T2)."""
    f = np.asarray(arrays.get("contact_forces", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(arrays.get("contact_frames", np.zeros((0, 3, 3))), dtype=np.float64).reshape(-1, 3, 3)
    if len(f) != len(frames):
        raise GroomError(f"result has {len(f)} contact forces but {len(frames)} contact frames")
    return np.einsum("mij,mi->mj", frames, f)


def vertex_contact_forces(arrays: dict, samples: Samples) -> tuple[np.ndarray, np.ndarray]:
    """Contact forces gathered on the nearest sample of each strand they act on.

    Returns (force (V, 3) N, the vector sum at each vertex; load (V,) N, the sum of the magnitudes
    at each vertex).  A strand/strand contact acts on both strands (+f on a, -f on b).
    """
    V = len(samples.points)
    force, load = np.zeros((V, 3)), np.zeros(V)
    fw = contact_forces_world(arrays)
    if len(fw) == 0:
        return force, load
    a = np.asarray(arrays["contact_strand_a"], dtype=np.int64)
    b = np.asarray(arrays["contact_strand_b"], dtype=np.int64)
    mag = np.linalg.norm(fw, axis=1)
    ia = nearest_samples(samples, a, arrays["contact_s_a"])
    np.add.at(force, ia, fw)
    np.add.at(load, ia, mag)
    other = b >= 0
    if other.any():
        ib = nearest_samples(samples, b[other], np.asarray(arrays["contact_s_b"])[other])
        np.add.at(force, ib, -fw[other])
        np.add.at(load, ib, mag[other])
    return force, load


def strand_fields(arrays: dict) -> dict:
    """Per-strand (S,) fields: see docs/outputs.md (VTP cell data)."""
    offsets = np.asarray(arrays["strand_offsets"], dtype=np.int64)
    S = len(offsets) - 1
    counts = np.diff(offsets)
    csum = np.concatenate([[0.0], np.cumsum(arrays["element_lengths"])])
    lengths = csum[offsets[1:]] - csum[offsets[:-1]]
    ratio = np.asarray(arrays.get("stiffness_ratio", np.zeros(0)), dtype=np.float64)
    if ratio.shape != (S,):
        ratio = np.full(S, np.nan)
    fit = np.asarray(arrays.get("fit_max_error", np.zeros(0)), dtype=np.float64)
    if fit.shape != (S,):
        fit = np.full(S, np.nan)
    q = np.asarray(arrays["curvatures"]).reshape(-1, 3)
    q0 = np.asarray(arrays["rest_curvatures"]).reshape(-1, 3)
    change = np.linalg.norm(q0 - q, axis=1)
    max_change = np.zeros(S)
    if len(change):
        elem_strand = np.repeat(np.arange(S), counts)
        np.maximum.at(max_change, elem_strand, change)
    n_contacts, contact_load = np.zeros(S, np.int64), np.zeros(S)
    fw = contact_forces_world(arrays)
    if len(fw):
        mag = np.linalg.norm(fw, axis=1)
        for key in ("contact_strand_a", "contact_strand_b"):
            ids = np.asarray(arrays[key], dtype=np.int64)
            on = ids >= 0
            np.add.at(n_contacts, ids[on], 1)
            np.add.at(contact_load, ids[on], mag[on])
    return {
        "strand_id": np.arange(S, dtype=np.int64),
        "length": lengths,
        "n_elements": counts,
        "fit_error": fit,
        "stiffness_ratio": ratio,
        "stability_margin": 1.0 - ratio,
        "max_curvature_change": max_change,
        "contacts": n_contacts,
        "contact_load": contact_load,
    }


def vertex_fields(arrays: dict, samples: Samples) -> dict:
    """Per-sample (V,) or (V, 3) fields: see docs/outputs.md (VTP point data)."""
    q = np.asarray(arrays["curvatures"]).reshape(-1, 3)[samples.element]
    q0 = np.asarray(arrays["rest_curvatures"]).reshape(-1, 3)[samples.element]
    force, load = vertex_contact_forces(arrays, samples)
    per_strand = strand_fields(arrays)
    return {
        "strand_id": samples.strand,
        "arc_length": samples.arc,
        "curvature": np.linalg.norm(q[:, 1:], axis=1),
        "rest_curvature": np.linalg.norm(q0[:, 1:], axis=1),
        "twist": q[:, 0],
        "rest_twist": q0[:, 0],
        "curvature_change": np.linalg.norm(q0 - q, axis=1),
        "q": q,
        "q0": q0,
        "contact_force": force,
        "contact_force_magnitude": load,
        "stiffness_ratio": per_strand["stiffness_ratio"][samples.strand],
        "stability_margin": per_strand["stability_margin"][samples.strand],
        "fit_error": per_strand["fit_error"][samples.strand],
        "rest_displacement": samples.rest_points - samples.points,
    }


# ------------------------------------------------------------------------------------- discrete rods
def polyline_arc(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(V,) arc length of every vertex from its strand's root along the polyline."""
    d = np.concatenate([[0.0], np.linalg.norm(np.diff(points, axis=0), axis=1)])
    d[offsets[:-1][np.diff(offsets) > 0]] = 0.0
    c = np.cumsum(d)
    return c - np.repeat(c[offsets[:-1]], np.diff(offsets))


def der_rest_geometry(arrays: dict, points: np.ndarray, offsets: np.ndarray, arc=None) -> dict:
    """Discrete-Elastic-Rods rest data of the rest helix, sampled where ``points`` lie.

    ``points`` (V, 3), ``offsets`` (S + 1,) is the groomed polyline the data belong to (every strand
    >= 3 vertices); ``arc`` (V,) the helix arc length of each vertex (default: the polyline's arc
    length scaled to the helix length).  Conventions of Bergou et al. 2008/2010, on the rest polyline
    (the rest helix evaluated at ``arc``), edge j from vertex j to j + 1, interior vertex i:

    - der_rest_lengths (E,) m: |e_j|;
    - der_rest_kappa (I, 2): ((kb)_i . m2, -(kb)_i . m1) with the curvature binormal
      (kb)_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1} . e_i) (dimensionless, integrated) and
      (m1, m2) the average of the material frames of edges i-1 and i;
    - der_rest_twist (I,) rad: angle from m1 of edge i-1, parallel-transported onto edge i, to m1
      of edge i, about its tangent;
    - der_frames (E, 3, 3): the groomed polyline's material frames, rows (d1, d2, d3 = tangent),
      d1 from the fitted helix's n1 at the edge midpoint made normal to the edge.

    The material frame of an edge is the helix frame (columns tangent, n1, n2) at its midpoint arc
    length, n1 made normal to the edge: m1 = n1, m2 = t x m1.  This is the rest shape's own
    geometry, exact as the sampling is refined; the exact discrete equilibrium is rods.der's export.
    """
    from ..rods.discrete import edge_start_vertices, interior_vertices

    points = np.asarray(points, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    fitted, rest = result_helix(arrays), result_helix(arrays, rest=True)
    S = len(offsets) - 1
    counts = np.diff(offsets)
    if np.any(counts < 3):
        raise GroomError("DER rest data need strands of at least 3 vertices")
    strand = np.repeat(np.arange(S), counts)
    if arc is None:
        arc = polyline_arc(points, offsets)
        tips = arc[offsets[1:] - 1]
        arc = arc * (fitted.strand_lengths / np.where(tips > 0, tips, 1.0))[strand]
    rest_points, _ = sh.evaluate(rest, strand, arc)
    e0 = edge_start_vertices(offsets)
    mid = 0.5 * (arc[e0] + arc[e0 + 1])
    _, rest_frames = sh.evaluate(rest, strand[e0], mid)
    _, fitted_frames = sh.evaluate(fitted, strand[e0], mid)

    def frames_on(polyline, helix_frames):
        e = polyline[e0 + 1] - polyline[e0]
        length = np.linalg.norm(e, axis=1)
        t = e / length[:, None]
        d1 = helix_frames[:, :, 1] - np.einsum("ij,ij->i", helix_frames[:, :, 1], t)[:, None] * t
        d1 /= np.linalg.norm(d1, axis=1)[:, None]
        return np.stack([d1, np.cross(t, d1), t], axis=1), e, length

    rest_dirs, e, rest_len = frames_on(rest_points, rest_frames)
    groomed_dirs, _, _ = frames_on(points, fitted_frames)
    # interior vertex v sits between edges a (ending at v) and a + 1
    a = np.searchsorted(e0, interior_vertices(offsets)) - 1
    ea, eb = e[a], e[a + 1]
    kb = 2.0 * np.cross(ea, eb) / (rest_len[a] * rest_len[a + 1] + np.einsum("ij,ij->i", ea, eb))[:, None]
    m1 = 0.5 * (rest_dirs[a, 0] + rest_dirs[a + 1, 0])
    m2 = 0.5 * (rest_dirs[a, 1] + rest_dirs[a + 1, 1])
    kappa = np.stack([np.einsum("ij,ij->i", kb, m2), -np.einsum("ij,ij->i", kb, m1)], axis=1)
    ta, tb = rest_dirs[a, 2], rest_dirs[a + 1, 2]
    b = np.cross(ta, tb)
    c = np.einsum("ij,ij->i", ta, tb)
    u = rest_dirs[a, 0]
    pu = c[:, None] * u + np.cross(b, u) + b * (np.einsum("ij,ij->i", b, u) / (1.0 + c))[:, None]
    w = rest_dirs[a + 1, 0]
    twist = np.arctan2(np.einsum("ij,ij->i", np.cross(pu, w), tb), np.einsum("ij,ij->i", pu, w))
    return {"der_rest_lengths": rest_len, "der_rest_kappa": kappa, "der_rest_twist": twist,
            "der_frames": groomed_dirs}
