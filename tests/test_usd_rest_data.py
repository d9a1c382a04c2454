"""USD rest data under the names simulators and DCCs read (docs/usd.md, "Rest data for consumers"):
checked against the geometry of rest.npz's helices, not against the writer's own helpers; per-strand
material; the signed up axis; usd-core's validators on every variant we write."""

import numpy as np
import pytest

pytest.importorskip("pxr", reason="usd-core is not installed")
from pxr import Usd, UsdGeom  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from groomtool.io.usd import read_usd, write_usd  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402
from groomtool.rods.der import der_rest_data  # noqa: E402
from groomtool.io import fields, results  # noqa: E402
from test_viz_fields import synthetic_result  # noqa: E402

F32 = 2e-6  # float32 round-off on unit vectors / metre-scale values


def _stage(source, tmp_path, name="g.usdc"):
    return Usd.Stage.Open(str(write_usd(source, tmp_path / name)))  # callers hold it


def _get(prim, name):
    attr = prim.GetAttribute(name)
    assert attr and attr.HasAuthoredValue(), name
    return np.asarray(attr.Get(), dtype=np.float64)


def _rot(q):
    return Rotation.from_quat(q)  # scalar last, USD's quatf memory order


def _edges(points, offsets):
    """Unit directions of the edge leaving each non-tip vertex, and those vertex indices."""
    tips = offsets[1:] - 1
    starts = np.setdiff1d(np.arange(len(points)), tips)
    d = points[starts + 1] - points[starts]
    return d / np.linalg.norm(d, axis=1)[:, None], starts, tips


@pytest.fixture(scope="module")
def result():
    return synthetic_result(n_strands=8, seed=3)


def test_rest_attributes_match_the_rest_helices(result, tmp_path):
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    stage = _stage(result, tmp_path)  # held: prims do not keep their stage alive
    prim = stage.GetPrimAtPath("/Groom/Strands")
    points = _get(prim, "points")
    offsets = samples.offsets
    # rest positions: the rest helices at the same arc lengths as the groomed vertices
    want, _ = sh.evaluate(results.result_helix(arrays, rest=True), samples.strand, samples.arc)
    for name in ("physics:restShapePoints", "primvars:rest_position"):
        got = _get(prim, name)
        assert got.shape == points.shape
        assert np.abs(got - want).max() <= F32, name
    assert np.abs(want - points).max() > 1e-3  # the rest shape is not the groomed one
    rest_dir, starts, tips = _edges(want, offsets)
    # rest rotation: local Z along the rest edge leaving the vertex, local X the rest normal
    rot = _get(prim, "primvars:rest_rotation")
    assert np.abs(np.linalg.norm(rot, axis=1) - 1).max() <= F32
    z = _rot(rot).apply([0.0, 0.0, 1.0])
    assert np.abs(z[starts] - rest_dir).max() <= 1e-5
    assert np.abs(rot[tips] - rot[tips - 1]).max() == 0  # the tip repeats its last edge
    normals = _get(prim, "physics:restNormals")
    assert np.abs(np.linalg.norm(normals, axis=1) - 1).max() <= F32
    assert np.abs(np.einsum("ij,ij->i", normals[starts], rest_dir)).max() <= 1e-5
    assert np.abs(_rot(rot).apply([1.0, 0.0, 0.0]) - normals).max() <= 1e-5
    # bend rotation: rest_rotation[i] * bend[i] = rest_rotation[i + 1] (Blender's Hair Dynamics)
    bend = _get(prim, "primvars:rest_bend_rotation")
    inner = np.setdiff1d(starts, tips - 1)
    composed = (_rot(rot[inner]) * _rot(bend[inner])).as_matrix()
    assert np.abs(composed - _rot(rot[inner + 1]).as_matrix()).max() <= 1e-5
    assert np.linalg.norm(bend[inner, :3], axis=1).max() > 1e-3  # the rest shape bends
    assert np.all(bend[tips] == [0, 0, 0, 1])
    # rest length: the rest edge leaving the vertex, 0 at the tip; adds up to the chord length
    length = _get(prim, "primvars:rest_length")
    assert np.abs(length[starts] - np.linalg.norm(want[starts + 1] - want[starts], axis=1)).max() <= 1e-8
    assert np.all(length[tips] == 0)
    # orient: the groomed frame, local Z along the groomed edge
    orient = _get(prim, "primvars:orient")
    groomed_dir, _, _ = _edges(points, offsets)
    assert np.abs(_rot(orient).apply([0.0, 0.0, 1.0])[starts] - groomed_dir).max() <= 1e-5
    # the rest-shape guide prim: same points (vertex for vertex), with its own orient
    rest_prim = prim.GetStage().GetPrimAtPath("/Groom/RestShape")
    assert np.abs(_get(rest_prim, "points") - want).max() <= F32
    assert np.abs(_get(rest_prim, "primvars:orient") - rot).max() == 0


def test_frames_are_quaternions_that_read_back_as_matrices(result, tmp_path):
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    path = write_usd(result, tmp_path / "q.usda")
    stage = Usd.Stage.Open(str(path))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Groom/Strands"))
    q = np.asarray(pv.GetPrimvar("groom:der_frames").Get(), dtype=np.float64)
    assert q.shape == (len(samples.points), 4) and np.all(np.linalg.norm(q, axis=1) > 0.99)  # no zeros
    want = fields.der_rest_geometry(arrays, samples.points, samples.offsets, samples.arc)["der_frames"]
    got = read_usd(path).metadata["rest_data"]["der_frames"]
    assert got.shape == want.shape and np.abs(got - want).max() <= 1e-6


def test_discrete_export_rest_lengths_and_rest_shape_topology(tmp_path):
    r = synthetic_result(n_strands=8, seed=2)
    r.extra_arrays = der_rest_data(r.groom.points, r.groom.offsets, r.material, r.gravity)
    stage = _stage(r, tmp_path)
    prim = stage.GetPrimAtPath("/Groom/Strands")
    offsets = r.extra_arrays["rod_offsets"]
    length = _get(prim, "primvars:rest_length")
    starts = np.setdiff1d(np.arange(offsets[-1]), offsets[1:] - 1)
    assert np.abs(length[starts] - r.extra_arrays["der_rest_lengths"]).max() <= 1e-9
    rest = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Groom/RestShape"))
    assert list(rest.GetCurveVertexCountsAttr().Get()) == list(np.diff(offsets))  # same points as Strands
    orient = _get(prim, "primvars:orient")
    d = r.extra_arrays["cosserat_directors"] if "cosserat_directors" in r.extra_arrays else \
        r.extra_arrays["der_frames"]
    assert np.abs(_rot(orient[starts]).as_matrix() - np.transpose(d, (0, 2, 1))).max() <= 1e-5


def test_per_strand_material_primvars(tmp_path):
    r = synthetic_result(n_strands=5, seed=4, contacts=False)
    rng = np.random.default_rng(0)
    factor = rng.uniform(0.5, 2.0, 5)
    r.extra_arrays = {"stiffness_factor": factor, "strand_young_modulus": 3e9 * factor,
                      "strand_shear_modulus": 1e9 * factor}
    path = write_usd(r, tmp_path / "m.usdc")
    stage = Usd.Stage.Open(str(path))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Groom/Strands"))
    for name, want in (("young_modulus", 3e9 * factor), ("shear_modulus", 1e9 * factor),
                       ("stiffness_factor", factor)):
        primvar = pv.GetPrimvar("groom:" + name)
        assert str(primvar.GetTypeName()) == "float[]" and primvar.GetInterpolation() == "uniform"
        assert np.array_equal(np.asarray(primvar.Get()), want.astype(np.float32)), name
    rest = read_usd(path).metadata["rest_data"]
    for key in ("stiffness_factor", "strand_young_modulus", "strand_shear_modulus"):
        assert np.array_equal(rest[key], r.extra_arrays[key]), key  # exact
    assert rest["young_modulus"] == r.material.young_modulus  # the scalar stays a scalar
    arrays = {k: v for k, v in results.load_arrays(synthetic_result(n_strands=5, seed=4, contacts=False)).items()
              if k not in ("stiffness_factor", "strand_young_modulus", "strand_shear_modulus")}
    plain = write_usd(arrays, tmp_path / "p.usdc")  # a result without per-strand material: the scalar
    stage = Usd.Stage.Open(str(plain))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Groom/Strands"))
    assert np.all(np.asarray(pv.GetPrimvar("groom:young_modulus").Get()) == np.float32(r.material.young_modulus))
    assert not pv.GetPrimvar("groom:stiffness_factor").IsDefined()


@pytest.mark.parametrize("up, gravity, axis", [("-y", (0, 9.81, 0), "Y"), ("x", (-9.81, 0, 0), "Y"),
                                               ("-z", (0, 0, 9.81), "Z")])
def test_signed_up_axis(result, tmp_path, up, gravity, axis):
    arrays = dict(results.load_arrays(result))
    arrays["gravity"] = np.array(gravity, dtype=np.float64)
    path = write_usd(arrays, tmp_path / "up.usda")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == axis  # USD knows only Y and Z
    assert stage.GetRootLayer().customLayerData["groomtool"]["up"] == up
    groom = read_usd(path)
    assert groom.up == up
    assert np.array_equal(groom.gravity(9.81), arrays["gravity"])


def _validation_errors(stage):
    UsdValidation = pytest.importorskip("pxr.UsdValidation", reason="this usd-core has no UsdValidation")
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [e.GetMessage() for e in context.Validate(stage)]


@pytest.mark.parametrize("variant", ["helix", "discrete", "material", "z_up_no_contacts"])
def test_validators_pass_on_every_variant(tmp_path, variant):
    """usd-core 26 replaced the Python ComplianceChecker (usdchecker) by UsdValidation: all its
    validators find nothing on each kind of file we write."""
    r = synthetic_result(n_strands=8, seed=5, up="z" if variant == "z_up_no_contacts" else "y",
                         contacts=variant != "z_up_no_contacts")
    if variant == "discrete":
        r.extra_arrays = der_rest_data(r.groom.points, r.groom.offsets, r.material, r.gravity)
    if variant == "material":
        r.extra_arrays = {"stiffness_factor": np.linspace(0.5, 2, 8)}
    for suffix in (".usda", ".usdc", ".usdz"):
        stage = Usd.Stage.Open(str(write_usd(r, tmp_path / f"{variant}{suffix}")))
        assert _validation_errors(stage) == [], suffix


def test_validators_can_fail(tmp_path):
    """The check above is not vacuous: a stage without metersPerUnit/upAxis is reported."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "bare.usda"))
    UsdGeom.BasisCurves.Define(stage, "/c")
    assert _validation_errors(stage)
