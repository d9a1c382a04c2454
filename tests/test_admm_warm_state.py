"""The strand-split ADMM restarted from its own end state (solvers/admm.py ADMMState) after the problem's D changed,
as the inversion's stiffening rounds do (invert.py): the same optimum as clarabel's, fewer iterations than a start
from the forces alone, and the state plumbed through solve_inverse_problem and invert_groom."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from groomtool.solvers import ContactProblem, solve_contact_problem
from groomtool.solvers import admm
from groomtool.solvers.admm import StrandSplit, run_admm

_spec = importlib.util.spec_from_file_location("bench_problems",
                                               Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def _stiffened(P, seed, fraction=0.2, factor=3.0, scale=0.9):
    """P with K raised by ``factor`` on a ``fraction`` of its strands (D = K^-2 / w_scale: D_s / factor^2 there),
    every D scaled by ``scale`` (w_scale moves) and b perturbed (b = -H K^-1 d depends on K)."""
    rng = np.random.default_rng(seed)
    raised = rng.random(P.n_strands) < fraction
    raised[rng.integers(P.n_strands)] = True
    blocks = [np.array(d) * scale / (factor ** 2 if raised[s] else 1.0) for s, d in enumerate(P.D_blocks)]
    b = P.b * (1.0 + 0.2 * rng.uniform(-1, 1, size=P.b.shape))
    return ContactProblem(H=P.H, D_blocks=blocks, dof_offsets=P.dof_offsets, gamma=P.gamma, b=b, mu=P.mu), raised


def _first_round(P, iterations):
    """An unconverged first solve (as the inversion's, stopped by its q0 bound): ``iterations`` ADMM iterations."""
    out = run_admm(P, tol=1e-14, max_iter=iterations)
    assert not out.converged and out.state is not None and out.iterations == iterations
    return out


CASES = [(300, None, 4), (200, 8, 4), (400, None, 11)]  # (contacts, strands, seed) of make_hair_like("inverse")


@pytest.mark.parametrize("m, strands, seed", CASES)
def test_restart_from_the_state_reaches_clarabels_optimum_after_a_stiffness_change(m, strands, seed):
    P = problems.make_hair_like(m, n_strands=strands, elements=6, variant="inverse", seed=seed)[0]
    first = _first_round(P, 60)
    Q, _ = _stiffened(P, seed)
    ref = solve_contact_problem(Q, "soc", "clarabel", polish=False)  # independent of ADMM
    assert ref.status == "Solved"
    holder = {}
    res = solve_contact_problem(Q, "soc", "admm", tol=1e-10, max_iter=50_000, r0=first.r,
                                initial_state=first.state, state_out=holder)
    assert res.converged and res.residual <= 1e-10
    assert res.cone_violation <= 1e-14 * max(1.0, np.abs(res.r).max())
    assert abs(res.objective - ref.objective) <= 1e-7 * max(1.0, abs(ref.objective))
    assert np.linalg.norm(res.r - ref.r) <= 1e-3 * np.linalg.norm(ref.r)
    assert holder["state"].z.shape == first.state.z.shape  # the new end state, for the next round


def _scaled(P, c):
    """P with D, gamma and b all times c: the same optimum, and the same ADMM iterates (rho scales with W)."""
    return ContactProblem(H=P.H, D_blocks=[np.array(d) * c for d in P.D_blocks], dof_offsets=P.dof_offsets,
                          gamma=P.gamma * c, b=P.b * c, mu=P.mu)


@pytest.mark.parametrize("m, strands, seed", CASES)
def test_a_run_resumed_from_its_state_continues_where_it_stopped(m, strands, seed):
    """Plain ADMM (no Anderson history to lose) stopped after k iterations and resumed from its state on the same
    problem rescaled (as the inversion's w_scale moves) takes the iterations the uninterrupted run had left, to
    the same forces; from the forces alone it does not continue (its multipliers are rebuilt from the forces).
    Whether that restart is faster or slower than continuing depends on the problem (with Anderson mixing and
    after a stiffness change both ways were measured: docs/solvers.md section 12), so no order is asserted."""
    P = problems.make_hair_like(m, n_strands=strands, elements=6, variant="inverse", seed=seed)[0]
    whole = run_admm(P, tol=1e-9, max_iter=50_000, anderson=0, check_every=1)
    k = whole.iterations // 3
    first = run_admm(P, tol=1e-14, max_iter=k, anderson=0)
    Q = _scaled(P, 0.7)
    resumed = run_admm(Q, tol=1e-9, max_iter=50_000, anderson=0, check_every=1, r0=first.r, initial_state=first.state)
    assert resumed.from_state and resumed.converged
    assert abs(k + resumed.iterations - whole.iterations) <= 1
    np.testing.assert_allclose(resumed.r, whole.r, rtol=0, atol=1e-7 * np.abs(whole.r).max())
    restarted = run_admm(Q, tol=1e-9, max_iter=50_000, anderson=0, check_every=1, r0=first.r)
    assert restarted.converged and k + restarted.iterations != whole.iterations


def test_state_of_a_converged_run_restarts_exactly_where_the_forces_do():
    """At the fixed point z_e = s_i - v_e / rho_i (v_e: strand s(e)'s part of contact i's velocity), so the state
    rescaled for the new D (ADMMState) must equal the start the forces alone give on the new problem."""
    P = problems.make_hair_like(300, elements=6, variant="inverse", seed=4)[0]
    first = run_admm(P, tol=1e-13, max_iter=50_000)
    assert first.converged
    Q, raised = _stiffened(P, 4, factor=5.0)
    assert raised.any() and not raised.all()
    diag = Q.diagonal_blocks()
    rho_c = admm.BETA * np.einsum("kii->k", diag) / 3.0
    split = StrandSplit(Q, rho_c)
    z, s = admm._start_from_state(first.state, split, rho_c, admm.strand_traces(Q))
    se = np.ascontiguousarray(first.state.s[split.end_contact])
    expect = se - split.strand_velocity(se) / split.rho_end[:, None]
    np.testing.assert_allclose(z, expect, rtol=1e-6, atol=1e-8 * np.abs(expect).max())
    np.testing.assert_array_equal(s, first.state.s)


def test_a_state_of_other_contacts_is_ignored():
    """A state whose ends differ (another H) is not used: the run starts from r0 as before."""
    P = problems.make_hair_like(300, elements=6, variant="inverse", seed=4)[0]
    other = problems.make_hair_like(200, elements=6, variant="inverse", seed=5)[0]
    state = run_admm(other, tol=1e-6).state
    out = run_admm(P, tol=1e-10, max_iter=50_000, initial_state=state)
    assert not out.from_state and out.warm_sweeps > 0 and out.converged


def test_inversion_stiffening_rounds_restart_admm_from_its_state(monkeypatch):
    """invert_groom's re-solves after stiffening get the previous round's ADMM state, end on the q0 tolerance, and
    the report stays free of the state (AUTO_CLARABEL_MAX_CONTACTS lowered so that auto takes ADMM)."""
    import json

    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    inv = sys.modules["groomtool.invert"]
    calls = []
    solve = inv.solve_inverse_problem

    def spy(*args, **kw):
        out = solve(*args, **kw)
        calls.append((kw.get("initial_state"), out["admm_state"]))
        return out

    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    monkeypatch.setattr(inv, "solve_inverse_problem", spy)
    groom, head = example_groom(150)  # 3,805 contacts, one strand stiffened once
    res = invert_groom(groom, head=head, params=InversionParams(contacts="all", contact_radius=3e-4))
    assert len(calls) >= 2, "the example should need a stiffening round"
    assert calls[0][0] is None and all(c[1] is not None for c in calls)
    for prev, cur in zip(calls, calls[1:]):
        assert cur[0] is prev[1]
    solve_report = res.report["solve"]
    assert solve_report["solver"] == "admm" and solve_report["status"] == "solved"
    assert solve_report["q0_error_bound"] <= 1e-3
    assert "admm_state" not in solve_report
    json.dumps(res.report["solve"], default=float)
