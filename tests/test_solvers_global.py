"""Global contact solvers: ContactProblem helpers, W assembly, Gauss-Seidel (both forms), APGD, clarabel,
the Coulomb fixed point and the public API."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from groomtool.solvers import ContactProblem, solve_contact_problem, solve_coulomb, solve_socqp
from groomtool.solvers.blocks import UpperBlockDelassus, assemble_upper, upper_block_matvec
from groomtool.solvers.cones import project_cone
from groomtool.solvers.gauss_seidel import GIVE_UP_MIN_SWEEPS
from reference.solvers import coulomb_contact_errors

_spec = importlib.util.spec_from_file_location("bench_problems", Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def hair(m, **kw):
    return problems.make_hair_like(m, **kw)[0]


def upper_times(U, r):
    """W r, (m, 3), for W stored as its upper block triangle (the kernel Gauss-Seidel and APGD use)."""
    m = U.n_contacts
    r = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(m, 3))
    out = np.empty((m, 3))
    upper_block_matvec(U.indptr, U.indices, U.blocks, r, np.zeros((m, 3)), out)
    return out


def kkt_errors(P, r, law="soc"):
    """(max cone violation of r, of u_eff in the dual cone, max |r.u_eff|), all relative to the scale."""
    r = r.reshape(-1, 3)
    u = P.velocity(r.reshape(-1)).reshape(-1, 3)
    if law == "coulomb":
        u = u.copy()
        u[:, 0] += P.mu * np.linalg.norm(u[:, 1:], axis=1)
    sr = max(np.abs(r).max(), 1e-300)
    su = max(np.abs(u).max(), np.abs(P.b).max())
    cone = np.maximum(0, np.linalg.norm(r[:, 1:], axis=1) - P.mu * r[:, 0]).max() / sr
    dual = np.maximum(0, P.mu * np.linalg.norm(u[:, 1:], axis=1) - u[:, 0]).max() / su
    comp = np.abs(np.sum(r * u, axis=1)).max() / (sr * su)
    return cone, dual, comp


# ----------------------------------------------------------------------------------------------
# ContactProblem and assembly
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["inverse", "dynamics"])
def test_problem_operators_agree(variant):
    P = hair(120, variant=variant, seed=3)
    r = np.random.default_rng(0).normal(size=3 * P.n_contacts)
    W = P.assemble_W()
    np.testing.assert_allclose(P.delassus_apply(r), W @ r, rtol=1e-12, atol=1e-12)
    d = P.diagonal_blocks()
    Wd = W.toarray()
    for i in range(P.n_contacts):
        np.testing.assert_allclose(d[i], Wd[3 * i:3 * i + 3, 3 * i:3 * i + 3], atol=1e-13)
    np.testing.assert_allclose(P.objective(r), 0.5 * r @ W @ r + P.b @ r, rtol=1e-12)
    U = assemble_upper(P)
    np.testing.assert_allclose(upper_times(U, r).reshape(-1), W @ r, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(upper_times(UpperBlockDelassus.from_sparse(W), r).reshape(-1), W @ r, rtol=1e-11, atol=1e-12)
    # W is symmetric positive definite with gamma > 0
    assert np.linalg.eigvalsh(Wd).min() > 1.9 * P.gamma


@pytest.mark.parametrize("dense", [True, False])
def test_assembly_unstructured(dense):
    P = problems.random_factored_problem(40, 6, 9, dense=dense, seed=1)
    r = np.random.default_rng(1).normal(size=(40, 3))
    np.testing.assert_allclose(upper_times(assemble_upper(P), r).reshape(-1), P.assemble_W() @ r.reshape(-1), atol=1e-11)


def test_problem_validation():
    H = sp.random(6, 10, density=0.5, random_state=0)
    with pytest.raises(ValueError):
        ContactProblem(H, np.ones(10), [0, 5, 10], 0.01, np.zeros(5), 0.3)  # b size
    with pytest.raises(ValueError):
        ContactProblem(H, np.ones(10), [0, 5, 10], 0.01, np.zeros(6), -0.3)  # mu < 0
    with pytest.raises(ValueError):
        ContactProblem(H, [np.eye(4), np.eye(5)], [0, 5, 10], 0.01, np.zeros(6), 0.3)  # block shape
    with pytest.raises(ValueError):
        ContactProblem(sp.random(5, 10, density=0.5), np.ones(10), [0, 5, 10], 0.01, np.zeros(5), 0.3)


def test_residual_definition():
    """0 at a solution, scale invariant, positive away from it; cone violation of a feasible r is 0."""
    P = hair(60, seed=2)
    res = solve_contact_problem(P, tol=1e-12)
    assert res.converged and res.residual <= 1e-12
    assert P.residual(np.zeros(3 * P.n_contacts)) > 1e-3
    assert res.cone_violation <= 1e-12
    # scaling W by a and b by c scales r by c / a; the residual does not move
    a, c = 7.0, 0.01
    Q = ContactProblem(P.H, [a * d for d in P.D_blocks], P.dof_offsets, a * P.gamma, c * P.b, P.mu)
    assert Q.residual(res.r * c / a) == pytest.approx(P.residual(res.r), rel=1e-6, abs=1e-14)
    bad = res.r.copy().reshape(-1, 3)
    bad[:, 1] += 10.0
    assert P.cone_violation(bad) > 1.0


# ----------------------------------------------------------------------------------------------
# Gauss-Seidel against exact solvers
# ----------------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    m=st.integers(2, 40),
    n_strands=st.integers(2, 10),
    dofs=st.integers(3, 40),
    mu=st.sampled_from([0.0, 1e-3, 0.3, 1.0, 3.0, "mixed"]),
    dense=st.booleans(),
    seed=st.integers(0, 10_000),
)
def test_gs_matches_clarabel(m, n_strands, dofs, mu, dense, seed):
    """GS objective within 1e-7 (relative) of clarabel's on random factored problems, and KKT holds.
    (n >= 3m as on hair, where strands carry more dofs than contact rows: with n << 3m, W's spectrum
    reaches down to 2 gamma and Gauss-Seidel needs tens of thousands of sweeps.)"""
    assume(n_strands * dofs >= 3 * m)
    rng = np.random.default_rng(seed)
    mus = rng.choice([0.0, 0.2, 0.5, 2.0], size=m) if mu == "mixed" else mu
    P = problems.random_factored_problem(m, n_strands, dofs, dense=dense, mu=mus, seed=seed)
    gs = solve_contact_problem(P, "soc", "gs", tol=1e-10)
    ref = solve_contact_problem(P, "soc", "clarabel", polish=False)  # clarabel's own point: independent
    assert gs.converged and gs.residual <= 1e-10
    assert ref.status == "Solved"
    assert gs.objective <= ref.objective + 1e-7 * max(1.0, abs(ref.objective))
    assert abs(gs.objective - ref.objective) <= 1e-7 * max(1.0, abs(ref.objective))
    cone, dual, comp = kkt_errors(P, gs.r)
    assert max(cone, dual, comp) < 1e-8


def test_gs_matches_independent_cvxpy():
    """An independently written cvxpy model of the SOCQP (dense W, SOC constraints)."""
    cp = pytest.importorskip("cvxpy")
    for seed, mu in [(0, 0.3), (1, 0.0), (2, 1.5)]:
        P = hair(30, seed=seed, mu_range=(mu, mu))
        W = P.assemble_W().toarray()
        r = cp.Variable(3 * P.n_contacts)
        cons = []
        for i in range(P.n_contacts):
            if mu == 0:
                cons += [r[3 * i + 1:3 * i + 3] == 0, r[3 * i] >= 0]
            else:
                cons.append(cp.SOC(mu * r[3 * i], r[3 * i + 1:3 * i + 3]))
        L = np.linalg.cholesky(W)
        prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(L.T @ r) + P.b @ r), cons)
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
        gs = solve_contact_problem(P, tol=1e-10)
        assert gs.objective == pytest.approx(prob.value, rel=1e-7, abs=1e-9)
        assert np.linalg.norm(gs.r - r.value) <= 1e-4 * max(1.0, np.linalg.norm(r.value))


@pytest.mark.parametrize("variant", ["inverse", "dynamics"])
def test_methods_agree_on_hair(variant):
    P = hair(300, variant=variant, seed=5)
    gs = solve_contact_problem(P, method="gs", tol=1e-9)
    ap = solve_contact_problem(P, method="apgd", tol=1e-9)
    mf = solve_contact_problem(P, method="gs", form="matrix_free", tol=1e-9)
    cl = solve_contact_problem(P, method="clarabel", polish=False)
    for res in (gs, ap, mf):
        assert res.converged and res.residual <= 1e-9, res.method
        assert res.objective == pytest.approx(cl.objective, rel=1e-7)
    np.testing.assert_allclose(gs.r, ap.r, atol=1e-6 * np.abs(gs.r).max())


def test_matrix_free_and_assembled_identical():
    """Same sweep order, same local solver: the two forms give the same iterates (up to rounding).  (The
    matrix-free form takes no subspace Newton steps: they are off here for both.)"""
    P = hair(200, variant="dynamics", seed=7)
    kw = dict(tol=0.0, max_iter=40, anderson=0, newton=None)
    a = solve_contact_problem(P, method="gs", form="assembled", **kw)
    b = solve_contact_problem(P, method="gs", form="matrix_free", **kw)
    assert a.iterations == b.iterations == 40
    np.testing.assert_allclose(a.r, b.r, rtol=0, atol=1e-10 * np.abs(a.r).max())
    assert a.residual == pytest.approx(b.residual, rel=1e-6)


@pytest.mark.parametrize("order", ["natural", "columns", "columns_reversed"])
def test_orders_reach_the_same_solution(order):
    P = hair(150, seed=8)
    ref = solve_contact_problem(P, method="clarabel", polish=False)
    res = solve_contact_problem(P, tol=1e-9, order=order)
    assert res.converged
    assert res.objective == pytest.approx(ref.objective, rel=1e-7)


def test_warm_start():
    P = hair(300, seed=9)
    cold = solve_contact_problem(P, tol=1e-9)
    again = solve_contact_problem(P, tol=1e-9, r0=cold.r)
    assert again.iterations == 0 and again.converged
    near = cold.r * (1 + 1e-4 * np.random.default_rng(0).normal(size=cold.r.size))
    warm = solve_contact_problem(P, tol=1e-9, r0=near)
    assert warm.converged and warm.iterations < cold.iterations


def test_non_convergence_is_reported():
    P = hair(300, seed=10)
    for method in ("gs", "apgd"):
        res = solve_contact_problem(P, method=method, tol=1e-12, max_iter=5)
        assert not res.converged
        assert res.status == "max_iter"
        assert np.isfinite(res.residual) and res.residual > 1e-12
        assert res.residual == pytest.approx(P.residual(res.r), rel=1e-9)


@pytest.mark.parametrize("method", ["gs", "apgd"])
def test_stop_rule_ends_the_run_with_status_certified(method):
    """The caller's stop(r, u) is asked at every residual check with r in the cones and u = W r + b; True ends the
    run before the residual reaches tol (status "certified", not converged)."""
    P = hair(300, seed=10)
    seen = []

    def stop(r, u):
        seen.append(len(seen))
        assert P.cone_violation(r) <= 1e-12 * np.abs(r).max()
        np.testing.assert_allclose(u, P.velocity(r), rtol=1e-9, atol=1e-12 * np.abs(u).max())
        return len(seen) == 3

    res = solve_contact_problem(P, method=method, tol=1e-14, max_iter=10_000, stop=stop)
    assert res.status == "certified" and not res.converged
    assert len(seen) == 3 and res.iterations == 30


def test_projected_sweeps_of_a_geometric_history():
    from groomtool.solvers.gauss_seidel import projected_sweeps

    hist = [(s, 10.0 ** (-s / 100), 0.0) for s in range(0, 401, 10)]  # one decade per 100 sweeps
    assert projected_sweeps(hist, 1e-8) == pytest.approx(800.0)
    assert projected_sweeps(hist, 1e-4) == 400.0  # already there
    bump = hist[:-1] + [(400, 1.0, 0.0)]  # the best residual so far counts, not the last one
    assert projected_sweeps(bump, 1e-8) == pytest.approx(400 + 4.1 * 200 / 1.9)  # best 10^-3.9, from 10^-2 at 200
    flat = [(s, 1e-3, 0.0) for s in range(0, 401, 10)]
    assert projected_sweeps(flat, 1e-8) == np.inf


def test_give_up_waits_out_a_plateau():
    """A plateau projects far past the limit for a while; give_up waits for the projection to stay over the
    limit for the last fifth of the run, so the run that speeds up again is not stopped."""
    from groomtool.solvers.gauss_seidel import give_up_projection, projected_sweeps

    def res(s):  # a decade per 300 sweeps, flat from 900 to 1,050, then a decade per 300 again
        return 10.0 ** (-(min(s, 900) + max(s - 1050, 0)) / 300)

    hist = [(s, res(s), 0.0) for s in range(0, 2001, 10)]
    limit = 3800.0
    over = [hist[k][0] for k in range(40, len(hist)) if projected_sweeps(hist[:k + 1], 1e-10) > limit]
    assert len(over) >= 10 and 900 < over[0] < 1050  # the single-check rule would stop inside the plateau
    assert all(give_up_projection(hist[:k + 1], 1e-10, limit, 400) is None for k in range(len(hist)))
    # a run that stays slow is stopped, once its whole last fifth projects past the limit
    slow = [(s, 10.0 ** (-s / 1000), 0.0) for s in range(0, 2001, 10)]  # 10,000 sweeps to 1e-10
    stops = [k for k in range(len(slow)) if give_up_projection(slow[:k + 1], 1e-10, limit, 400) is not None]
    assert slow[stops[0]][0] == 400
    assert give_up_projection(slow[:stops[0] + 1], 1e-10, limit, 400) == pytest.approx(10000.0)
    assert give_up_projection(slow[:stops[0] + 1], 1e-10, limit, 500) is None  # not judged before first_judged


def _chain(m=100):
    """Contacts coupled in a chain, W = tridiag(-1, 2, -1) (x) I3 + 1e-6 I: plain Gauss-Seidel's slowest
    classic case (its rate is 1 - O(1 / m^2) per sweep)."""
    T = sp.diags([-np.ones(m - 1), 2 * np.ones(m), -np.ones(m - 1)], [-1, 0, 1])
    W = sp.kron(T, sp.identity(3)).tocsr() + 1e-6 * sp.identity(3 * m)
    b = np.zeros(3 * m)
    b[0::3] = -1.0
    b[1::3] = 0.1
    return W, b


def test_give_up_stops_a_stalling_gauss_seidel_early():
    """On plain Gauss-Seidel (no Anderson, no Newton steps: a linear rate)."""
    W, b = _chain()
    full = solve_socqp(W, b, 0.5, tol=1e-10, max_iter=2000, anderson=0, newton=None)
    assert not full.converged and full.status == "max_iter" and full.iterations == 2000
    early = solve_socqp(W, b, 0.5, tol=1e-10, max_iter=2000, anderson=0, newton=None, give_up=2.0)
    assert early.status == "stalled" and not early.converged
    assert early.iterations == 500  # judged from a quarter of the budget on (and GIVE_UP_MIN_SWEEPS)
    projected = early.info["projected_sweeps"]
    assert projected > 2 * 2000
    assert early.residual > 1e-10 and early.residual == pytest.approx(full.info["history"][50][1], rel=1e-12)
    # rightly: even twice the budget does not converge (it takes ~24,000 sweeps; projected here ~29,000)
    longer = solve_socqp(W, b, 0.5, tol=1e-10, max_iter=2 * 2000, anderson=0, newton=None)
    assert not longer.converged
    # with the default subspace Newton steps the chain is a linear system on fixed faces: solved long before
    # give_up may judge
    newton = solve_socqp(W, b, 0.5, tol=1e-10, max_iter=2000, give_up=2.0)
    assert newton.converged and newton.iterations < GIVE_UP_MIN_SWEEPS


@pytest.mark.parametrize("seed", [12, 13])
def test_projection_never_gives_up_on_a_run_that_converges(seed):
    """On converging hair problems, every prefix of the run projects no more than twice the sweeps the
    run really took (the rule of give_up is optimistic) -- for Anderson-accelerated sweeps.  Subspace Newton
    steps (the default) converge faster than any geometric rate, so the projection is not optimistic there;
    such runs end before give_up judges (GIVE_UP_MIN_SWEEPS)."""
    from groomtool.solvers.gauss_seidel import projected_sweeps

    P = hair(400, seed=seed)
    default = solve_contact_problem(P, tol=1e-10, check_every=5)
    assert default.converged and default.iterations < GIVE_UP_MIN_SWEEPS
    res = solve_contact_problem(P, tol=1e-10, check_every=5, newton=None)
    assert res.converged
    hist = res.info["history"]
    for k in range(4, len(hist)):
        assert projected_sweeps(hist[:k], 1e-10) <= 2 * res.iterations


def test_over_relaxation_still_converges():
    P = hair(200, seed=11)
    ref = solve_contact_problem(P, tol=1e-9)
    res = solve_contact_problem(P, tol=1e-9, omega=1.3, anderson=0)
    assert res.converged and res.objective == pytest.approx(ref.objective, rel=1e-8)
    with pytest.raises(ValueError):
        solve_contact_problem(P, law="coulomb", omega=1.3)


# ----------------------------------------------------------------------------------------------
# Coulomb
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["gs", "fixed_point", "auto"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coulomb_small_problems_satisfy_the_law(method, seed):
    P = hair(80, seed=seed)
    res = solve_contact_problem(P, law="coulomb", method=method, tol=1e-10)
    if method == "gs" and not res.converged:
        pytest.skip("plain GS on the Coulomb law may cycle (that is what 'auto' handles)")
    assert res.converged and res.residual <= 1e-10
    assert coulomb_contact_errors(P, res.r).max() < 1e-7


def test_coulomb_auto_recovers_from_a_cycling_gauss_seidel():
    """A 2000-contact hair problem where GS on the Coulomb law cycles: 'auto' switches to the fixed point."""
    P = hair(2000, seed=0)
    gs = solve_contact_problem(P, law="coulomb", method="gs", max_iter=400)
    assert not gs.converged and gs.status == "max_iter"
    auto = solve_contact_problem(P, law="coulomb", method="auto", tol=1e-8)
    assert auto.converged and auto.info.get("switched_to") == "fixed_point"
    assert coulomb_contact_errors(P, auto.r).max() < 1e-6


def test_coulomb_differs_from_soc():
    """De Saxce's shift makes the Coulomb solution differ from the SOCQP one (u_N = 0 when slipping)."""
    P = hair(100, seed=4)
    soc = solve_contact_problem(P, law="soc", tol=1e-10)
    cou = solve_contact_problem(P, law="coulomb", tol=1e-10)
    assert cou.converged
    assert np.abs(soc.r - cou.r).max() > 1e-6
    assert P.residual(cou.r, "coulomb") <= 1e-10


# ----------------------------------------------------------------------------------------------
# assembled-W API
# ----------------------------------------------------------------------------------------------
def test_assembled_api():
    P = hair(150, seed=12)
    W = P.assemble_W()
    fact = solve_contact_problem(P, tol=1e-10)
    for method in ("gs", "apgd", "clarabel", "auto"):
        res = solve_socqp(W, P.b, P.mu, method=method, tol=1e-10)
        assert res.converged, method
        assert res.objective == pytest.approx(fact.objective, rel=1e-7)
        assert res.cone_violation <= 1e-9
    cou = solve_coulomb(W, P.b, P.mu, tol=1e-10)
    assert cou.converged and cou.residual <= 1e-10
    with pytest.raises(ValueError):
        solve_coulomb(W, P.b, P.mu, method="clarabel")
    with pytest.raises(ValueError):
        solve_socqp(W, P.b, P.mu, method="newton")
    with pytest.raises(ValueError):
        solve_socqp(W[:-1, :-1], P.b[:-1], P.mu)


@pytest.mark.parametrize("api", ["factored", "assembled"])
def test_clarabel_point_is_polished_to_the_tolerance(api):
    """clarabel stops on its duality gap, not on the natural-map residual; Gauss-Seidel sweeps from its
    optimum bring the residual below tol without moving the objective."""
    P = hair(300, seed=17)
    if api == "factored":
        raw = solve_contact_problem(P, method="clarabel", polish=False)
        res = solve_contact_problem(P, method="clarabel", tol=1e-11)
    else:
        W = P.assemble_W()
        raw = solve_socqp(W, P.b, P.mu, method="clarabel", polish=False)
        res = solve_socqp(W, P.b, P.mu, method="clarabel", tol=1e-11)
    assert raw.status == "Solved" and raw.residual > 1e-11  # so the polish has work to do
    assert res.converged and res.residual <= 1e-11
    assert res.info["polish_sweeps"] > 0 and res.info["clarabel_residual"] == pytest.approx(raw.residual, rel=1e-6)
    assert res.objective == pytest.approx(raw.objective, rel=1e-7)
    assert res.cone_violation <= 1e-12


def test_frictionless_contacts_in_clarabel():
    """mu = 0 must become r_T = 0, r_N >= 0 (clarabel's SOC(3) would leave r_N free)."""
    P = hair(60, seed=13, mu_range=(0.0, 0.0))
    cl = solve_contact_problem(P, method="clarabel", polish=False)
    gs = solve_contact_problem(P, tol=1e-10)
    r = cl.r.reshape(-1, 3)
    assert np.abs(r[:, 1:]).max() < 1e-9 and r[:, 0].min() > -1e-9
    assert cl.objective == pytest.approx(gs.objective, rel=1e-7)


def test_diagonal_dense_blocks_are_stored_as_diagonals():
    """np.diag(...) blocks (as the inversion builds them) take the diagonal fast paths, same answer."""
    P = hair(120, seed=15)
    dense = [np.diag(d) for d in P.D_blocks]
    Q = ContactProblem(P.H, dense, P.dof_offsets, P.gamma, P.b, P.mu)
    assert Q.is_diagonal
    a = solve_contact_problem(P, tol=1e-10)
    b = solve_contact_problem(Q, tol=1e-10)
    np.testing.assert_allclose(a.r, b.r, rtol=0, atol=1e-12 * np.abs(a.r).max())


def test_residual_scale_option():
    """A caller's residual scale (the simulator floors it) is used for stopping and for the result."""
    P = hair(200, seed=16)
    small = ContactProblem(P.H, P.D_blocks, P.dof_offsets, P.gamma, 1e-9 * P.b, P.mu)
    res = solve_contact_problem(small, law="coulomb", method="auto", tol=1e-8, scale=1.0)
    assert res.converged and res.residual <= 1e-8
    assert res.residual == pytest.approx(small.residual(res.r, "coulomb") * small.residual_scale(), rel=1e-6, abs=1e-18)
    cl = solve_contact_problem(P, method="clarabel", scale=1.0)
    assert cl.converged


def test_result_fields():
    P = hair(50, seed=14)
    res = solve_contact_problem(P)
    assert res.method == "gs" and res.status == "solved" and res.r.shape == (150,)
    assert res.time_s > 0 and res.info["form"] in ("assembled", "matrix_free")
    assert res.info["history"][-1][1] == pytest.approx(res.residual, rel=1e-6)


def test_projection_is_a_projection():
    assert project_cone(0.0, -1.0, 0.0, 0.0) == (0.0, 0.0, 0.0)  # mu = 0: the cone is a ray
    assert project_cone(0.0, 2.0, 0.0, 0.0) == (2.0, 0.0, 0.0)
    rng = np.random.default_rng(0)
    for mu in [0.0, 0.3, 1.0, 7.0]:
        for _ in range(200):
            z = rng.normal(size=3) * 10 ** rng.uniform(-3, 3)
            p = np.array(project_cone(mu, *z))
            assert np.linalg.norm(p[1:]) <= mu * p[0] + 1e-12 * np.linalg.norm(z)
            # z - p is in the polar cone and orthogonal to p
            d = z - p
            assert abs(d @ p) <= 1e-10 * np.linalg.norm(z) ** 2
            assert mu * np.linalg.norm(d[1:]) <= -d[0] + 1e-10 * np.linalg.norm(z) if mu > 0 else True


def test_a_dense_block_is_stored_as_its_diagonal_only_when_it_is_exactly_diagonal():
    H = sp.random(6, 4, density=0.8, random_state=2, format="csr")
    d = np.array([1.0, 2.0, 0.0, 3.0])
    diag = ContactProblem(H=H, D_blocks=[np.diag(d)], dof_offsets=[0, 4], gamma=0.0, b=np.zeros(6), mu=0.3)
    assert diag.is_diagonal and np.array_equal(diag.D_blocks[0], d)  # a zero on the diagonal is still diagonal
    for value in (1e-300, np.nan):
        block = np.diag(d)
        block[2, 1] = value
        dense = ContactProblem(H=H, D_blocks=[block], dof_offsets=[0, 4], gamma=0.0, b=np.zeros(6), mu=0.3)
        assert not dense.is_diagonal and dense.D_blocks[0].shape == (4, 4)
