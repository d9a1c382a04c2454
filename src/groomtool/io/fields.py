"""Fields of an inversion result, for export (VTP, USD, Alembic) and display (the viewer).

Everything here works on the dict of rest.npz arrays (:func:`groomtool.io.results.load_arrays` reads
it from an ``InversionResult``, an output directory of ``groom invert`` or its ``rest.npz``), in SI
units.  The strands are shown as the fitted rods -- Super-Helices, or Super Space Clothoids for a
``groom invert --model clothoid`` result (rest.npz ``model``) -- sampled ``per_element`` times per
element; the rest shape is sampled at the same arc lengths, so the two polylines correspond vertex by
vertex.  The Darboux vector q = (twist, kappa1, kappa2) at a point is its element's constant value for
a Super-Helix and the linear interpolation of the element's two nodal values for a clothoid
(:func:`darboux_at`, :func:`sample_darboux`).  No pyvista import here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..groom import GroomError
from ..rods import clothoid as cl
from .results import result_model, result_rod, rod_module


# ------------------------------------------------------------------------------------- sampling
@dataclass
class Samples:
    """The fitted and rest shapes sampled at the same arc lengths.

    points, rest_points (V, 3) m; offsets (S + 1,); strand (V,) strand id; arc (V,) arc length (m);
    element (V,) index of the vertex's element in the flat element list (a node belongs to the
    element it starts; a strand's tip to its last element); model: "superhelix" or "clothoid".
    """

    points: np.ndarray
    rest_points: np.ndarray
    offsets: np.ndarray
    strand: np.ndarray
    arc: np.ndarray
    element: np.ndarray
    per_element: int
    model: str = "superhelix"

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


def sample(arrays: dict, per_element: int = 8) -> Samples:
    """Sample the fitted and the rest rods (helices or clothoids) ``per_element`` times per element
    (nodes included)."""
    h = result_rod(arrays)
    mod = rod_module(h)
    points, offsets, strand, arc = mod.sample(h, per_element)
    rest_points, _, _, _ = mod.sample(result_rod(arrays, rest=True), per_element)
    local = np.arange(len(strand)) - offsets[strand]
    elem = np.minimum(local // per_element, np.maximum(h.n_elements[strand] - 1, 0))
    element = np.concatenate([[0], np.cumsum(h.n_elements)]).astype(np.int64)[strand] + elem
    return Samples(points, rest_points, offsets, strand, arc, element, per_element, result_model(arrays))


def _nodal(arrays: dict, rest: bool) -> tuple[np.ndarray, np.ndarray]:
    """A clothoid result's node offsets (S + 1,) and nodal Darboux vectors (n_nodes, 3)."""
    key = "clothoid_rest_curvatures" if rest else "clothoid_curvatures"
    return (np.asarray(arrays["clothoid_node_offsets"], dtype=np.int64),
            np.asarray(arrays[key], dtype=np.float64).reshape(-1, 3))


def sample_darboux(arrays: dict, samples: Samples, rest: bool = False) -> np.ndarray:
    """(V, 3) the Darboux vector q (``rest``: q0) at every sample: a Super-Helix's element value (the sample's
    element); a clothoid's (1 - u) q_j + u q_(j+1) on element j at the sample's fraction u of it (the nodal
    values exactly at the nodes, which are samples)."""
    if samples.model != "clothoid":
        return np.asarray(arrays["rest_curvatures" if rest else "curvatures"]).reshape(-1, 3)[samples.element]
    nodes, q = _nodal(arrays, rest)
    strand_offsets = np.asarray(arrays["strand_offsets"], dtype=np.int64)
    local = samples.element - strand_offsets[samples.strand]  # element within the strand
    index = np.arange(len(samples.strand)) - samples.offsets[samples.strand]
    u = ((index - local * samples.per_element) / samples.per_element)[:, None]
    node = nodes[samples.strand] + local
    return (1.0 - u) * q[node] + u * q[node + 1]


def darboux_at(arrays: dict, strand, s, rest: bool = False) -> np.ndarray:
    """(P, 3) the Darboux vector q (``rest``: q0) at arc lengths ``s`` (m, clamped to the strand) of ``strand``:
    a Super-Helix's element value, a clothoid's linear interpolation of its element's nodal values."""
    rod = result_rod(arrays, rest=rest)
    strand = np.asarray(strand, dtype=np.int64).reshape(-1)
    elem, t = rod_module(rod).locate(rod, strand, np.asarray(s, dtype=np.float64).reshape(-1))
    if result_model(arrays) != "clothoid":
        return rod.curvatures[strand, elem]
    length = rod.lengths[strand, elem]
    u = np.where(length > 0, t / np.where(length > 0, length, 1.0), 0.0)[:, None]
    return (1.0 - u) * rod.curvatures[strand, elem] + u * rod.curvatures[strand, elem + 1]


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
    if result_model(arrays) == "clothoid":  # q0 - q is linear on each element: its norm is largest at a node
        nodes, q = _nodal(arrays, rest=False)
        q0 = _nodal(arrays, rest=True)[1]
        owner = np.repeat(np.arange(S), np.diff(nodes))
    else:
        q = np.asarray(arrays["curvatures"]).reshape(-1, 3)
        q0 = np.asarray(arrays["rest_curvatures"]).reshape(-1, 3)
        owner = np.repeat(np.arange(S), counts)
    change = np.linalg.norm(q0 - q, axis=1)
    max_change = np.zeros(S)
    if len(change):
        np.maximum.at(max_change, owner, change)
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
    q = sample_darboux(arrays, samples)
    q0 = sample_darboux(arrays, samples, rest=True)
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
    """Discrete-Elastic-Rods rest data of the rest rod (helix or clothoid), sampled where ``points`` lie.

    ``points`` (V, 3), ``offsets`` (S + 1,) is the groomed polyline the data belong to (every strand
    >= 3 vertices); ``arc`` (V,) the rod arc length of each vertex (default: the polyline's arc
    length scaled to the rod length).  Conventions of Bergou et al. 2008/2010, on the rest polyline
    (the rest rod evaluated at ``arc``), edge j from vertex j to j + 1, interior vertex i:

    - der_rest_lengths (E,) m: |e_j|;
    - der_rest_kappa (I, 2): ((kb)_i . m2, -(kb)_i . m1) with the curvature binormal
      (kb)_i = 2 e_{i-1} x e_i / (|e_{i-1}| |e_i| + e_{i-1} . e_i) (dimensionless, integrated) and
      (m1, m2) the average of the material frames of edges i-1 and i;
    - der_rest_twist (I,) rad: angle from m1 of edge i-1, parallel-transported onto edge i, to m1
      of edge i, about its tangent;
    - der_frames (E, 3, 3): the groomed polyline's material frames, rows (d1, d2, d3 = tangent),
      d1 from the fitted rod's n1 at the edge midpoint made normal to the edge.

    The material frame of an edge is the rod's frame (columns tangent, n1, n2) at its midpoint arc
    length, n1 made normal to the edge: m1 = n1, m2 = t x m1.  This is the rest shape's own
    geometry, exact as the sampling is refined; the exact discrete equilibrium is rods.der's export.
    """
    from ..rods.discrete import edge_start_vertices, interior_vertices

    points = np.asarray(points, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    fitted, rest = result_rod(arrays), result_rod(arrays, rest=True)
    mod = rod_module(fitted)
    S = len(offsets) - 1
    counts = np.diff(offsets)
    if np.any(counts < 3):
        raise GroomError("DER rest data need strands of at least 3 vertices")
    strand = np.repeat(np.arange(S), counts)
    if arc is None:
        arc = polyline_arc(points, offsets)
        tips = arc[offsets[1:] - 1]
        arc = arc * (fitted.strand_lengths / np.where(tips > 0, tips, 1.0))[strand]
    rest_kin = mod.kinematics(rest, **_light(mod))
    rest_points, _ = mod.evaluate(rest, strand, arc, rest_kin)
    e0 = edge_start_vertices(offsets)
    mid = 0.5 * (arc[e0] + arc[e0 + 1])
    _, rest_frames = mod.evaluate(rest, strand[e0], mid, rest_kin)
    _, fitted_frames = mod.evaluate(fitted, strand[e0], mid)

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


# ------------------------------------------------------------------------- rest data for other simulators
ROD_PREFIXES = ("der_", "cosserat_", "node_")  #: rest.npz keys of the discrete-rod export


def _light(mod) -> dict:
    """kinematics() keywords for positions and frames only (the clothoid's moments are for derivatives)."""
    return {"moments": False} if mod is cl else {}


def _rest_arc(arrays: dict, points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Rod arc length of the rod vertices: their polyline arc length scaled to the fitted rod's length
    (as :func:`der_rest_geometry` does)."""
    arc = polyline_arc(points, offsets)
    counts = np.diff(offsets)
    tips = arc[np.maximum(offsets[1:] - 1, 0)]
    lengths = result_rod(arrays).strand_lengths
    strand = np.repeat(np.arange(len(counts)), counts)
    return arc * (lengths / np.where(tips > 0, tips, 1.0))[strand]


def _edge_frames(points: np.ndarray, offsets: np.ndarray, helix_frames: np.ndarray) -> np.ndarray:
    """(E, 3, 3) frames of the polyline's edges, rows (d1, d2, d3 = edge tangent): d1 the helix
    frame's n1 at the edge midpoint made normal to the edge (docs/usd.md)."""
    from ..rods.discrete import edge_start_vertices

    e0 = edge_start_vertices(offsets)
    t = points[e0 + 1] - points[e0]
    t /= np.linalg.norm(t, axis=1)[:, None]
    d1 = helix_frames[:, :, 1] - np.einsum("ij,ij->i", helix_frames[:, :, 1], t)[:, None] * t
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    return np.stack([d1, np.cross(t, d1), t], axis=1)


def _per_vertex(edge_values: np.ndarray, offsets: np.ndarray, tip=None) -> np.ndarray:
    """Edge values at vertices: edge j at its first vertex; each tip gets ``tip`` (default: the
    value of the strand's last edge)."""
    from ..rods.discrete import edge_start_vertices

    e0 = edge_start_vertices(offsets)
    out = np.empty((int(offsets[-1]),) + edge_values.shape[1:], dtype=edge_values.dtype)
    out[e0] = edge_values
    tips = offsets[1:] - 1
    out[tips] = edge_values[np.searchsorted(e0, tips) - 1] if tip is None else tip
    return out


def frames_to_quaternions(frames: np.ndarray) -> np.ndarray:
    """(n, 3, 3) frames with rows (d1, d2, d3) -> (n, 4) unit quaternions (x, y, z, w) of the
    rotation taking the axes (X, Y, Z) to (d1, d2, d3), w >= 0."""
    from scipy.spatial.transform import Rotation

    if len(frames) == 0:
        return np.zeros((0, 4))
    q = Rotation.from_matrix(np.transpose(frames, (0, 2, 1))).as_quat()
    return q * np.where(q[:, 3:] < 0, -1.0, 1.0)


def quaternions_to_frames(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`frames_to_quaternions`: (n, 4) (x, y, z, w) -> (n, 3, 3) rows (d1, d2, d3)."""
    from scipy.spatial.transform import Rotation

    if len(q) == 0:
        return np.zeros((0, 3, 3))
    return np.transpose(Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix(), (0, 2, 1))


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a b of (n, 4) quaternions (x, y, z, w)."""
    av, aw, bv, bw = a[:, :3], a[:, 3:], b[:, :3], b[:, 3:]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv),
                           aw * bw - np.einsum("ij,ij->i", av, bv)[:, None]], axis=1)


def consumer_rest_data(arrays: dict, points: np.ndarray, offsets: np.ndarray, arc, rod_data: dict) -> dict:
    """Per-vertex rest data of the rod polyline (V vertices) as simulators name them (USD, Alembic).

    points: the rest rods (helices or clothoids) at the vertices' arc lengths; rotation: the rest frame of
    the edge leaving each vertex (tip: its last edge's) as a quaternion; bend: q_i^-1 q_(i+1) (identity at
    the last edge and the tip); length: the rest length of the edge leaving each vertex (der_rest_lengths
    when the data have them; 0 at the tip); normal: d1 of the rest frame; orient: the groomed frame.
    A clothoid result also gets darboux and rest_darboux (V, 3): q and q0 at the vertices' arc lengths
    (:func:`darboux_at`), its curvatures being linear along each element rather than constant.
    """
    from ..rods.discrete import edge_start_vertices

    counts = np.diff(offsets)
    S = len(counts)
    strand = np.repeat(np.arange(S), counts)
    if arc is None:
        arc = _rest_arc(arrays, points, offsets)
    rest_helix = result_rod(arrays, rest=True)
    mod = rod_module(rest_helix)
    rest_kin = mod.kinematics(rest_helix, **_light(mod))
    rest_points, _ = mod.evaluate(rest_helix, strand, arc, rest_kin)
    out = {"points": rest_points}
    if np.any(counts < 2):
        raise GroomError("USD rest data need strands of at least 2 vertices")
    e0 = edge_start_vertices(offsets)
    mid = 0.5 * (arc[e0] + arc[e0 + 1])
    _, rest_helix_frames = mod.evaluate(rest_helix, strand[e0], mid, rest_kin)
    rest_frames = _edge_frames(rest_points, offsets, rest_helix_frames)
    if "cosserat_directors" in rod_data:
        groomed = rod_data["cosserat_directors"][0]
    elif "der_frames" in rod_data:
        groomed = rod_data["der_frames"][0]
    else:
        _, fitted_frames = mod.evaluate(result_rod(arrays), strand[e0], mid)
        groomed = _edge_frames(points, offsets, fitted_frames)
    q_rest = frames_to_quaternions(rest_frames)
    rotation = _per_vertex(q_rest, offsets)
    out["rotation"] = rotation
    out["normals"] = _per_vertex(rest_frames[:, 0], offsets)
    nxt = np.minimum(np.arange(len(points)) + 1, len(points) - 1)
    bend = _quat_multiply(rotation * [-1.0, -1.0, -1.0, 1.0], rotation[nxt])
    bend[offsets[1:] - 1] = [0.0, 0.0, 0.0, 1.0]
    out["bend_rotation"] = bend * np.where(bend[:, 3:] < 0, -1.0, 1.0)
    if "der_rest_lengths" in rod_data:
        lengths = rod_data["der_rest_lengths"][0]
    else:
        lengths = np.linalg.norm(rest_points[e0 + 1] - rest_points[e0], axis=1)
    out["length"] = _per_vertex(np.asarray(lengths, dtype=np.float64), offsets, tip=0.0)
    out["orient"] = _per_vertex(frames_to_quaternions(np.asarray(groomed, dtype=np.float64)), offsets)
    if result_model(arrays) == "clothoid":
        out["darboux"] = darboux_at(arrays, strand, arc)
        out["rest_darboux"] = darboux_at(arrays, strand, arc, rest=True)
    return out


def rod_polyline_data(arrays: dict, samples) -> tuple:
    """Points, offsets, {key: (values, layout)}, origin and rod arc lengths (None: from the
    polyline) of the discrete-rod polyline the USD and Alembic writers write.

    With a discrete export (``rod_points``, ``rod_offsets`` and der_/cosserat_/node_ arrays) that
    polyline and its arrays; without, the fitted rod samples.  DER data missing from the export
    are computed from the rest rod (:func:`der_rest_geometry`): "rest helix geometry", or "rest
    clothoid geometry" for a clothoid result.
    """
    if "rod_points" in arrays and "rod_offsets" in arrays:
        points = np.asarray(arrays["rod_points"], dtype=np.float64).reshape(-1, 3)
        offsets = np.asarray(arrays["rod_offsets"], dtype=np.int64)
        arc, origin = None, "discrete export"
    else:
        points, offsets, arc = samples.points, samples.offsets, samples.arc
        origin = f"rest {'clothoid' if samples.model == 'clothoid' else 'helix'} geometry"
    V, S = len(points), len(offsets) - 1
    sizes = {V: "vertex", V - S: "edge", V - 2 * S: "interior"}
    data = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        if key.startswith(ROD_PREFIXES) and value.dtype.kind in "fiub" and value.ndim >= 1 and S > 0:
            if len(value) in sizes:
                data[key] = (value, sizes[len(value)])
    if not any(k.startswith("der_rest_") for k in data) and np.all(np.diff(offsets) >= 3):
        for key, value in der_rest_geometry(arrays, points, offsets, arc).items():
            data[key] = (value, sizes[len(value)])
        if origin == "discrete export":
            origin = f"discrete export; DER data from the rest {_rod_word(arrays)} geometry"
    return points, offsets, data, origin, arc



def _rod_word(arrays: dict) -> str:
    return "clothoid" if result_model(arrays) == "clothoid" else "helix"
