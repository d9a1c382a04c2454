"""Stable inversion (issue 14): stability with the contacts that hold a strand, and the stiffening.

- the dead-load stiffness d(J^T f)/dq (analytic for Super-Helices) against second differences of the
  load potential f . C(s; q) (positions only, an independent route) and against the central differences
  of the exact generalized force it replaced (tests/reference/stability.py), on random strands, edge
  cases (loads at nodes and ends, several per element, nearly straight and strongly curled elements,
  one-element strands) and real fitted strands;
- the held ratios against a dense reference built here (dense gravity Hessian, second-difference load
  Hessian, scipy's null space of the dense constraint rows);
- no contacts: the held criterion equals the isolated one (1e-9);
- the forward simulator: a strand stiffened by its factor comes back after a kick, one at 0.9 x its
  certified factor falls; the stabilised inversion is still an exact equilibrium and rest.npz carries
  the per-strand moduli.
"""

import numpy as np
import pytest
import scipy.linalg
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from groomtool import Groom, Material
from groomtool.contact.jacobian import contact_jacobian
from groomtool.invert import InversionParams, invert_groom
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator
from groomtool.stability import contact_load_hessians, held_stiffness_ratios, stiffness_ratios
from groomtool.stabilize import stiffening_step

from reference.grooms import random_helix
from reference.rods import gravity_force_jacobian_reference
from reference.stability import contact_load_hessians_reference
from test_invert_contacts import SPHERE_R, _independent_cvxpy, _w_scale, draped_groom, draped_strand
from test_invert_contacts import _params as _contact_params

MAT = Material()
G = np.array([0.0, -9.81, 0.0])


def load_potential_hessian(helix, strand, s, f, h=1e-4):
    """d^2/dq^2 of sum_p f_p . C(s_p; q) for one strand by second differences of positions."""
    sub = helix.subset([strand])
    n = 3 * int(sub.n_elements[0])
    q0 = sub.curvatures.copy()

    def phi(dq):
        q = q0.copy()
        q[0, :n // 3] += dq.reshape(-1, 3)
        x = sh.evaluate_positions(sub.with_curvatures(q), np.zeros(len(s), np.int64), s)
        return float(np.sum(x * f))

    steps = h / sub.lengths[0, :n // 3].repeat(3)
    out = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            ei, ej = np.zeros(n), np.zeros(n)
            ei[i], ej[j] = steps[i], steps[j]
            v = (phi(ei + ej) - phi(ei - ej) - phi(-ei + ej) + phi(-ei - ej)) / (4 * steps[i] * steps[j])
            out[i, j] = out[j, i] = v
    return out


@given(seed=st.integers(0, 10_000), loads=st.integers(1, 4))
@settings(max_examples=12, deadline=None)
def test_contact_load_hessian_is_the_second_derivative_of_the_load_potential(seed, loads):
    helix = random_helix(seed, n_strands=3, max_elements=6)
    rng = np.random.default_rng(seed + 1)
    strand = np.repeat(np.arange(helix.n_strands), loads)
    s = rng.uniform(0, 1, len(strand)) * helix.strand_lengths[strand]
    f = rng.normal(size=(len(strand), 3)) * 1e-4
    ours = contact_load_hessians(helix, np.arange(helix.n_strands), strand, s, f, chunk_dofs=20)
    for k in range(helix.n_strands):
        mine = strand == k
        ref = load_potential_hessian(helix, k, s[mine], f[mine], h=1e-3)
        scale = np.abs(ref).max()
        # the reference's own round-off: eps |phi| / step^2 (second differences of a potential)
        phi = np.abs(f[mine]).sum() * (np.abs(helix.root_positions[k]).max() + helix.strand_lengths[k])
        noise = 64 * np.finfo(float).eps * phi / (1e-3 / helix.lengths[k, :helix.n_elements[k]].min()) ** 2
        # the analytic Hessian: within the reference's truncation (measured <= 5e-7 relative over 180 strands)
        np.testing.assert_allclose(ours[k], ref, atol=2e-6 * scale + noise, rtol=0)
        np.testing.assert_allclose(ours[k], ours[k].T, atol=1e-14 * scale)


def _check_against_references(helix, strand, s, f, rel=1e-8, second_differences=True):
    """contact_load_hessians against the central differences it replaced (``rel`` of the largest entry) and,
    optionally, against second differences of the potential (h = 1e-3 rad, as the hypothesis test); exactly
    symmetric."""
    ids = np.arange(helix.n_strands)
    ours = contact_load_hessians(helix, ids, strand, s, f)
    fd = contact_load_hessians_reference(helix, ids, strand, s, f)
    # the reference's own error, estimated from the same differences at twice the step (it matters where the
    # Hessian is tiny, e.g. a load next to the root: 1e-16 entries that the differences get to 2e-8 relative)
    fd2 = contact_load_hessians_reference(helix, ids, strand, s, f, rotation_step=2e-6)
    for k in ids:
        n = 3 * int(helix.n_elements[k])
        assert ours[k].shape == (n, n)
        scale = np.abs(fd[k]).max()
        np.testing.assert_allclose(ours[k], fd[k], atol=rel * scale + 4.0 * np.abs(fd2[k] - fd[k]).max(), rtol=0)
        assert np.array_equal(ours[k], ours[k].T)
        if second_differences:
            mine = strand == k
            ref = load_potential_hessian(helix, k, s[mine], f[mine], h=1e-3)
            phi = np.abs(f[mine]).sum() * (np.abs(helix.root_positions[k]).max() + helix.strand_lengths[k])
            noise = 64 * np.finfo(float).eps * phi / (1e-3 / helix.lengths[k, :n // 3].min()) ** 2
            np.testing.assert_allclose(ours[k], ref, atol=2e-6 * np.abs(ref).max() + noise, rtol=0)
    return ours


@given(seed=st.integers(0, 10_000), loads=st.integers(1, 6))
@settings(max_examples=20, deadline=None)
@example(seed=836, loads=1)  # a 1-element strand loaded 0.15 mm from its root: Hessian entries ~1e-16
def test_analytic_load_hessian_matches_the_finite_differences_it_replaced(seed, loads):
    helix = random_helix(seed, n_strands=4, max_elements=8)
    rng = np.random.default_rng(seed + 2)
    strand = np.repeat(np.arange(helix.n_strands), loads)
    s = rng.uniform(0, 1, len(strand)) * helix.strand_lengths[strand]
    f = rng.normal(size=(len(strand), 3)) * 1e-4
    _check_against_references(helix, strand, s, f, second_differences=False)


def _edge_loads(helix, rng, per_element=3):
    """Loads at every node (s = 0 and s = L included), and ``per_element`` inside each element."""
    strand, s = [], []
    for k in range(helix.n_strands):
        n = int(helix.n_elements[k])
        nodes = helix.element_starts[k, :n + 1]
        inside = (nodes[:-1, None] + rng.uniform(0, 1, (n, per_element)) * helix.lengths[k, :n, None]).ravel()
        arcs = np.concatenate([nodes, inside])
        strand.append(np.full(len(arcs), k))
        s.append(arcs)
    strand, s = np.concatenate(strand), np.concatenate(s)
    return strand, s, rng.normal(size=(len(s), 3)) * 1e-4


@pytest.mark.parametrize("curvature", [1e-9, 1.0, 30.0, 400.0])
def test_load_hessian_edge_cases(curvature):
    """Loads exactly at nodes (element boundaries, s = 0, s = L) and several per element, on strands of 1 to 5
    elements, from nearly straight (|q| ~ 1e-9) to strongly curled (|q| l up to ~16 rad per element)."""
    rng = np.random.default_rng(int(curvature * 7) + 3)
    from scipy.spatial.transform import Rotation
    n = np.array([1, 1, 2, 5])
    lengths = np.zeros((len(n), n.max()))
    q = np.zeros((len(n), n.max(), 3))
    for i, k in enumerate(n):
        lengths[i, :k] = rng.uniform(0.01, 0.04, k)
        d = rng.normal(size=(k, 3))
        q[i, :k] = curvature * d / np.linalg.norm(d, axis=1, keepdims=True)
    helix = sh.SuperHelix(0.05 * rng.normal(size=(len(n), 3)), Rotation.random(len(n), random_state=4).as_matrix(),
                          lengths, q, n)
    strand, s, f = _edge_loads(helix, rng)
    ours = _check_against_references(helix, strand, s, f)
    # a load at the root moves nothing: the Hessian of that load alone is zero
    root = contact_load_hessians(helix, [0, 3], [0, 3], [0.0, 0.0], f[:2])
    assert all(np.all(h == 0.0) for h in root)
    # the Hessian is linear in the loads: splitting the loads of strand 3 over two calls adds up
    mine = np.flatnonzero(strand == 3)
    a = contact_load_hessians(helix, [3], strand[mine[::2]], s[mine[::2]], f[mine[::2]])[0]
    b = contact_load_hessians(helix, [3], strand[mine[1::2]], s[mine[1::2]], f[mine[1::2]])[0]
    np.testing.assert_allclose(a + b, ours[3], atol=1e-13 * np.abs(ours[3]).max(), rtol=0)


def test_load_hessian_on_real_fitted_strands(shared_data):
    """Strands of harolongo (every 500th), fitted within 0.5 mm, loaded at random arc lengths and at nodes."""
    from groomtool.fit import fit_groom
    from groomtool.io import read_data

    path = shared_data / "digital-salon" / "harolongo.data"
    if not path.exists():
        pytest.skip("harolongo.data not found")
    strands = list(read_data(path, scale=0.01).strands())[::500]
    helix = fit_groom(Groom.from_strands(strands), tolerance=5e-4).helix
    assert helix.n_elements.max() >= 10
    rng = np.random.default_rng(5)
    strand, s, f = _edge_loads(helix, rng, per_element=1)
    _check_against_references(helix, strand, s, f, second_differences=False)


def test_stiffening_step_raises_only_the_unstable_strands():
    ratio = np.array([0.5, 2.0, 300.0, 1.0])
    factor = np.array([1.0, 1.0, 1.0, 1.5])
    new = stiffening_step(ratio, factor, margin=1.1, cap=100.0)
    np.testing.assert_allclose(new, [1.0, 2.2, 100.0, 1.5])
    assert stiffening_step(ratio, new, margin=1.1, cap=100.0) is None  # 300 stays unstable at the cap
    assert stiffening_step(np.array([0.2]), np.array([1.0])) is None


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_R)


def _params(**kw):
    """test_invert_contacts' parameters, with the stabilisation on (its default)."""
    return _contact_params(**{"stabilize": "stiffness", **kw})


@pytest.fixture(scope="module")
def draped(sphere):
    """test_invert_contacts' draped groom, inverted with the stabilisation reporting only."""
    groom = draped_groom()
    return groom, invert_groom(groom, head=sphere, params=_params(stabilize="report"))


def test_held_ratios_equal_a_dense_reference(draped):
    """rho = lambda_max(Z^T K^-1/2 (dF/dq + dF_c/dq) K^-1/2 Z), built here from dense pieces."""
    _, res = draped
    helix, g, c, r = res.helix, res.gravity, res.contacts, res.forces
    H = contact_jacobian(helix, c)
    mu = np.full(len(r), MAT.friction)
    held = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, g, c, r, H, mu)
    assert np.any(held.kind == 1)
    Hd = H.toarray()
    cols = 3 * helix.flat_offsets()
    world = np.einsum("pji,pj->pi", c.frame, r)
    loaded = r[:, 0] > 0
    for s in np.flatnonzero(held.kind == 1):
        n = 3 * int(helix.n_elements[s])
        dF = gravity_force_jacobian_reference(helix.subset([s]), MAT.linear_density, g)[0, :n, :n]
        on_a = loaded & (c.strand_a == s)
        on_b = loaded & (c.strand_b == s)
        arc = np.concatenate([c.s_a[on_a], c.s_b[on_b]])
        f = np.concatenate([world[on_a], -world[on_b]])
        sub = helix.subset([s])
        dFc = load_potential_hessian(sub, 0, arc, f, h=1e-3)
        scale = 1.0 / np.sqrt(sh.stiffness(sub, MAT.stiffness_diag).reshape(-1)[:n])
        A = scale[:, None] * (dF + dFc) * scale[None, :]
        norm = np.linalg.norm(A, 2)
        rows = []
        for i in np.flatnonzero(loaded & (c.strand_a == s) & (c.strand_b < 0)):
            stick = np.linalg.norm(r[i, 1:]) < (1 - 1e-6) * MAT.friction * r[i, 0]
            rows += [3 * i, 3 * i + 1, 3 * i + 2] if stick else [3 * i]
        if rows:
            Z = scipy.linalg.null_space(Hd[rows, cols[s]:cols[s] + n] * scale[None, :])
            A = Z.T @ A @ Z
        ref = np.linalg.eigvalsh(0.5 * (A + A.T))[-1]
        assert held.ratio[s] == pytest.approx(ref, rel=1e-5, abs=1e-6 * norm), s
    # the head contacts hold some strand that is unstable alone
    iso = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, g)
    assert np.any(held.ratio < iso - 1e-3 * np.abs(iso))


def test_without_contacts_the_held_criterion_is_the_isolated_one():
    """A strand/strand contact with a negligible force blocks nothing and loads nothing: the dense route
    must give the certified isolated ratio (1e-9)."""
    from groomtool.contact import Contacts, contact_frames

    helix = random_helix(7, n_strands=2, max_elements=8)
    iso = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G)
    x, R = sh.evaluate(helix, np.array([0]), np.array([0.5 * helix.strand_lengths[0]]))
    normal = np.array([[0.0, 0.0, 1.0]])
    c = Contacts(np.array([0]), np.array([0.5 * helix.strand_lengths[0]]), np.array([1]), np.array([0.0]), x, x,
                 normal, contact_frames(normal, R[:, :, 0]), np.array([0.0]), 5e-5)
    H = contact_jacobian(helix, c)
    held = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G, c, np.array([[1e-300, 0, 0]]), H,
                                 MAT.friction, isolated_ratios=iso)
    assert held.kind[0] == 1 and held.kind[1] == 1  # went through the route with contacts (here O(N), unblocked)
    np.testing.assert_allclose(held.ratio, iso, rtol=1e-9)


def test_stabilised_inversion_is_exact_and_stable(draped, sphere, tmp_path):
    groom, report_only = draped
    assert report_only.report["stability"]["stabilization"]["stiffened_strands"] == 0
    res = invert_groom(groom, head=sphere, params=_params())
    stab = res.report["stability"]["stabilization"]
    held = res.held_ratio
    assert stab["unstable_strands"] == 0 and np.all(held < res.stiffness_factor)
    stiffened = res.stiffness_factor > 1
    assert stab["stiffened_strands"] == int(stiffened.sum())
    # exactly the strands that need it: the others keep the input material
    np.testing.assert_array_equal(res.stiffness_factor[held < 1], 1.0)
    assert res.report["equilibrium"]["max_relative_residual"] < 1e-8
    # the re-solved forces are the optimum of the inverse problem with the new K (independent cvxpy)
    _, obj_ref = _independent_cvxpy(res, res.params.gamma * _w_scale(res))
    assert res.report["solve"]["objective"] == pytest.approx(obj_ref, rel=1e-7)
    res.save(tmp_path / "out")
    arrays = np.load(tmp_path / "out" / "rest.npz")
    np.testing.assert_allclose(arrays["strand_young_modulus"], MAT.young_modulus * res.stiffness_factor)
    np.testing.assert_allclose(arrays["strand_shear_modulus"], MAT.G * res.stiffness_factor)


def standing_strand(length=0.16, n=6):
    """A straight strand rising vertically (y up) from the origin, beyond Greenhill's 9 cm."""
    frame = np.stack([[0.0, 1.0, 0], [1, 0, 0], [0, 0, -1.0]], axis=1)
    return sh.SuperHelix(np.zeros((1, 3)), frame[None], np.full((1, n), length / n), np.zeros((1, n, 3)))


def kicked_drift(factor, seconds=2.0):
    """Max tip drift over the last half of a simulation from the inverted standing strand with stiffness
    factor ``factor`` and a small kick."""
    helix = standing_strand()
    K = sh.stiffness(helix, MAT.stiffness_diag) * factor
    rest = helix.curvatures  # straight and vertical: gravity has no moment, q0 = q
    rates = np.zeros_like(helix.curvatures)
    rates[0, :, 1] = 0.05  # a small bending kick (1/(m s))
    sim = Simulator(helix, rest, MAT, G, params=SimulationParams(contacts="none"), initial_rates=rates, stiffness=K)
    tip0 = sim.tips()
    drift = []
    for _ in range(int(round(seconds / sim.params.dt))):
        sim.step()
        drift.append(float(np.linalg.norm(sim.tips() - tip0)))
    return np.array(drift)


def test_a_stiffened_strand_comes_back_and_one_below_its_factor_falls():
    helix = standing_strand()
    rho = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G)[0]
    assert rho > 1.5  # unstable with the input material
    factor = stiffening_step(np.array([rho]), np.ones(1))[0]
    assert factor == pytest.approx(1.1 * rho)
    stable = kicked_drift(factor)
    below = kicked_drift(0.9 * rho)
    n = len(stable)
    assert stable[n // 2:].max() < 1.5 * stable[:n // 2].max()  # oscillates, does not grow
    assert stable.max() < 1e-3
    assert below[-1] > 1e-3 and below[-1] > 10 * stable.max()  # falls


def test_wisp_radius_is_the_contact_radius_and_keeps_the_fibre_curvatures(sphere):
    """A strand 3 mm above the sphere touches nothing as a fibre and rests on it as a 4 mm wisp; a loose
    wisp scales mass and stiffness together, so a strand without contacts keeps a fibre's rest curvatures."""
    hovering = draped_strand(0.3, 3e-3)
    far = draped_strand(0.3, 2e-4) + np.array([0.0, 0.0, 0.5])
    groom = Groom.from_strands([hovering, far], source="wisps")
    fibre = invert_groom(groom, head=sphere, params=_params(contact_radius=None, contacts="head"))
    wisp = invert_groom(groom, head=sphere, params=_params(contact_radius=None, wisp_radius=4e-3, contacts="head"))
    assert not np.any(fibre.contacts.strand_a == 0)
    assert np.any(wisp.contacts.strand_a == 0) and wisp.contacts.radius == 4e-3
    assert wisp.report["wisp"]["fibres_per_strand"] == pytest.approx(0.5 * (4e-3 / MAT.radius) ** 2)
    assert wisp.report["equilibrium"]["max_relative_residual"] < 1e-8
    np.testing.assert_allclose(wisp.rest_curvatures[1], fibre.rest_curvatures[1], rtol=1e-12)
    with pytest.raises(ValueError, match="not both"):
        InversionParams(contact_radius=1e-3, wisp_radius=4e-3)


def test_simulate_api_uses_the_per_strand_moduli(tmp_path):
    """groomtool.simulate on a stabilised result (in memory and saved) runs with the stiffened K."""
    from groomtool.api import simulate

    pts = np.stack([np.zeros(40), np.linspace(0, 0.16, 40), np.zeros(40)], axis=1)  # standing, 16 cm
    bent = pts + np.stack([0.004 * np.sin(np.linspace(0, 3, 40)), np.zeros(40), np.zeros(40)], axis=1)
    groom = Groom.from_strands([pts + [0.01, 0, 0], bent], source="standing")
    res = invert_groom(groom, params=InversionParams(material=MAT, contacts="none", discrete_rest_data=False))
    assert np.all(res.stiffness_factor > 1)
    res.save(tmp_path / "out")
    for source in (res, tmp_path / "out"):
        seen = []
        simulate(source, seconds=2 / 240, contacts="none", callback=lambda sim, _: seen.append(sim.K))
        np.testing.assert_allclose(seen[0], res.stiffness(), rtol=1e-12)


def test_forces_keep_a_friction_margin(draped):
    """The inverse problem keeps every force in the cone of (1 - margin) mu: strictly inside the friction
    cone, so the simulator's contacts stick instead of sitting on the edge of sliding."""
    _, res = draped
    r = res.forces
    margin = res.params.friction_margin
    assert margin == 0.1
    loaded = r[:, 0] > 1e-9 * np.abs(r).max()
    tangential = np.linalg.norm(r[:, 1:], axis=1)
    assert np.all(tangential[loaded] <= (1 - margin) * MAT.friction * r[loaded, 0] * (1 + 1e-7))
    assert np.any(tangential[loaded] > 0.5 * (1 - margin) * MAT.friction * r[loaded, 0])  # friction is used
    with pytest.raises(ValueError, match="friction margin"):
        InversionParams(friction_margin=1.0)


def test_an_inverted_groom_stays_at_round_off_in_the_simulator(draped, sphere):
    """The stabilised draped groom, 120 steps (0.5 s): the tips stay within round-off.  Each step sweeps
    once from the accepted warm start (SimulationParams.refresh_warm_start): a warm start taken as it is
    holds the contact forces constant instead of imposing the contacts, and the drift then grew to
    ~5e-12 m over the same steps before the solver stepped in."""
    groom, _ = draped
    res = invert_groom(groom, head=sphere, params=_params())
    params = SimulationParams(contacts="all", contact_radius=res.contacts.radius)
    assert params.refresh_warm_start
    sim = Simulator(res.helix, res.rest_curvatures, MAT, res.gravity, head=sphere, params=params,
                    stiffness=res.stiffness(), warm_start=(res.contacts, res.forces))
    tips0 = sim.tips()
    for _ in range(120):
        system = sim.step()
        assert system.stats["solver_converged"]
    assert np.abs(sim.tips() - tips0).max() < 1e-14


def test_loose_stiffening_rounds_end_with_a_solve_to_the_requested_q0_tolerance(draped, sphere):
    """With the strand-split ADMM the stiffening rounds before the last are solved to 10x the q0 tolerance; the
    forces written come from a solve to the user's tolerance, whose q0 is within the certified bound of a tightly
    solved reference with the same stiffness factors, and the stability verdict is on those forces."""
    groom, _ = draped
    tol = 1e-4
    res = invert_groom(groom, head=sphere, params=_params(solver="admm", q0_tolerance=tol, solver_tolerance=1e-12))
    stab = res.report["stability"]["stabilization"]
    history = stab["history"]
    assert stab["rounds"] >= 1 and history[0]["q0_tolerance"] == pytest.approx(10 * tol)  # looser rounds first
    assert history[-1]["q0_tolerance"] == tol  # the last solve to the user's tolerance
    solve = res.report["solve"]
    assert solve["status"] == "solved" and solve["q0_error_bound"] <= tol
    assert solve["cone_violation"] <= 1e-14 * np.abs(res.forces).max()
    assert res.report["equilibrium"]["max_relative_residual"] < 1e-12
    ref = invert_groom(groom, head=sphere, params=_params(stabilize="none", stiffness_factor=res.stiffness_factor))
    ref_bound = ref.report["solve"]["q0_error_bound"]
    assert ref_bound < 1e-7
    true = np.linalg.norm(res.rest_curvatures - ref.rest_curvatures) / np.linalg.norm(ref.rest_curvatures)
    assert true <= solve["q0_error_bound"] + ref_bound
    # the verdict is on the forces written: the held ratios of those forces, all below their factors
    c, H = res.contacts, contact_jacobian(res.helix, res.contacts)
    held = held_stiffness_ratios(res.helix, MAT.stiffness_diag, MAT.linear_density, res.gravity, c, res.forces,
                                 H, MAT.friction, isolated_ratios=res.stiffness_ratio)
    np.testing.assert_allclose(held.ratio, res.held_ratio, rtol=1e-12)
    assert stab["unstable_strands"] == 0 and np.all(held.ratio < res.stiffness_factor)
    # an intermediate tolerance is only used by ADMM (Gauss-Seidel restarts from the forces alone) and only below
    # the user's: a looser user tolerance than LOOSE_Q0_MAX solves every round to it
    gs = invert_groom(groom, head=sphere, params=_params(solver="gs", q0_tolerance=tol, solver_tolerance=1e-12))
    assert all(h["q0_tolerance"] == tol for h in gs.report["stability"]["stabilization"]["history"])
    loose = invert_groom(groom, head=sphere, params=_params(solver="admm", q0_tolerance=0.05))
    assert all(h["q0_tolerance"] == 0.05 for h in loose.report["stability"]["stabilization"]["history"])


def test_stiffening_step_extrapolates_the_growth_of_a_raised_strand():
    """A strand raised from f0 = 1 (rho0 = 2) to f = 2.2 whose rho grew to 2.42 (rho ~ f^k, k = log 1.21 / log 2.2):
    the next factor is the fixed point f = margin rho (f / 2.2)^k, not margin * 2.42; a strand without a previous
    raise, or whose rho fell, gets margin * rho."""
    ratio = np.array([2.42, 3.0, 2.3])
    factor = np.array([2.2, 1.0, 2.2])
    previous = (np.array([2.0, 0.0, 2.5]), np.array([1.0, 1.0, 1.0]))
    new = stiffening_step(ratio, factor, margin=1.1, cap=100.0, previous=previous)
    k = np.log(2.42 / 2.0) / np.log(2.2)
    f = new[0]
    assert f == pytest.approx(1.1 * 2.42 * (f / 2.2) ** k, rel=1e-12) and f > 1.1 * 2.42
    np.testing.assert_allclose(new[1:], [3.3, 1.1 * 2.3])
    # the growth exponent is capped (MAX_GROWTH = 0.5): f = (margin rho)^2 / f_now at most
    steep = stiffening_step(np.array([4.0]), np.array([2.2]), 1.1, 100.0, previous=(np.array([0.5]), np.array([1.0])))
    assert steep[0] == pytest.approx((1.1 * 4.0) ** 2 / 2.2)


def test_strands_no_head_contact_blocks_take_the_certified_route_with_the_dense_result(draped, monkeypatch):
    """Loaded strands without loaded head contacts (nothing blocks them) get lambda_max of the whole
    K^-1/2 (dF/dq + dF_c/dq) K^-1/2 from its generators in O(N) (stability._lambda_max), and blocked ones on the null
    space of their rows in O(N k^2): the same numbers as the dense eigvalsh they replaced (forced here by a batch
    that certifies nothing), to 1e-10."""
    import groomtool.stability as stability

    _, res = draped
    helix, c = res.helix, res.contacts
    H = contact_jacobian(helix, c)
    r = np.zeros_like(res.forces)  # strand/strand loads only: no strand is blocked
    ss = np.flatnonzero(c.strand_b >= 0)
    assert len(ss)
    r[ss, 0] = MAT.linear_density * 9.81 * 5.0 * np.linspace(0.5, 1.5, len(ss))  # loads that matter against gravity
    r[ss, 1] = 0.3 * MAT.friction * r[ss, 0]
    fast = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G, c, r, H, MAT.friction)
    assert np.count_nonzero(fast.kind == 1) >= 2 and np.all(fast.blocked_rows == 0)

    blocked = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G, c, res.forces, H, MAT.friction)
    assert np.any(blocked.blocked_rows > 0)

    def certifies_nothing(*args):
        args[-1][:] = False  # ok: no strand certified, every one takes the dense route

    monkeypatch.setattr(stability, "_held_batch", certifies_nothing)
    dense = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G, c, r, H, MAT.friction)
    np.testing.assert_allclose(fast.ratio, dense.ratio, rtol=1e-10)
    iso = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G)
    assert np.any(np.abs(fast.ratio - iso) > 1e-3 * np.abs(iso))  # the loads count
    # strands their head contacts block: the O(N k^2) route (P A P - beta Q^T Q) against the dense null space route
    dense_blocked = held_stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G, c, res.forces, H,
                                          MAT.friction)
    norms = np.maximum(np.abs(dense_blocked.ratio), 1.0)
    assert np.all(np.abs(blocked.ratio - dense_blocked.ratio) <= 1e-10 * norms)
    np.testing.assert_array_equal(blocked.blocked_rows, dense_blocked.blocked_rows)
