"""The simulator with frictional contact.

- a strand dropped on a sphere comes to rest on it and never goes deeper than the contact thickness;
- a strand lying across a slope sticks when mu > tan(slope) and slides when mu < tan(slope);
- at an equilibrium K (q - q0) = F + H^T r_inv with r_inv in the friction cones, v = 0 and
  r = h r_inv solve the first step exactly, and the groom stays put;
- contact bookkeeping: matching, gaps, normal-velocity targets.
"""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from groomtool.contact import as_head_surface
from groomtool.contact.jacobian import generalized_contact_force
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.simulate import (SimulationParams, Simulator, State, contact_gaps, match_contacts,
                                normal_velocity_targets)

GRAVITY = np.array([0.0, -9.81, 0.0])
R_C = 50e-6  # the contact module's default contact radius


def frame(tangent, normal):
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    n = np.asarray(normal, float) - np.dot(normal, t) * t
    n /= np.linalg.norm(n)
    return np.stack([t, n, np.cross(t, n)], axis=1)


def test_strand_dropped_on_a_sphere_rests_on_it_without_penetrating():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    surface = as_head_surface(sphere)
    n = 8
    helix = sh.SuperHelix([-0.04, 0.07, 0.0], frame([1, 0, 0], [0, 1, 0]), np.full((1, n), 0.01), np.zeros((1, n, 3)))
    sim = Simulator(helix, np.zeros((1, n, 3)), Material(), GRAVITY, head=sphere,
                    params=SimulationParams(dt=1 / 240, contacts="head"))
    lowest, peak = np.inf, 0.0
    for _ in range(240):
        system = sim.step()
        pts = sh.sample(sim.helix(), 8)[0]
        lowest = min(lowest, surface.query(pts)[0].min())
        peak = max(peak, np.abs(sim.state.rates).max())
    assert system.stats["contacts"] >= 1
    # while the strand wraps round the sphere, points beside the single supporting contact (one per
    # local minimum of the distance) may dip in for a step before they are detected and pushed out
    assert lowest >= -1.5 * R_C
    pts = sh.sample(sim.helix(), 8)[0]
    assert 0.0 <= surface.query(pts)[0].min() < R_C  # at rest: in contact, within the thickness
    assert np.abs(sim.state.rates).max() < 1e-4 * peak  # at rest


def slope_run(mu_over_tan, slope_deg=20.0, seconds=0.3):
    """A straight soft strand lying across a slope (along its level line), root clamped at one end;
    returns the downhill displacement of its tip."""
    theta = np.radians(slope_deg)
    box = trimesh.creation.box(extents=[1.0, 0.1, 1.0])  # top face at y = 0.05
    rot = trimesh.transformations.rotation_matrix(theta, [0, 0, 1])
    box.apply_transform(rot)
    normal = rot[:3, :3] @ [0.0, 1.0, 0.0]
    downhill = GRAVITY - GRAVITY @ normal * normal
    downhill /= np.linalg.norm(downhill)
    level = np.cross(normal, downhill)
    root = rot[:3, :3] @ [0.0, 0.05, 0.0] + 0.6 * R_C * normal - 0.05 * level  # inside the thickness: no push
    n = 10
    helix = sh.SuperHelix(root, frame(level, downhill), np.full((1, n), 0.01), np.zeros((1, n, 3)))
    material = Material(friction=mu_over_tan * np.tan(theta))
    sim = Simulator(helix, np.zeros((1, n, 3)), material, GRAVITY, head=box,
                    params=SimulationParams(dt=1 / 240, contacts="head"))
    tip0 = sim.tips()[0]
    for _ in range(int(seconds * 240)):
        sim.step()
    return float((sim.tips()[0] - tip0) @ downhill)


def test_coulomb_threshold_on_a_slope():
    assert abs(slope_run(1.1)) < 2e-4  # sticks (the residue: elastic settling between discrete contacts)
    assert slope_run(0.9) > 2e-3  # slides


# --------------------------------------------------------------------------- exact equilibrium
def draped_strands():
    """Three strands over a sphere, crossing one another: head and strand/strand contacts."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    n = 10
    roots, frames, qs = [], [], []
    for k, angle in enumerate((0.0, 0.5, -0.45)):
        t = np.array([np.cos(angle), 0.0, np.sin(angle)])
        roots.append(np.array([0.0, 0.05 + (1.4 + 2.0 * k) * R_C, 0.0]) - 0.02 * t)
        frames.append(frame(t, [0, 1, 0]))
        q = np.zeros((n, 3))
        q[:, 2] = -1.0 / (0.05 + (1.4 + 2.0 * k) * R_C)  # follow the sphere's great circle
        qs.append(q)
    helix = sh.SuperHelix(np.array(roots), np.array(frames), np.full((3, n), 0.006), np.array(qs))
    return helix, sphere


def test_inverted_equilibrium_is_exact_for_the_first_step():
    helix, sphere = draped_strands()
    material = Material(friction=0.3)
    # a cold solve to 1e-8 (the default 1e-6 leaves rates ~5e-6 of the free ones: the bound below is the solve's)
    params = SimulationParams(dt=1 / 240, contacts="all", solver_tolerance=1e-8, max_sweeps=2000)
    probe = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params)
    contacts = probe.assemble().contacts
    assert contacts.n_strand_head >= 3 and contacts.n_strand_strand >= 2
    # any forces inside the cones make an equilibrium: q0 = q - K^-1 (F + H^T r_inv)
    rng = np.random.default_rng(0)
    m = len(contacts.strand_a)
    r_inv = np.zeros((m, 3))
    r_inv[:, 0] = material.linear_density * 9.81 * 0.03 * rng.uniform(0.5, 1.5, m)
    direction = rng.normal(size=(m, 2))
    r_inv[:, 1:] = 0.8 * material.friction * r_inv[:, :1] * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    K = sh.stiffness(helix, material.stiffness_diag)
    F = sh.gravity_force(helix, material.linear_density, GRAVITY)
    q0 = helix.curvatures - (F + generalized_contact_force(helix, contacts, r_inv)) / np.where(K > 0, K, 1.0)

    sim = Simulator(helix, q0, material, GRAVITY, head=sphere, params=params)
    system = sim.assemble()
    idx = match_contacts(contacts, system.contacts, 1e-12)
    assert np.all(idx >= 0) and len(idx) == m
    r = params.dt * r_inv[idx] / system.r_scale
    u = system.problem.velocity(r.ravel())
    assert np.abs(u).max() <= 1e-9 * np.abs(system.problem.b).max()  # u = W (h r_inv) + b = 0: stick
    assert system.problem.residual(r.ravel(), law="coulomb") < 1e-9
    impulses = sim.solve_contacts(system)
    sim.finish(system, impulses)
    assert np.abs(sim.state.rates).max() < 1e-6 * np.abs(system.v_free).max()
    tips0 = sim.tips()
    for _ in range(59):
        sim.step()
    assert np.linalg.norm(sim.tips() - tips0, axis=1).max() < 1e-6

    naive = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params)
    for _ in range(60):
        naive.step()
    assert np.linalg.norm(naive.tips() - tips0, axis=1).max() > 1e-4


def test_a_groom_at_rest_reuses_its_assembly_and_moves_as_with_a_new_one_every_step():
    """Simulator._at_rest_system: at rest the step matrices, contacts and H of the last assembly are kept (only F(q),
    K (q - q0), the right-hand side and the solve are new): the same motion as assembling every step; a sagging
    groom never reuses."""
    helix, sphere = draped_strands()
    material = Material(friction=0.3)
    probe = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere,
                      params=SimulationParams(dt=1 / 240, contacts="all"))
    contacts = probe.assemble().contacts
    m = len(contacts.strand_a)
    rng = np.random.default_rng(1)
    r_inv = np.zeros((m, 3))
    r_inv[:, 0] = material.linear_density * 9.81 * 0.03 * rng.uniform(0.5, 1.5, m)
    K = sh.stiffness(helix, material.stiffness_diag)
    F = sh.gravity_force(helix, material.linear_density, GRAVITY)
    q0 = helix.curvatures - (F + generalized_contact_force(helix, contacts, r_inv)) / np.where(K > 0, K, 1.0)
    runs = {}
    for rotation in (1e-7, 0.0):
        params = SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=rotation)
        sim = Simulator(helix, q0, material, GRAVITY, head=sphere, params=params, warm_start=(contacts, r_inv))
        tips0 = sim.tips()
        for _ in range(40):
            sim.step()
        runs[rotation] = (sim.reused_steps, sim.tips(), np.linalg.norm(sim.tips() - tips0, axis=1).max())
    reused, tips, drift = runs[1e-7]
    assert reused >= 30 and runs[0.0][0] == 0
    assert drift < 1e-7 and runs[0.0][2] < 1e-7
    assert np.linalg.norm(tips - runs[0.0][1], axis=1).max() <= 1e-3 * max(drift, runs[0.0][2]) + 1e-12

    naive = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere,
                      params=SimulationParams(dt=1 / 240, contacts="all"))
    for _ in range(20):
        naive.step()
    assert naive.reused_steps == 0


def test_a_step_at_rest_has_the_free_rates_and_contact_problem_of_a_new_assembly():
    """The kept assembly with this step's rates and forces: v_free and b as a fresh assembly's (the change of M, H
    and Mhat over the curvatures moved since, below reuse_rotation, is all that differs)."""
    helix, sphere = draped_strands()
    material = Material(friction=0.3)
    params = SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=1e-7)
    sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params)
    sim.assemble()
    assert sim._at_rest is not None
    rng = np.random.default_rng(2)
    rates = 1e-2 * rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    moved = helix.curvatures + 1e-9 * rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    sim.state = State(0.0, moved, rates)
    kept = sim.assemble()
    assert sim.reused_steps == 1
    fresh_sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere,
                          params=SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=0.0))
    fresh_sim.state = State(0.0, moved, rates)
    fresh = fresh_sim.assemble()
    assert fresh_sim._at_rest is None
    scale = np.abs(fresh.v_free).max()
    assert np.abs(kept.v_free - fresh.v_free).max() <= 1e-6 * scale
    idx = match_contacts(fresh.contacts, kept.contacts, 1e-12)
    assert np.all(idx >= 0) and len(idx) == len(fresh.contacts.strand_a)
    b_kept = kept.problem.b.reshape(-1, 3)[idx] * kept.r_scale
    b_fresh = fresh.problem.b.reshape(-1, 3) * fresh.r_scale
    assert np.abs(b_kept - b_fresh).max() <= 1e-6 * np.abs(b_fresh).max()
    assert kept.problem.rho() is sim._at_rest.system.problem.rho()  # W's cached data shared, not rebuilt


@pytest.mark.parametrize("damping", [(0.0, 0.0), (2.0, 1e-3)])
def test_a_step_at_rest_without_mass_matrices_is_the_assembled_step(damping):
    """Simulator._at_rest_system keeps no M: v_free = v + Mhat^-1 (h (F - K (q - q0) - A) - (Mhat - M) v) with
    (Mhat - M) v from K, the dF/dq generators, the unstable-mode corrections C and (with mass damping, a != 1) Mhat
    itself.  At the assembly's own curvatures it is the assembled step to round-off: strands rising against
    gravity (every one needs a C), random rates, velocity terms on, with and without damping."""
    n = 12
    roots = np.zeros((3, 3))
    roots[:, 0] = [0.0, 0.01, 0.02]
    frames = np.array([frame(np.array([0.1 * k, 0.0, 1.0]) / np.linalg.norm([0.1 * k, 0.0, 1.0]), [0, 1, 0])
                       for k in range(3)])
    rng = np.random.default_rng(0)
    helix = sh.SuperHelix(roots, frames, np.full((3, n), 0.05), 0.3 * rng.normal(size=(3, n, 3)))
    material = Material(young_modulus=1e4)
    rest = helix.curvatures + 0.1 * rng.normal(size=helix.curvatures.shape)
    rates = 0.5 * rng.normal(size=helix.curvatures.shape)
    params = dict(contacts="none", mass_damping=damping[0], stiffness_damping=damping[1])
    sim = Simulator(helix, rest, material, GRAVITY, params=SimulationParams(reuse_rotation=1e-7, **params),
                    initial_rates=rates)
    fresh = sim.assemble()
    assert sim._at_rest is not None and sim._factors.corrected.all()
    fresh = replace(fresh, v_free=fresh.v_free.copy())
    kept = sim.assemble()  # the same state: at rest
    assert sim.reused_steps == 1
    np.testing.assert_allclose(kept.v_free, fresh.v_free, rtol=0, atol=1e-11 * np.abs(fresh.v_free).max())


def test_a_strand_that_moved_alone_is_assembled_alone_and_the_step_is_the_assembled_one():
    """Simulator._partial_assembly: at rest but for one strand that turned by more than reuse_rotation, only that
    strand gets a new M, A, dF/dq and Mhat; the others keep theirs.  With the others exactly where they were
    assembled (and the same rates) the step equals a full assembly: free rates to round-off, the same contacts and
    free contact velocities.  The kept parts of the moved strand are replaced: the next step is at rest again."""
    helix, sphere = draped_strands()
    material = Material(friction=0.3)
    rng = np.random.default_rng(3)
    rates = 1e-2 * rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    params = SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=1e-7)
    sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params, initial_rates=rates)
    sim.assemble()
    moved = helix.curvatures.copy()
    moved[1] += 1e-3 * rng.normal(size=moved[1].shape) * helix.element_mask[1, :, None]  # strand 1 turned ~1e-4 rad
    sim.state = State(0.0, moved, rates)
    partial = sim.assemble()
    assert sim.partial_steps == 1 and sim.partial_strands == 1 and sim.reused_steps == 0
    fresh_sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, initial_rates=rates,
                          params=SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=0.0))
    fresh_sim.state = State(0.0, moved, rates)
    fresh = fresh_sim.assemble()
    np.testing.assert_allclose(partial.v_free, fresh.v_free, rtol=0, atol=1e-11 * np.abs(fresh.v_free).max())
    idx = match_contacts(fresh.contacts, partial.contacts, 1e-12)  # partial contact i is fresh contact idx[i]
    assert np.all(idx >= 0) and len(idx) == len(fresh.contacts.strand_a) == len(partial.contacts.strand_a)
    b_partial = partial.problem.b.reshape(-1, 3) * partial.r_scale
    b_fresh = fresh.problem.b.reshape(-1, 3)[idx] * fresh.r_scale
    np.testing.assert_allclose(b_partial, b_fresh, rtol=0, atol=1e-10 * np.abs(b_fresh).max())
    # W: the unmoved strands' D blocks taken from the kept problem, the moved one's new: those of a full assembly
    assert len(partial.problem.D_blocks) == len(fresh.problem.D_blocks)
    for mine, theirs in zip(partial.problem.D_blocks, fresh.problem.D_blocks):
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-11 * np.abs(theirs).max())
    np.testing.assert_array_equal(sim._at_rest.curvatures[1], moved[1])  # the moved strand's parts replaced
    sim.state = State(0.0, moved.copy(), rates)
    sim.assemble()
    assert sim.reused_steps == 1 and sim.partial_steps == 1


# --------------------------------------------------------------------------- bookkeeping
class _C:
    def __init__(self, a, b, sa, sb, d=None):
        self.strand_a, self.strand_b = np.array(a), np.array(b)
        self.s_a, self.s_b = np.array(sa, float), np.array(sb, float)
        self.distance = np.zeros(len(a)) if d is None else np.array(d, float)


def test_match_contacts_by_strands_and_arc_length():
    old = _C([0, 0, 1, 2], [-1, 1, 2, -1], [0.10, 0.05, 0.2, 0.3], [np.nan, 0.07, 0.1, np.nan])
    new = _C([0, 0, 1, 2, 3], [1, -1, 2, -1, -1], [0.0501, 0.1003, 0.2, 0.4, 0.1], [0.0702, np.nan, 0.2, np.nan, np.nan])
    assert match_contacts(old, new, 1e-3).tolist() == [1, 0, -1, -1, -1]


def test_gaps_and_normal_velocity_targets():
    c = _C([0, 0, 1], [-1, 1, -1], [0, 0, 0], [0, 0, 0], d=[3 * R_C, 1.5 * R_C, 0.2 * R_C])
    gap = contact_gaps(c, R_C)
    assert np.allclose(gap, [2 * R_C, -0.5 * R_C, -0.8 * R_C])
    h = 0.01
    ubar = normal_velocity_targets(gap, np.array([0.5 * R_C, 0.5 * R_C, 0.5 * R_C]), h, 0.2, 1.0)
    assert ubar[0] == pytest.approx(-2 * R_C / h)  # may close the gap in one step
    assert ubar[1] == 0.0  # within the allowance: no push
    assert ubar[2] == pytest.approx(0.2 * 0.3 * R_C / h)  # gentle push of the excess
