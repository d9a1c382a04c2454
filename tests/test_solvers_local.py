"""The 3x3 local contact solver (groomtool.solvers.local) against problems with known solutions,
brute-force SOCQP minimisation (cvxpy / clarabel) and the disjunctive form of Coulomb's law."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groomtool.solvers.cones import project_cone
from groomtool.solvers.local import FAILED, real_roots
from reference.solvers import solve_local

MUS = [0.0, 1e-6, 0.3, 1.0, 5.0, 1e6]


def random_spd(rng, decades=4):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q @ np.diag(10.0 ** rng.uniform(-decades / 2, decades / 2, 3)) @ q.T


def make_singular(rng):
    A = random_spd(rng)
    w, V = np.linalg.eigh(A)
    w[rng.integers(3)] = 0.0
    return V @ np.diag(w) @ V.T


def known_solution(rng, mu, law):
    """(r, u) satisfying the law: take-off, stick or slip drawn at random."""
    state = rng.integers(3)
    if state == 0:  # take-off: r = 0, u in the dual cone (SOC) / u_N >= 0 (Coulomb)
        ut = rng.normal(size=2)
        un = (mu * np.linalg.norm(ut) if law == "soc" else 0.0) + abs(rng.normal()) * rng.integers(2)
        return np.zeros(3), np.r_[un, ut]
    if state == 1 or mu == 0.0:  # stick: u = 0, r in the cone
        rt = rng.normal(size=2) if mu > 0 else np.zeros(2)
        rn = np.linalg.norm(rt) / mu * (1 + rng.uniform()) if mu > 0 else abs(rng.normal())
        return np.r_[rn, rt], np.zeros(3)
    w = rng.normal(size=2)
    w /= np.linalg.norm(w)
    t = abs(rng.normal()) + 0.01
    r = t * np.r_[1.0, mu * w]
    beta = abs(rng.normal()) + 0.01
    u = beta * np.r_[mu, -w] if law == "soc" else np.r_[0.0, -beta * w]  # SOC: u = beta (mu, -w)
    return r, u


def soc_kkt_error(A, c, mu, r):
    """||r - P_K(r - rho u)|| / max(rho ||c||, ||r||), rho = 3 / tr A (scale-free)."""
    u = A @ r + c
    rho = 3.0 / np.trace(A)
    p = np.array(project_cone(mu, *(r - rho * u)))
    return np.linalg.norm(r - p) / max(rho * np.linalg.norm(c), np.linalg.norm(r), 1e-300)


def coulomb_law_error(A, c, mu, r):
    """Distance to the disjunctive Coulomb law (take-off | stick | slip), relative to the problem's scale."""
    u = A @ r + c
    sr = max(np.linalg.norm(r), 3.0 / np.trace(A) * np.linalg.norm(c), 1e-300)
    su = max(np.linalg.norm(u), np.trace(A) / 3.0 * np.linalg.norm(r), np.linalg.norm(c), 1e-300)
    rn, rt, un, ut = r[0], r[1:], u[0], u[1:]
    if np.linalg.norm(r) <= 1e-12 * sr:  # take-off
        return max(0.0, -un) / su
    cone = max(0.0, np.linalg.norm(rt) - mu * rn) / sr
    if mu == 0.0:
        return max(cone, abs(un) / su, np.linalg.norm(rt) / sr)
    stick = np.linalg.norm(u) / su
    # slip: ||r_T|| = mu r_N, u_N = 0, u_T = -alpha r_T with alpha >= 0
    nrt = np.linalg.norm(rt)
    if nrt > 0:
        alpha = max(0.0, -ut @ rt / nrt**2)
        # u_T + alpha r_T is measured against both terms: a perturbation d of r moves it by alpha ||d||
        slip = max(abs(nrt - mu * rn) / sr, abs(un) / su, np.linalg.norm(ut + alpha * rt) / (su + alpha * sr))
    else:
        slip = np.inf
    return max(cone, min(stick, slip))


def batch(rng, law, mu, n, singular=False):
    A = np.array([make_singular(rng) if singular else random_spd(rng) for _ in range(n)])
    sols = [known_solution(rng, mu, law) for _ in range(n)]
    R = np.array([s[0] for s in sols])
    U = np.array([s[1] for s in sols])
    C = U - np.einsum("kab,kb->ka", A, R)
    return A, C, R


@pytest.mark.parametrize("mu", MUS)
def test_soc_local_recovers_known_solution(mu):
    """SOC law with A SPD: the solution is unique, so it must be the one the problem was built from."""
    rng = np.random.default_rng(1)
    A, C, R = batch(rng, "soc", mu, 2000)
    r, status = solve_local(A, C, mu, "soc")
    assert np.all(status != FAILED)
    err = np.linalg.norm(r - R, axis=1) / np.maximum(1.0, np.linalg.norm(R, axis=1))
    # conditioning of A up to 1e4 and of the cone for extreme mu: 1e-6 relative on r
    assert err.max() < 1e-6
    assert max(soc_kkt_error(A[k], C[k], mu, r[k]) for k in range(len(A))) < 1e-10


@pytest.mark.parametrize("mu", MUS)
@pytest.mark.parametrize("singular", [False, True])
def test_coulomb_local_satisfies_law(mu, singular):
    """Coulomb law (solutions need not be unique): check the disjunctive conditions directly."""
    rng = np.random.default_rng(2)
    A, C, R = batch(rng, "coulomb", mu, 2000, singular)
    r, status = solve_local(A, C, mu, "coulomb")
    errs = np.array([coulomb_law_error(A[k], C[k], mu, r[k]) for k in range(len(A))])
    ok = status != FAILED
    # every reported success satisfies the law; failures are rare and reported
    assert errs[ok].max() < 1e-7
    assert (~ok).mean() < (0.005 if singular else 1e-9)


@pytest.mark.parametrize("mu", [1e-6, 0.3, 5.0, 1e6])
def test_soc_local_singular_matrix(mu):
    """Rank-2 A (gamma = 0 and a degenerate contact): any minimiser is fine, KKT must hold."""
    rng = np.random.default_rng(3)
    A, C, _ = batch(rng, "soc", mu, 1000, singular=True)
    r, status = solve_local(A, C, mu, "soc")
    assert np.all(status != FAILED)
    assert max(soc_kkt_error(A[k], C[k], mu, r[k]) for k in range(len(A))) < 1e-10


def test_soc_local_matches_cvxpy():
    """Brute force: the 3D SOCQP minimised by cvxpy (clarabel) on random problems (no planted solution)."""
    cp = pytest.importorskip("cvxpy")
    rng = np.random.default_rng(4)
    x = cp.Variable(3)
    Aq = cp.Parameter((3, 3), PSD=True)
    for k in range(100):
        mu = [0.0, 1e-6, 0.3, 1.0, 5.0][k % 5]
        L = rng.normal(size=(3, 3))
        A = L @ L.T + 0.05 * np.eye(3)
        c = rng.normal(size=3)
        cons = [x[1:] == 0, x[0] >= 0] if mu == 0 else [cp.SOC(mu * x[0], x[1:])]
        Aq.value = A
        prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, Aq) + c @ x), cons)
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
        r, status = solve_local(A, c, mu, "soc")
        assert status != FAILED
        ours = 0.5 * r @ A @ r + c @ r
        assert ours <= prob.value + 1e-7 * max(1.0, abs(prob.value))
        # the interior-point point is accurate to ~sqrt(its tolerance) on badly conditioned A
        assert np.linalg.norm(r - x.value) <= 1e-5 * max(1.0, np.linalg.norm(x.value))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    entries=st.lists(st.floats(-10, 10).filter(lambda x: x == 0 or abs(x) > 1e-6), min_size=9, max_size=9),
    c=st.lists(st.floats(-100, 100).filter(lambda x: x == 0 or abs(x) > 1e-6), min_size=3, max_size=3),
    mu=st.sampled_from(MUS),
    scale=st.sampled_from([1e-8, 1.0, 1e8]),
    law=st.sampled_from(["soc", "coulomb"]),
)
def test_local_hypothesis(entries, c, mu, scale, law):
    """Arbitrary (possibly singular) PSD A = L L^T + tiny, badly scaled (1e-8 .. 1e8; entries kept away
    from subnormal magnitudes): the result satisfies the law whenever it is reported as solved, and the
    SOC law is always solved."""
    L = np.array(entries).reshape(3, 3)
    A = scale * (L @ L.T + 1e-3 * np.eye(3))
    c = scale * np.array(c)
    r, status = solve_local(A, c, mu, law)
    assert np.all(np.isfinite(r))
    if law == "soc":
        assert status != FAILED
        assert soc_kkt_error(A, c, mu, r) < 1e-9
    elif status != FAILED:
        assert coulomb_law_error(A, c, mu, r) < 1e-7


def test_warm_start_is_used_and_harmless():
    rng = np.random.default_rng(5)
    A, C, R = batch(rng, "soc", 0.3, 500)
    cold, _ = solve_local(A, C, 0.3, "soc")
    warm, _ = solve_local(A, C, 0.3, "soc", r0=R * (1 + 1e-3))
    np.testing.assert_allclose(warm, cold, rtol=1e-8, atol=1e-10 * np.abs(R).max())


@pytest.mark.parametrize("law", ["soc", "coulomb"])
def test_absolute_tolerance_bounds_the_natural_map(law):
    """atol: a slip solve may stop early, but only once ||r - P_K(r - u_eff / s)|| <= atol (s = tr A / 3),
    and it does stop earlier than the 1e-13 relative default (fewer Newton steps, a looser answer)."""
    from groomtool.solvers.cones import natural_map_norm, law_code

    rng = np.random.default_rng(11)
    A, C, R = batch(rng, law, 0.3, 1000)
    warm = R * (1 + 1e-2 * rng.normal(size=R.shape))
    atol = 1e-6 * np.abs(R).max()
    tight, _ = solve_local(A, C, 0.3, law, r0=warm)
    loose, status = solve_local(A, C, 0.3, law, r0=warm, atol=atol)
    assert np.all(status != FAILED)
    code = law_code(law)

    def natural(r):
        out = []
        for k in range(len(A)):
            u = A[k] @ r[k] + C[k]
            out.append(natural_map_norm(code, 0.3, 3.0 / np.trace(A[k]), *r[k], *u))
        return np.array(out)

    e_loose, e_tight = natural(loose), natural(tight)
    assert e_loose.max() <= atol * (1 + 1e-9)
    assert e_tight.max() < 1e-11 * np.abs(R).max()
    assert e_loose.max() > 10 * e_tight.max()  # it did stop early somewhere


def test_local_rejects_negative_mu():
    with pytest.raises(ValueError):
        solve_local(np.eye(3), np.ones(3), -0.1)


def test_real_roots():
    np.testing.assert_allclose(real_roots(np.array([24.0, -50, 35, -10, 1]), 0.0, 100.0), [1, 2, 3, 4])
    np.testing.assert_allclose(real_roots(np.array([-2.0, 0, 1]), -10.0, 10.0), [-np.sqrt(2), np.sqrt(2)])
    assert real_roots(np.array([1.0, 0, 1]), -10.0, 10.0).size == 0
    # a double root is kept
    np.testing.assert_allclose(real_roots(np.array([1.0, -2, 1]), -10.0, 10.0), [1.0], atol=1e-7)
