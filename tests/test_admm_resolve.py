"""The strand-split ADMM's re-solve set-up (solvers/admm.py StrandSplit.reusing): a run started from a previous run's
state on the same H keeps that run's ends, W_ii, rho and strand factors wherever D changed by a scalar only (as the
inversion's stiffening rounds change it), and refactors the rest.  What it builds must equal a fresh set-up with the
same rho, and its runs must reach the same optimum as clarabel's."""

import importlib.util
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


def _problem(variant, seed, m=300, strands=None):
    return problems.make_hair_like(m, n_strands=strands, elements=6, variant=variant, seed=seed)[0]


def _changed(P, seed, fraction=0.2, factor=3.0, scale=0.9, perturbed=0):
    """P as the next stiffening round makes it: every D_s times ``scale`` (w_scale moves), a ``fraction`` of the
    strands' D_s divided by factor^2 too (K raised), ``perturbed`` strands' D_s changed by more than a scalar, b
    perturbed.  Returns (problem, raised or perturbed strands)."""
    rng = np.random.default_rng(seed)
    raised = rng.random(P.n_strands) < fraction
    raised[rng.integers(P.n_strands)] = True
    odd = rng.choice(P.n_strands, size=perturbed, replace=False)
    blocks = []
    for s, d in enumerate(P.D_blocks):
        d = np.array(d) * scale / (factor ** 2 if raised[s] else 1.0)
        if s in odd:
            d = d * (1.0 + 0.3 * rng.random(d.shape)) if d.ndim == 1 else d + 0.1 * np.abs(d).max() * np.eye(len(d))
        blocks.append(d)
    b = P.b * (1.0 + 0.2 * rng.uniform(-1, 1, size=P.b.shape))
    changed = raised.copy()
    changed[odd] = True
    Q = ContactProblem(H=P.H, D_blocks=blocks, dof_offsets=P.dof_offsets, gamma=P.gamma, b=b, mu=P.mu)
    Q.test_ratio = np.where(raised, scale / factor ** 2, scale)  # D'_s = ratio D_s (NaN: not by a scalar)
    Q.test_ratio[odd] = np.nan
    return Q, changed


def _fresh_copy(Q):
    """The same problem, a new object (no cache shared with Q)."""
    return ContactProblem(H=Q.H, D_blocks=[np.array(d) for d in Q.D_blocks], dof_offsets=Q.dof_offsets,
                          gamma=Q.gamma, b=Q.b, mu=Q.mu)


def _assert_same_setup(split, Q):
    """``split`` (reused) against a fresh StrandSplit of Q with the same rho: ends, W_ii, factors, x-steps."""
    Q2 = _fresh_copy(Q)
    fresh = StrandSplit(Q2, split.rho_c)
    for name in ("cend_ptr", "end_contact", "end_strand", "end_p0", "end_p1", "ends_sorted", "strand_ptr", "L_ptr"):
        np.testing.assert_array_equal(getattr(split, name), getattr(fresh, name), err_msg=name)
    np.testing.assert_array_equal(split.rho_end, fresh.rho_end)
    np.testing.assert_allclose(split.diag, Q2.diagonal_blocks(), rtol=1e-12, atol=1e-14 * np.abs(split.diag).max())
    for s in range(Q.n_strands):
        a, b = split.factor(s), fresh.factor(s)
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13 * np.abs(b).max(initial=1.0), err_msg=f"strand {s}")
    rng = np.random.default_rng(1)
    w = rng.normal(size=(split.n_ends, 3))
    x, y = np.empty_like(w), np.empty_like(w)
    split.x_step(w, x)
    fresh.x_step(w, y)
    np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12 * np.abs(y).max())


@pytest.mark.parametrize("variant, seed, perturbed", [("inverse", 4, 0), ("inverse", 7, 5), ("dynamics", 3, 3)])
def test_reused_setup_equals_a_fresh_one_after_a_stiffness_change(variant, seed, perturbed):
    P = _problem(variant, seed)
    first = run_admm(P, tol=1e-14, max_iter=30)
    previous = first.state.split
    assert previous is not None and previous.problem is None  # the state does not keep the problem's caches
    Q, changed = _changed(P, seed, perturbed=perturbed)
    split = StrandSplit.reusing(Q, previous, admm.BETA)
    assert split is not None and previous.L is None  # consumed: its factors were updated in place
    used = np.diff(split.strand_ptr) > 0
    # the strands whose D changed by more than the common scale are refactored, and so are their partners
    touched = np.zeros(Q.n_strands, dtype=bool)
    for i in range(Q.n_contacts):
        ends = split.end_strand[split.cend_ptr[i]:split.cend_ptr[i + 1]]
        if changed[ends].any() and not changed[ends].all():
            touched[ends] = True
    assert 0 < split.refactored < used.sum()
    assert split.refactored >= np.count_nonzero(touched & used)
    kept = split.L_scale != 1.0
    assert kept.sum() == used.sum() - split.refactored and not (kept & touched).any()
    # a contact between strands of one ratio keeps its rho times that ratio where that is within RHO_RTOL of the
    # rule's (beta tr(W_ii) / 3), the others get the rule's
    ratio = Q.test_ratio
    fresh_rho = admm.contact_rho(_fresh_copy(Q).diagonal_blocks())
    ends = [split.end_strand[split.cend_ptr[i]:split.cend_ptr[i + 1]] for i in range(Q.n_contacts)]
    one = np.array([len(e) > 0 and np.all(np.isfinite(ratio[e])) and len(set(ratio[e])) == 1 for e in ends])
    scaled = ratio[split.end_strand[np.minimum(split.cend_ptr[:-1], split.n_ends - 1)]] * first.state.rho_c
    kept = one & (np.abs(scaled - fresh_rho) <= admm.RHO_RTOL * fresh_rho)
    assert kept.mean() > 0.3
    np.testing.assert_allclose(split.rho_c, np.where(kept, scaled, fresh_rho), rtol=1e-12)
    _assert_same_setup(split, Q)


def test_reuse_over_several_rounds_and_a_rescaled_problem():
    """Three rounds, each from the last one's state (factor scales accumulate), then a round that scales D, gamma and
    b alike (every factor kept): each set-up equals a fresh one with its rho."""
    P = _problem("inverse", 11, m=400)
    out = run_admm(P, tol=1e-14, max_iter=20)
    for k in range(3):
        Q, _ = _changed(P, 20 + k, fraction=0.1, scale=0.8 + 0.1 * k)
        holder = {}
        run_admm(Q, tol=1e-14, max_iter=20, initial_state=out.state, state_out=holder)
        split = holder["state"].split
        assert split.refactored < np.count_nonzero(np.diff(split.strand_ptr) > 0)
        _assert_same_setup(split, Q)
        out, P = type("o", (), {"state": holder["state"]}), Q
    c = 0.7
    R = ContactProblem(H=P.H, D_blocks=[np.array(d) * c for d in P.D_blocks], dof_offsets=P.dof_offsets,
                       gamma=P.gamma * c, b=P.b * c, mu=P.mu)
    split = StrandSplit.reusing(R, out.state.split, admm.BETA)
    assert split.refactored == 0
    _assert_same_setup(split, R)


def test_fresh_factors_are_the_cholesky_factors_of_the_strand_systems():
    """The compiled factorisation (both set-ups use it) against np.linalg.cholesky of M_s built densely."""
    for variant in ("inverse", "dynamics"):
        P = _problem(variant, 5, m=150, strands=6)
        rho_c = np.random.default_rng(0).uniform(0.05, 2.0, P.n_contacts)
        split = StrandSplit(P, rho_c)
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
            M = np.linalg.inv(D) + J.T @ np.diag(1.0 / np.repeat(rho_c[split.end_contact[ends]], 3)) @ J
            expect = np.linalg.cholesky(0.5 * (M + M.T))
            np.testing.assert_allclose(split.factor(s), expect, rtol=1e-10, atol=1e-12 * np.abs(expect).max())


@pytest.mark.parametrize("variant, seed", [("inverse", 4), ("dynamics", 6)])
def test_resolve_from_a_reused_setup_reaches_clarabels_optimum(variant, seed):
    """A re-solve whose set-up is the previous run's (reused) and one from the same state without it (fresh set-up)
    reach the same forces, clarabel's; the state's set-up is used once."""
    P = _problem(variant, seed)
    first = run_admm(P, tol=1e-14, max_iter=60)
    Q, _ = _changed(P, seed, perturbed=2)
    ref = solve_contact_problem(Q, "soc", "clarabel", polish=False)
    assert ref.status == "Solved"
    bare = admm.ADMMState(**{k: getattr(first.state, k) for k in ("z", "s", "rho_c", "d_trace", "end_strand",
                                                                   "cend_ptr")})
    outs = []
    for state in (first.state, bare):
        holder = {}
        res = solve_contact_problem(Q, "soc", "admm", tol=1e-10, max_iter=50_000, initial_state=state,
                                    state_out=holder)
        assert res.converged and res.residual <= 1e-10
        assert abs(res.objective - ref.objective) <= 1e-7 * max(1.0, abs(ref.objective))
        assert np.linalg.norm(res.r - ref.r) <= 1e-3 * np.linalg.norm(ref.r)
        outs.append((res, holder["state"].split))
    assert first.state.split is None  # consumed by the first re-solve; the second built its own
    assert outs[0][1].refactored < outs[1][1].refactored
    np.testing.assert_allclose(outs[0][0].r, outs[1][0].r, rtol=0, atol=1e-3 * np.abs(ref.r).max())
    again = run_admm(Q, tol=1e-10, max_iter=50_000, initial_state=first.state)  # a consumed state still starts a run
    assert again.from_state and again.converged


def test_another_H_or_beta_gets_a_fresh_setup():
    P = _problem("inverse", 4)
    other = _problem("inverse", 5, m=200)
    state = run_admm(P, tol=1e-14, max_iter=10).state
    assert StrandSplit.reusing(other, state.split, admm.BETA) is None
    assert StrandSplit.reusing(P, state.split, 2 * admm.BETA) is None
    H = P.H.copy()
    H.data[0] *= 1.0 + 1e-12
    moved = ContactProblem(H=H, D_blocks=P.D_blocks, dof_offsets=P.dof_offsets, gamma=P.gamma, b=P.b, mu=P.mu)
    assert StrandSplit.reusing(moved, state.split, admm.BETA) is None
    same = ContactProblem(H=P.H.copy(), D_blocks=P.D_blocks, dof_offsets=P.dof_offsets, gamma=P.gamma, b=P.b,
                          mu=P.mu)  # equal values in other memory: reused
    split = StrandSplit.reusing(same, state.split, admm.BETA)
    assert split is not None and split.refactored == 0
    _assert_same_setup(split, same)
