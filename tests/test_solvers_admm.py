"""The strand-split ADMM (solvers/admm.py) against clarabel's optimum, its pieces against dense restatements."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from groomtool.solvers import ContactProblem, solve_contact_problem, solve_socqp
from groomtool.solvers.admm import StrandSplit

_spec = importlib.util.spec_from_file_location("bench_problems",
                                               Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def _agrees_with_clarabel(P, res, rel=1e-7):
    ref = solve_contact_problem(P, "soc", "clarabel", polish=False)  # clarabel's own point: independent
    assert ref.status == "Solved"
    assert res.converged and res.residual <= 1e-9
    assert res.cone_violation <= 1e-14 * max(1.0, np.abs(res.r).max())
    assert abs(res.objective - ref.objective) <= rel * max(1.0, abs(ref.objective))


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    m=st.integers(2, 40),
    n_strands=st.integers(2, 10),
    dofs=st.integers(3, 40),
    mu=st.sampled_from([0.0, 0.3, 1.0, 3.0, "mixed"]),
    dense=st.booleans(),
    seed=st.integers(0, 10_000),
)
def test_admm_matches_clarabel(m, n_strands, dofs, mu, dense, seed):
    """Objective within 1e-7 (relative) of clarabel's on random factored problems, diagonal or dense D blocks."""
    assume(n_strands * dofs >= 3 * m)
    rng = np.random.default_rng(seed)
    mus = rng.choice([0.0, 0.2, 0.5, 2.0], size=m) if mu == "mixed" else mu
    P = problems.random_factored_problem(m, n_strands, dofs, dense=dense, mu=mus, seed=seed)
    res = solve_contact_problem(P, "soc", "admm", tol=1e-10, max_iter=50_000)
    _agrees_with_clarabel(P, res)


@pytest.mark.parametrize("variant", ["inverse", "dynamics"])
def test_admm_on_hair_like_problems_with_redundant_contacts(variant):
    """Hair-like problems (body and strand/strand contacts), also with far more contact rows than dofs on a
    strand (the redundant contacts where Gauss-Seidel stalls), cold and from a given start."""
    for m, strands in [(300, None), (200, 8)]:
        P = problems.make_hair_like(m, n_strands=strands, elements=6, variant=variant, seed=4)[0]
        res = solve_contact_problem(P, "soc", "admm", tol=1e-10, max_iter=50_000)
        _agrees_with_clarabel(P, res)
        assert res.info["form"] == "strand_split" and res.info["warm_sweeps"] > 0
        again = solve_contact_problem(P, "soc", "admm", tol=1e-10, r0=res.r)
        assert again.converged and again.iterations == 0 and again.info["warm_sweeps"] == 0


def test_strand_split_x_step_solves_each_strand_system_exactly():
    """x_s = (J_s D_s J_s^T + P_s)^-1 P_s w_s per strand (Woodbury with the Cholesky factors), against the dense
    solve; the strand velocities J_e D_s J_s^T x_s add up to H D H^T x over each contact's ends."""
    for dense in (False, True):
        P = problems.random_factored_problem(30, 4, 25, dense=dense, mu=0.3, seed=2)
        rng = np.random.default_rng(0)
        rho_c = rng.uniform(0.05, 2.0, P.n_contacts)
        split = StrandSplit(P, rho_c)
        E = split.n_ends
        w = rng.normal(size=(E, 3))
        x = np.empty((E, 3))
        split.x_step(w, x)
        H = P.H.tocsr()
        for s in range(P.n_strands):
            ends = split.ends_sorted[split.strand_ptr[s]:split.strand_ptr[s + 1]]
            if not len(ends):
                continue
            a, c = P.dof_offsets[s], P.dof_offsets[s + 1]
            rows = (3 * split.end_contact[ends][:, None] + np.arange(3)).ravel()
            J = H[rows][:, a:c].toarray()
            D = P.D_blocks[s]
            D = np.diag(D) if D.ndim == 1 else D
            Pm = np.diag(np.repeat(rho_c[split.end_contact[ends]], 3))
            expect = np.linalg.solve(J @ D @ J.T + Pm, Pm @ w[ends].ravel())
            np.testing.assert_allclose(x[ends].ravel(), expect, rtol=1e-9, atol=1e-12 * np.abs(expect).max())
        r = rng.normal(size=(P.n_contacts, 3))
        v = split.strand_velocity(np.ascontiguousarray(r[split.end_contact]))
        total = np.zeros_like(r)
        np.add.at(total, split.end_contact, v)
        np.testing.assert_allclose(total.ravel(), P.delassus_apply(r.ravel()) - 2 * P.gamma * r.ravel(),
                                   rtol=1e-10, atol=1e-12)


def test_admm_iterates_stay_in_the_cones_and_the_stop_rule_ends_the_run():
    P = problems.make_hair_like(300, seed=5)[0]
    seen = []

    def stop(r, u):
        seen.append(P.cone_violation(r))
        np.testing.assert_allclose(u, P.velocity(r), rtol=1e-9, atol=1e-12 * np.abs(u).max())
        return len(seen) == 4

    res = solve_contact_problem(P, "soc", "admm", tol=1e-14, check_every=5, stop=stop)
    assert res.status == "certified" and not res.converged and res.iterations == 20
    assert max(seen) <= 1e-14 * np.abs(res.r).max()


def test_admm_needs_a_contact_problem_and_checks_its_options():
    P = problems.make_hair_like(50, seed=1)[0]
    with pytest.raises(ValueError, match="ContactProblem"):
        solve_socqp(P.assemble_W(), P.b, P.mu, method="admm")
    with pytest.raises(ValueError, match="alpha"):
        solve_contact_problem(P, "soc", "admm", alpha=2.0)
    with pytest.raises(ValueError, match="not solve the coulomb law"):
        solve_contact_problem(P, "coulomb", "admm")


def test_admm_with_contacts_on_no_dof_and_a_strand_without_contacts():
    """A contact whose rows are all zero (no end: s = P_K(-b / 2 gamma)) and strands no contact touches."""
    P = problems.random_factored_problem(12, 5, 20, dense=False, mu=0.5, seed=7)
    H = P.H.tolil()
    H[0:3, :] = 0.0
    H[:, P.dof_offsets[4]:] = 0.0
    Q = ContactProblem(sp.csr_matrix(H), P.D_blocks, P.dof_offsets, P.gamma, P.b, P.mu)
    res = solve_contact_problem(Q, "soc", "admm", tol=1e-10, max_iter=50_000)
    _agrees_with_clarabel(Q, res)


def test_auto_takes_the_strand_split_admm_for_dense_contacts_where_it_fits(monkeypatch):
    import groomtool.solver_choice as sc
    from groomtool.solvers.admm import strand_split_bytes

    P = problems.make_hair_like(300, seed=5)[0]
    assert sc.dense_iterative_method(P, 1.0) == "admm"
    assert sc.dense_iterative_method(P, sc.AUTO_GS_MAX_REDUNDANT) == "gs"  # sparse contacts: Gauss-Seidel
    assert 8 * sum(d.size ** 2 for d in P.D_blocks) <= strand_split_bytes(P)
    monkeypatch.setattr(sc, "ADMM_MEMORY_CAP", strand_split_bytes(P) - 1)
    assert sc.dense_iterative_method(P, 1.0) == "gs"  # the strand factors would not fit


def test_inversion_of_dense_contacts_beyond_clarabels_reach_runs_admm_to_the_q0_tolerance(monkeypatch):
    """auto on dense contacts beyond AUTO_CLARABEL_MAX_CONTACTS (lowered here to make a small groom count as such):
    the strand-split ADMM, stopped by the certified rest-curvature bound; the rest curvatures then lie within that
    bound of clarabel's (certified to 1e-7)."""
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    groom, head = example_groom(60)
    ref = invert_groom(groom, head=head, params=InversionParams(contacts="all", contact_radius=3e-4, solver="clarabel"))
    assert ref.report["solve"]["q0_error_bound"] < 1e-6
    assert ref.report["solve"]["redundant_strand_fraction"] > sc.AUTO_GS_MAX_REDUNDANT
    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    res = invert_groom(groom, head=head, params=InversionParams(contacts="all", contact_radius=3e-4))
    solve = res.report["solve"]
    assert solve["solver"] == "admm" and solve["status"] == "solved" and solve["stopped_on"] == "q0_tolerance"
    assert solve["q0_error_bound"] <= 1e-3
    true = np.linalg.norm(res.rest_curvatures - ref.rest_curvatures) / np.linalg.norm(ref.rest_curvatures)
    assert true <= solve["q0_error_bound"] + ref.report["solve"]["q0_error_bound"]
    assert res.report["equilibrium"]["max_relative_residual"] < 1e-8


def test_inversion_admm_gives_up_on_the_rate_of_its_bound_and_keeps_feasible_forces(monkeypatch):
    """Gauss-Seidel's give_up rule applied to the certified bound's history: with GS_GIVE_UP = 0.05 the limit (80
    iterations for a budget of 1,600) is below every projection, so ADMM stops at the first judged iteration (400),
    status "stalled", its forces kept (feasible, with their bound)."""
    import groomtool.inverse_problem as ip
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import FeasibleSolveWarning, InversionParams, invert_groom

    groom, head = example_groom(60)
    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    monkeypatch.setattr(ip, "GS_GIVE_UP", 0.05)
    params = InversionParams(contacts="all", contact_radius=3e-4, q0_tolerance=1e-12, solver_tolerance=1e-12,
                             max_sweeps=1600, stabilize="none")
    with pytest.warns(FeasibleSolveWarning, match="stalled"):
        res = invert_groom(groom, head=head, params=params)
    solve = res.report["solve"]
    assert solve["solver"] == "admm" and solve["status"] == "feasible" and solve["stopped_with"] == "stalled"
    assert solve["iterations"] == 400 and solve["projected_sweeps"] > 0.05 * 1600
    assert 0 < solve["q0_error_bound"] < 1e-2
