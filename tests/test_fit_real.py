"""The fit on real grooms (../shared/data): every strand within tolerance, errors measured independently."""

import numpy as np
import pytest
from test_fit import libm_numpy

from groomtool.fit import cohelicity, fitter, sampling
from groomtool.fit import fit_groom
from groomtool.fit.sampling import vertex_arc_lengths
from groomtool.groom import Groom
from groomtool.io import read_data
from reference import fit as fit_reference
from reference.fit import closest_distances, curve_table




def check(groom, res, tol):
    assert res.converged.all(), f"strands above tolerance: {res.failed}"
    assert res.max_error.max() <= tol
    # the errors again, from the returned SuperHelix alone (through superhelix.kinematics)
    arc, L = vertex_arc_lengths(groom.points, groom.offsets)
    strand = groom.strand_index
    d, _, _ = closest_distances(curve_table(res.helix), groom.points, strand,
                                arc / L[strand] * res.helix.strand_lengths[strand])
    again = np.zeros(groom.n_strands)
    np.maximum.at(again, strand, d)
    assert np.allclose(again, res.max_error, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def usc_groom(shared_data):
    files = sorted((shared_data / "usc" / "cstrands").glob("*.data"))
    if not files:
        pytest.skip("no USC cstrands files")
    strands = [s for f in files[::3] for s in read_data(f, repair=True).strands()]           # 115 styles, 575 strands
    return Groom.from_strands(strands, source="usc cstrands (every 3rd style)")


@pytest.fixture(scope="module")
def harolongo(shared_data):
    path = shared_data / "digital-salon" / "harolongo.data"
    if not path.exists():
        pytest.skip("harolongo.data not found")
    strands = list(read_data(path, scale=0.01).strands())                              # centimetres
    return Groom.from_strands(strands[::4], source="harolongo (every 4th strand)")


def test_usc_styles_within_absolute_tolerance(usc_groom):
    res = fit_groom(usc_groom, tolerance=5e-4)
    check(usc_groom, res, 5e-4)
    assert res.helix.n_elements.max() < 256


def test_usc_styles_relative_tolerance(usc_groom):
    res = fit_groom(usc_groom, tolerance=5e-4, relative_tolerance=1e-3)
    tol = np.minimum(5e-4, 1e-3 * usc_groom.lengths())
    assert np.allclose(res.tolerance, tol)
    assert res.converged.all() and np.all(res.max_error <= tol)


def test_usc_exact_helices(usc_groom):
    """twist_budget=0: every element exactly through its relaxed points; still within tolerance."""
    res = fit_groom(usc_groom, tolerance=5e-4, twist_budget=0.0)
    check(usc_groom, res, 5e-4)


def test_harolongo_within_tolerance(harolongo):
    res = fit_groom(harolongo, tolerance=5e-4)
    check(harolongo, res, 5e-4)
    assert np.all(res.relative_max_error < 5e-4 / 0.2)


def numpy_pipeline(monkeypatch):
    """fit_groom with every numba kernel replaced by the numpy version it was ported from."""
    def assemble_flat(roots, tangents, phi, lengths, n, N, frames=None):
        mask = np.arange(N)[None, :] < n[:, None]
        padded_phi, padded_l = np.zeros((len(n), N, 3)), np.zeros((len(n), N))
        padded_phi[mask], padded_l[mask] = phi, lengths
        return fit_reference.assemble_numpy(roots, tangents, padded_phi, padded_l, n, frames)

    monkeypatch.setattr(fitter, "solve_chain", fit_reference.solve_chain_numpy)
    monkeypatch.setattr(fitter, "assemble_flat", assemble_flat)
    monkeypatch.setattr(fitter, "strand_errors", fit_reference.strand_errors_numpy)
    monkeypatch.setattr(fitter, "drop_repeated_vertices", fit_reference.drop_repeated_vertices_numpy)
    monkeypatch.setattr(fitter, "vertex_arc_lengths", fit_reference.vertex_arc_lengths_numpy)
    monkeypatch.setattr(sampling, "vertex_arc_lengths", fit_reference.vertex_arc_lengths_numpy)
    monkeypatch.setattr(sampling.PolylineCurves, "evaluate", fit_reference.evaluate_numpy)
    monkeypatch.setattr(cohelicity, "_project", lambda X, T, n, eps: fit_reference.project_numpy(
        X, T[:, 1:] - T[:, :-1], n, eps))


def test_kernels_reproduce_the_numpy_fit(harolongo, monkeypatch):
    """The numba pipeline against the numpy one (with libm's arctan2, arcsin, sin, cos, which the kernels
    call) on a quarter of harolongo: the same N per strand, SuperHelix and errors."""
    sub = Groom.from_strands([harolongo.points[harolongo.offsets[i]:harolongo.offsets[i + 1]]
                              for i in range(0, harolongo.n_strands, 4)], source="harolongo (every 16th strand)")
    res = fit_groom(sub, tolerance=5e-4)
    with monkeypatch.context() as m, libm_numpy():
        numpy_pipeline(m)
        ref = fit_groom(sub, tolerance=5e-4)
    assert res.passes == ref.passes > 2
    np.testing.assert_array_equal(res.helix.n_elements, ref.helix.n_elements)
    for name in ("root_positions", "root_frames", "lengths"):
        np.testing.assert_array_equal(getattr(res.helix, name), getattr(ref.helix, name))
    # the frames go through 3x3 products (numpy: BLAS, with or without fused multiply-adds)
    q = ref.helix.curvatures
    np.testing.assert_allclose(res.helix.curvatures, q, rtol=0, atol=1e-12 * np.abs(q).max())
    np.testing.assert_allclose(res.max_error, ref.max_error, rtol=1e-10, atol=0)
    np.testing.assert_allclose(res.mean_error, ref.mean_error, rtol=1e-10, atol=0)
