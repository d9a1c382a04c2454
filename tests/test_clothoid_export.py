"""The exporters on Super Space Clothoid results (issue 20): every format written, read back (our readers, pxr,
pyvista) and compared with the clothoid kinematics evaluated directly from rest.npz's nodal data
(``rods.clothoid.evaluate``), and the attributes with rest.npz; the discrete rest data of a clothoid inversion;
``groom invert --model clothoid --format usd`` and ``groom export`` on a small example."""

import json

import numpy as np
import pytest

from groomtool.cli.main import EXIT_OK, main
from groomtool.examples import write_example
from groomtool.groom import Groom
from groomtool.invert import InversionParams, invert_groom
from groomtool.io import fields, load_groom, load_head, results
from groomtool.io.export import export_formats, export_path
from groomtool.rods import clothoid as cl
from groomtool.rods import superhelix as sh
from groomtool.rods.cosserat import cosserat_static_residual
from groomtool.rods.discrete import node_forces

F32 = 2e-6  # float32 round-off on metre-scale values and unit vectors
ROD_KEYS = ("rod_", "der_", "cosserat_", "node_")


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A clothoid inversion of 6 example strands with a head contact, saved; (directory, groom, result)."""
    d = tmp_path_factory.mktemp("clothoid_export")
    groom_path, head_path = write_example(d, n_strands=20, seed=5)
    full = load_groom(groom_path)
    ids = [0, 3, 5, 7, 9, 12]
    pts = np.concatenate([full.points[full.offsets[i]:full.offsets[i + 1]] for i in ids])
    off = np.concatenate([[0], np.cumsum([full.offsets[i + 1] - full.offsets[i] for i in ids])])
    groom = Groom(pts, off, up=full.up, source=str(groom_path))
    result = invert_groom(groom, load_head(head_path),
                          InversionParams(model="clothoid", contacts="head", stabilize="none"))
    assert result.model == "clothoid" and len(result.forces) >= 1
    result.save(d / "out")
    return d / "out", groom, result


@pytest.fixture(scope="module")
def arrays(saved):
    """rest.npz of the clothoid result, as the exporters read it (with the discrete export)."""
    return results.load_arrays(saved[0])


@pytest.fixture(scope="module")
def bare(arrays):
    """The same result without the discrete export: the exporters sample the clothoids themselves."""
    return {k: v for k, v in arrays.items() if not k.startswith(ROD_KEYS)}


def _expected_samples(rod, per_element):
    """Strand, arc length, element and fraction of every sample, computed here (nodes included, tip last)."""
    strand, arc, elem, frac = [], [], [], []
    for s in range(rod.n_strands):
        n = int(rod.n_elements[s])
        for e in range(n):
            for k in range(per_element + (1 if e == n - 1 else 0)):
                u = k / per_element
                strand.append(s)
                elem.append(e)
                frac.append(u)
                arc.append(rod.element_starts[s, e] + u * rod.lengths[s, e])
    return np.array(strand), np.array(arc), np.array(elem), np.array(frac)


def _interpolated(rod, strand, elem, frac):
    """q at (element, fraction): the clothoid's Darboux vector, linear between the element's two nodes."""
    q = rod.curvatures
    return (1.0 - frac)[:, None] * q[strand, elem] + frac[:, None] * q[strand, elem + 1]


def _darboux_at_arc(rod, strand, s):
    """q at arc lengths s (elements located by a search here, not by the library)."""
    elem = np.array([min(np.searchsorted(rod.element_starts[k, 1:rod.n_elements[k]], x, side="right"),
                         rod.n_elements[k] - 1) for k, x in zip(strand, s)])
    t = s - rod.element_starts[strand, elem]
    return _interpolated(rod, strand, elem, np.clip(t / rod.lengths[strand, elem], 0.0, 1.0))


def _polyline_arc(points, offsets):
    arc = np.zeros(len(points))
    for s in range(len(offsets) - 1):
        p = points[offsets[s]:offsets[s + 1]]
        arc[offsets[s]:offsets[s + 1]] = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    return arc


def test_samples_and_fields_follow_the_clothoid(arrays):
    rod, rest = results.result_clothoid(arrays), results.result_clothoid(arrays, rest=True)
    samples = fields.sample(arrays, 8)
    strand, arc, elem, frac = _expected_samples(rod, 8)
    assert samples.model == "clothoid"
    np.testing.assert_array_equal(samples.strand, strand)
    assert np.abs(samples.arc - arc).max() <= 1e-15
    assert np.abs(samples.points - cl.evaluate(rod, strand, arc)[0]).max() <= 1e-13
    assert np.abs(samples.rest_points - cl.evaluate(rest, strand, arc)[0]).max() <= 1e-13
    # not a Super-Helix of the element means: the clothoid's own centreline
    means = sh.SuperHelix(rod.root_positions, rod.root_frames, rod.lengths,
                          0.5 * (rod.curvatures[:, 1:] + rod.curvatures[:, :-1]), rod.n_elements)
    assert np.abs(sh.sample(means, 8)[0] - samples.points).max() > 1e-5
    # the Darboux vectors per sample: the nodal values at the nodes, linear in between
    vf = fields.vertex_fields(arrays, samples)
    q, q0 = _interpolated(rod, strand, elem, frac), _interpolated(rest, strand, elem, frac)
    scale = np.abs(q0).max()
    assert np.abs(vf["q"] - q).max() <= 1e-14 * scale and np.abs(vf["q0"] - q0).max() <= 1e-14 * scale
    at_node = frac == 0
    np.testing.assert_array_equal(vf["q0"][at_node], rest.curvatures[strand[at_node], elem[at_node]])
    np.testing.assert_allclose(vf["rest_curvature"], np.linalg.norm(q0[:, 1:], axis=1), rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(vf["twist"], q[:, 0], rtol=1e-13, atol=1e-12)
    assert np.abs(vf["rest_displacement"] - (samples.rest_points - samples.points)).max() == 0
    # per strand: the largest |q0 - q| is at a node (it is linear per element)
    nodes = np.asarray(arrays["clothoid_node_offsets"])
    change = np.linalg.norm(arrays["clothoid_rest_curvatures"] - arrays["clothoid_curvatures"], axis=1)
    want = [change[nodes[s]:nodes[s + 1]].max() for s in range(rod.n_strands)]
    np.testing.assert_array_equal(fields.strand_fields(arrays)["max_curvature_change"], want)
    # fields.darboux_at anywhere: the same interpolation
    s = np.random.default_rng(0).uniform(0, 1, 50) * rod.strand_lengths[strand[:50]]
    assert np.abs(fields.darboux_at(arrays, strand[:50], s, rest=True) - _darboux_at_arc(rest, strand[:50], s)).max() \
        <= 1e-12 * scale


def _edge_frames(points, offsets, frames_at_mid):
    """Rows (d1, d2, t) per edge: t the unit edge, d1 the rod frame's n1 at the edge's middle made normal to it."""
    tips = offsets[1:] - 1
    starts = np.setdiff1d(np.arange(len(points)), tips)
    t = points[starts + 1] - points[starts]
    t /= np.linalg.norm(t, axis=1)[:, None]
    n1 = frames_at_mid[:, :, 1]
    d1 = n1 - np.einsum("ij,ij->i", n1, t)[:, None] * t
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    return np.stack([d1, np.cross(t, d1), t], axis=1), starts


def _quat_rows(q):
    """quatf (x, y, z, w) -> rotation rows (d1, d2, d3): the images of X, Y, Z."""
    from scipy.spatial.transform import Rotation

    return np.transpose(Rotation.from_quat(q).as_matrix(), (0, 2, 1))


def test_usd_of_the_clothoid_samples(bare, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is not installed")
    from pxr import Usd, UsdGeom

    from groomtool.io.usd import read_usd, write_usd

    rod, rest = results.result_clothoid(bare), results.result_clothoid(bare, rest=True)
    strand, arc, elem, frac = _expected_samples(rod, 8)
    path = write_usd(bare, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(path))
    info = dict(stage.GetRootLayer().customLayerData["groomtool"])
    assert info["model"] == "clothoid" and info["discrete_rest_data"] == "rest clothoid geometry"
    prim = stage.GetPrimAtPath("/Groom/Strands")

    def get(name, p=prim):
        return np.asarray(p.GetAttribute(name).Get(), dtype=np.float64)

    points = get("points")
    want_rest = cl.evaluate(rest, strand, arc)[0]
    assert np.abs(points - cl.evaluate(rod, strand, arc)[0]).max() <= F32
    for name in ("physics:restShapePoints", "primvars:rest_position"):
        assert np.abs(get(name) - want_rest).max() <= F32, name
    assert np.abs(get("points", stage.GetPrimAtPath("/Groom/RestShape")) - want_rest).max() <= F32
    # frames: the clothoid's own frames at the edges' middles (rest shape: rest_rotation, groomed: orient)
    offsets = np.concatenate([[0], np.cumsum(rod.n_elements * 8 + 1)])
    tips = offsets[1:] - 1
    starts = np.setdiff1d(np.arange(len(points)), tips)
    mid = 0.5 * (arc[starts] + arc[starts + 1])
    want, _ = _edge_frames(want_rest, offsets, cl.evaluate(rest, strand[starts], mid)[1])
    assert np.abs(_quat_rows(get("primvars:rest_rotation")[starts]) - want).max() <= 1e-5
    assert np.abs(get("physics:restNormals")[starts] - want[:, 0]).max() <= 1e-5
    want_groomed, _ = _edge_frames(points, offsets, cl.evaluate(rod, strand[starts], mid)[1])
    assert np.abs(_quat_rows(get("primvars:orient")[starts]) - want_groomed).max() <= 1e-5
    length = get("primvars:rest_length")
    assert np.abs(length[starts] - np.linalg.norm(want_rest[starts + 1] - want_rest[starts], axis=1)).max() <= 1e-8
    # the Darboux vectors at the vertices, linear along each element
    scale = np.abs(rest.curvatures).max()
    pv = UsdGeom.PrimvarsAPI(prim)
    for name, r in (("groom:darboux", rod), ("groom:rest_darboux", rest)):
        primvar = pv.GetPrimvar(name)
        assert primvar.GetInterpolation() == UsdGeom.Tokens.vertex
        got = np.asarray(primvar.Get(), dtype=np.float64)
        assert np.abs(got - _interpolated(r, strand, elem, frac)).max() <= 1e-6 * scale, name
    # the exact data: rest.npz's keys, bit for bit; the clothoid rebuilt from them is the same rod
    assert prim.GetAttribute("groomtool:model").Get() == "clothoid"
    for key in results.CLOTHOID_KEYS + ("element_lengths", "curvatures", "rest_curvatures", "root_positions"):
        np.testing.assert_array_equal(get("groomtool:" + key).reshape(np.shape(bare[key])), bare[key])
    data = read_usd(path).metadata["rest_data"]
    assert str(data["model"]) == "clothoid"
    back = results.result_clothoid(data, rest=True)
    np.testing.assert_array_equal(back.curvatures, rest.curvatures)
    np.testing.assert_array_equal(back.root_frames, rest.root_frames)
    # the DER rest data of the rest clothoid (no discrete export): test below
    want = fields.der_rest_geometry(bare, points, offsets, arc)
    for key in ("der_rest_lengths", "der_rest_kappa", "der_rest_twist"):
        assert np.abs(data[key] - want[key]).max() <= 1e-6 * np.abs(want[key]).max(), key


def _der_error(arrays, per_element):
    """Max over interior vertices of |DER integrated curvature / Voronoi length - (kappa2, -kappa1)| and of
    |twist / Voronoi length - twist| of fields.der_rest_geometry on the rest clothoid sampled per_element times
    per element, against its Darboux vector at the vertex (t' = kappa2 n1 - kappa1 n2 with frames (t, n1, n2))."""
    rest = results.result_clothoid(arrays, rest=True)
    strand, arc, elem, frac = _expected_samples(rest, per_element)
    points = cl.evaluate(results.result_clothoid(arrays), strand, arc)[0]
    offsets = np.concatenate([[0], np.cumsum(rest.n_elements * per_element + 1)])
    der = fields.der_rest_geometry(arrays, points, offsets, arc)
    tips = offsets[1:] - 1
    inner = np.setdiff1d(np.arange(len(points)), np.concatenate([offsets[:-1], tips]))
    q0 = _interpolated(rest, strand, elem, frac)[inner]
    edge = np.zeros(len(points))
    edge[np.setdiff1d(np.arange(len(points)), tips)] = der["der_rest_lengths"]
    vor = 0.5 * (edge[inner - 1] + edge[inner])
    kappa = np.abs(der["der_rest_kappa"] / vor[:, None] - np.stack([q0[:, 2], -q0[:, 1]], axis=1)).max()
    return kappa, np.abs(der["der_rest_twist"] / vor - q0[:, 0]).max()


def test_der_rest_geometry_of_the_rest_clothoid_converges(bare):
    """The DER rest data of the exporters' fallback (no discrete export) are the rest clothoid's own geometry:
    exact as the sampling is refined (at least first order here; up to 385 1/m over 1-2 cm elements)."""
    coarse, fine = _der_error(bare, 8), _der_error(bare, 32)
    scale = np.abs(results.result_clothoid(bare, rest=True).curvatures).max()
    assert fine[0] <= coarse[0] / 3 and fine[1] <= coarse[1] / 3
    assert fine[0] <= 0.01 * scale and fine[1] <= 0.01 * scale


def test_usd_validates(bare, arrays, tmp_path):
    """usd-core's validators (as tests/test_usd_rest_data.py runs them) find nothing in the clothoid files."""
    pytest.importorskip("pxr", reason="usd-core is not installed")
    from pxr import Usd

    from groomtool.io.usd import write_usd

    UsdValidation = pytest.importorskip("pxr.UsdValidation", reason="this usd-core has no UsdValidation")
    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    for name, source in (("bare.usdz", bare), ("export.usda", arrays)):
        stage = Usd.Stage.Open(str(write_usd(source, tmp_path / name)))
        assert [e.GetMessage() for e in context.Validate(stage)] == [], name


def test_usd_with_the_discrete_export(saved, arrays, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is not installed")
    from groomtool.io.usd import read_usd, write_usd

    rest = results.result_clothoid(arrays, rest=True)
    path = write_usd(saved[0], tmp_path / "d.usdc")
    groom = read_usd(path)
    data = groom.metadata["rest_data"]
    rod_points, rod_offsets = arrays["rod_points"], arrays["rod_offsets"]
    assert np.abs(groom.points - rod_points).max() <= F32  # the rod polyline: the input vertices
    np.testing.assert_array_equal(groom.offsets, rod_offsets)
    for key in ("der_rest_lengths", "der_rest_kappa", "der_rest_twist", "cosserat_rest_kappa"):
        assert np.abs(data[key] - arrays[key]).max() <= 1e-6 * np.abs(arrays[key]).max() + 1e-12, key
    # the rest shape: the rest clothoid at the vertices' polyline arc lengths scaled to the rod length
    strand = np.repeat(np.arange(len(rod_offsets) - 1), np.diff(rod_offsets))
    arc = _polyline_arc(rod_points, rod_offsets)
    arc *= (rest.strand_lengths / arc[rod_offsets[1:] - 1])[strand]
    assert np.abs(data["rest_points"] - cl.evaluate(rest, strand, arc)[0]).max() <= F32
    scale = np.abs(rest.curvatures).max()
    assert np.abs(data["rest_darboux"] - _darboux_at_arc(rest, strand, arc)).max() <= 1e-6 * scale
    assert len(data["contact_forces"]) == len(arrays["contact_forces"]) >= 1


def test_discrete_rest_data_of_a_clothoid_inversion(saved, arrays):
    """The Cosserat rest data of the clothoid result make the input polylines an equilibrium of PyElastica's
    statics under gravity and the contact forces (carried from the clothoid's arc lengths to the polyline's),
    re-evaluated here from rest.npz."""
    _, groom, result = saved
    np.testing.assert_array_equal(arrays["rod_points"], groom.points)
    rod = results.result_clothoid(arrays)
    rod_points, rod_offsets = arrays["rod_points"], arrays["rod_offsets"]
    arc = _polyline_arc(rod_points, rod_offsets)
    a = np.asarray(arrays["contact_strand_a"])
    world = np.einsum("mij,mi->mj", arrays["contact_frames"], arrays["contact_forces"])
    s_poly = arrays["contact_s_a"] * arc[rod_offsets[a + 1] - 1] / rod.strand_lengths[a]
    assert np.all(arrays["contact_strand_b"] == -1)  # head contacts only here
    material = results.read_result(saved[0]).material
    forces, _ = node_forces(rod_points, rod_offsets, arc, arrays["cosserat_rest_lengths"], material,
                            arrays["gravity"], point_forces=(a, s_poly, world))
    fres, tres = cosserat_static_residual(rod_points, rod_offsets, arrays["cosserat_directors"],
                                          arrays["cosserat_rest_kappa"], arrays["cosserat_rest_sigma"],
                                          arrays["cosserat_rest_lengths"], forces, material)
    assert np.linalg.norm(fres) <= 1e-6 * np.linalg.norm(forces)
    assert np.abs(tres).max() <= 1e-9
    der = result.report["discrete_rest_data"]["der_residual"]
    assert der["force_rel"] < 1e-7 and der["torque_rel"] < 1e-12


def test_alembic_of_the_clothoid(bare, tmp_path):
    pytest.importorskip("alembic3d", reason="alembic3d is not installed")
    rod, rest = results.result_clothoid(bare), results.result_clothoid(bare, rest=True)
    strand, arc, elem, frac = _expected_samples(rod, 8)
    (path,) = export_formats(bare, tmp_path, ["abc"])
    groom = load_groom(path, units="cm")
    assert np.abs(groom.points - cl.evaluate(rod, strand, arc)[0]).max() <= 1e-7  # float32 centimetres
    data = groom.metadata["rest_data"]
    assert np.abs(data["rest_position"] - cl.evaluate(rest, strand, arc)[0]).max() <= 1e-7
    scale = np.abs(rest.curvatures).max()
    assert np.abs(data["groomtool_rest_darboux"] - _interpolated(rest, strand, elem, frac)).max() <= 1e-6 * scale
    assert np.abs(data["groomtool_darboux"] - _interpolated(rod, strand, elem, frac)).max() <= 1e-6 * scale


def test_vtp_of_the_clothoid(bare, tmp_path):
    pv = pytest.importorskip("pyvista")
    rod, rest = results.result_clothoid(bare), results.result_clothoid(bare, rest=True)
    strand, arc, elem, frac = _expected_samples(rod, 4)
    for shape, r in (("fitted", rod), ("rest", rest)):
        (path, head) = export_formats(bare, tmp_path, ["vtp"], shape=shape, per_element=4,
                                      output=tmp_path / f"{shape}.vtp")
        poly = pv.read(path)
        assert np.abs(np.asarray(poly.points) - cl.evaluate(r, strand, arc)[0]).max() <= 1e-12
        q0 = _interpolated(rest, strand, elem, frac)
        assert np.abs(poly.point_data["q0"] - q0).max() <= 1e-13 * np.abs(q0).max()
        np.testing.assert_array_equal(poly.cell_data["n_elements"], rod.n_elements)
        assert str(poly.field_data["model"][0]) == "clothoid" and str(poly.field_data["shape"][0]) == shape
        assert head.name == f"{shape}_head.vtp" and head.is_file()


@pytest.mark.parametrize("suffix, tol", [(".hair", 1e-7), (".obj", 1e-8), (".data", 1e-7)])
def test_polylines_of_the_clothoid(bare, tmp_path, suffix, tol):
    rod, rest = results.result_clothoid(bare), results.result_clothoid(bare, rest=True)
    strand, arc, _, _ = _expected_samples(rod, 8)
    for shape, r in (("rest", rest), ("fitted", rod)):
        if suffix == ".data":
            path = export_path(bare, tmp_path / f"{shape}.data", shape=shape)
        else:
            (path,) = export_formats(bare, tmp_path, [suffix[1:]], shape=shape)
        groom = load_groom(path)
        np.testing.assert_array_equal(groom.counts, rod.n_elements * 8 + 1)
        assert np.abs(groom.points - cl.evaluate(r, strand, arc)[0]).max() <= tol, (shape, path)


def test_cli_invert_clothoid_to_usd_and_export(tmp_path):
    pytest.importorskip("pxr", reason="usd-core is not installed")
    from pxr import Usd

    groom_path, _ = write_example(tmp_path, n_strands=3, seed=2)
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "--model", "clothoid", "--format", "usd", "--stabilize", "none",
                 "--rod-segments", "12", "-o", str(out), "--quiet"]) == EXIT_OK
    assert json.loads((out / "report.json").read_text())["model"] == "clothoid"
    arrays = results.load_arrays(out)
    stage = Usd.Stage.Open(str(out / "groom.usdc"))
    assert stage.GetRootLayer().customLayerData["groomtool"]["model"] == "clothoid"
    prim = stage.GetPrimAtPath("/Groom/Strands")
    # the discrete rest data at the simulator's resolution: 13 vertices per strand
    assert list(prim.GetAttribute("curveVertexCounts").Get()) == [13, 13, 13]
    np.testing.assert_array_equal(np.diff(arrays["rod_offsets"]), 13)
    assert np.abs(np.asarray(prim.GetAttribute("points").Get()) - arrays["rod_points"]).max() <= F32
    got = np.asarray(prim.GetAttribute("groomtool:clothoid_rest_curvatures").Get())
    np.testing.assert_array_equal(got, arrays["clothoid_rest_curvatures"])
    rest = results.result_clothoid(arrays, rest=True)
    rest_points = np.asarray(stage.GetPrimAtPath("/Groom/RestShape").GetAttribute("points").Get())
    assert np.abs(rest_points[0] - rest.root_positions[0]).max() <= F32
    # groom export: every other format of the same result
    assert main(["export", str(out), "--format", "vtp", "--format", "hair", "--format", "obj"]) == EXIT_OK
    for name in ("groom.vtp", "rest_shape.hair", "rest_shape.obj"):
        assert (out / name).is_file(), name


def test_groom_view_of_a_clothoid_result(saved, tmp_path, monkeypatch):
    """The viewer draws from the same fields: a screenshot of the clothoid result is not blank."""
    pytest.importorskip("pyvista", reason="pyvista is not installed")
    import subprocess
    import sys

    probe = ("import pyvista as pv; p = pv.Plotter(off_screen=True, window_size=(64, 64)); "
             "p.add_mesh(pv.Sphere()); img = p.screenshot(); assert img.std() > 0, 'blank render'")
    if subprocess.run([sys.executable, "-c", probe], capture_output=True, timeout=120).returncode != 0:
        pytest.skip("pyvista/vtk cannot render off-screen here")
    from PIL import Image

    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["view", str(saved[0]), "--rest", "--screenshot", str(tmp_path / "v.png"), "--size", "160", "120"]) \
        == EXIT_OK
    with Image.open(tmp_path / "v.png") as im:
        assert im.size == (160, 120) and np.asarray(im.convert("RGB")).std() > 10.0
