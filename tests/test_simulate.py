"""The forward simulator without contact, against physics and finite differences.

- mass matrix: translational part equals superhelix.mass_matrix, rotational part a brute-force
  quadrature of Jm^T diag(rho J, rho I, rho I) Jm with Jm from finite differences of the frames;
- the velocity terms A(q, qd): point accelerations against second differences of positions, and A
  against Lagrange's equations A = Mdot qd - 1/2 d(qd^T M qd)/dq by finite differences of M;
- a hinge (rigid rod) pendulum's small-angle period against 2 pi sqrt(I_hinge / (m g L / 2));
- energy conservation without damping; stability at animation time steps;
- an isolated inverted strand (q0 = q - K^-1 F) stays put, the naive one (q0 = q) sags;
- a head accelerating upwards is the same as a stronger gravity in the head frame.
"""

import numpy as np
import pytest

from reference import dynamics as ref
from groomtool.material import Material
from groomtool.rods import dynamics as dyn
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator, simulate

MAT = Material()
GRAVITY = np.array([0.0, -9.81, 0.0])


def frame(tangent, normal):
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    n = np.asarray(normal, float) - np.dot(normal, t) * t
    n /= np.linalg.norm(n)
    return np.stack([t, n, np.cross(t, n)], axis=1)


def random_helix(seed, n_strands=2, n_elements=4, scale=20.0, pad=True):
    rng = np.random.default_rng(seed)
    frames = np.stack([frame(rng.normal(size=3), rng.normal(size=3)) for _ in range(n_strands)])
    lengths = rng.uniform(0.01, 0.04, size=(n_strands, n_elements))
    q = rng.normal(size=(n_strands, n_elements, 3)) * scale
    if pad and n_strands > 1:
        lengths[1, -1] = 0.0
        q[1, -1] = 0.0
    return sh.SuperHelix(rng.normal(size=(n_strands, 3)) * 0.05, frames, lengths, q)


def perturb(helix, i, eps):
    q = helix.curvatures.copy()
    q.reshape(helix.n_strands, -1)[:, i] += eps
    return helix.with_curvatures(q * helix.element_mask[..., None])


# --------------------------------------------------------------------------- inertia
def test_translational_mass_matrix_matches_superhelix():
    helix = random_helix(0)
    M = dyn.mass_matrix(helix, dyn.Inertia(0.01, (0.0, 0.0, 0.0)), order=6)
    ref = sh.mass_matrix(helix, 0.01, order=6)
    assert np.allclose(M, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_rotational_mass_matrix_matches_brute_force_quadrature():
    helix = random_helix(1, n_strands=1, n_elements=3)
    rot = np.array([3e-3, 1e-3, 2e-3])
    M = dyn.mass_matrix(helix, dyn.Inertia(0.0, tuple(rot)), order=6)
    xg, wg = np.polynomial.legendre.leggauss(6)
    ref = np.zeros_like(M[0])
    eps = 1e-6
    for j in range(helix.n_elements[0]):
        for xq, wq in zip(0.5 * (xg + 1), 0.5 * wg):
            s = np.array([helix.element_starts[0, j] + xq * helix.lengths[0, j]])
            _, R = sh.evaluate(helix, [0], s)
            Jw = np.zeros((3, M.shape[1]))
            for i in range(M.shape[1]):
                _, Rp = sh.evaluate(perturb(helix, i, eps), [0], s)
                _, Rm = sh.evaluate(perturb(helix, i, -eps), [0], s)
                W = (Rp[0] - Rm[0]) / (2 * eps) @ R[0].T  # [dtheta]x
                Jw[:, i] = [W[2, 1], W[0, 2], W[1, 0]]
            Jm = R[0].T @ Jw
            ref += wq * helix.lengths[0, j] * Jm.T @ np.diag(rot) @ Jm
    assert np.allclose(M[0], ref, rtol=0, atol=1e-7 * np.abs(ref).max())


def test_inertia_of_a_fibre():
    inertia = dyn.Inertia.from_material(MAT, rotational_scale=2.0)
    assert inertia.linear == pytest.approx(MAT.density * np.pi * MAT.radius**2)
    assert inertia.rotational[0] == pytest.approx(2 * 2 * MAT.density * MAT.second_moment)
    assert inertia.rotational[1] == pytest.approx(2 * MAT.density * MAT.second_moment)


def test_mass_matrix_is_positive_definite_with_rotation():
    """Straight elements: translation alone leaves twist without inertia; the cross-section fixes it."""
    helix = sh.SuperHelix(np.zeros(3), frame([0, -1, 0], [1, 0, 0]), np.full((1, 4), 0.02), np.zeros((1, 4, 3)))
    M = dyn.mass_matrix(helix, dyn.Inertia.from_material(MAT))
    assert np.linalg.eigvalsh(M[0]).min() > 0
    M_trans = sh.mass_matrix(helix, MAT.linear_density)
    assert np.linalg.eigvalsh(M_trans[0]).min() < 1e-12 * np.linalg.eigvalsh(M[0]).min()


# --------------------------------------------------------------------------- velocity terms
@pytest.mark.parametrize("seed", [2, 3])
def test_point_accelerations_are_second_derivatives(seed):
    """a(s) = d^2/de^2 C(q + e v) at e = 0 and alpha(s) = d/de [Jw(q + e v) v] (qdd = 0)."""
    helix = random_helix(seed)
    rng = np.random.default_rng(seed)
    v = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    kin = sh.kinematics(helix)
    pts = ref.element_points(helix, kin, order=3)
    mo = ref.point_motion(helix, v, kin, pts, ref.node_motion(helix, v, kin))
    h = 1e-4

    def points(e):
        hh = helix.with_curvatures(helix.curvatures + e * v)
        k = sh.kinematics(hh)
        return ref.element_points(hh, k, order=3), k

    (pp, kp), (p0, k0), (pm, km) = points(h), points(0.0), points(-h)
    C = [p.x + k.C[:, :1, None] for p, k in ((pp, kp), (p0, k0), (pm, km))]
    acc_fd = (C[0] - 2 * C[1] + C[2]) / h**2
    vel_fd = (C[0] - C[2]) / (2 * h)
    mask = helix.element_mask[..., None, None]
    assert np.allclose(mo.V * mask, vel_fd * mask, rtol=0, atol=1e-6 * np.abs(vel_fd).max())
    assert np.allclose(mo.a * mask, acc_fd * mask, rtol=0, atol=1e-4 * np.abs(acc_fd).max())

    def omega(e):
        hh = helix.with_curvatures(helix.curvatures + e * v)
        k = sh.kinematics(hh)
        p = ref.element_points(hh, k, order=3)
        return ref.point_motion(hh, v, k, p, ref.node_motion(hh, v, k)).Omega

    alpha_fd = (omega(h) - omega(-h)) / (2 * h)
    assert np.allclose(mo.alpha * mask, alpha_fd * mask, rtol=0, atol=1e-6 * np.abs(alpha_fd).max())


def test_velocity_terms_satisfy_lagrange_equations():
    """A = Mdot v - 1/2 grad_q (v^T M v), both sides by central differences of M."""
    helix = random_helix(4, n_elements=3)
    inertia = dyn.Inertia(0.01, (3e-3, 1e-3, 2e-3))
    rng = np.random.default_rng(4)
    v = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    A = dyn.velocity_terms(helix, v, inertia, order=5).reshape(helix.n_strands, -1)
    S, n = A.shape
    e = 1e-6

    def M(hh):
        return dyn.mass_matrix(hh, inertia, order=5)

    vf = v.reshape(S, n)
    Mdot = (M(helix.with_curvatures(helix.curvatures + e * v)) - M(helix.with_curvatures(helix.curvatures - e * v))) / (2 * e)
    grad = np.zeros((S, n))
    for i in range(n):
        Tp = np.einsum("si,sij,sj->s", vf, M(perturb(helix, i, e)), vf)
        Tm = np.einsum("si,sij,sj->s", vf, M(perturb(helix, i, -e)), vf)
        grad[:, i] = (Tp - Tm) / (2 * e)
    ref = np.einsum("sij,sj->si", Mdot, vf) - 0.5 * grad
    assert np.allclose(A, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


# --------------------------------------------------------------------------- physics
def hinge_pendulum(L=0.1, theta0=0.02, hinge=1e-6):
    """A rigid rod of length L hanging from a hinge: a tiny first element (K = 0) bent by theta0 / hinge,
    a stiff second element (K large, rest straight)."""
    q = np.zeros((1, 2, 3))
    q[0, 0, 2] = theta0 / hinge  # bending about n2: the rod swings in the (n0, n1) plane
    helix = sh.SuperHelix(np.zeros(3), frame([0, -1, 0], [1, 0, 0]), np.array([[hinge, L]]), q)
    K = np.zeros((1, 2, 3))
    K[0, 1] = 1e4 * MAT.bending_stiffness * L
    return helix, K


def crossing_times(t, x):
    """Times of the downward zero crossings of x(t), linearly interpolated."""
    k = np.flatnonzero((x[:-1] > 0) & (x[1:] <= 0))
    return t[k] + (t[k + 1] - t[k]) * x[k] / (x[k] - x[k + 1])


@pytest.mark.parametrize("rotational_scale", [1.0, 3e6])
def test_hinge_pendulum_period(rotational_scale):
    """T = 2 pi sqrt((rhoS L^3 / 3 + rho I L) / (rhoS L g L / 2)); the large scale makes the
    cross-section's rotational inertia a ~30 % effect, so it is tested too."""
    L, hinge = 0.1, 1e-6
    helix, K = hinge_pendulum(L, hinge=hinge)
    params = SimulationParams(dt=1e-3, contacts="none", rotational_inertia_scale=rotational_scale)
    sim = Simulator(helix, np.zeros_like(helix.curvatures), MAT, GRAVITY, params=params, stiffness=K)
    rhoS = MAT.linear_density
    rhoI = MAT.density * MAT.second_moment * rotational_scale
    period = 2 * np.pi * np.sqrt((rhoS * L**3 / 3 + rhoI * L) / (rhoS * L * 9.81 * L / 2))
    t, angle = [], []
    for _ in range(int(1.3 * period / params.dt)):
        sim.step()
        t.append(sim.state.time)
        angle.append(sim.state.curvatures[0, 0, 2] * hinge)
    down = crossing_times(np.array(t), np.array(angle))
    assert len(down) >= 2
    assert down[1] - down[0] == pytest.approx(period, rel=2e-3)


def energy_drift(velocity_terms: bool, steps=1000, dt=2.5e-4):
    """max |E(t) - E(0)| / max kinetic energy for a curved strand falling from a horizontal root."""
    q = np.zeros((1, 3, 3))
    q[0, :, 1], q[0, :, 2] = 5.0, 3.0
    helix = sh.SuperHelix(np.zeros(3), frame([1, 0, 0], [0, 1, 0]), np.full((1, 3), 0.05), q)
    params = SimulationParams(dt=dt, contacts="none", velocity_terms=velocity_terms)
    sim = Simulator(helix, q.copy(), MAT, GRAVITY, params=params)
    e0 = sum(sim.energies().values())
    drift, kinetic = 0.0, 0.0
    for k in range(steps):
        sim.step()
        if k % 25 == 24:
            e = sim.energies()
            drift = max(drift, abs(sum(e.values()) - e0))
            kinetic = max(kinetic, e["kinetic"])
    return drift / kinetic


def test_energy_is_conserved_without_damping():
    """Semi-implicit Euler with implicit elasticity: first-order energy error, small at dt = 2.5e-4
    over 1,000 steps.  Dropping A(q, qd) breaks it by an order of magnitude on the same motion."""
    with_a = energy_drift(True)
    assert with_a < 0.01
    assert energy_drift(False) > 10 * with_a


def hanging_strand(n=10, length=0.15, wiggle=4.0, seed=0):
    """A strand leaving a horizontal root and curving down, with some 3D waviness."""
    rng = np.random.default_rng(seed)
    q = np.zeros((1, n, 3))
    q[0, :, 2] = -np.pi / 2 / (0.3 * length)  # bend down over the first 30 %
    q[0, int(0.3 * n):, 2] = 0.0
    q[0] += rng.normal(size=(n, 3)) * wiggle
    return sh.SuperHelix(np.zeros(3), frame([1, 0, 0], [0, 1, 0]), np.full((1, n), length / n), q)


@pytest.mark.parametrize("dt", [1 / 24, 1 / 240])
def test_stable_at_animation_steps(dt):
    """A naive strand (rest = its curved shape) sags and swings: finite, no energy created."""
    helix = hanging_strand()
    sim = Simulator(helix, helix.curvatures.copy(), MAT, GRAVITY, params=SimulationParams(dt=dt, contacts="none"))
    e0 = sum(sim.energies().values())
    for _ in range(int(round(1.0 / dt))):
        sim.step()
    e = sum(sim.energies().values())
    assert np.all(np.isfinite(sim.state.rates))
    assert e <= e0 + 1e-3 * abs(e0)


def test_isolated_inverted_strand_stays_put_and_naive_sags():
    helix = hanging_strand(seed=1)
    K = sh.stiffness(helix, MAT.stiffness_diag)
    F = sh.gravity_force(helix, MAT.linear_density, GRAVITY)
    inverted = helix.curvatures - F / K
    kw = dict(seconds=1.0, dt=1 / 240, contacts="none", frames_per_second=None)
    still = simulate(helix, inverted, MAT, GRAVITY, **kw)
    sag = simulate(helix, helix.curvatures.copy(), MAT, GRAVITY, **kw)
    drift = np.linalg.norm(still.tips[-1] - still.tips[0], axis=-1).max()
    sagged = np.linalg.norm(sag.tips[-1] - sag.tips[0], axis=-1).max()
    assert drift < 1e-6
    assert sagged > 1e-2
    assert len(still.frames) == still.timings["steps"] + 1


def test_accelerating_head_is_stronger_gravity():
    """Root translating with x(t) = 1/2 a t^2: in the head frame, gravity g - a (equivalence principle)."""
    helix = hanging_strand(n=6, seed=2)
    a = np.array([0.0, 4.0, 0.0])
    params = SimulationParams(dt=1 / 240, contacts="none", implicit_gravity=False)

    def motion(t):
        return np.eye(3), 0.5 * a * t * t

    moving = Simulator(helix, helix.curvatures.copy(), MAT, GRAVITY, params=params, head_motion=motion)
    fixed = Simulator(helix, helix.curvatures.copy(), MAT, GRAVITY - a, params=params)
    for _ in range(48):
        moving.step()
        fixed.step()
    assert np.allclose(moving.state.curvatures, fixed.state.curvatures, rtol=0,
                       atol=1e-6 * np.abs(fixed.state.curvatures).max())
    assert np.allclose(moving.helix().root_positions, 0.5 * a * moving.state.time**2)
