"""USD: our writer -> pxr -> the documented prims and primvars -> read back within float32 round-off;
plain BasisCurves written by other tools (units, up axis, transforms); the load_groom hook."""

import numpy as np
import pytest

pxr = pytest.importorskip("pxr", reason="usd-core is not installed")
from pxr import Gf, Sdf, Usd, UsdGeom, Vt  # noqa: E402

from groomtool.groom import GroomError  # noqa: E402
from groomtool.io import load_groom  # noqa: E402
from groomtool.io.usd import read_usd, write_usd  # noqa: E402
from groomtool.rods.der import der_rest_data  # noqa: E402
from groomtool.io import fields, results  # noqa: E402
from test_viz_fields import synthetic_result  # noqa: E402

# (name, interpolation, type) as listed in docs/usd.md, on /Groom/Strands: all float (DCCs drop doubles)
STRAND_PRIMVARS = [
    ("groom:young_modulus", "uniform", "float[]"), ("groom:shear_modulus", "uniform", "float[]"),
    ("groom:radius", "uniform", "float[]"), ("groom:density", "uniform", "float[]"),
    ("groom:friction", "uniform", "float[]"), ("groom:fit_max_error", "uniform", "float[]"),
    ("groom:stiffness_ratio", "uniform", "float[]"),
    ("groom:der_rest_lengths", "vertex", "float[]"), ("groom:der_rest_kappa", "vertex", "float2[]"),
    ("groom:der_rest_twist", "vertex", "float[]"), ("groom:der_frames", "vertex", "quatf[]"),
    ("rest_position", "vertex", "point3f[]"), ("rest_length", "vertex", "float[]"),
    ("rest_rotation", "vertex", "quatf[]"), ("rest_bend_rotation", "vertex", "quatf[]"),
    ("orient", "vertex", "quatf[]"),
]
# (name, type) of the exact data, plain attributes of /Groom/Strands
STRAND_EXACT = [
    ("groomtool:young_modulus", "double"), ("groomtool:shear_modulus", "double"), ("groomtool:radius", "double"),
    ("groomtool:density", "double"), ("groomtool:friction", "double"), ("groomtool:gravity", "double3"),
    ("groomtool:strand_offsets", "int[]"), ("groomtool:element_lengths", "double[]"),
    ("groomtool:curvatures", "double3[]"), ("groomtool:rest_curvatures", "double3[]"),
    ("groomtool:root_positions", "double3[]"), ("groomtool:root_frames", "double[]"),
    ("groomtool:fit_max_error", "double[]"), ("groomtool:stiffness_ratio", "double[]"),
    ("physics:restShapePoints", "point3f[]"), ("physics:restNormals", "normal3f[]"),
]
TOL = 1e-6


def float32_close(got, want):
    """Equal to ``want`` stored as float32: |got - want| <= 1e-6 max(1, |want|)."""
    want = np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape
    assert np.all(np.abs(got - want) <= TOL * np.maximum(1.0, np.abs(want)))


@pytest.fixture(scope="module")
def result():
    return synthetic_result()


@pytest.fixture(scope="module")
def der_result():
    """A result carrying the discrete export arrays (rods.der on the groomed polyline)."""
    r = synthetic_result(seed=2)
    r.extra_arrays = der_rest_data(r.groom.points, r.groom.offsets, r.material, r.gravity)
    return r


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_stage_layout_and_primvars(result, tmp_path, suffix):
    path = write_usd(result, tmp_path / f"groom{suffix}")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Groom")
    curves = [p for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    rendered = [p for p in curves if UsdGeom.Imageable(p).ComputePurpose() != UsdGeom.Tokens.guide]
    assert [str(p.GetPath()) for p in rendered] == ["/Groom/Strands"]  # one groom, one curves prim
    assert [str(p.GetPath()) for p in curves] == ["/Groom/Strands", "/Groom/RestShape"]
    strands = UsdGeom.BasisCurves(rendered[0])
    assert strands.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    assert list(strands.GetCurveVertexCountsAttr().Get()) == list(np.diff(fields.sample(
        results.load_arrays(result)).offsets))
    assert strands.GetWidthsAttr().Get()[0] == pytest.approx(2 * result.material.radius)
    assert strands.GetWidthsInterpolation() == UsdGeom.Tokens.constant
    pv = UsdGeom.PrimvarsAPI(rendered[0])
    for name, interpolation, type_name in STRAND_PRIMVARS:
        primvar = pv.GetPrimvar(name)
        assert primvar.IsDefined(), name
        assert primvar.GetInterpolation() == interpolation, name
        assert str(primvar.GetTypeName()) == type_name, name
        assert primvar.ValueMightBeTimeVarying() is False
    prim = rendered[0]
    for name, type_name in STRAND_EXACT:
        attr = prim.GetAttribute(name)
        assert attr and attr.HasAuthoredValue(), name
        assert str(attr.GetTypeName()) == type_name, name
    for p in stage.Traverse():  # what Blender drops (double) or reads as zeros (9-value elements)
        for primvar in UsdGeom.PrimvarsAPI(p).GetPrimvars():
            assert "double" not in str(primvar.GetTypeName()), primvar.GetName()
            assert primvar.GetElementSize() == 1, primvar.GetName()
    assert pv.GetPrimvar("groom:der_rest_kappa").GetAttr().GetCustomDataByKey("groomtool:layout") == "interior"
    assert stage.GetPrimAtPath("/Groom/Head").IsA(UsdGeom.Mesh)
    assert stage.GetPrimAtPath("/Groom/Contacts").IsA(UsdGeom.Points)
    assert UsdGeom.Imageable(stage.GetPrimAtPath("/Groom/RestShape")).ComputePurpose() == UsdGeom.Tokens.guide


def test_round_trip_strands_and_rest_data(result, tmp_path):
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    groom = read_usd(write_usd(result, tmp_path / "groom.usda"))
    assert groom.up == "y" and groom.n_strands == result.helix.n_strands
    assert np.array_equal(groom.offsets, samples.offsets)
    assert np.abs(groom.points - samples.points).max() <= TOL
    rest = groom.metadata["rest_data"]
    for key in ("element_lengths", "curvatures", "rest_curvatures", "root_positions", "root_frames",
                "fit_max_error", "stiffness_ratio", "gravity"):
        assert np.array_equal(rest[key], arrays[key]), key  # stored as double: exact
    assert np.array_equal(rest["strand_offsets"], arrays["strand_offsets"])
    for key in ("young_modulus", "shear_modulus", "radius", "density", "friction"):
        assert rest[key] == arrays[key]
    der = fields.der_rest_geometry(arrays, samples.points, samples.offsets, samples.arc)
    for key, value in der.items():
        float32_close(rest[key], value)
    float32_close(rest["rest_points"], samples.rest_points)
    assert np.array_equal(rest["rest_offsets"], samples.offsets)
    float32_close(rest["contact_points"], arrays["contact_points"])
    assert np.array_equal(rest["contact_forces"], arrays["contact_forces"])
    assert np.array_equal(rest["contact_frames"], arrays["contact_frames"])
    assert np.array_equal(rest["contact_strand_b"], arrays["contact_strand_b"])
    float32_close(rest["head_vertices"], arrays["head_vertices"])
    assert np.array_equal(rest["head_faces"], arrays["head_faces"])


def test_round_trip_of_the_discrete_export(der_result, tmp_path):
    """With rod_points and der_* arrays in the result, the strands are the rod polyline and every
    per-edge / per-interior-vertex array comes back unpadded."""
    extra = der_result.extra_arrays
    groom = read_usd(write_usd(der_result, tmp_path / "der.usdc"))
    assert np.array_equal(groom.offsets, extra["rod_offsets"])
    assert np.abs(groom.points - extra["rod_points"]).max() <= TOL
    rest = groom.metadata["rest_data"]
    for key in ("der_rest_lengths", "der_rest_kappa", "der_rest_twist", "der_voronoi_lengths", "der_frames",
                "der_tension", "der_vertex_mass", "node_forces"):
        float32_close(rest[key], extra[key])
    assert "der_residual" not in rest
    stage = Usd.Stage.Open(str(tmp_path / "der.usdc"))
    data = stage.GetRootLayer().customLayerData["groomtool"]
    assert data["discrete_rest_data"] == "discrete export"


def test_z_up_result(tmp_path):
    r = synthetic_result(up="z", contacts=False)
    path = write_usd(r, tmp_path / "z.usda")
    assert UsdGeom.GetStageUpAxis(Usd.Stage.Open(str(path))) == UsdGeom.Tokens.z
    groom = read_usd(path, up="y")  # the file's upAxis wins
    assert groom.up == "z"
    assert not Usd.Stage.Open(str(path)).GetPrimAtPath("/Groom/Contacts")


def plain_curves_stage(path, strands_cm, up=UsdGeom.Tokens.z, meters=0.01, translate=None, extra_prims=False):
    """A BasisCurves file as another tool writes it: no groomtool data."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    if meters is not None:
        UsdGeom.SetStageMetersPerUnit(stage, meters)
    xform = UsdGeom.Xform.Define(stage, "/hair")
    if translate is not None:
        xform.AddTranslateOp().Set(Gf.Vec3d(*translate))
    if extra_prims:
        UsdGeom.Sphere.Define(stage, "/hair/aaa_sphere")
    curves = UsdGeom.BasisCurves.Define(stage, "/hair/strands")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.concatenate(strands_cm).astype(np.float32)))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([len(s) for s in strands_cm]))
    curves.CreateWidthsAttr(Vt.FloatArray([0.008]))
    stage.GetRootLayer().Save()
    return stage


def test_plain_basis_curves_in_centimetres_z_up(tmp_path):
    rng = np.random.default_rng(0)
    strands = [np.cumsum(rng.normal(size=(n, 3)), axis=0) + [0, 0, 170] for n in (5, 9, 3)]
    path = tmp_path / "plain.usda"
    plain_curves_stage(path, strands, extra_prims=True)
    groom = load_groom(path)  # through io.load_groom's hook, --units m ignored: metersPerUnit wins
    assert groom.up == "z"
    assert list(groom.counts) == [5, 9, 3]
    want = np.concatenate(strands).astype(np.float32).astype(np.float64) * 0.01
    assert np.abs(groom.points - want).max() <= TOL
    assert groom.metadata["usd"]["meters_per_unit"] == 0.01
    assert groom.metadata["rest_data"] == {}


def test_plain_curves_transform_and_unauthored_units(tmp_path):
    strands = [np.array([[0.0, 0, 0], [0, -1, 0], [0, -2, 0.5]])]
    path = tmp_path / "moved.usdc"
    plain_curves_stage(path, strands, up=UsdGeom.Tokens.y, meters=None, translate=(1.0, 2.0, 3.0))
    assert not UsdGeom.StageHasAuthoredMetersPerUnit(Usd.Stage.Open(str(path)))
    groom = read_usd(path, scale=0.01, up="z")  # scale applies: metersPerUnit is not authored
    assert groom.up == "y"
    assert np.allclose(groom.points, (strands[0] + [1.0, 2.0, 3.0]) * 0.01)


def test_all_curves_and_prim_selection(tmp_path):
    path = tmp_path / "two.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    for i, name in enumerate(("a", "b")):
        c = UsdGeom.BasisCurves.Define(stage, f"/{name}")
        c.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(i, 0, 0), Gf.Vec3f(i, -1, 0)]))
        c.CreateCurveVertexCountsAttr(Vt.IntArray([2]))
    stage.GetRootLayer().Save()
    assert read_usd(path).n_strands == 1
    both = read_usd(path, all_curves=True)
    assert both.n_strands == 2 and both.metadata["usd"]["prims"] == ["/a", "/b"]
    assert read_usd(path, prim="/b").points[0, 0] == 1.0
    with pytest.raises(GroomError, match="no BasisCurves prim at /c"):
        read_usd(path, prim="/c")


def test_errors(tmp_path):
    empty = tmp_path / "empty.usda"
    stage = Usd.Stage.CreateNew(str(empty))
    UsdGeom.Sphere.Define(stage, "/ball")
    stage.GetRootLayer().Save()
    with pytest.raises(GroomError, match="no BasisCurves prim .*Sphere"):
        read_usd(empty)
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\n(\n this is not usd\n")
    with pytest.raises(GroomError, match="cannot open as USD"):
        read_usd(bad)
    wrong = tmp_path / "count.usda"
    plain_curves_stage(wrong, [np.zeros((3, 3)) + np.arange(3)[:, None]])
    s = Usd.Stage.Open(str(wrong))
    UsdGeom.BasisCurves(s.GetPrimAtPath("/hair/strands")).GetCurveVertexCountsAttr().Set(Vt.IntArray([4]))
    s.GetRootLayer().Save()
    with pytest.raises(GroomError, match="add up to 4 but there are 3 points"):
        read_usd(wrong)
    with pytest.raises(GroomError, match="end in .usda"):
        write_usd(synthetic_result(contacts=False), tmp_path / "groom.abc")


def test_usdz_package(result, tmp_path):
    path = write_usd(result, tmp_path / "groom.usdz")
    groom = read_usd(path)
    assert groom.n_strands == result.helix.n_strands
    assert sorted(p.name for p in tmp_path.iterdir()) == ["groom.usdz"]  # no temporary left behind


def test_write_from_an_output_directory(result, tmp_path):
    result.save(tmp_path, formats=("npz",))
    a = read_usd(write_usd(tmp_path, tmp_path / "from_dir.usda"))
    b = read_usd(write_usd(result, tmp_path / "from_result.usda"))
    assert np.array_equal(a.points, b.points)
    assert np.array_equal(a.metadata["rest_data"]["der_rest_kappa"], b.metadata["rest_data"]["der_rest_kappa"])


def test_usd_validators_pass(der_result, tmp_path):
    """usd-core's own validators (stage metadata, attribute types, encapsulation, ...) find nothing."""
    UsdValidation = pytest.importorskip("pxr.UsdValidation", reason="this usd-core has no UsdValidation")
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    for suffix in (".usda", ".usdz"):
        stage = Usd.Stage.Open(str(write_usd(der_result, tmp_path / f"groom{suffix}")))
        errors = context.Validate(stage)
        assert not errors, [e.GetMessage() for e in errors]
