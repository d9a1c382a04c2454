"""Super-Helix kinematics and derivatives against independent references.

- positions and frames against direct ODE integration of the Darboux problem (solve_ivp);
- dC/dq, F = -dV/dq and dF/dq against central finite differences;
- the series functions against the closed forms, including w -> 0.
"""

from math import factorial

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from groomtool.rods import superhelix as sh
from groomtool.rods.series import SERIES_X, c_table
from reference.rods import f_table, kinematics_reference


def random_helix(seed, n_strands=3, n_elements=5, scale=30.0, zero_some=True):
    rng = np.random.default_rng(seed)
    frames = Rotation.random(n_strands, random_state=seed).as_matrix()
    lengths = rng.uniform(0.01, 0.05, size=(n_strands, n_elements))
    q = rng.normal(size=(n_strands, n_elements, 3)) * scale
    if zero_some:
        q[0, 1] = 1e-9  # w -> 0 through the series
        q[-1, -1] = 0.0
    return sh.SuperHelix(0.05 * rng.normal(size=(n_strands, 3)), frames, lengths, q)


def ode_end_state(helix, strand):
    """Integrate C' = n0, n_i' = Omega x n_i element by element with tight tolerances."""
    w = helix.curvatures[strand]
    starts = helix.element_starts[strand]
    y = np.concatenate([helix.root_positions[strand], helix.root_frames[strand].ravel()])
    for j in range(helix.n_elements[strand]):
        def rhs(s, y, j=j):
            R = y[3:].reshape(3, 3)
            omega_world = R @ w[j]
            return np.concatenate([R[:, 0], np.cross(omega_world, R.T).T.ravel()])

        sol = solve_ivp(rhs, (starts[j], starts[j + 1]), y, rtol=1e-12, atol=1e-14, method="DOP853")
        y = sol.y[:, -1]
    return y[:3], y[3:].reshape(3, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kinematics_match_darboux_ode(seed):
    helix = random_helix(seed)
    kin = sh.kinematics(helix)
    for strand in range(helix.n_strands):
        pos, frame = ode_end_state(helix, strand)
        assert np.allclose(kin.C[strand, -1], pos, atol=1e-12, rtol=0)
        assert np.allclose(kin.R[strand, -1], frame, atol=1e-11, rtol=0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-6, 3.0, 30.0, 300.0]))
def test_compiled_kinematics_match_vectorised_reference(seed, scale):
    """Every Kinematics field of the compiled pass equals the numpy formulas to round-off, on strands
    padded to different lengths, straight elements, the series/closed-form switch and tight coils."""
    helix = random_helix(seed % 1000, n_strands=4, n_elements=6, scale=scale)
    rng = np.random.default_rng(seed)
    n = rng.integers(1, 7, size=4)
    n[0] = 6
    for k in range(4):
        helix.lengths[k, n[k]:] = 0.0
        helix.curvatures[k, n[k]:] = 0.0
    helix = sh.SuperHelix(helix.root_positions, helix.root_frames, helix.lengths, helix.curvatures, n)
    got, ref = sh.kinematics(helix), kinematics_reference(helix)
    for name in ("C", "R", "Q", "p", "P", "D", "DP", "Theta", "c", "dc", "z"):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.shape == b.shape, name
        assert np.allclose(a, b, rtol=1e-13, atol=1e-13 * max(1.0, np.abs(b).max())), name


@pytest.mark.parametrize("scale", [0.0, 3.0, 300.0])
def test_sample_positions_equal_evaluate(scale):
    """sample's positions-only kernel gives exactly evaluate's positions (series and closed-form f_2, f_3)."""
    helix = random_helix(7, n_strands=5, n_elements=4, scale=scale)
    pts, offsets, strand, arc = sh.sample(helix, 8)
    pos, _ = sh.evaluate(helix, strand, arc)
    assert np.array_equal(pts, pos)
    assert offsets[-1] == len(pts) == 5 * (4 * 8 + 1)


def test_evaluate_matches_ode_mid_element():
    helix = random_helix(4, n_strands=1, n_elements=3)
    s = 0.6 * helix.strand_lengths[0]
    cut = sh.SuperHelix(helix.root_positions, helix.root_frames, helix.lengths.copy(), helix.curvatures)
    # shorten the strand to end at s and integrate to its end
    starts = helix.element_starts[0]
    e = np.searchsorted(starts, s) - 1
    cut.lengths[0, e] = s - starts[e]
    cut.lengths[0, e + 1:] = 0.0
    cut.n_elements = np.array([e + 1])
    pos_ref, frame_ref = ode_end_state(cut, 0)
    pos, frame = sh.evaluate(helix, [0], [s])
    assert np.allclose(pos[0], pos_ref, atol=1e-12)
    assert np.allclose(frame[0], frame_ref, atol=1e-11)


def test_frames_stay_orthonormal_and_tangent_is_derivative():
    helix = random_helix(5)
    strand = np.repeat(np.arange(3), 20)
    s = np.tile(np.linspace(0.0, 0.1, 20), 3)
    pos, frames = sh.evaluate(helix, strand, s)
    assert np.allclose(frames @ np.swapaxes(frames, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(frames), 1.0, atol=1e-12)
    h = 1e-6
    p1, _ = sh.evaluate(helix, strand, s + h)
    p0, _ = sh.evaluate(helix, strand, s - h)
    interior = (s > h) & (s < helix.strand_lengths[strand] - h)
    assert np.allclose(((p1 - p0) / (2 * h))[interior], frames[interior, :, 0], atol=1e-7)


def _central_difference(fun, q, eps):
    """d fun / dq by central differences over every (element, component) of q (S, N, 3)."""
    out = []
    for k in range(q.shape[1]):
        for a in range(3):
            qp = q.copy()
            qp[:, k, a] += eps
            qm = q.copy()
            qm[:, k, a] -= eps
            out.append((fun(qp) - fun(qm)) / (2 * eps))
    return np.stack(out, axis=-1)  # (..., 3N)


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0, 150.0]))
@settings(max_examples=25, deadline=None)
def test_point_jacobian_matches_finite_differences(seed, scale):
    helix = random_helix(seed, scale=scale, zero_some=False)
    rng = np.random.default_rng(seed)
    strand = rng.integers(0, helix.n_strands, size=6)
    s = rng.uniform(0, 1, size=6) * helix.strand_lengths[strand]
    J, _ = sh.point_jacobians(helix, strand, s)
    fd = _central_difference(lambda q: sh.evaluate(helix.with_curvatures(q), strand, s)[0],
                             helix.curvatures, 1e-5)
    J_flat = J.transpose(0, 2, 1, 3).reshape(len(s), 3, -1)
    assert np.allclose(J_flat, fd, atol=1e-8 * max(1.0, np.abs(J).max()))


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-7, 3.0, 60.0]))
@settings(max_examples=20, deadline=None)
def test_gravity_force_is_minus_gradient_of_potential(seed, scale):
    helix = random_helix(seed, scale=scale, zero_some=False)
    g = np.array([0.0, -9.81, 0.0])
    rho = 0.004
    F = sh.gravity_force(helix, rho, g)
    fd = -_central_difference(lambda q: sh.gravity_potential(helix.with_curvatures(q), rho, g),
                              helix.curvatures, 1e-5)
    assert np.allclose(F.reshape(helix.n_strands, -1), fd, atol=1e-8 * np.abs(F).max() + 1e-15)


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-7, 3.0, 60.0]))
@settings(max_examples=20, deadline=None)
def test_gravity_force_kernel_is_the_integrated_jacobians_product(seed, scale):
    """The compiled F_j = rhoS (DP_j^T u + m D_j^T u + Theta_j^T (X x g)) is rhoS G_j^T g of the batched G (to
    round-off), padded strands included (zero there)."""
    from reference.rods import gravity_force_reference

    full = random_helix(seed, scale=scale)
    lengths, q = full.lengths.copy(), full.curvatures.copy()
    lengths[1, 3:], q[1, 3:] = 0.0, 0.0  # strand 1 has 3 elements, padded to 5
    helix = sh.SuperHelix(full.root_positions, full.root_frames, lengths, q, np.array([5, 3, 5]))
    g = np.array([0.3, -9.81, 0.5])
    F = sh.gravity_force(helix, 0.004, g)
    ref = gravity_force_reference(helix, 0.004, g)
    np.testing.assert_allclose(F, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    assert np.all(F[~helix.element_mask] == 0.0)


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-7, 3.0, 60.0]))
@settings(max_examples=20, deadline=None)
def test_gravity_force_jacobian_matches_finite_differences(seed, scale):
    helix = random_helix(seed, scale=scale, zero_some=False)
    g = np.array([0.3, -9.81, 0.5])
    rho = 0.004
    dF = sh.gravity_force_jacobian(helix, rho, g)
    fd = _central_difference(lambda q: sh.gravity_force(helix.with_curvatures(q), rho, g).reshape(helix.n_strands, -1),
                             helix.curvatures, 1e-5)
    assert np.allclose(dF, fd, atol=1e-7 * np.abs(dF).max() + 1e-15)
    assert np.allclose(dF, np.swapaxes(dF, 1, 2), atol=1e-12 * np.abs(dF).max())


def test_gravity_potential_matches_quadrature():
    helix = random_helix(7)
    g = np.array([0.0, 0.0, -9.81])
    s = np.linspace(0, 1, 4001)
    for strand in range(helix.n_strands):
        L = helix.strand_lengths[strand]
        pos, _ = sh.evaluate(helix, np.full(len(s), strand), s * L)
        ref = -0.01 * np.trapezoid(pos @ g, s * L)
        assert sh.gravity_potential(helix, 0.01, g)[strand] == pytest.approx(ref, rel=1e-6)


def test_mass_matrix_is_kinetic_energy_of_velocities():
    """q' M q' equals rhoS int |dC/dt|^2 ds computed from finite differences of positions."""
    helix = random_helix(8, n_strands=2)
    rng = np.random.default_rng(8)
    qdot = rng.normal(size=helix.curvatures.shape)
    M = sh.mass_matrix(helix, 0.01, order=6)
    s = np.linspace(0, 1, 3001)
    h = 1e-6
    for strand in range(2):
        L = helix.strand_lengths[strand]
        ids = np.full(len(s), strand)
        p1, _ = sh.evaluate(helix.with_curvatures(helix.curvatures + h * qdot), ids, s * L)
        p0, _ = sh.evaluate(helix.with_curvatures(helix.curvatures - h * qdot), ids, s * L)
        v = (p1 - p0) / (2 * h)
        ref = 0.01 * np.trapezoid(np.sum(v * v, axis=1), s * L)
        qd = qdot[strand].ravel()
        assert qd @ M[strand] @ qd == pytest.approx(ref, rel=1e-5)
        assert np.allclose(M[strand], M[strand].T)


@pytest.mark.parametrize("x", [0.0, 1e-12, 1e-4, 0.5, SERIES_X * 0.999, SERIES_X * 1.001, 10.0, 400.0])
def test_series_functions_match_closed_forms(x):
    f, d1, d2 = f_table(np.array([x]))
    th = np.sqrt(x)
    if x > 1e-3:
        closed = [np.cos(th), np.sin(th) / th, (1 - np.cos(th)) / x, (th - np.sin(th)) / th**3,
                  (x / 2 - 1 + np.cos(th)) / x**2]
        for n in range(5):
            assert f[n, 0] == pytest.approx(closed[n], rel=1e-11, abs=1e-14)
    else:
        for n in range(5):
            taylor = 1.0 / factorial(n) - x / factorial(n + 2) + x * x / factorial(n + 4)
            assert f[n, 0] == pytest.approx(taylor, rel=1e-13)
    # derivatives by central differences of the functions themselves
    h = 1e-5 * max(x, 1.0)
    if x > h:
        fp, _, _ = f_table(np.array([x + h]))
        fm, _, _ = f_table(np.array([x - h]))
        assert np.allclose(d1[:, 0], (fp - fm)[:, 0] / (2 * h), rtol=1e-6, atol=1e-10)
        _, dp, _ = f_table(np.array([x + h]))
        _, dm, _ = f_table(np.array([x - h]))
        assert np.allclose(d2[:, 0], (dp - dm)[:, 0] / (2 * h), rtol=1e-6, atol=1e-10)


def test_series_continuous_across_switch():
    """The jump between the series (below) and closed forms (above) is the function's own change."""
    x = np.array([SERIES_X * (1 - 1e-10), SERIES_X * (1 + 1e-10)])
    dx = x[1] - x[0]
    f, d1, d2 = f_table(x)
    assert np.allclose(f[:, 1] - f[:, 0], d1[:, 0] * dx, rtol=0, atol=1e-14)
    assert np.allclose(d1[:, 1] - d1[:, 0], d2[:, 0] * dx, rtol=0, atol=1e-13)
    assert np.allclose(d2[:, 1], d2[:, 0], rtol=1e-9, atol=1e-12)


def test_c_table_straight_limit():
    c, _, _ = c_table(np.array([0.3]), np.array([0.0]))
    assert np.allclose(c[:, 0], [1.0, 0.3, 0.045, 0.0045, 0.3**4 / 24])


def test_padding_elements_are_identity():
    helix = random_helix(9, n_strands=2, n_elements=4)
    padded = sh.SuperHelix(helix.root_positions, helix.root_frames,
                           np.concatenate([helix.lengths, np.zeros((2, 3))], axis=1),
                           np.concatenate([helix.curvatures, np.zeros((2, 3, 3))], axis=1),
                           n_elements=helix.n_elements)
    k0 = sh.kinematics(helix)
    k1 = sh.kinematics(padded)
    assert np.allclose(k0.C[:, -1], k1.C[:, -1])
    g = np.array([0, -9.81, 0])
    F0 = sh.gravity_force(helix, 0.01, g)
    F1 = sh.gravity_force(padded, 0.01, g)
    assert np.allclose(F1[:, :4], F0) and np.all(F1[:, 4:] == 0)


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-7, 3.0, 40.0, 150.0, 600.0]))
@settings(max_examples=25, deadline=None)
def test_compiled_point_jacobian_parts_equal_the_dense_jacobian(seed, scale):
    """point_jacobian_parts (compiled, point by point) against point_jacobians (vectorised numpy, itself
    checked by finite differences above): own blocks, points, and B_k - [x]x Theta_k upstream."""
    helix = random_helix(seed, scale=scale, zero_some=True)
    rng = np.random.default_rng(seed)
    strand = rng.integers(0, helix.n_strands, size=40)
    s = rng.uniform(0, 1, size=40) * helix.strand_lengths[strand]
    s[:3] = 0.0  # roots and tips: t at the ends of an element
    s[3:6] = helix.strand_lengths[strand[3:6]]
    kin = sh.kinematics(helix)
    J, elem_ref = sh.point_jacobians(helix, strand, s, kin)
    elem, x, own = sh.point_jacobian_parts(helix, strand, s, kin)
    np.testing.assert_array_equal(elem, elem_ref)
    scale_J = max(1.0, np.abs(J).max())
    assert np.abs(own - J[np.arange(len(s)), elem]).max() <= 1e-13 * scale_J
    pos = sh.evaluate_positions(helix, strand, s, kin)
    assert np.abs(x - pos).max() <= 1e-14 * max(1.0, np.abs(pos).max())
    B = sh.upstream_jacobian_terms(kin)[strand]
    up = B - sh.skew(x)[:, None] @ kin.Theta[strand]
    k = np.arange(helix.max_elements)[None, :] < elem[:, None]
    assert np.abs(up[k] - J[k]).max(initial=0.0) <= 1e-12 * scale_J
