"""Super Space Clothoid kinematics and derivatives against independent references.

- frames and positions against direct ODE integration of R' = R [Omega]x, C' = R e0 (solve_ivp, DOP853);
- a helix (constant Omega) against the Super-Helix closed form;
- dC/dq, F = -dV/dq, dF/dq against central finite differences; V against quadrature of positions;
- K symmetric positive definite and consistent with the energy integral; M against finite-difference
  velocities; the truncation bound against the series it bounds.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from groomtool.fit import least_squares as ls
from groomtool.rods import clothoid as cl
from groomtool.rods import superhelix as sh
from reference import rods as rods_reference

GRAVITY = np.array([0.0, -9.81, 0.0])
RHO_S = 6.5e-6  # kg/m, a hair


def random_clothoid(seed, n_strands=3, n_elements=4, scale=30.0, zeros=False, pad=False):
    """Random nodal Darboux values (S, N + 1, 3); ``zeros`` puts exact zeros (a straight stretch) on strand 0,
    ``pad`` gives the strands different element counts (zero lengths and nodes beyond)."""
    rng = np.random.default_rng(seed)
    frames = Rotation.random(n_strands, random_state=seed).as_matrix()
    lengths = rng.uniform(0.005, 0.05, size=(n_strands, n_elements))
    q = rng.normal(size=(n_strands, n_elements + 1, 3)) * scale
    if zeros:
        q[0, : max(2, n_elements // 2 + 1)] = 0.0
        q[-1, -1] = 0.0
    n = np.full(n_strands, n_elements)
    if pad:
        n = rng.integers(1, n_elements + 1, size=n_strands)
        n[0] = n_elements
        for k in range(n_strands):
            lengths[k, n[k]:] = 0.0
            q[k, n[k] + 1:] = 0.0
    return cl.SuperClothoid(0.05 * rng.normal(size=(n_strands, 3)), frames, lengths, q, n)


def ode_states(clothoid, strand, s_eval):
    """Integrate C' = R e0, R' = R [Omega(s)]x element by element (rtol 1e-13); states at s_eval (sorted)."""
    q = clothoid.curvatures[strand]
    l = clothoid.lengths[strand]
    starts = clothoid.element_starts[strand]
    y = np.concatenate([clothoid.root_positions[strand], clothoid.root_frames[strand].ravel()])
    out = {}
    for j in range(clothoid.n_elements[strand]):
        a, b = q[j], (q[j + 1] - q[j]) / l[j]

        def rhs(s, y, a=a, b=b, s0=starts[j]):
            R = y[3:].reshape(3, 3)
            w = a + b * (s - s0)
            W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
            return np.concatenate([R[:, 0], (R @ W).ravel()])

        inside = [x for x in s_eval if starts[j] < x <= starts[j + 1] or (j == 0 and x == 0.0)]
        sol = solve_ivp(rhs, (starts[j], starts[j + 1]), y, method="DOP853", rtol=1e-13, atol=1e-15,
                        t_eval=sorted(set(inside) | {starts[j + 1]}))
        for x, col in zip(sol.t, sol.y.T):
            out[x] = col
        y = sol.y[:, -1]
    return np.array([out[x][:3] for x in s_eval]), np.array([out[x][3:].reshape(3, 3) for x in s_eval])


# --------------------------------------------------------------------------- kinematics
@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-7, 3.0, 60.0, 400.0]),
       n=st.integers(1, 4), zeros=st.booleans())
def test_kinematics_match_darboux_ode(seed, scale, n, zeros):
    """Nodes and interior points against solve_ivp; scale 400/m over 5 cm elements is ~20 rad per element
    (many sub-steps), 0 and 1e-7 the straight limit."""
    c = random_clothoid(seed % 10_000, n_strands=1, n_elements=n, scale=scale, zeros=zeros)
    kin = cl.kinematics(c)
    L = c.strand_lengths[0]
    rng = np.random.default_rng(seed)
    s_eval = np.unique(np.concatenate([c.element_starts[0, 1:], rng.uniform(0.0, L, 5)]))
    pos_ref, frames_ref = ode_states(c, 0, list(s_eval))
    pos, frames = cl.evaluate(c, np.zeros(len(s_eval), dtype=np.int64), s_eval, kin)
    assert np.abs(pos - pos_ref).max() <= 1e-12 * max(1.0, L)
    assert np.abs(frames - frames_ref).max() <= 1e-11
    assert np.abs(kin.C[0, 1:] - pos_ref[np.searchsorted(s_eval, c.element_starts[0, 1:])]).max() <= 1e-12
    assert np.abs(kin.R[0, 1:] - frames_ref[np.searchsorted(s_eval, c.element_starts[0, 1:])]).max() <= 1e-11


def test_frames_orthonormal_tangent_is_derivative_and_curvature_continuous():
    c = random_clothoid(5, scale=40.0)
    kin = cl.kinematics(c)
    strand = np.repeat(np.arange(3), 30)
    s = np.concatenate([np.linspace(0.0, L, 30) for L in c.strand_lengths])
    pos, frames = cl.evaluate(c, strand, s, kin)
    assert np.allclose(frames @ np.swapaxes(frames, 1, 2), np.eye(3), atol=1e-13)
    assert np.allclose(np.linalg.det(frames), 1.0, atol=1e-13)
    h = 1e-6
    interior = (s > h) & (s < c.strand_lengths[strand] - h)
    p1, f1 = cl.evaluate(c, strand, s + h, kin)
    p0, f0 = cl.evaluate(c, strand, s - h, kin)
    assert np.allclose(((p1 - p0) / (2 * h))[interior], frames[interior, :, 0], atol=1e-8)
    # C2 at the joints: C'' = R (Omega x e0) from both sides of every interior node
    nodes = c.element_starts[:, 1:-1]
    st_ = np.repeat(np.arange(3), nodes.shape[1])
    x = nodes.ravel()
    h = 2e-5

    def one_sided(sign):  # second-order one-sided stencil (2, -5, 4, -1) / h^2, within one element
        f = [cl.evaluate_positions(c, st_, x + sign * i * h, kin) for i in range(4)]
        return (2 * f[0] - 5 * f[1] + 4 * f[2] - f[3]) / h**2

    _, fr = cl.evaluate(c, st_, x, kin)
    w = c.curvatures[:, 1:-1].reshape(-1, 3)
    exact = np.einsum("pab,pb->pa", fr, np.cross(w, [1.0, 0.0, 0.0]))
    for sign in (-1, 1):
        assert np.allclose(one_sided(sign), exact, atol=1e-4 * np.abs(exact).max())


def test_sample_matches_evaluate_and_padding_is_identity():
    c = random_clothoid(3, n_strands=4, n_elements=5, pad=True)
    kin = cl.kinematics(c)
    pts, offsets, strand, arc = cl.sample(c, 6, kin)
    assert offsets[-1] == len(pts) == int((c.n_elements * 6 + 1).sum())
    assert np.array_equal(pts, cl.evaluate_positions(c, strand, arc, kin))
    for k in range(c.n_strands):  # nodes after the last real one repeat it
        n = c.n_elements[k]
        assert np.array_equal(kin.C[k, n:], np.broadcast_to(kin.C[k, n], kin.C[k, n:].shape))
    # the tip equals the unpadded strand's tip
    k = int(np.argmin(c.n_elements))
    alone = c.subset([k])
    assert np.allclose(cl.kinematics(alone).C[0, -1], kin.C[k, -1], atol=1e-15)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-9, 1.0, 50.0, 500.0]))
def test_constant_darboux_reproduces_the_super_helix(seed, scale):
    """Equal nodes (zero slopes) give a helix: nodes and interior points equal the Super-Helix closed form."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 5))
    w = rng.normal(size=3) * scale
    lengths = rng.uniform(0.005, 0.05, size=(1, n))
    frame = Rotation.random(1, random_state=seed % 10_000).as_matrix()
    root = rng.normal(size=(1, 3)) * 0.05
    c = cl.SuperClothoid(root, frame, lengths, np.broadcast_to(w, (1, n + 1, 3)))
    h = sh.SuperHelix(root, frame, lengths, np.broadcast_to(w, (1, n, 3)))
    kc, kh = cl.kinematics(c), sh.kinematics(h)
    assert np.abs(kc.C - kh.C).max() <= 1e-12
    assert np.abs(kc.R - kh.R).max() <= 1e-12
    s = rng.uniform(0, lengths.sum(), 7)
    pc, fc = cl.evaluate(c, np.zeros(7, dtype=np.int64), s, kc)
    ph, fh = sh.evaluate(h, np.zeros(7, dtype=np.int64), s, kh)
    assert np.abs(pc - ph).max() <= 1e-12 and np.abs(fc - fh).max() <= 1e-12


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-5, 2.0, 80.0, 600.0]))
def test_single_element_with_zero_slope_is_a_helix_element(seed, scale):
    """One element with b = 0 (discontinuous piecewise helices are built from these): Phi(l), p(l), P(l)
    equal the Super-Helix's Q, p, P for any omega."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=3) * scale
    l = float(rng.uniform(0.001, 0.08))
    Phi, p, P = np.empty((3, 3)), np.empty(3), np.empty(3)
    Mphi, MX, MZ = np.empty((2, 3, 3)), np.empty((3, 3, 3)), np.empty((2, 3, 3))
    cl._propagate(w, np.zeros(3), l, Phi, p, P, Mphi, MX, MZ, *cl._scratch(np.float64))
    kh = sh.kinematics(sh.SuperHelix(np.zeros(3), np.eye(3), [[l]], [[w]]))
    assert np.abs(Phi - kh.Q[0, 0]).max() <= 1e-13
    assert np.abs(p - kh.p[0, 0]).max() <= 1e-15 + 1e-13 * l
    assert np.abs(P - kh.P[0, 0]).max() <= 1e-16 + 1e-13 * l * l
    # the moment int Phi is Theta's local part Psi_1(l) of the helix
    assert np.abs(Mphi[0] - np.linalg.solve(kh.R[0, 0], kh.Theta[0, 0])).max() <= 1e-15 + 1e-13 * l


@settings(max_examples=200, deadline=None)
@given(alpha=st.floats(0.0, 0.5), beta=st.floats(0.0, 0.5))
def test_truncation_bound_bounds_the_majorant_tail(alpha, beta):
    """The stopping rule's bound really bounds sum_{k > K} d_k of exp(2 alpha x + beta x^2) (summed far out)."""
    K, bound = cl.n_terms(alpha, beta)
    assert bound <= cl.TOL and K < cl.K_MAX
    d = [1.0, 2 * alpha]
    for k in range(1, 120):
        d.append((2 * alpha * d[k] + 2 * beta * d[k - 1]) / (k + 1))
    tail = sum(d[K + 1:])
    assert tail <= bound * (1 + 1e-12) + 1e-300


def test_substeps_respect_the_bound_and_report_it():
    c = random_clothoid(11, n_strands=2, n_elements=3, scale=300.0)
    kin = cl.kinematics(c)
    assert (kin.stats[..., 2] <= cl.TOL).all()
    assert (kin.stats[..., 0] >= 2).any()  # tight coils are sub-stepped
    for A, B, T in [(0.0, 0.0, 0.1), (300.0, 0.0, 0.05), (10.0, 5e4, 0.05), (0.0, 1e5, 0.02)]:
        m = cl.n_substeps(A, B, T)
        h = T / m
        assert 2 * (A * h + B * h * h) <= cl.RHO * (1 + 1e-9)
        if m > 1:
            h = T / (m - 1)
            assert 2 * (A * h + B * h * h) > cl.RHO


# --------------------------------------------------------------------------- derivatives
def _central(fun, q, eps):
    """d fun / dq (fun: q (S, N+1, 3) -> (S, ...)) by central differences, stacked on a last axis (i, c)."""
    cols = []
    for i in range(q.shape[1]):
        for a in range(3):
            qp, qm = q.copy(), q.copy()
            qp[:, i, a] += eps
            qm[:, i, a] -= eps
            cols.append((fun(qp) - fun(qm)) / (2 * eps))
    return np.stack(cols, axis=-1)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 5.0, 80.0]), zeros=st.booleans())
def test_point_jacobians_match_finite_differences(seed, scale, zeros):
    c = random_clothoid(seed % 10_000, n_strands=3, n_elements=4, scale=scale, zeros=zeros, pad=True)
    rng = np.random.default_rng(seed)
    strand = np.repeat(np.arange(3), 4)
    s = rng.uniform(0, 1, 12) * c.strand_lengths[strand]
    s[0] = c.element_starts[0, 2]  # on a node
    J, _ = cl.point_jacobians(c, strand, s)
    eps = 1e-6
    fd = _central(lambda q: cl.evaluate_positions(c.with_curvatures(q), strand, s)[None], c.curvatures, eps)[0]
    fd = fd.reshape(len(s), 3, c.max_elements + 1, 3).transpose(0, 2, 1, 3)
    assert np.abs(J - fd).max() <= 1e-8 * max(1.0, np.abs(J).max() * 1e3)
    # nodes past the point's element carry nothing
    _, elem = cl.point_jacobians(c, strand, s)
    for i, e in enumerate(elem):
        assert not J[i, e + 2:].any()


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 5.0, 80.0]), zeros=st.booleans())
def test_gravity_force_is_minus_gradient_of_potential(seed, scale, zeros):
    c = random_clothoid(seed % 10_000, scale=scale, zeros=zeros, pad=True)
    F = cl.gravity_force(c, RHO_S, GRAVITY)
    fd = -_central(lambda q: cl.gravity_potential(c.with_curvatures(q), RHO_S, GRAVITY), c.curvatures, 1e-5)
    fd = fd.reshape(F.shape)
    assert np.abs(F - fd).max() <= 1e-7 * np.abs(F).max() + 1e-20
    assert not F[~c.node_mask].any()


def test_gravity_potential_matches_quadrature_of_positions():
    c = random_clothoid(2, scale=60.0)
    x, w = np.polynomial.legendre.leggauss(24)
    V = np.zeros(c.n_strands)
    for k in range(c.n_strands):
        for j in range(c.n_elements[k]):
            s = c.element_starts[k, j] + 0.5 * (x + 1) * c.lengths[k, j]
            pos = cl.evaluate_positions(c, np.full(len(s), k), s)
            V[k] += -RHO_S * 0.5 * c.lengths[k, j] * (w @ pos) @ GRAVITY
    assert np.allclose(cl.gravity_potential(c, RHO_S, GRAVITY), V, rtol=1e-12, atol=0)


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 5.0, 80.0]), zeros=st.booleans())
def test_gravity_force_jacobian_matches_finite_differences(seed, scale, zeros):
    c = random_clothoid(seed % 10_000, scale=scale, zeros=zeros, pad=True)
    H = cl.gravity_force_jacobian(c, RHO_S, GRAVITY)
    fd = _central(lambda q: cl.gravity_force(c.with_curvatures(q), RHO_S, GRAVITY).reshape(c.n_strands, -1),
                  c.curvatures, 1e-5)
    assert np.abs(H - fd).max() <= 1e-7 * np.abs(H).max()
    assert np.allclose(H, np.swapaxes(H, 1, 2), atol=1e-13 * np.abs(H).max())
    # the separable far blocks (j <= i - 2): rhoS A_i [g]x Theta_j
    A, Theta = rods_reference.clothoid_gravity_hessian_factors(c)
    gx = np.array([[0, -GRAVITY[2], GRAVITY[1]], [GRAVITY[2], 0, -GRAVITY[0]], [-GRAVITY[1], GRAVITY[0], 0]])
    for i in range(c.max_elements + 1):
        for j in range(i - 1):
            far = RHO_S * A[:, i] @ gx @ Theta[:, j]
            assert np.allclose(far, H[:, 3 * i:3 * i + 3, 3 * j:3 * j + 3], rtol=0, atol=1e-12 * np.abs(H).max())
    # recomputing only the two elements a node touches changes nothing (beyond round-off)
    assert np.allclose(H, rods_reference.clothoid_gravity_force_jacobian_full(c, RHO_S, GRAVITY), rtol=0,
                       atol=1e-13 * np.abs(H).max())


# --------------------------------------------------------------------------- stiffness and mass
def test_stiffness_is_spd_and_matches_the_energy_integral():
    c = random_clothoid(8, n_strands=3, n_elements=5, pad=True)
    D = np.array([2e-10, 3e-10, 4e-10])
    rng = np.random.default_rng(0)
    q0 = rng.normal(size=c.curvatures.shape) * 10 * c.node_mask[..., None]
    K = cl.stiffness_matrix(c, D)
    d = (c.curvatures - q0).reshape(c.n_strands, -1)
    E = cl.elastic_energy(c, q0, D)
    assert np.allclose(K, np.swapaxes(K, 1, 2))
    assert np.allclose(0.5 * np.einsum("si,sij,sj->s", d, K, d), E, rtol=1e-13)
    assert np.allclose(cl.stiffness_apply(c, D, c.curvatures - q0).reshape(c.n_strands, -1),
                       np.einsum("sij,sj->si", K, d), rtol=1e-13, atol=0)
    for k in range(c.n_strands):  # SPD on the real nodes
        m = np.repeat(c.node_mask[k], 3)
        assert np.linalg.eigvalsh(K[k][np.ix_(m, m)]).min() > 0
    # direct quadrature of 1/2 int (Omega - Omega0)^T D (Omega - Omega0) (quadratic per element: exact)
    x, w = np.polynomial.legendre.leggauss(3)
    t = 0.5 * (x + 1)
    diff = (c.curvatures - q0)
    ref = np.zeros(c.n_strands)
    for k in range(c.n_strands):
        for j in range(c.n_elements[k]):
            om = (1 - t)[:, None] * diff[k, j] + t[:, None] * diff[k, j + 1]
            ref[k] += 0.5 * 0.5 * c.lengths[k, j] * w @ (om ** 2 @ D)
    assert np.allclose(E, ref, rtol=1e-13)
    # the gradient of E is K d
    grad = _central(lambda q: cl.elastic_energy(c.with_curvatures(q), q0, D), c.curvatures, 1e-4)
    assert np.allclose(grad, np.einsum("sij,sj->si", K, d), rtol=1e-7, atol=1e-7 * np.abs(K @ d[..., None]).max())


def test_mass_matrix_gives_the_kinetic_energy_of_finite_difference_velocities():
    c = random_clothoid(9, n_strands=2, n_elements=3, scale=40.0)
    M = cl.mass_matrix(c, RHO_S)
    assert np.allclose(M, np.swapaxes(M, 1, 2), atol=1e-14 * np.abs(M).max())
    assert np.linalg.eigvalsh(M).min() > -1e-12 * np.abs(M).max()
    rng = np.random.default_rng(1)
    v = rng.normal(size=c.curvatures.shape)
    x, w = np.polynomial.legendre.leggauss(20)
    eps = 1e-6
    for k in range(c.n_strands):
        T = 0.0
        for j in range(c.n_elements[k]):
            s = c.element_starts[k, j] + 0.5 * (x + 1) * c.lengths[k, j]
            st_ = np.full(len(s), k)
            vel = (cl.evaluate_positions(c.with_curvatures(c.curvatures + eps * v), st_, s)
                   - cl.evaluate_positions(c.with_curvatures(c.curvatures - eps * v), st_, s)) / (2 * eps)
            T += RHO_S * 0.5 * c.lengths[k, j] * w @ (vel ** 2).sum(axis=1)
        vk = v[k].ravel()
        assert np.isclose(vk @ M[k] @ vk, T, rtol=1e-7)


# --------------------------------------------------------------------------- fitting prototype
def test_fit_prototype_recovers_a_sampled_clothoid_and_beats_the_helix_on_it():
    """A 3-element clothoid sampled every mm: the least-squares clothoid fit with N = 3 lies within 5e-5 m of
    every vertex (the distances measured to the fitted curve, independently of the fit's residual), the
    helix fit with N = 3 cannot (its curvature is piecewise constant)."""
    q = np.array([[1.0, 5, -3], [0, 25, 10], [-2, -15, 30], [1, 5, -20]])
    c = cl.SuperClothoid(np.zeros(3), np.eye(3), [[0.05, 0.05, 0.05]], q[None])
    X = cl.evaluate_positions(c, np.zeros(151, dtype=np.int64), np.linspace(0, 0.15, 151))
    fit = ls.fit_polyline_ls(X, 3, "clothoid", iterations=60)
    assert fit.max_error < 5e-5
    assert abs(fit.rod.strand_lengths[0] - 0.15) < 1e-4
    pts = cl.sample(fit.rod, 32)[0]
    assert np.allclose(ls.polyline_distances(X, pts).max(), fit.max_error)
    helix = ls.fit_polyline_ls(X, 3, "helix", iterations=60)
    assert helix.max_error > 10 * fit.max_error


def test_polyline_distances_brute_force():
    rng = np.random.default_rng(0)
    curve = np.cumsum(rng.normal(size=(20, 3)), axis=0)
    pts = rng.normal(size=(7, 3)) * 3
    t = np.linspace(0, 1, 2001)
    dense = (curve[:-1, None] + t[None, :, None] * (curve[1:] - curve[:-1])[:, None]).reshape(-1, 3)
    ref = np.sqrt(((pts[:, None] - dense[None]) ** 2).sum(-1)).min(axis=1)
    assert np.allclose(ls.polyline_distances(pts, curve), ref, atol=2e-3)
    assert (ls.polyline_distances(pts, curve) <= ref + 1e-12).all()


def test_isolated_inversion_solves_the_equilibrium():
    """q0 = q - K^-1 F: K (q - q0) = F (banded product) and the Thomas solve equals a dense solve, on padded strands."""
    c = random_clothoid(12, n_strands=4, n_elements=6, scale=40.0, pad=True)
    D = np.array([1.5e-10, 2e-10, 2.5e-10])
    q0 = cl.rest_curvatures(c, RHO_S, GRAVITY, D)
    F = cl.gravity_force(c, RHO_S, GRAVITY)
    assert np.allclose(cl.stiffness_apply(c, D, c.curvatures - q0), F, rtol=0, atol=1e-12 * np.abs(F).max())
    assert not q0[~c.node_mask].any()
    K = cl.stiffness_matrix(c, D)
    for k in range(c.n_strands):
        m = np.repeat(c.node_mask[k], 3)
        ref = np.linalg.solve(K[k][np.ix_(m, m)], F[k].ravel()[m])
        assert np.allclose((c.curvatures[k] - q0[k]).ravel()[m], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    # the equilibrium is the stationary point of E + V: its gradient K (q - q0) - F vanishes
    grad = _central(lambda q: cl.elastic_energy(c.with_curvatures(q), q0, D)
                    + cl.gravity_potential(c.with_curvatures(q), RHO_S, GRAVITY), c.curvatures, 1e-5)
    assert np.abs(grad).max() <= 1e-6 * np.abs(F).max()


def test_state_only_path_equals_the_full_propagation():
    """evaluate's Phi, p pass (no moments) gives the full kernel's Phi, p to round-off."""
    c = random_clothoid(21, n_strands=3, n_elements=4, scale=150.0, pad=True)
    kin = cl.kinematics(c)
    strand = np.repeat(np.arange(3), 9)
    s = np.concatenate([np.linspace(0, L, 9) for L in c.strand_lengths])
    elem, t = cl.locate(c, strand, s)
    Phi, p, _, _ = cl._partial(c, kin, strand, elem, t)
    pos, frames = cl.evaluate(c, strand, s, kin)
    Re = kin.R[strand, elem]
    assert np.allclose(frames, Re @ Phi, rtol=0, atol=1e-14)
    assert np.allclose(pos, kin.C[strand, elem] + np.einsum("pab,pb->pa", Re, p), rtol=0, atol=1e-15)
    light = cl.kinematics(c, moments=False)
    assert np.allclose(light.C, kin.C, rtol=0, atol=1e-15) and np.allclose(light.R, kin.R, rtol=0, atol=1e-14)
    assert np.array_equal(cl.evaluate(c, strand, s, light)[0], cl.evaluate(c, strand, s)[0])
    with pytest.raises(ValueError, match="moments"):
        cl.gravity_force(c, RHO_S, GRAVITY, light)


def test_non_finite_curvatures_propagate_instead_of_hanging():
    c = random_clothoid(4, n_strands=2, n_elements=3)
    c.curvatures[1, 2, 1] = np.nan
    kin = cl.kinematics(c)
    assert np.isfinite(kin.C[0]).all() and np.isnan(kin.C[1, 2:]).all()
    assert cl.n_terms(np.nan, 0.0)[0] == cl.K_MAX and cl.n_substeps(np.inf, 0.0, 0.1) == 1
