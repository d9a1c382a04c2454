"""Super Space Clothoids through the pipeline (issue 20): the production fit on real strands, the inversion with
contacts checked against an independent equilibrium computation, rest.npz and the CLI round trip."""

import json
from pathlib import Path

import numpy as np
import pytest

from groomtool.cli.main import EXIT_OK, main
from groomtool.examples import write_example
from groomtool.fit import fit_groom
from groomtool.fit.clothoid_fit import fit_clothoid_groom
from groomtool.fit.least_squares import polyline_distances
from groomtool.groom import Groom
from groomtool.invert import InversionParams, invert_groom
from groomtool.io import load_groom, load_head
from groomtool.io.results import ModelError, read_result
from groomtool.rods import clothoid as cl

USC = Path("/work/shared/data/usc/cstrands")
needs_usc = pytest.mark.skipif(not USC.is_dir(), reason="USC data not available")
EPS = 1e-30


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    d = tmp_path_factory.mktemp("example")
    return write_example(d, n_strands=20, seed=5)


def _subset(groom, ids):
    pts = np.concatenate([groom.points[groom.offsets[i]:groom.offsets[i + 1]] for i in ids])
    off = np.concatenate([[0], np.cumsum([groom.offsets[i + 1] - groom.offsets[i] for i in ids])])
    return Groom(pts, off, up=groom.up, source=groom.source)


def _check_fit_independently(groom, fit, per_element=64):
    """Every vertex within the reported error (and the tolerance) of the fitted clothoid, measured on a dense
    sampling of the curve (nearest segment), allowing the sagitta of the samples' chords."""
    rod = fit.helix
    pts, offsets, _, _ = cl.sample(rod, per_element)
    for s in range(rod.n_strands):
        X = groom.points[groom.offsets[s]:groom.offsets[s + 1]]
        d = polyline_distances(X, pts[offsets[s]:offsets[s + 1]])
        n = int(rod.n_elements[s])
        bend = np.linalg.norm(rod.curvatures[s, :n + 1, 1:], axis=1).max()  # |kappa| is largest at a node
        h = rod.lengths[s, :n].max() / per_element
        sagitta = bend * h * h / 8.0 + 1e-12
        assert d.max() <= fit.max_error[s] + sagitta
        assert d.max() <= fit.tolerance[s] + sagitta


@needs_usc
@pytest.mark.parametrize("style, curly", [("cstrands00375.data", False), ("cstrands00084.data", True)])
def test_fit_within_tolerance_on_usc_strands(style, curly):
    groom = load_groom(USC / style)
    helix_fit = fit_groom(groom)
    fit = fit_clothoid_groom(groom, helix_fit=helix_fit)
    assert fit.settings["model"] == "clothoid"
    assert np.all(fit.converged) and np.all(fit.max_error <= fit.tolerance)
    assert np.all(fit.mean_error <= fit.max_error)
    _check_fit_independently(groom, fit)
    # the root is the input's, the curvature continuous by construction (nodal values)
    np.testing.assert_allclose(fit.helix.root_positions, groom.points[groom.offsets[:-1]], atol=1e-9)
    if curly:  # curly hair needs fewer elements than the production helix fit at the same tolerance
        assert fit.helix.n_elements.sum() < helix_fit.helix.n_elements.sum()


def test_fit_recovers_a_sampled_clothoid():
    """A polyline sampled from a 3-element clothoid is fitted within a tight tolerance."""
    q = np.array([[[2.0, 30.0, -5.0], [0.0, 50.0, 10.0], [-3.0, 20.0, 40.0], [1.0, -10.0, 25.0]]])
    rod = cl.SuperClothoid(np.zeros(3), np.eye(3), np.full((1, 3), 0.04), q)
    s = np.linspace(0.0, 0.12, 60)
    pts = cl.evaluate_positions(rod, np.zeros(60, dtype=np.int64), s)
    groom = Groom(pts, np.array([0, 60]))
    fit = fit_clothoid_groom(groom, tolerance=2e-5)
    assert fit.converged.all()
    _check_fit_independently(groom, fit)


def _complex_step_columns(rod, strand, fn):
    """d fn / d q over the strand's real dofs by the complex step (exact to round-off): fn(clothoid of copies) ->
    (copies,) values; returns (3 (N + 1),)."""
    n = int(rod.n_elements[strand])
    sub = rod.subset([strand])
    dofs = 3 * (n + 1)
    q = np.repeat(sub.curvatures.astype(np.complex128), dofs, axis=0).reshape(dofs, -1)
    q[np.arange(dofs), np.arange(dofs)] += 1j * EPS
    copies = cl.SuperClothoid(np.repeat(sub.root_positions, dofs, 0), np.repeat(sub.root_frames, dofs, 0),
                              np.repeat(sub.lengths, dofs, 0), q.reshape(dofs, n + 1, 3),
                              np.repeat(sub.n_elements, dofs))
    return np.imag(fn(copies)) / EPS


def _dense_stiffness(lengths, D):
    """K = D (x) M_FE from the energy's formula: K_ii = D (l_{i-1} + l_i) / 3, K_{i,i+1} = D l_i / 6."""
    n = len(lengths)
    M = np.zeros((n + 1, n + 1))
    for j, l in enumerate(lengths):
        M[j:j + 2, j:j + 2] += l / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    return np.kron(M, np.diag(D))


def _independent_residuals(result):
    """(||K (q - q0) - F - H^T r|| / ||F|| per strand, the same without H^T r, the number of point forces), F = -dV/dq and H^T r = d(sum_p f_p . C(s_p))/dq by the
    complex step on V and on the positions (neither gravity_force nor point_jacobians), K from its formula."""
    rod, q0 = result.helix, result.rest_curvatures
    mat = result.material
    g = result.gravity
    c = result.contacts
    forces = np.asarray(result.forces).reshape(-1, 3)
    world = np.einsum("pji,pj->pi", np.asarray(c.frame), forces) if c is not None and len(forces) else np.zeros((0, 3))
    pt_strand = np.concatenate([np.asarray(c.strand_a), np.asarray(c.strand_b)]) if len(world) else np.zeros(0, int)
    pt_s = np.concatenate([np.asarray(c.s_a), np.asarray(c.s_b)]) if len(world) else np.zeros(0)
    pt_f = np.concatenate([world, -world]) if len(world) else np.zeros((0, 3))
    factor = result.stiffness_factor
    out = []
    for s in range(rod.n_strands):
        n = int(rod.n_elements[s])
        F = -_complex_step_columns(rod, s, lambda cp: cl.gravity_potential(cp, mat.linear_density, g))
        mine = np.flatnonzero(pt_strand == s)
        HtR = np.zeros_like(F)
        if len(mine):
            def work(cp):
                k = cp.n_strands
                strand = np.repeat(np.arange(k), len(mine))
                pos = cl.evaluate_positions(cp, strand, np.tile(pt_s[mine], k)).reshape(k, len(mine), 3)
                return np.einsum("kpc,pc->k", pos, pt_f[mine])
            HtR = _complex_step_columns(rod, s, work)
        K = factor[s] * _dense_stiffness(rod.lengths[s, :n], mat.stiffness_diag)
        d = (rod.curvatures[s, :n + 1] - q0[s, :n + 1]).ravel()
        out.append((np.linalg.norm(K @ d - F - HtR) / np.linalg.norm(F), np.linalg.norm(K @ d - F) / np.linalg.norm(F)))
    out = np.array(out).reshape(-1, 2)
    return out[:, 0], out[:, 1], len(pt_f)


def test_inverted_clothoid_groom_with_contacts_is_an_equilibrium(example):
    groom_path, head_path = example
    groom = load_groom(groom_path)
    head = load_head(head_path)
    # a 2 mm contact radius: about a hundred contacts, head and strand/strand
    result = invert_groom(groom, head, InversionParams(model="clothoid", contacts="all", contact_radius=2e-3))
    assert result.model == "clothoid"
    assert result.report["model"] == "clothoid"
    assert result.report["solve"]["status"] == "solved"
    assert result.report["contacts"]["strand_strand"] > 0 and result.report["contacts"]["strand_head"] > 0
    assert result.report["fit"]["strands_over_tolerance"] == 0
    assert result.report["equilibrium"]["max_relative_residual"] < 1e-8
    res, without_contacts, n_points = _independent_residuals(result)
    assert n_points > 0 and np.count_nonzero(result.forces[:, 0] > 0) > 10
    assert res.max() < 1e-8
    # the contacts matter: without their forces the same q0 is no equilibrium of the strands they load
    loaded = np.asarray(result.contacts.strand_a)[result.forces[:, 0] > 0]
    assert without_contacts[loaded].min() > 1e-3


def test_isolated_clothoid_inversion_is_an_equilibrium(example):
    groom_path, _ = example
    groom = load_groom(groom_path)
    result = invert_groom(_subset(groom, [0, 3, 7]), None, InversionParams(model="clothoid", stabilize="none"))
    assert result.report["equilibrium"]["max_relative_residual"] < 1e-9
    res, _, _ = _independent_residuals(result)
    assert res.max() < 1e-9
    assert result.rest_curvatures.shape == result.helix.curvatures.shape  # nodal: (S, N + 1, 3)


def test_cli_round_trip_and_clear_refusals(example, tmp_path):
    groom_path, head_path = example
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "--head", str(head_path), "--contacts", "head", "--model", "clothoid",
                 "-o", str(out), "--quiet"]) == EXIT_OK
    report = json.loads((out / "report.json").read_text())
    assert report["model"] == "clothoid" and report["parameters"]["model"] == "clothoid"
    assert report["equilibrium"]["max_relative_residual"] < 1e-8
    saved = read_result(out)
    assert saved.model == "clothoid"
    rod, rest = saved.clothoid(), saved.clothoid(rest=True)
    assert isinstance(rod, cl.SuperClothoid)
    assert rest.curvatures.shape == rod.curvatures.shape == saved.rest_curvatures.shape
    # the nodal data written reproduce the fitted shape: the vertices lie within tolerance of it
    groom = load_groom(groom_path)
    pts, offsets, _, _ = cl.sample(rod, 32)
    for s in range(rod.n_strands):
        d = polyline_distances(groom.points[groom.offsets[s]:groom.offsets[s + 1]], pts[offsets[s]:offsets[s + 1]])
        assert d.max() < report["fit"]["tolerance_m"] * 1.01
    with np.load(out / "rest.npz") as z:
        assert str(z["model"]) == "clothoid"
        assert len(z["clothoid_node_offsets"]) == len(z["strand_offsets"])
        np.testing.assert_array_equal(np.diff(z["clothoid_node_offsets"]), np.diff(z["strand_offsets"]) + 1)
    with pytest.raises(ModelError, match="Super Space Clothoid"):
        saved.helix()
    np.testing.assert_array_equal(saved.rod().curvatures, rod.curvatures)
    # the exporters take it (tests/test_clothoid_export.py checks what they write)
    assert main(["export", str(out), "--format", "vtp", "-o", str(tmp_path / "g.vtp")]) == EXIT_OK
    assert (tmp_path / "g.vtp").is_file()
    # the default stays the Super-Helix, and says so
    out2 = tmp_path / "helix"
    assert main(["invert", str(groom_path), "-o", str(out2), "--quiet"]) == EXIT_OK
    assert read_result(out2).model == "superhelix"
    assert json.loads((out2 / "report.json").read_text())["model"] == "superhelix"


def test_python_api(example, tmp_path):
    import groomtool

    groom_path, _ = example
    groom = load_groom(groom_path)
    result = groomtool.invert(_subset(groom, [1, 2]), model="clothoid", stabilize="none")
    assert result.model == "clothoid" and result.report["equilibrium"]["max_relative_residual"] < 1e-9
    result.save(tmp_path / "r")
    assert read_result(tmp_path / "r").model == "clothoid"
    assert groomtool.export(tmp_path / "r", tmp_path / "r.vtp").is_file()
    with pytest.raises(ValueError, match="model"):
        groomtool.invert(groom, model="helix")


def test_clothoid_stiffness_ratio_against_a_generalized_eigenproblem(example):
    """rho = lambda_max(K^-1 dF/dq) of the stability analysis against scipy's generalized eigvalsh with dF/dq by
    central differences of the gravity force and K from its formula."""
    import scipy.linalg

    from groomtool.material import Material
    from groomtool.stability import stiffness_ratios

    groom_path, _ = example
    fit = fit_clothoid_groom(_subset(load_groom(groom_path), [0, 4, 9]))
    rod = fit.helix
    mat = Material()
    g = np.array([0.0, -9.81, 0.0])
    rho = stiffness_ratios(rod, mat.stiffness_diag, mat.linear_density, g)
    for s in range(rod.n_strands):
        n = int(rod.n_elements[s])
        sub = rod.subset([s])
        dofs = 3 * (n + 1)
        dF = np.zeros((dofs, dofs))
        for k in range(dofs):
            h = 1e-4 * max(1.0, abs(sub.curvatures.reshape(-1)[k]))
            plus, minus = sub.curvatures.copy(), sub.curvatures.copy()
            plus.reshape(-1)[k] += h
            minus.reshape(-1)[k] -= h
            dF[:, k] = (cl.gravity_force(sub.with_curvatures(plus), mat.linear_density, g)
                        - cl.gravity_force(sub.with_curvatures(minus), mat.linear_density, g)).reshape(-1) / (2 * h)
        K = _dense_stiffness(rod.lengths[s, :n], mat.stiffness_diag)
        ref = scipy.linalg.eigh(0.5 * (dF + dF.T), K, eigvals_only=True)[-1]
        assert rho[s] == pytest.approx(ref, rel=1e-6)


def test_read_result_checks_the_clothoid_nodes(example, tmp_path):
    groom_path, _ = example
    result = invert_groom(_subset(load_groom(groom_path), [2]), None, InversionParams(model="clothoid"))
    result.save(tmp_path / "r", formats=("npz",))
    with np.load(tmp_path / "r" / "rest.npz") as z:
        arrays = {k: z[k] for k in z.files}
    np.testing.assert_array_equal(read_result(arrays).clothoid(rest=True).curvatures, result.rest_curvatures)
    arrays["clothoid_node_offsets"] = arrays["clothoid_node_offsets"] - 1
    from groomtool.groom import GroomError

    with pytest.raises(GroomError, match="clothoid_node_offsets"):
        read_result(arrays).clothoid()


def test_clothoid_inversion_with_contacts_but_none_found(example):
    """contacts asked for, none found (one strand, no head): the solve has no rows and q0 is the isolated one."""
    groom_path, _ = example
    one = _subset(load_groom(groom_path), [6])
    with_contacts = invert_groom(one, None, InversionParams(model="clothoid", contacts="all"))
    isolated = invert_groom(one, None, InversionParams(model="clothoid"))
    assert with_contacts.report["contacts"]["total"] == 0
    np.testing.assert_allclose(with_contacts.rest_curvatures, isolated.rest_curvatures, rtol=0, atol=1e-12)
