"""A real client: Blender imports our USD as a hair Curves object with every documented rest
attribute non-zero and equal to rest.npz (through its helices) to float precision.

Needs Blender's Python module: ``import bpy`` here, or a Python that has it in
``GROOMTOOL_BPY_PYTHON`` (bpy wheels are large and pin their own numpy, so a separate venv is
the practical way: ``python -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install bpy``).  Skipped
otherwise.  Result recorded in docs/usd.md.
"""

import importlib.util
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("pxr", reason="usd-core is not installed")
from scipy.spatial.transform import Rotation  # noqa: E402

from groomtool.io.usd import write_usd  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402
from groomtool.io import fields, results  # noqa: E402
from test_viz_fields import synthetic_result  # noqa: E402

PYTHON = os.environ.get("GROOMTOOL_BPY_PYTHON") or (sys.executable if importlib.util.find_spec("bpy") else None)
pytestmark = pytest.mark.skipif(PYTHON is None, reason="Blender's Python module (bpy) is not available")

DUMP = textwrap.dedent('''
    import sys
    import bpy
    import numpy as np
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.wm.usd_import(filepath=sys.argv[1]) == {"FINISHED"}
    ob = next(o for o in bpy.data.objects if o.type == "CURVES")
    c = ob.data
    out = {"version": np.array(bpy.app.version_string), "counts": np.array([len(k.points) for k in c.curves])}
    width = {"FLOAT": 1, "FLOAT_VECTOR": 3, "QUATERNION": 4, "FLOAT2": 2, "INT": 1}
    for a in c.attributes:
        if a.data_type in width:
            k = width[a.data_type]
            arr = np.zeros(len(a.data) * k, dtype=np.float32)
            key = {"FLOAT_VECTOR": "vector", "FLOAT2": "vector"}.get(a.data_type, "value")
            a.data.foreach_get(key, arr)
            out[a.name] = arr.reshape(-1, k) if k > 1 else arr
            out[a.name + ".domain"] = np.array(a.domain)
    np.savez(sys.argv[2], **out)
''')


def blender_attributes(usd_path, tmp_path) -> dict:
    """The curves' attributes as Blender imports ``usd_path`` (DUMP run by Blender's Python)."""
    script = tmp_path / "dump.py"
    script.write_text(DUMP)
    run = subprocess.run([PYTHON, str(script), str(usd_path), str(tmp_path / "blender.npz")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return dict(np.load(tmp_path / "blender.npz"))


def test_blender_imports_rest_attributes(tmp_path):
    result = synthetic_result(n_strands=8, seed=6)
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    got = blender_attributes(write_usd(result, tmp_path / "groom.usdc"), tmp_path)
    print("Blender", got["version"])
    assert np.array_equal(got["counts"], np.diff(samples.offsets))
    assert np.abs(got["position"] - samples.points).max() <= 2e-6
    # rest position: the rest helices at the vertices' arc lengths
    want, _ = sh.evaluate(results.result_helix(arrays, rest=True), samples.strand, samples.arc)
    assert np.abs(got["rest_position"] - want).max() <= 2e-6
    tips = samples.offsets[1:] - 1
    starts = np.setdiff1d(np.arange(len(want)), tips)
    edge = want[starts + 1] - want[starts]
    assert np.abs(got["rest_length"][starts] - np.linalg.norm(edge, axis=1)).max() <= 1e-8
    # Blender's quaternions are (w, x, y, z); local Z of the rest rotation along the rest edge
    for name in ("rest_rotation", "rest_bend_rotation", "orient", "groom:der_frames"):
        q = got[name]
        assert q.shape == (len(want), 4) and str(got[name + ".domain"]) == "POINT", name
        assert np.abs(np.linalg.norm(q, axis=1) - 1).max() <= 1e-5, name  # no zeros
    rot = Rotation.from_quat(got["rest_rotation"][:, [1, 2, 3, 0]])
    z = rot.apply([0.0, 0.0, 1.0])[starts]
    assert np.abs(z - edge / np.linalg.norm(edge, axis=1)[:, None]).max() <= 1e-5
    bend = got["rest_bend_rotation"]
    assert np.linalg.norm(bend[:, 1:], axis=1).max() > 1e-3  # the rest shape bends: not all identity
    # material per curve
    for key, want_value in (("groom:young_modulus", arrays["strand_young_modulus"] if "strand_young_modulus" in
                             arrays else np.full(8, float(arrays["young_modulus"]))),
                            ("groom:density", np.full(8, float(arrays["density"])))):
        assert str(got[key + ".domain"]) == "CURVE"
        assert np.array_equal(got[key], np.asarray(want_value, dtype=np.float32)), key


def test_blender_imports_a_clothoid_result(tmp_path):
    """A Super Space Clothoid result (issue 20): the clothoid samples, their rest positions and the per-vertex
    Darboux vectors (groom:darboux, groom:rest_darboux) arrive as point attributes."""
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom
    from groomtool.rods import clothoid as cl

    groom, _ = example_groom(n_strands=3, seed=4)
    result = invert_groom(groom, None, InversionParams(model="clothoid", stabilize="none", discrete_rest_data=False))
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    got = blender_attributes(write_usd(result, tmp_path / "clothoid.usdc"), tmp_path)
    rod, rest = results.result_clothoid(arrays), results.result_clothoid(arrays, rest=True)
    assert np.array_equal(got["counts"], rod.n_elements * 8 + 1)
    assert np.abs(got["position"] - cl.evaluate(rod, samples.strand, samples.arc)[0]).max() <= 2e-6
    assert np.abs(got["rest_position"] - cl.evaluate(rest, samples.strand, samples.arc)[0]).max() <= 2e-6
    for name, r in (("groom:darboux", rod), ("groom:rest_darboux", rest)):
        assert str(got[name + ".domain"]) == "POINT", name
        elem, t = cl.locate(r, samples.strand, samples.arc)
        u = (t / r.lengths[samples.strand, elem])[:, None]
        want = (1 - u) * r.curvatures[samples.strand, elem] + u * r.curvatures[samples.strand, elem + 1]
        assert np.abs(got[name] - want).max() <= 1e-6 * np.abs(want).max(), name
