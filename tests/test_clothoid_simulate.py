"""The forward simulator and groom check on Super Space Clothoids (issue 20): the clothoid inertia (mass matrix with
the cross-section rotation, node velocities) against finite differences of the kinematics, an inverted clothoid groom
with head and strand/strand contacts that stays put while the naive one sags, and `groom check` on a
`groom invert --model clothoid` output."""

import json

import numpy as np
import pytest

from groomtool.cli.main import EXIT_OK, main
from groomtool.examples import example_groom
from groomtool.invert import InversionParams, invert_groom
from groomtool.io import save_groom
from groomtool.rods import clothoid as cl
from groomtool.rods import dynamics as dyn
from groomtool.simulate import SimulationParams, Simulator, simulate

ROT = (2e-3, 1e-3, 1e-3)  # exaggerated rotational inertia: its term must show in the kinetic energy


def _rod():
    rng = np.random.default_rng(0)
    q = rng.normal(0.0, 30.0, (2, 4, 3))
    q[1, 3] = 0.0  # padding node of the 2-element strand
    lengths = np.array([[0.03, 0.02, 0.04], [0.03, 0.05, 0.0]])
    return cl.SuperClothoid(rng.normal(size=(2, 3)), np.stack([np.eye(3)] * 2), lengths, q)


EPS = 1e-30  # complex step: exact derivatives to round-off


def _kinetic_energy_cs(rod, v, linear, rot, order=40):
    """1/2 int rhoS |Cdot|^2 + w_mat^T diag(rot) w_mat ds per strand, Cdot and the frame's angular velocity by the
    complex step of cl.evaluate along the rates v (not point_jacobians), Gauss points per element."""
    xg, wg = np.polynomial.legendre.leggauss(order)
    moved = rod.with_curvatures(rod.curvatures + 1j * EPS * v)
    out = np.zeros(rod.n_strands)
    for s in range(rod.n_strands):
        n = int(rod.n_elements[s])
        starts = np.concatenate([[0.0], np.cumsum(rod.lengths[s, :n])])
        arc = np.concatenate([starts[j] + 0.5 * (xg + 1.0) * rod.lengths[s, j] for j in range(n)])
        w = np.concatenate([0.5 * wg * rod.lengths[s, j] for j in range(n)])
        strand = np.full(len(arc), s)
        x, Rc = cl.evaluate(moved, strand, arc, cl.kinematics(moved, moments=False))
        R = Rc.real
        W = (Rc.imag / EPS) @ np.swapaxes(R, 1, 2)  # dR R^T = [w]x
        omega = np.einsum("pba,pb->pa", R, np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1))
        vel = x.imag / EPS
        out[s] = 0.5 * np.sum(w * (linear * np.sum(vel ** 2, axis=1) + omega ** 2 @ np.asarray(rot)))
    return out


def test_clothoid_mass_matrix_against_kinetic_energy():
    rod = _rod()
    v = np.random.default_rng(1).normal(size=rod.curvatures.shape) * rod.node_mask[..., None]
    M = dyn.clothoid_mass_matrix(rod, dyn.Inertia(0.01, ROT), order=12)
    T = _kinetic_energy_cs(rod, v, 0.01, ROT)
    np.testing.assert_allclose(dyn.kinetic_energy(M, v), T, rtol=1e-9)
    T_lin = _kinetic_energy_cs(rod, v, 0.01, (0.0, 0.0, 0.0))
    assert np.all(T - T_lin > 1e-3 * T)  # the rotational term is there and counted
    # without the cross-section term it is the translational mass matrix of rods/clothoid.py
    M0 = dyn.clothoid_mass_matrix(rod, dyn.Inertia(0.01, (0.0, 0.0, 0.0)), order=8)
    np.testing.assert_allclose(M0, cl.mass_matrix(rod, 0.01, order=8), rtol=0, atol=1e-14 * np.abs(M0).max())
    assert np.all(np.abs(M[1, 9:]) == 0.0) and np.all(np.abs(M[1, :, 9:]) == 0.0)  # padding node


def test_clothoid_node_velocities_against_finite_differences():
    rod = _rod()
    v = np.random.default_rng(2).normal(size=rod.curvatures.shape) * rod.node_mask[..., None]
    fd = cl.kinematics(rod.with_curvatures(rod.curvatures + 1j * EPS * v), moments=False).C.imag / EPS
    got = cl.node_velocities(rod, v)
    np.testing.assert_allclose(got, fd * rod.node_mask[..., None], rtol=0, atol=1e-12 * np.abs(fd).max())
    np.testing.assert_allclose(dyn.clothoid_node_speeds(rod, v),
                               np.linalg.norm(fd * rod.node_mask[..., None], axis=-1).max(axis=1), rtol=1e-12)


@pytest.fixture(scope="module")
def inverted():
    """A small clothoid groom inverted with head and strand/strand contacts (r_c = 0.5 mm)."""
    groom, head = example_groom(4, seed=3)
    result = invert_groom(groom, head, InversionParams(model="clothoid", contacts="all", contact_radius=5e-4))
    assert result.model == "clothoid" and len(result.forces) > 10
    return result, head


def test_inverted_clothoid_groom_with_contacts_stays_put_and_the_naive_one_sags(inverted):
    result, head = inverted
    params = SimulationParams(contacts="all", contact_radius=5e-4)
    runs = {}
    for name, rest in (("inverted", result.rest_curvatures), ("naive", result.helix.curvatures.copy())):
        runs[name] = simulate(result.helix, rest, result.material, result.gravity, head=head, seconds=0.25,
                              params=params, frames_per_second=None,
                              warm_start=(result.contacts, result.forces) if name == "inverted" else None)
    inv, naive = runs["inverted"], runs["naive"]
    assert inv.stats["model"] == "clothoid" and inv.stats["velocity_terms"] is False
    assert inv.final.curvatures.shape == result.helix.curvatures.shape  # nodal state (S, N + 1, 3)
    assert min(inv.stats["contacts_per_step"]) > 10
    drift = np.linalg.norm(inv.tips - inv.tips[0], axis=-1).max()
    sag = np.linalg.norm(naive.tips[-1] - naive.tips[0], axis=-1).max()
    assert drift < 1e-6
    assert inv.stats["solver_failures"] == 0
    assert sag > 1e-3


def test_first_step_of_the_inverted_clothoid_groom_is_exact(inverted):
    """v = 0, r = h r_inv solve the first step: the banded K (not its diagonal) in K (q - q0)."""
    result, head = inverted
    sim = Simulator(result.helix, result.rest_curvatures, result.material, result.gravity, head=head,
                    params=SimulationParams(contacts="all", contact_radius=5e-4),
                    warm_start=(result.contacts, result.forces))
    system = sim.assemble()
    assert np.abs(system.problem.velocity(system.r0)).max() <= 1e-9 * np.abs(system.problem.b).max()
    sim.finish(system, sim.solve_contacts(system))
    assert np.abs(sim.state.rates).max() < 1e-6 * np.abs(system.v_free).max()


def test_groom_check_on_a_clothoid_inversion_output(tmp_path):
    groom, head = example_groom(3, seed=1)
    save_groom(groom, tmp_path / "g.obj")
    head.export(tmp_path / "head.obj")
    out = tmp_path / "out"
    assert main(["invert", str(tmp_path / "g.obj"), "--head", str(tmp_path / "head.obj"), "--contacts", "head",
                 "--contact-radius", "5e-4", "--model", "clothoid", "-o", str(out), "--quiet"]) == EXIT_OK
    assert main(["check", str(out), "--seconds", str(12 / 240), "--quiet"]) == EXIT_OK
    report = json.loads((out / "check.json").read_text())
    assert report["model"] == "clothoid" and "dropped" in report["velocity_terms"]
    assert report["inverted"]["max_tip_drift_m"] < 1e-8
    assert report["naive"]["max_tip_drift_m"] > 1e3 * max(report["inverted"]["max_tip_drift_m"], 1e-12)
    assert report["inverted"]["solver"]["failures"] == 0


def test_per_strand_stiffness_is_the_banded_blocks():
    """Stiffened strands (groom check's per-strand materials): the banded (diagonal, off-diagonal) blocks times the
    factor hold the isolated equilibrium computed with that K; the scalar material's K does not."""
    from groomtool.material import Material

    mat = Material()
    q = np.zeros((2, 5, 3))
    q[:, :, 1], q[:, :, 2] = 20.0, -8.0
    frames = np.stack([np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 1.0, 0], [-1, 0, 0], [0, 0, 1]])])
    rod = cl.SuperClothoid(np.zeros((2, 3)), frames, np.full((2, 4), 0.02), q)
    factor = np.array([3.0, 1.0])
    diag, off = cl.stiffness(rod, mat.stiffness_diag)
    K = (diag * factor[:, None, None], off * factor[:, None, None])
    gravity = np.array([0.0, -9.81, 0.0])
    F = cl.gravity_force(rod, mat.linear_density, gravity)
    q0 = q - cl.stiffness_solve(rod, mat.stiffness_diag, F) / factor[:, None, None]
    params = SimulationParams(contacts="none")
    held = simulate(rod, q0, mat, gravity, seconds=10 / 240, params=params, stiffness=K, frames_per_second=None)
    soft = simulate(rod, q0, mat, gravity, seconds=10 / 240, params=params, frames_per_second=None)
    assert np.linalg.norm(held.tips[-1] - held.tips[0], axis=1).max() < 1e-12
    assert np.linalg.norm(soft.tips[-1, 0] - soft.tips[0, 0]) > 1e-5  # the stiffened strand sags with the scalar K
    with pytest.raises(ValueError, match="banded"):
        Simulator(rod, q0, mat, gravity, params=params, stiffness=K[0])


def test_clothoid_velocity_terms_follow_lagranges_equations():
    """A = Mdot qd - 1/2 d(qd^T M qd)/dq with M differentiated by central differences (its own Gauss points); the
    kinetic energy and momentum from the point velocities equal 1/2 v^T M v and M v; the opt-in reaches the step."""
    rod = _rod()
    inertia = dyn.Inertia(0.01, ROT)
    rng = np.random.default_rng(3)
    v = rng.normal(size=rod.curvatures.shape) * rod.node_mask[..., None]
    M = dyn.clothoid_mass_matrix(rod, inertia, order=4)
    vf = v.reshape(2, -1)
    np.testing.assert_allclose(dyn.clothoid_kinetic_energy(rod, inertia, v, order=4), dyn.kinetic_energy(M, v),
                               rtol=1e-12)
    np.testing.assert_allclose(dyn.clothoid_momentum(rod, inertia, v, order=4).reshape(2, -1),
                               np.einsum("sij,sj->si", M, vf), rtol=0, atol=1e-12 * np.abs(M).max())
    A = dyn.clothoid_velocity_terms(rod, inertia, v, order=4).reshape(2, -1)
    h = 1e-6
    ref = np.zeros_like(A)
    for s in range(2):
        for j in range(3 * (int(rod.n_elements[s]) + 1)):
            e = np.zeros(rod.curvatures.shape)
            e.reshape(2, -1)[s, j] = h
            dM = (dyn.clothoid_mass_matrix(rod.with_curvatures(rod.curvatures + e), inertia, order=4)[s]
                  - dyn.clothoid_mass_matrix(rod.with_curvatures(rod.curvatures - e), inertia, order=4)[s]) / (2 * h)
            ref[s] += dM @ vf[s] * vf[s, j]
            ref[s, j] -= 0.5 * vf[s] @ dM @ vf[s]
    np.testing.assert_allclose(A, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    assert np.abs(A).max() > 1e-3 * np.abs(ref).max() and np.all(A.reshape(v.shape)[1, 3] == 0.0)
    from groomtool.material import Material

    on = simulate(rod, rod.curvatures, Material(), [0.0, -9.81, 0.0], seconds=2 / 240, frames_per_second=None,
                  params=SimulationParams(contacts="none", clothoid_velocity_terms=True))
    off = simulate(rod, rod.curvatures, Material(), [0.0, -9.81, 0.0], seconds=2 / 240, frames_per_second=None,
                   params=SimulationParams(contacts="none"))
    assert on.stats["velocity_terms"] is True and off.stats["velocity_terms"] is False
    assert not np.array_equal(on.final.rates, off.final.rates)  # A(q, v) != 0 at the second step
