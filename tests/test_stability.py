"""The fast stability and equilibrium checks against the dense routes they replace.

- the O(N) kernels (products, block Cholesky, solves) against the dense matrix A = K^-1/2 dF/dq K^-1/2;
- stiffness_ratios against the dense eigvalsh (one strand at a time: no padding), on random, straight
  (double eigenvalues), hanging (negative rho) and real fitted strands;
- the constrained top eigenvalue against scipy's null space + eigvalsh, including rank-deficient and fully
  blocked rows (the held ratios themselves: tests/test_stabilize.py);
- gravity_force_jacobian and equilibrium_residuals against their original implementations.
"""

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from groomtool import semiseparable, stability
from groomtool.inverse_problem import equilibrium_residuals
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.stability import stiffness_ratios
from reference.equilibrium import equilibrium_residuals_reference, stiffness_ratios_reference
from reference.grooms import random_helix
from reference.rods import gravity_force_jacobian_reference

MAT = Material()
G = np.array([0.3, -9.81, 0.5])
EPS = np.finfo(float).eps


def straight(length, n, up=True):
    """A straight strand rising (or hanging) vertically from the origin along y."""
    sign = 1.0 if up else -1.0
    frame = np.stack([[0.0, sign, 0], [1, 0, 0], [0, 0, -sign]], axis=1)
    return sh.SuperHelix(np.zeros((1, 3)), frame[None], np.full((1, n), length / n), np.zeros((1, n, 3)))


def dense_A(helix, s, gravity=G, mat=MAT):
    """A = K^-1/2 dF/dq K^-1/2 of strand s over its real dofs, from the original dense dF/dq."""
    sub = helix.subset([s])
    n = 3 * int(sub.n_elements[0])
    dF = gravity_force_jacobian_reference(sub, mat.linear_density, gravity)[0, :n, :n]
    scale = 1.0 / np.sqrt(sh.stiffness(sub, mat.stiffness_diag).reshape(-1)[:n])
    return scale[:, None] * dF * scale[None, :]


def generators(helix, s, gravity=G, mat=MAT):
    u, v, d = stability._scaled_generators(helix.subset([s]), mat.stiffness_diag, mat.linear_density, gravity)
    N = int(helix.n_elements[s])
    return u[0, :N], v[0, :N], d[0, :N], N


def assert_ratios_close(new, ref, norms):
    """Round-off agreement: 1e-10 relative, or a few eps ||A||_F (a dense eigvalsh is that accurate)."""
    new, ref, norms = np.asarray(new), np.asarray(ref), np.asarray(norms)
    assert np.all(np.abs(new - ref) <= 1e-10 * np.abs(ref) + 64 * EPS * norms), (new, ref)


# --------------------------------------------------------------------------- dF/dq
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-7, 3.0, 60.0]))
@settings(max_examples=25, deadline=None)
def test_gravity_force_jacobian_equals_the_original(seed, scale):
    helix = random_helix(seed, scale=scale)
    new = sh.gravity_force_jacobian(helix, 0.004, G)
    ref = gravity_force_jacobian_reference(helix, 0.004, G)
    assert np.abs(new - ref).max() <= 1e-13 * np.abs(ref).max()
    assert np.array_equal(new, np.swapaxes(new, 1, 2))
    pad = ~np.repeat(helix.element_mask, 3, axis=1)
    assert not np.any(new[pad[:, :, None] | pad[:, None, :]])


# --------------------------------------------------------------------------- O(N) kernels
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 3.0, 40.0]))
@settings(max_examples=20, deadline=None)
def test_kernels_match_the_dense_matrix(seed, scale):
    helix = random_helix(seed, n_strands=1, max_elements=int(seed % 12) + 1, scale=scale, ragged=False)
    A = dense_A(helix, 0)
    u, v, d, N = generators(helix, 0)
    assert np.array_equal(stability._dense(u, v, d, N), stability._dense(u, v, d, N).T)
    assert np.abs(stability._dense(u, v, d, N) - A).max() <= 1e-13 * np.abs(A).max()
    later, earlier, neg_later = stability._semiseparable_form(u, v, N)
    assert stability._frobenius(d, later, earlier, N) == pytest.approx(np.linalg.norm(A), rel=1e-12)
    rng = np.random.default_rng(seed)
    x = rng.normal(size=3 * N)
    y = np.empty(3 * N)
    semiseparable.matvec_strand(d, later, earlier, 0, N, x, y)
    assert np.abs(y - A @ x).max() <= 1e-12 * np.abs(A).max() * np.abs(x).sum()
    lam = np.linalg.eigvalsh(A)
    diag, L, Y = np.empty((N, 3, 3)), np.empty((N, 3, 3)), np.empty((N, 3, 3))
    norm = np.linalg.norm(A)
    # positive definite exactly above lambda_max (up to round-off)
    assert stability._cholesky(d, neg_later, earlier, N, lam[-1] + 1e-9 * norm + 1e-300, diag, L, Y)
    if lam[-1] - lam[0] > 1e-6 * norm:
        assert not stability._cholesky(d, neg_later, earlier, N, lam[-1] - 1e-9 * norm, diag, L, Y)
        sigma = lam[-1] + 0.3 * (lam[-1] - lam[0])
        assert stability._cholesky(d, neg_later, earlier, N, sigma, diag, L, Y)
        stability._solve(neg_later, L, Y, N, x, y)
        ref = np.linalg.solve(sigma * np.eye(3 * N) - A, x)
        assert np.abs(y - ref).max() <= 1e-9 * np.abs(ref).max()


# --------------------------------------------------------------------------- isolated ratios
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 3.0, 30.0, 100.0]),
       gravity=st.sampled_from([(0.3, -9.81, 0.5), (0.0, 9.81, 0.0), (0.0, 0.0, -9.81)]))
@settings(max_examples=40, deadline=None)
def test_stiffness_ratios_equal_the_dense_eigvalsh(seed, scale, gravity):
    g = np.array(gravity)
    helix = random_helix(seed, n_strands=5, max_elements=14, scale=scale)
    new = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, g)
    ref = stiffness_ratios_reference(helix, MAT.stiffness_diag, MAT.linear_density, g, chunk=1)
    norms = [np.linalg.norm(dense_A(helix, s, g)) for s in range(helix.n_strands)]
    assert_ratios_close(new, ref, norms)
    # and by the O(N) route, not the dense fallback (never needed on 37,500 such strands nor on harolongo)
    ok = np.empty(helix.n_strands, dtype=bool)
    u, v, d = stability._scaled_generators(helix, MAT.stiffness_diag, MAT.linear_density, g)
    stability._lambda_max_batch(u, v, d, helix.n_elements, stability.RTOL, stability.ATOL_EPS, stability.MAX_STEPS,
                                stability.LANCZOS_STEPS, np.empty(helix.n_strands), ok)
    assert ok.all()


@pytest.mark.parametrize("n", [1, 2, 10, 40, 96])
@pytest.mark.parametrize("up", [True, False])
def test_straight_strands_double_eigenvalues_and_negative_ratios(n, up):
    """Straight strands: rho is a double eigenvalue (kappa1, kappa2 alike); hanging ones have rho <= 0."""
    helix = straight(0.2, n, up)
    new = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, np.array([0.0, -9.81, 0.0]))
    A = dense_A(helix, 0, np.array([0.0, -9.81, 0.0]))
    assert_ratios_close(new, [np.linalg.eigvalsh(A)[-1]], [np.linalg.norm(A)])
    assert (new[0] > 0) == (up and n > 0) or abs(new[0]) <= 64 * EPS * np.linalg.norm(A)


def test_uncertified_strands_fall_back_to_the_dense_route(monkeypatch):
    helix = random_helix(11, n_strands=6, max_elements=12)
    ref = stiffness_ratios_reference(helix, MAT.stiffness_diag, MAT.linear_density, G, chunk=1)
    norms = [np.linalg.norm(dense_A(helix, s)) for s in range(helix.n_strands)]
    assert_ratios_close(stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G), ref, norms)
    ok = np.empty(helix.n_strands, dtype=bool)
    u, v, d = stability._scaled_generators(helix, MAT.stiffness_diag, MAT.linear_density, G)
    stability._lambda_max_batch(u, v, d, helix.n_elements, stability.RTOL, stability.ATOL_EPS, 0, 12,
                                np.empty(helix.n_strands), ok)
    assert not ok.any()  # no step allowed: nothing certified
    monkeypatch.setattr(stability, "MAX_STEPS", 0)
    assert_ratios_close(stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G), ref, norms)


def test_certified_value_is_pinned_by_the_cholesky_test():
    """lambda_max(A) is where sigma I - A stops being positive definite: the returned theta is within the
    certified gap of the dense eigenvalue, and just below it the Cholesky fails."""
    helix = random_helix(5, n_strands=1, max_elements=20, ragged=False)
    u, v, d, N = generators(helix, 0)
    later, earlier, neg_later = stability._semiseparable_form(u, v, N)
    theta, ok = stability._lambda_max(d, later, earlier, N, stability.RTOL, stability.ATOL_EPS, 60, 12)
    A = dense_A(helix, 0)
    lam = np.linalg.eigvalsh(A)[-1]
    assert ok
    tol = stability.RTOL * abs(theta) + stability.ATOL_EPS * EPS * np.linalg.norm(A)
    assert lam - 2 * tol <= theta <= lam + 64 * EPS * np.linalg.norm(A)
    diag, L, Y = np.empty((N, 3, 3)), np.empty((N, 3, 3)), np.empty((N, 3, 3))
    assert not stability._cholesky(d, neg_later, earlier, N, theta - 1e-8 * abs(theta), diag, L, Y)
    assert stability._cholesky(d, neg_later, earlier, N, theta + tol, diag, L, Y)


# --------------------------------------------------------------------------- contact-held ratios
def _blocked_rows(helix, s, arcs, seed):
    """The rows of H for contacts at arc lengths ``arcs`` on strand s (random frames), (3 m, 3 n)."""
    n = int(helix.n_elements[s])
    J, _ = sh.point_jacobians(helix, np.full(len(arcs), s), np.asarray(arcs))
    frames = Rotation.random(len(arcs), random_state=seed).as_matrix()
    rows = np.einsum("pij,pkjb->pikb", frames, J[:, :n])
    return rows.reshape(3 * len(arcs), 3 * n)


def test_constrained_top_eigenvalue_equals_the_null_space_route():
    import scipy.linalg

    helix = random_helix(3, n_strands=3, max_elements=10, ragged=False)
    L = helix.strand_lengths
    row = _blocked_rows(helix, 0, [0.6 * L[0]], 1)
    cases = [
        (0, None),  # nothing blocked: the isolated ratio
        (0, np.zeros((0, 30))),
        (0, _blocked_rows(helix, 0, [0.0], 1)),  # a contact at the root: rows of zeros, nothing blocked
        (0, np.concatenate([row, row, 2 * row])),  # rank deficient: the same rows three times
        (1, _blocked_rows(helix, 1, np.linspace(0.05, 1.0, 12) * L[1], 2)),  # 36 rows, 30 dofs: all blocked
        (2, _blocked_rows(helix, 2, [L[2], 0.3 * L[2]], 3)),
    ]
    for s, rows in cases:
        A = dense_A(helix, s)
        scale = 1.0 / np.sqrt(sh.stiffness(helix.subset([s]), MAT.stiffness_diag).reshape(-1))
        C = None if rows is None else rows * scale[None, :]
        new = stability.constrained_top_eigenvalue(A, C)
        if C is None or len(C) == 0 or not np.any(C):
            ref = np.linalg.eigvalsh(A)[-1]
        else:
            Z = scipy.linalg.null_space(C)
            ref = np.linalg.eigvalsh(Z.T @ A @ Z)[-1] if Z.shape[1] else 0.0
        assert_ratios_close([new], [ref], [3 * np.linalg.norm(A)])
        u, v, d, N = generators(helix, s)
        later, earlier, _ = stability._semiseparable_form(u, v, N)
        rows = np.zeros((0, 3 * N)) if C is None else np.ascontiguousarray(C)
        fast, certified = stability._held_lambda_max(d, later, earlier, N, rows, stability.RTOL, stability.ATOL_EPS,
                                                     stability.MAX_STEPS, stability.LANCZOS_STEPS)
        assert certified
        assert_ratios_close([fast], [ref], [3 * np.linalg.norm(A)])
    iso = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, G)
    assert stability.constrained_top_eigenvalue(dense_A(helix, 0), None) == pytest.approx(iso[0], rel=1e-9)
    assert stability.constrained_top_eigenvalue(dense_A(helix, 1), cases[4][1]) == 0.0


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 3.0, 40.0]), k=st.integers(1, 12),
       contact_rows=st.booleans())
@settings(max_examples=40, deadline=None)
def test_held_top_eigenvalue_equals_the_dense_null_space_route(seed, scale, k, contact_rows):
    """The O(N k^2) route (P A P - beta Q^T Q in semiseparable form) against scipy's null space + eigvalsh, for the
    rows of head contacts (rigid upstream of the contact, as H's) and for arbitrary dense rows, rank-deficient
    ones included."""
    import scipy.linalg

    helix = random_helix(seed, n_strands=1, max_elements=int(seed % 14) + 1, scale=scale, ragged=False)
    u, v, d, N = generators(helix, 0)
    A = dense_A(helix, 0)
    rng = np.random.default_rng(seed)
    if contact_rows:
        arcs = rng.uniform(0, 1, max(1, k // 3)) * helix.strand_lengths[0]
        C = _blocked_rows(helix, 0, arcs, seed)[:k]
        C = C / np.sqrt(sh.stiffness(helix.subset([0]), MAT.stiffness_diag).reshape(-1))[None, :3 * N]
    else:
        C = rng.normal(size=(k, 3 * N))
        if k > 2:
            C[-1] = C[0] - 2.0 * C[1]  # rank deficient
    Z = scipy.linalg.null_space(C)
    ref = np.linalg.eigvalsh(Z.T @ A @ Z)[-1] if Z.shape[1] else 0.0
    later, earlier, _ = stability._semiseparable_form(u, v, N)
    fast, certified = stability._held_lambda_max(d, later, earlier, N, np.ascontiguousarray(C), stability.RTOL,
                                                 stability.ATOL_EPS, stability.MAX_STEPS, stability.LANCZOS_STEPS)
    assert certified
    assert_ratios_close([fast], [ref], [3 * np.linalg.norm(A)])


def test_projected_form_is_p_a_p_minus_beta_q_q():
    helix = random_helix(7, n_strands=1, max_elements=9, scale=3.0, ragged=False)
    u, v, d, N = generators(helix, 0)
    A = dense_A(helix, 0)
    Q = np.linalg.qr(np.random.default_rng(1).normal(size=(3 * N, 4)))[0].T.copy()
    later, earlier, _ = stability._semiseparable_form(u, v, N)
    d_b, later_b, earlier_b = stability._projected_form(d, later, earlier, N, Q, 2.5)
    P = np.eye(3 * N) - Q.T @ Q
    B = P @ A @ P - 2.5 * Q.T @ Q
    from reference.semiseparable import dense_strand
    assert np.abs(dense_strand(d_b, later_b, earlier_b, 0, N) - B).max() <= 1e-13 * np.abs(A).max()


# --------------------------------------------------------------------------- equilibrium check
def _random_contacts(rng, helix, m):
    S = helix.n_strands
    L = helix.strand_lengths
    strand_a = rng.integers(0, S, m)
    strand_b = rng.integers(-1, S, m)  # -1: the head; a == b: a self contact
    s_a = rng.uniform(0, 1, m) * L[strand_a]
    s_b = np.where(strand_b >= 0, rng.uniform(0, 1, m) * L[np.maximum(strand_b, 0)], np.nan)
    return SimpleNamespace(strand_a=strand_a, s_a=s_a, strand_b=strand_b, s_b=s_b,
                           frame=Rotation.random(m, random_state=int(rng.integers(1 << 30))).as_matrix())


@given(seed=st.integers(0, 10_000), m=st.integers(0, 30), chunk=st.sampled_from([1, 2, 1024]))
@settings(max_examples=30, deadline=None)
def test_equilibrium_residuals_equal_the_original(seed, m, chunk):
    rng = np.random.default_rng(seed)
    helix = random_helix(seed, n_strands=5, max_elements=9, scale=20.0)
    rest = helix.curvatures + rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    contacts = _random_contacts(rng, helix, m)
    forces = rng.normal(size=(m, 3)) * 1e-3
    new = equilibrium_residuals(helix, rest, MAT, G, contacts, forces, chunk=chunk)
    ref = equilibrium_residuals_reference(helix, rest, MAT, G, contacts, forces)
    assert np.allclose(new, ref, rtol=1e-10, atol=1e-13)
    none = equilibrium_residuals(helix, rest, MAT, G, chunk=chunk)
    assert np.allclose(none, equilibrium_residuals_reference(helix, rest, MAT, G), rtol=1e-10, atol=1e-13)
    if m and np.abs(forces).max() > 0:
        assert not np.allclose(new, none, rtol=1e-6, atol=0)  # the contact forces are in it


# --------------------------------------------------------------------------- real strands
def test_real_strands_match_the_dense_route(shared_data):
    from groomtool.fit import fit_groom
    from groomtool.groom import Groom
    from groomtool.io import read_data

    strands = list(read_data(shared_data / "digital-salon" / "harolongo.data", scale=0.01).strands())
    lengths = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in strands])
    pick = np.concatenate([np.argsort(lengths)[-12:], np.arange(0, len(strands), len(strands) // 24)])
    groom = Groom.from_strands([strands[i] for i in pick], source="harolongo subset")
    helix = fit_groom(groom, tolerance=5e-4).helix
    g = groom.gravity(MAT.gravity)
    new = stiffness_ratios(helix, MAT.stiffness_diag, MAT.linear_density, g)
    ref = stiffness_ratios_reference(helix, MAT.stiffness_diag, MAT.linear_density, g, chunk=1)
    norms = [np.linalg.norm(dense_A(helix, s, g)) for s in range(helix.n_strands)]
    assert_ratios_close(new, ref, norms)
    assert np.all(np.abs(new - ref) <= 1e-10 * np.abs(ref))  # real strands: relative agreement
    assert (new >= 1).any() and (new < 1).any()
