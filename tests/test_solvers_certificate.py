"""The certified error bound of solvers/certificate.py: the duality gap against its textbook definition, and
the bound against the true error from an independent cvxpy/clarabel optimum on small random problems."""

import cvxpy as cp
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from groomtool.solvers import ContactProblem, solve_contact_problem
from groomtool.solvers.certificate import duality_gap, error_bound, project_forces


def random_problem(seed, m, n_strands, dofs, gamma, mu, redundant=False):
    """A factored problem u = (H D H^T + 2 gamma I) r + b with diagonal D (the inverse problem's form):
    H random sparse, b = H v (pushing into some contacts, pulling away from others).  redundant: more
    contact rows than dofs on every strand (the dense-groom case)."""
    rng = np.random.default_rng(seed)
    n = n_strands * dofs
    rows, cols, vals = [], [], []
    for i in range(m):
        s = rng.integers(n_strands)
        k = rng.integers(1, dofs + 1) if not redundant else rng.integers(1, min(3, dofs) + 1)
        c = s * dofs + rng.choice(dofs, size=k, replace=False)
        for a in range(3):
            rows += [3 * i + a] * k
            cols += list(c)
            vals += list(rng.standard_normal(k))
    H = sp.csr_matrix((vals, (rows, cols)), shape=(3 * m, n))
    D = np.exp(rng.uniform(-2, 2, n))
    b = H @ rng.standard_normal(n) + 0.3 * rng.standard_normal(3 * m)
    offs = np.arange(n_strands + 1) * dofs
    return ContactProblem(H=H, D_blocks=D, dof_offsets=offs, gamma=gamma, b=b, mu=mu)


def cvxpy_optimum(P):
    """min 1/2 |D^1/2 H^T r|^2 + gamma |r|^2 + b^T r over the cones, written independently with cvxpy.
    Returns (r*, a bound on |A^T (r* - r_exact)|) certified by cvxpy's own cone multipliers s (in the dual
    cones): the Lagrangian dual value -1/2 (s - b)^T W^-1 (s - b) <= f*, so 1/2 |A^T (r - r_exact)|^2 <=
    f(r) - dual value for r in the cones (a different dual from certificate.py's)."""
    m = P.n_contacts
    A = (P.H.T.multiply(np.sqrt(P.D_data)[:, None])).tocsr()  # D^1/2 H^T
    r = cp.Variable(3 * m)
    obj = 0.5 * cp.sum_squares(A @ r) + P.gamma * cp.sum_squares(r) + P.b @ r
    socs = [cp.SOC(P.mu[i] * r[3 * i], r[3 * i + 1:3 * i + 3]) for i in range(m)]
    normal = r[0::3] >= 0  # K_0 = {r_T = 0, r_N >= 0}: the SOC alone would leave r_N free when mu = 0
    prob = cp.Problem(cp.Minimize(obj), socs + [normal])
    try:
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11, max_iter=500)
    except cp.error.SolverError:  # no reference for this problem (ill-conditioned draw): nothing to test
        return None, np.inf
    if prob.status not in ("optimal", "optimal_inaccurate"):  # the certificate below says how good it is
        return None, np.inf
    s = np.zeros((m, 3))
    for i, c in enumerate(socs):
        dv = c.dual_value  # [multiplier of t, of x] for SOC(t, x)
        t, x = float(np.ravel(dv[0])[0]), np.ravel(dv[1])
        s[i, 0] = P.mu[i] * t
        s[i, 1:] = x
    s[:, 0] += np.asarray(normal.dual_value)
    r_star, _ = project_forces(np.asarray(r.value), P.mu)
    return r_star, lagrangian_certificate(P, r_star, s)


def lagrangian_certificate(P, r, s):
    """sqrt(2 (f(r) - q(s))) >= |A^T (r - r*)| for r in the cones, q(s) = min_r f(r) - s^T r =
    -1/2 (s - b)^T W^-1 (s - b) the Lagrangian dual at s (moved into the dual cones {mu |s_T| <= s_N})."""
    s = np.array(s, dtype=np.float64).reshape(-1, 3)
    for i in range(len(s)):
        if P.mu[i] == 0:
            s[i, 0] = max(s[i, 0], 0.0)
        else:
            s[i] = project_forces(s[i], 1.0 / P.mu[i])[0]
    z = s.ravel() - P.b
    W = P.assemble_W().toarray()
    x = np.linalg.solve(W, z)
    x += np.linalg.solve(W, z - W @ x)  # one step of iterative refinement: q to working precision
    dual = -0.5 * z @ x
    primal = P.objective(r)
    # f(r) - q(s) is a difference of two rounded numbers of size |f|: below a few hundred eps |f| it means
    # nothing (a reference off by 2e-7 in y was certified exact); count that round-off
    roundoff = 256 * np.finfo(float).eps * (abs(primal) + abs(dual))
    return float(np.sqrt(2.0 * (max(primal - dual, 0.0) + roundoff)))


def y_of(P, r):
    return np.sqrt(P.D_data) * (P.H.T @ r)


def dual_value(P, lam):
    """g(l) = -1/2 |l|^2 - |P_K(-(A l + b))|^2 / (4 gamma), A = H D^1/2, written out densely."""
    c = P.H @ (np.sqrt(P.D_data) * lam) + P.b
    p, _ = project_forces(-c, P.mu)
    return -0.5 * lam @ lam - p @ p / (4 * P.gamma)


def test_gap_equals_primal_minus_dual_value():
    P = random_problem(1, 30, 4, 9, 0.05, 0.4)
    rng = np.random.default_rng(2)
    r, _ = project_forces(rng.standard_normal(3 * P.n_contacts), P.mu)
    gap = duality_gap(r, P.velocity(r), P.mu, P.gamma)
    direct = P.objective(r) - dual_value(P, y_of(P, r))
    assert gap == pytest.approx(direct, rel=1e-10)
    assert gap > 0
    assert error_bound(P, r, line_search=False)["bound"] == pytest.approx(np.sqrt(gap), rel=1e-12)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(seed=st.integers(0, 10_000), m=st.integers(2, 25), redundant=st.booleans(),
       log_gamma=st.floats(-4, -1), mu=st.sampled_from([0.0, 0.3, 1.0, 3.0]))
def test_bound_holds_against_an_independent_optimum(seed, m, redundant, log_gamma, mu):
    """For iterates along a Gauss-Seidel run and random points in the cones, with and without the dual line
    search: bound >= |A^T (r - r*)| - (the certified error of the cvxpy/clarabel reference r*)."""
    P = random_problem(seed, m, 3, 6, 10.0 ** log_gamma, mu, redundant)
    r_star, slack = cvxpy_optimum(P)
    assume(r_star is not None)
    y_star = y_of(P, r_star)
    assume(slack <= 1e-4 * (np.linalg.norm(y_star) + 0.1))  # a reference good enough to test anything (y ~ 1)
    rng = np.random.default_rng(seed)
    points = [project_forces(rng.standard_normal(3 * m) * s, P.mu)[0] for s in (0.01, 1.0)]
    points.append(project_forces(r_star + 1e-3 * rng.standard_normal(3 * m), P.mu)[0])
    for sweeps in (1, 3, 10):
        res = solve_contact_problem(P, method="gs", tol=1e-15, max_iter=sweeps, anderson=0)
        points.append(project_forces(res.r, P.mu)[0])
    for r in points:
        true = np.linalg.norm(y_of(P, r) - y_star)
        for ls in (False, True):
            assert error_bound(P, r, line_search=ls)["bound"] >= true - slack


def test_bound_vanishes_at_the_optimum_and_is_tight_on_gauss_seidel_iterates():
    """At a converged point the bound is near round-off; along a Gauss-Seidel run on a redundant problem it
    stays within a small factor of the true error (7-12x here, 13-20x without the line search)."""
    P = random_problem(7, 40, 3, 6, 1e-3, 0.3, redundant=True)
    conv = solve_contact_problem(P, method="gs", tol=1e-11, max_iter=20000)
    assert conv.converged
    r_star, _ = project_forces(conv.r, P.mu)
    y_star = y_of(P, r_star)
    # the reference, certified independently by the Lagrangian dual at s = u (its floor: the dense W^-1 of a
    # problem with 2 gamma = 2e-3 eigenvalues)
    c_ref = lagrangian_certificate(P, r_star, P.velocity(r_star))
    assert c_ref <= 1e-4 * np.linalg.norm(y_star)
    assert error_bound(P, r_star)["bound"] <= 1e-6 * np.linalg.norm(y_star)
    ratios = []
    for sweeps in (5, 20, 80, 320):
        res = solve_contact_problem(P, method="gs", tol=1e-15, max_iter=sweeps)
        r, _ = project_forces(res.r, P.mu)
        true = np.linalg.norm(y_of(P, r) - y_star)
        bound = error_bound(P, r)["bound"]
        assert bound >= true - c_ref
        if true > 100 * c_ref:
            ratios.append(bound / true)
    assert len(ratios) >= 3 and min(ratios) >= 1.0 and max(ratios) < 30.0, ratios


def test_no_bound_without_gamma():
    P = random_problem(3, 10, 2, 6, 0.0, 0.3)
    assert error_bound(P, np.zeros(3 * P.n_contacts))["bound"] == np.inf


def test_projection_onto_the_cones():
    rng = np.random.default_rng(0)
    r = rng.standard_normal(300)
    mu = rng.uniform(0, 2, 100)
    p, moved = project_forces(r, mu)
    p3, r3 = p.reshape(-1, 3), r.reshape(-1, 3)
    assert np.all(np.linalg.norm(p3[:, 1:], axis=1) <= mu * p3[:, 0] * (1 + 1e-12) + 1e-300)
    assert moved == pytest.approx(np.linalg.norm(p3 - r3, axis=1).max())
    again, moved2 = project_forces(p, mu)
    assert moved2 <= 1e-15 and np.allclose(again, p, atol=0, rtol=1e-15)


def test_bound_from_a_dual_point_holds_and_matches_the_primal_one_at_l_equal_y():
    """error_bound_with_dual: with l = A^T r it is the plain bound; with the dual's own point (r = r(l), a
    dual method's iterate) it holds against the independent optimum too."""
    from groomtool.solvers.certificate import error_bound_with_dual

    P = random_problem(11, 20, 3, 6, 1e-2, 0.5, redundant=True)
    r_star, slack = cvxpy_optimum(P)
    y_star = y_of(P, r_star)
    rng = np.random.default_rng(4)
    r, _ = project_forces(r_star + 0.05 * rng.standard_normal(3 * P.n_contacts), P.mu)
    plain = error_bound(P, r, line_search=False)["bound"]
    assert error_bound_with_dual(P, r, y_of(P, r))["bound"] == pytest.approx(plain, rel=1e-9)
    for scale in (0.0, 0.3, 1.0):
        lam = y_star + scale * rng.standard_normal(y_star.size)
        c = P.H @ (np.sqrt(P.D_data) * lam) + P.b
        r_lam, _ = project_forces(-c / (2 * P.gamma), P.mu)
        bound = error_bound_with_dual(P, r_lam, lam)["bound"]
        assert bound >= np.linalg.norm(y_of(P, r_lam) - y_star) - slack
