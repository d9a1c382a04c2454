"""Result fields shared by the VTP/USD writers and the viewer, on a hand-built InversionResult.

``synthetic_result`` (imported by test_usd/test_vtp/test_viz tests) builds a physically consistent
result without the fitter: Super-Helices hanging from a spherical head, the isolated rest
curvatures q0 = q - K^-1 F, a few head and strand/strand contacts with forces inside their cones.
"""

import numpy as np
import pytest
import trimesh

from groomtool.contact.detect import Contacts
from groomtool.groom import Groom
from groomtool.inverse_problem import isolated_rest_curvatures
from groomtool.invert import InversionParams, InversionResult
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.stability import stiffness_ratios
from groomtool.io import fields, results

HEAD_RADIUS = 0.1


def _root_frame(normal):
    """Columns (tangent, n1, n2): tangent along the outward normal tilted downwards."""
    t = normal + np.array([0.0, -1.5, 0.0])
    t /= np.linalg.norm(t)
    n1 = np.cross(t, [0.0, 0.0, 1.0])
    n1 = n1 / np.linalg.norm(n1) if np.linalg.norm(n1) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return np.stack([t, n1, np.cross(t, n1)], axis=1)


def synthetic_helix(n_strands=8, seed=0, max_elements=7, up="y"):
    rng = np.random.default_rng(seed)
    az = np.linspace(0.3, 2 * np.pi - 0.3, n_strands) + np.pi / 2
    polar = rng.uniform(0.4, 0.9, n_strands)
    normals = np.stack([np.sin(polar) * np.cos(az), np.cos(polar), np.sin(polar) * np.sin(az)], axis=1)
    roots = HEAD_RADIUS * normals
    frames = np.stack([_root_frame(n) for n in normals])
    n_elem = rng.integers(max_elements - 3, max_elements + 1, n_strands)
    n_elem[0] = max_elements
    lengths = rng.uniform(0.02, 0.04, (n_strands, max_elements))
    q = rng.normal(size=(n_strands, max_elements, 3)) * [5.0, 12.0, 12.0]
    mask = np.arange(max_elements)[None, :] < n_elem[:, None]
    lengths[~mask] = 0.0
    q[~mask] = 0.0
    if up == "z":  # the same groom rotated so that +z is up
        rot = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
        roots, frames = roots @ rot.T, rot @ frames
    return sh.SuperHelix(roots, frames, lengths, q, n_elem)


def synthetic_contacts(helix, rng, mu):
    """Three head contacts near roots and two strand/strand contacts, forces strictly in the cone."""
    strands, s, other, s_other = [], [], [], []
    for i in range(3):
        strands.append(i)
        s.append(0.3 * helix.lengths[i, 0])
        other.append(-1)
        s_other.append(np.nan)
    for a, b in ((3, 4), (5, 6)):
        strands.append(a)
        s.append(0.5 * helix.strand_lengths[a])
        other.append(b)
        s_other.append(0.4 * helix.strand_lengths[b])
    strands, s, other, s_other = map(np.asarray, (strands, s, other, s_other))
    pa, _ = sh.evaluate(helix, strands, s)
    pb = pa.copy()
    is_strand = other >= 0
    pb[is_strand], _ = sh.evaluate(helix, other[is_strand], s_other[is_strand])
    normal = np.where(is_strand[:, None], pa - pb, pa)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    t1 = np.cross(normal, [0.3, 0.2, 0.9])
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    frame = np.stack([normal, t1, np.cross(normal, t1)], axis=1)
    m = len(strands)
    fn = rng.uniform(1e-6, 5e-6, m)
    ft = rng.normal(size=(m, 2))
    ft *= (0.5 * mu * fn / np.linalg.norm(ft, axis=1))[:, None]
    contacts = Contacts(strands, s, other, s_other, pa, pb, normal, frame, np.linalg.norm(pa - pb, axis=1))
    return contacts, np.column_stack([fn, ft])


def synthetic_result(n_strands=8, seed=0, up="y", contacts=True):
    helix = synthetic_helix(n_strands, seed, up=up)
    material = Material()
    groom_pts, offsets, _, _ = sh.sample(helix, 4)
    groom = Groom(groom_pts, offsets, up=up, source=f"synthetic(seed={seed})")
    gravity = groom.gravity(material.gravity)
    rest = isolated_rest_curvatures(helix, material, gravity)
    rng = np.random.default_rng(seed + 1)
    head = trimesh.creation.icosphere(subdivisions=3, radius=HEAD_RADIUS)
    if up == "z":
        head.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    if contacts:
        c, forces = synthetic_contacts(helix, rng, material.friction)
    else:
        c, forces = None, np.zeros((0, 3))
    ratio = stiffness_ratios(helix, material.stiffness_diag, material.linear_density, gravity)
    fit_err = rng.uniform(1e-5, 4e-4, helix.n_strands)
    report = {"input": groom.source, "up": up, "strands": helix.n_strands,
              "elements": int(helix.n_elements.sum())}
    return InversionResult(groom=groom, head=head, params=InversionParams(material=material), helix=helix,
                           rest_curvatures=rest, fit_max_error=fit_err, fit_mean_error=0.5 * fit_err,
                           gravity=gravity, contacts=c, forces=forces, stiffness_ratio=ratio, report=report)


@pytest.fixture
def result():
    return synthetic_result()


def test_helix_round_trips_through_the_arrays(result):
    arrays = results.load_arrays(result)
    h = results.result_helix(arrays)
    assert np.array_equal(h.lengths, result.helix.lengths)
    assert np.array_equal(h.curvatures, result.helix.curvatures)
    assert np.array_equal(results.result_helix(arrays, rest=True).curvatures, result.rest_curvatures)
    assert results.up_axis(arrays) == "y"
    assert results.up_axis(results.load_arrays(synthetic_result(up="z", contacts=False))) == "z"


def test_load_arrays_from_a_directory(result, tmp_path):
    result.save(tmp_path, formats=("npz",))
    arrays = results.load_arrays(tmp_path)
    assert np.array_equal(arrays["rest_curvatures"], result.helix.to_flat(result.rest_curvatures))
    with pytest.raises(ValueError, match="no such file"):
        results.load_arrays(tmp_path / "nothing")


def test_samples_match_the_result_shapes(result):
    samples = fields.sample(results.load_arrays(result), per_element=8)
    pts, off = result.fitted_shape(8)
    rest, _ = result.rest_shape(8)
    assert np.array_equal(samples.offsets, off)
    assert np.allclose(samples.points, pts)
    assert np.allclose(samples.rest_points, rest)
    # every sample's element contains its arc length
    starts = np.concatenate([[0.0], np.cumsum(result.helix.to_flat(result.helix.lengths))])
    local0 = starts[samples.element] - starts[result.helix.flat_offsets()[samples.strand]]
    assert np.all(samples.arc >= local0 - 1e-12)


def test_vertex_fields(result):
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays, 4)
    f = fields.vertex_fields(arrays, samples)
    V = len(samples.points)
    for name, value in f.items():
        assert len(value) == V, name
    q = result.helix.to_flat(result.helix.curvatures)
    q0 = result.helix.to_flat(result.rest_curvatures)
    assert np.allclose(f["curvature_change"], np.linalg.norm(q0 - q, axis=1)[samples.element])
    # contact loads: every contact lands once on a (and once on b for strand/strand contacts)
    mags = np.linalg.norm(result.forces, axis=1)
    n_strand = np.count_nonzero(result.contacts.strand_b >= 0)
    assert np.isclose(f["contact_force_magnitude"].sum(), mags.sum() + mags[result.contacts.strand_b >= 0].sum())
    assert n_strand == 2
    # strand/strand forces cancel in the vector sum; head forces do not
    head = result.contacts.strand_b < 0
    world = np.einsum("mij,mi->mj", result.contacts.frame, result.forces)
    assert np.allclose(f["contact_force"].sum(axis=0), world[head].sum(axis=0))
    assert np.allclose(f["stability_margin"], 1 - result.stiffness_ratio[samples.strand])


def test_nearest_samples_picks_the_closest_arc_length(result):
    samples = fields.sample(results.load_arrays(result), 4)
    rng = np.random.default_rng(3)
    strand = rng.integers(0, result.helix.n_strands, 50)
    s = rng.uniform(-0.01, 1.1, 50) * result.helix.strand_lengths[strand]
    idx = fields.nearest_samples(samples, strand, s)
    for i, st, si in zip(idx, strand, s):
        own = np.arange(samples.offsets[st], samples.offsets[st + 1])
        assert i in own
        assert abs(samples.arc[i] - si) <= np.min(np.abs(samples.arc[own] - si)) + 1e-15


def test_der_rest_geometry_of_a_circle():
    """A planar circular rest arc of curvature k: kb = 2 tan(k h / 2) about the binormal, no twist."""
    k, h, n = 20.0, 0.004, 30
    helix = sh.SuperHelix(np.zeros((1, 3)), np.eye(3)[None], np.full((1, 1), n * h), np.array([[[0.0, 0.0, k]]]))
    arrays = {"strand_offsets": np.array([0, 1]), "element_lengths": np.array([n * h]),
              "root_positions": np.zeros((1, 3)), "root_frames": np.eye(3)[None],
              "curvatures": np.array([[0.0, 0.0, k]]), "rest_curvatures": np.array([[0.0, 0.0, k]])}
    s = np.linspace(0.0, n * h, n + 1)
    pts, _ = sh.evaluate(helix, np.zeros(n + 1, np.int64), s)
    der = fields.der_rest_geometry(arrays, pts, np.array([0, n + 1]), arc=s)
    chord = 2 * np.sin(k * h / 2) / k
    assert np.allclose(der["der_rest_lengths"], chord)
    # frame columns (t, n1, n2) with omega = k n2: the strand bends towards n1 and kb is along n2 = m2
    assert np.allclose(der["der_rest_kappa"][:, 0], 2 * np.tan(k * h / 2))
    assert np.allclose(der["der_rest_kappa"][:, 1], 0.0, atol=1e-12)
    assert np.allclose(der["der_rest_twist"], 0.0, atol=1e-12)


def test_der_rest_twist_of_a_twisted_straight_rod():
    tau, h, n = 15.0, 0.005, 10
    q = np.array([[[tau, 0.0, 0.0]]])
    arrays = {"strand_offsets": np.array([0, 1]), "element_lengths": np.array([n * h]),
              "root_positions": np.zeros((1, 3)), "root_frames": np.eye(3)[None], "curvatures": q[0],
              "rest_curvatures": q[0]}
    s = np.linspace(0.0, n * h, n + 1)
    pts = np.column_stack([s, np.zeros_like(s), np.zeros_like(s)])
    der = fields.der_rest_geometry(arrays, pts, np.array([0, n + 1]))
    assert np.allclose(der["der_rest_twist"], tau * h)
    assert np.allclose(der["der_rest_kappa"], 0.0, atol=1e-12)
