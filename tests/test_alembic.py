"""Alembic grooms (groomtool.io.alembic, optional alembic3d): our writer -> PyAlembic -> Unreal's
groom_* attributes and cm -> read back against the source data; other tools' files (transforms,
guides); the clear error without alembic3d; Blender (when a Python with bpy is available) imports
ours and writes one we read and invert."""

import importlib.util
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from groomtool.groom import GroomError
from groomtool.io import load_groom
from groomtool.rods import superhelix as sh
from groomtool.io import fields, results
from test_viz_fields import synthetic_result

HAVE_ABC = importlib.util.find_spec("alembic3d") is not None
needs_abc = pytest.mark.skipif(not HAVE_ABC, reason="alembic3d is not installed (pip install 'groomtool[alembic]')")
BPY = os.environ.get("GROOMTOOL_BPY_PYTHON") or (sys.executable if importlib.util.find_spec("bpy") else None)
needs_bpy = pytest.mark.skipif(BPY is None, reason="Blender's Python module (bpy) is not available")
F32_CM = 2e-6  # float32 round-off of cm coordinates at head scale, in metres


@pytest.fixture(scope="module")
def result():
    return synthetic_result(n_strands=8, seed=7, contacts=False)


def _params(path):
    from alembic3d import Abc, AbcGeom

    top = Abc.IArchive(str(path)).getTop()
    curves = AbcGeom.ICurves(top.children[0].children[0], Abc.WrapExistingFlag.kWrapExisting)
    schema = curves.getSchema()
    arb = schema.getArbGeomParams()
    headers = {arb.getPropertyHeader(i).getName(): arb.getPropertyHeader(i).getMetaData().serialize()
               for i in range(arb.getNumProperties())}
    return schema, arb, headers


@needs_abc
def test_round_trip_against_the_source(result, tmp_path):
    from groomtool.io.alembic import read_alembic, write_alembic

    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    path = write_alembic(result, tmp_path / "groom.abc")
    groom = read_alembic(path, scale=0.01)  # Unreal's convention: cm
    assert np.array_equal(groom.offsets, samples.offsets)
    assert np.abs(groom.points - samples.points).max() <= F32_CM
    rest = groom.metadata["rest_data"]
    want, _ = sh.evaluate(results.result_helix(arrays, rest=True), samples.strand, samples.arc)
    assert np.abs(rest["rest_position"] - want).max() <= F32_CM
    tips = samples.offsets[1:] - 1
    starts = np.setdiff1d(np.arange(len(want)), tips)
    assert np.abs(rest["rest_length"][starts] - np.linalg.norm(want[starts + 1] - want[starts], axis=1)).max() <= 1e-9
    assert np.array_equal(rest["groom_id"], np.arange(8))
    assert load_groom(path, units="cm").n_points == groom.n_points  # through load_groom's hook
    assert sorted(p.name for p in tmp_path.iterdir()) == ["groom.abc"]  # atomic: no temporary left


@needs_abc
def test_unreal_attributes(result, tmp_path):
    from groomtool.io.alembic import write_alembic

    schema, arb, headers = _params(write_alembic(result, tmp_path / "groom.abc"))
    assert "geoScope=con" in headers["groom_guide"] and "int32_t" in headers["groom_guide"]
    assert "geoScope=uni" in headers["groom_id"] and "geoScope=uni" in headers["groom_width"]
    assert "geoScope=vtx" in headers["rest_position"] and "string" in headers["groom_version"]
    from alembic3d import AbcGeom

    width = np.array(AbcGeom.IFloatGeomParam(arb, "groom_width").getExpandedValue().getVals())
    assert np.allclose(width, 2 * result.material.radius * 100, rtol=1e-6)  # cm
    assert list(AbcGeom.IStringGeomParam(arb, "groom_version").getExpandedValue().getVals()) == ["1.0"]
    young = np.array(AbcGeom.IFloatGeomParam(arb, "groomtool_young_modulus").getExpandedValue().getVals())
    assert young.shape == (8,) and np.all(young > 0)
    sample = schema.getValue()
    assert str(sample.getType()) == "kLinear" and str(sample.getBasis()) == "kNoBasis"


@needs_abc
def test_guides_and_transforms(result, tmp_path):
    """Render strands win over guides; a guides-only file reads its guides; Xforms are applied."""
    import imath
    from alembic3d import Abc, AbcGeom

    from groomtool.io.alembic import read_alembic, write_alembic

    both = read_alembic(write_alembic(result, tmp_path / "g.abc", guides=True), scale=0.01)
    assert both.metadata["alembic"]["objects"] == ["/groom/strands"] and not both.metadata["alembic"]["guides"]
    path = tmp_path / "moved.abc"
    archive = Abc.OArchive(str(path))
    xform = AbcGeom.OXform(archive.getTop(), "hair")
    xs = AbcGeom.XformSample()
    xs.setTranslation(imath.V3d(1.0, 2.0, 3.0))
    xform.getSchema().set(xs)
    curves = AbcGeom.OCurves(xform, "guides_only")
    pts = np.array([[0, 0, 0], [0, -1, 0], [0, -2, 0.5], [1, 0, 0], [1, -1, 0]], dtype=np.float32)
    sample = AbcGeom.OCurvesSchemaSample(imath.V3fArrayFromBuffer(pts), imath.IntArrayFromBuffer(
        np.array([3, 2], dtype=np.int32)), AbcGeom.CurveType.kLinear, AbcGeom.CurvePeriodicity.kNonPeriodic)
    curves.getSchema().set(sample)
    guide = AbcGeom.OInt32GeomParam(curves.getSchema().getArbGeomParams(), "groom_guide", False,
                                    AbcGeom.GeometryScope.kConstantScope, 1)
    guide.set(AbcGeom.OInt32GeomParamSample(imath.IntArrayFromBuffer(np.array([1], dtype=np.int32)),
                                            AbcGeom.GeometryScope.kConstantScope))
    del guide, curves, xform, archive
    groom = read_alembic(path, scale=0.01, up="z")
    assert groom.up == "z" and list(groom.counts) == [3, 2] and groom.metadata["alembic"]["guides"]
    assert np.allclose(groom.points, (pts + [1.0, 2.0, 3.0]) * 0.01, atol=1e-8)


@needs_abc
def test_errors(tmp_path, result):
    from groomtool.io.alembic import read_alembic, write_alembic

    bad = tmp_path / "bad.abc"
    bad.write_bytes(b"not an alembic archive")
    with pytest.raises(GroomError, match="bad.abc: cannot open as Alembic"):
        read_alembic(bad)
    from alembic3d import Abc, AbcGeom

    empty = tmp_path / "empty.abc"
    archive = Abc.OArchive(str(empty))
    AbcGeom.OXform(archive.getTop(), "nothing")
    del archive
    with pytest.raises(GroomError, match="empty.abc: no curves"):
        read_alembic(empty)
    with pytest.raises(GroomError, match="end in .abc"):
        write_alembic(result, tmp_path / "groom.usd")


def test_clear_error_without_alembic3d(monkeypatch, tmp_path, result, capsys):
    from groomtool.cli.main import EXIT_USER_ERROR, main
    from groomtool.io.alembic import write_alembic

    monkeypatch.setitem(sys.modules, "alembic3d", None)  # import alembic3d -> ImportError
    with pytest.raises(GroomError, match=r"g.abc: .*pip install 'groomtool\[alembic\]'"):
        write_alembic(result, tmp_path / "g.abc")
    path = tmp_path / "g.abc"
    path.write_bytes(b"x")
    assert main(["info", str(path)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "g.abc: Alembic (.abc) support needs the optional alembic3d package" in err and "pip install" in err


DUMP = textwrap.dedent('''
    import sys
    import bpy
    import numpy as np
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.wm.alembic_import(filepath=sys.argv[1], as_background_job=False) == {"FINISHED"}
    obs = [o for o in bpy.data.objects if o.type == "CURVES"]
    c = obs[0].data
    pos = np.zeros(len(c.points) * 3, dtype=np.float32)
    c.points.foreach_get("position", pos)
    rad = np.zeros(len(c.points), dtype=np.float32)
    c.attributes["radius"].data.foreach_get("value", rad)
    values = {}
    for a in c.attributes:  # ours, if Blender imported them: their values
        if a.name.startswith(("groom", "rest_")) and a.data_type in ("FLOAT", "INT", "FLOAT_VECTOR"):
            key = "vector" if a.data_type == "FLOAT_VECTOR" else "value"
            v = np.zeros(len(a.data) * (3 if key == "vector" else 1), dtype=np.float32)
            a.data.foreach_get(key, v)
            values["attr_" + a.name] = v
    np.savez(sys.argv[2], n_objects=len(obs), position=pos.reshape(-1, 3), radius=rad,
             counts=np.array([len(k.points) for k in c.curves]),
             names=np.array([f"{a.name}:{a.domain}:{a.data_type}" for a in c.attributes]), **values)
''')

WRITE = textwrap.dedent('''
    import sys
    import bpy
    import numpy as np
    bpy.ops.wm.read_factory_settings(use_empty=True)
    d = np.load(sys.argv[2])
    curves = bpy.data.hair_curves.new("hair")
    curves.add_curves([int(n) for n in d["counts"]])
    curves.points.foreach_set("position", d["points"].astype(np.float32).ravel())
    ob = bpy.data.objects.new("hair", curves)
    bpy.context.scene.collection.objects.link(ob)
    assert bpy.ops.wm.alembic_export(filepath=sys.argv[1], as_background_job=False) == {"FINISHED"}
''')


@needs_abc
@needs_bpy
def test_blender_imports_ours_as_hair_curves(result, tmp_path):
    from groomtool.io.alembic import write_alembic

    samples = fields.sample(results.load_arrays(result))
    path = write_alembic(result, tmp_path / "groom.abc")
    (tmp_path / "dump.py").write_text(DUMP)
    run = subprocess.run([BPY, str(tmp_path / "dump.py"), str(path), str(tmp_path / "b.npz")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    got = np.load(tmp_path / "b.npz")
    assert int(got["n_objects"]) == 1 and np.array_equal(got["counts"], np.diff(samples.offsets))
    cm = samples.points * 100
    want = np.stack([cm[:, 0], -cm[:, 2], cm[:, 1]], axis=1)  # Blender turns Alembic's Y-up into Z-up
    assert np.abs(got["position"] - want).max() <= 1e-4
    assert np.allclose(got["radius"], result.material.radius * 100, rtol=1e-6)  # groom_width / 2, from .widths
    # Our groom_* / rest_* / groomtool_* arbGeomParams: those Blender imports must hold our values.  Blender
    # 5.0.1 imports none (its curves reader, abc_reader_curves.cc, reads positions, counts, basis, weights and
    # .widths only, whatever the scope or type: docs/formats.md); should a later Blender import them, this
    # checks them, and the second assertion says that docs/formats.md needs the news.
    from alembic3d import AbcGeom

    _, arb, headers = _params(path)
    names = {n.split(":")[0] for n in got["names"].tolist()}
    imported = sorted(set(headers) & set(names))
    for name in imported:
        pod = headers[name]
        kind = AbcGeom.IV3fGeomParam if "podExtent=3" in pod else (
            AbcGeom.IInt32GeomParam if "int32_t" in pod else AbcGeom.IFloatGeomParam)
        want = np.array(kind(arb, name).getExpandedValue().getVals(), dtype=np.float64).reshape(-1)
        if "podExtent=3" in pod:
            want = np.stack([want[0::3], -want[2::3], want[1::3]], axis=1).reshape(-1)  # Y-up into Z-up
        assert np.allclose(got[f"attr_{name}"], want, rtol=1e-6, atol=1e-6), name
    assert imported == [], f"Blender now imports {imported}: update docs/formats.md ('Tried with Blender')"
    assert set(names) == {"position", "radius", "curve_type"}, names


@needs_abc
@needs_bpy
def test_blender_written_groom_is_read_and_inverted(tmp_path):
    from groomtool.cli.main import EXIT_OK, main
    from groomtool.examples import example_groom

    groom, _ = example_groom(n_strands=6, seed=4)  # y-up, metres
    z_up = np.stack([groom.points[:, 0], -groom.points[:, 2], groom.points[:, 1]], axis=1)  # as Blender holds it
    np.savez(tmp_path / "pts.npz", points=z_up, counts=groom.counts)
    (tmp_path / "write.py").write_text(WRITE)
    run = subprocess.run([BPY, str(tmp_path / "write.py"), str(tmp_path / "blender.abc"), str(tmp_path / "pts.npz")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    read = load_groom(tmp_path / "blender.abc")  # Blender writes Y-up metres
    assert np.array_equal(read.counts, groom.counts)
    assert np.abs(read.points - groom.points).max() <= 1e-6
    assert main(["invert", str(tmp_path / "blender.abc"), "-q", "-o", str(tmp_path / "out")]) == EXIT_OK
    assert (tmp_path / "out" / "rest.npz").is_file()


@needs_abc
def test_groom_export_format_abc(result, tmp_path, capsys):
    from groomtool.cli.main import EXIT_OK, main

    result.save(tmp_path, formats=("npz",))
    assert main(["export", str(tmp_path), "--format", "abc"]) == EXIT_OK
    assert "groom.abc" in capsys.readouterr().out
    groom = load_groom(tmp_path / "groom.abc", units="cm")
    assert np.array_equal(groom.offsets, fields.sample(results.load_arrays(result)).offsets)
    assert main(["export", str(tmp_path), "--format", "abc", "-o", str(tmp_path / "x.usd")]) != EXIT_OK


@needs_abc
def test_invert_format_abc(tmp_path):
    from groomtool.cli.main import EXIT_OK, main
    from groomtool.examples import write_example

    groom_path, _ = write_example(tmp_path, n_strands=4, seed=5)
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "--format", "npz", "--format", "abc", "-q", "-o", str(out)]) == EXIT_OK
    assert load_groom(out / "groom.abc", units="cm").n_strands == 4


@needs_abc
def test_rerun_without_abc_drops_the_stale_groom_abc(tmp_path):
    """groom.abc is an output of the run (io/outset.py OWNED): a later run into the same directory without
    --format abc drops it instead of carrying the earlier run's Alembic beside the new rest.npz."""
    from groomtool.cli.main import EXIT_OK, main
    from groomtool.examples import write_example

    groom_path, _ = write_example(tmp_path, n_strands=3, seed=2)
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "--format", "npz", "--format", "abc", "-q", "-o", str(out)]) == EXIT_OK
    assert (out / "groom.abc").is_file()
    (out / "notes.txt").write_text("mine")
    assert main(["invert", str(groom_path), "-q", "-o", str(out)]) == EXIT_OK
    assert not (out / "groom.abc").exists() and (out / "notes.txt").read_text() == "mine"
