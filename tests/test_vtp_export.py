"""VTP: the strands as polylines with the documented point, cell and field data."""

import numpy as np
import pytest

pv = pytest.importorskip("pyvista", reason="pyvista is not installed")

from groomtool.groom import GroomError  # noqa: E402
from groomtool.io.vtp import lines_connectivity, write_vtp  # noqa: E402
from groomtool.io import fields, results  # noqa: E402
from test_viz_fields import synthetic_result  # noqa: E402

POINT_ARRAYS = {  # name: components (docs/outputs.md, VTP point data)
    "strand_id": 1, "arc_length": 1, "curvature": 1, "rest_curvature": 1, "twist": 1, "rest_twist": 1,
    "curvature_change": 1, "q": 3, "q0": 3, "contact_force": 3, "contact_force_magnitude": 1,
    "stiffness_ratio": 1, "stability_margin": 1, "fit_error": 1, "rest_displacement": 3,
}
CELL_ARRAYS = ("strand_id", "length", "n_elements", "fit_error", "stiffness_ratio", "stability_margin",
               "max_curvature_change", "contacts", "contact_load")


@pytest.fixture(scope="module")
def result():
    return synthetic_result()


def test_vtp_opens_with_the_arrays(result, tmp_path):
    path = write_vtp(result, tmp_path / "groom.vtp", head_path=tmp_path / "head.vtp")
    mesh = pv.read(path)
    arrays = results.load_arrays(result)
    samples = fields.sample(arrays)
    S = result.helix.n_strands
    assert mesh.n_lines == S and mesh.n_cells == S
    assert mesh.n_points == len(samples.points)
    assert np.allclose(mesh.points, samples.points, atol=1e-12)
    for name, k in POINT_ARRAYS.items():
        assert name in mesh.point_data, name
        assert mesh.point_data[name].shape[1:] == ((k,) if k > 1 else ()), name
    for name in CELL_ARRAYS:
        assert mesh.cell_data[name].shape == (S,), name
    for name in ("young_modulus", "shear_modulus", "radius", "density", "friction", "gravity"):
        assert name in mesh.field_data, name
    # values: strand lengths, contact counts, stability margin
    assert np.allclose(mesh.cell_data["length"], result.helix.strand_lengths)
    assert mesh.cell_data["contacts"].sum() == len(result.forces) + np.count_nonzero(result.contacts.strand_b >= 0)
    assert np.allclose(mesh.point_data["stability_margin"], 1 - result.stiffness_ratio[samples.strand])
    assert np.allclose(mesh.point_data["fit_error"], result.fit_max_error[samples.strand])
    q = result.helix.to_flat(result.helix.curvatures)
    q0 = result.helix.to_flat(result.rest_curvatures)
    assert np.allclose(mesh.point_data["curvature_change"], np.linalg.norm(q0 - q, axis=1)[samples.element])
    assert mesh.point_data["contact_force_magnitude"].max() > 0
    # each cell is one strand's polyline, in order
    first = mesh.get_cell(2).point_ids
    assert first == list(range(samples.offsets[2], samples.offsets[3]))
    head = pv.read(tmp_path / "head.vtp")
    assert head.n_cells == len(result.head.faces)


def test_rest_shape_vtp(result, tmp_path):
    mesh = pv.read(write_vtp(result, tmp_path / "rest.vtp", shape="rest"))
    samples = fields.sample(results.load_arrays(result))
    assert np.allclose(mesh.points, samples.rest_points, atol=1e-12)
    assert np.allclose(mesh.points - mesh.point_data["rest_displacement"], samples.points, atol=1e-12)


def test_lines_connectivity():
    assert lines_connectivity(np.array([0, 2, 5])).tolist() == [2, 0, 1, 3, 2, 3, 4]


def test_vtp_errors(result, tmp_path):
    with pytest.raises(GroomError, match="end in .vtp"):
        write_vtp(result, tmp_path / "groom.vtk")
    with pytest.raises(GroomError, match="shape must be"):
        write_vtp(result, tmp_path / "groom.vtp", shape="other")
    with pytest.raises(GroomError, match="no such file"):
        write_vtp(tmp_path / "missing", tmp_path / "groom.vtp")
