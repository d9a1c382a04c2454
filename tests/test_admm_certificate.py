"""The certificate from the strand-split ADMM's strand solves (certificate.error_bound_with_strands, issue 16):
the duality gap at the dual point l = D^1/2 h, h = sum_e J_e^T x_e, against a dense restatement of f(r) - g(l)
(diagonal and dense D), a true upper bound on the rest-curvature error at every ADMM iterate against a certified
clarabel optimum (and how tight), and the inversion taking the smaller of the two certified bounds."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from groomtool.solvers import solve_contact_problem
from groomtool.solvers.admm import StrandSplit, run_admm
from groomtool.solvers.certificate import error_bound, error_bound_with_dual, error_bound_with_strands, project_forces

_spec = importlib.util.spec_from_file_location("bench_problems",
                                               Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def _dense(P):
    """(H dense, D dense, D^1/2 dense) of a small ContactProblem."""
    n = P.n_dofs
    D = np.column_stack([P.D_apply(np.eye(n)[:, j]) for j in range(n)])
    D = 0.5 * (D + D.T)
    w, V = np.linalg.eigh(D)
    return P.H.toarray(), D, (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


def _f_minus_g(P, r, h):
    """f(r) - g(l) at l = D^1/2 h written out densely: f = 1/2 |A^T r|^2 + gamma |r|^2 + b^T r,
    g(l) = -1/2 |l|^2 - |P_K(-(A l + b))|^2 / (4 gamma), A = H D^1/2."""
    H, _, Dh = _dense(P)
    A = H @ Dh
    y = A.T @ r
    f = 0.5 * y @ y + P.gamma * r @ r + P.b @ r
    lam = Dh @ h
    proj, _ = project_forces(-(A @ lam + P.b), P.mu)
    g = -0.5 * lam @ lam - proj @ proj / (4.0 * P.gamma)
    return f - g


@pytest.mark.parametrize("dense", [False, True])
def test_gap_at_the_strand_dual_point_is_f_minus_g_written_out(dense):
    """The D_apply form of the gap (no D^1/2) equals f(r) - g(D^1/2 h) computed with a dense D^1/2, for diagonal
    and dense D blocks; with diagonal D it equals error_bound_with_dual at lam = D^1/2 h; with h = H^T r it is the
    primal certificate (l = A^T r)."""
    P = problems.random_factored_problem(12, 3, 10, dense=dense, mu=0.4, seed=7)
    rng = np.random.default_rng(1)
    r, _ = project_forces(rng.normal(size=3 * P.n_contacts), P.mu)
    h = P.H.T @ r + 0.3 * rng.normal(size=P.n_dofs)
    e = error_bound_with_strands(P, r, h)
    want = _f_minus_g(P, r, h)
    assert e["gap"] == pytest.approx(want, rel=1e-9)
    _, D, _ = _dense(P)
    d = P.H.T @ r - h
    assert e["delta"] == pytest.approx(math.sqrt(d @ D @ d), rel=1e-9)
    assert e["bound"] == pytest.approx(0.5 * (e["delta"] + math.sqrt(4 * want - e["delta"] ** 2)), rel=1e-9)
    if not dense:
        assert e["bound"] == pytest.approx(error_bound_with_dual(P, r, np.sqrt(P.D_data) * h)["bound"], rel=1e-9)
    at_y = error_bound_with_strands(P, r, P.H.T @ r)
    assert at_y["delta"] == 0.0
    assert at_y["bound"] == pytest.approx(error_bound(P, r, line_search=False)["bound"], rel=1e-9)


def test_strand_sum_of_the_forces_copies_is_H_transpose_r():
    """h = sum_e J_e^T x_e with every end's copy x_e = r_i(e) is H^T r (the ends split H's rows by strand)."""
    for dense in (False, True):
        P = problems.random_factored_problem(30, 4, 25, dense=dense, mu=0.3, seed=2)
        split = StrandSplit(P, np.ones(P.n_contacts))
        r = np.random.default_rng(3).normal(size=(P.n_contacts, 3))
        np.testing.assert_allclose(split.strand_sum(r[split.end_contact]), P.H.T @ r.ravel(), rtol=1e-12, atol=1e-12)


def _certified_optimum(P):
    """clarabel's optimum polished to residual 1e-12, in its cones, and its own certified error (primal bound)."""
    ref = solve_contact_problem(P, "soc", "clarabel", tol=1e-12)
    r, _ = project_forces(ref.r, P.mu)
    return r, error_bound(P, r)["bound"]


CASES = [("inverse", 300, None, 4), ("inverse", 200, 8, 4), ("inverse", 400, None, 11), ("dynamics", 300, None, 4)]


@pytest.mark.parametrize("variant, m, strands, seed", CASES)
def test_strand_bound_bounds_the_true_error_at_every_admm_iterate(variant, m, strands, seed):
    """At every ADMM iteration (check_every=1, from a cold start) the strand bound is >= the true
    |A^T (r - r*)| minus the reference's own certified error (clarabel, residual 1e-12), for the inversion's
    diagonal D and the dynamics' dense D.  Tightness while the error is well above the reference's: within 1.2x
    of the true error at the first iterates, and the primal certificate (l = A^T r) several times looser there."""
    P = problems.make_hair_like(m, n_strands=strands, elements=6, variant=variant, seed=seed)[0]
    r_star, eps = _certified_optimum(P)
    HTr_star = P.H.T @ r_star
    y_star = math.sqrt(HTr_star @ P.D_apply(HTr_star))
    assert eps <= 1e-7 * y_star  # the reference is far closer to the optimum than the iterates checked
    rows = []

    def stop(r, u, h):
        d = P.H.T @ r - HTr_star
        true = math.sqrt(max(d @ P.D_apply(d), 0.0))
        strands_bound = error_bound_with_strands(P, r, h)["bound"]
        primal = error_bound(P, r, u, line_search=False)["bound"]
        rows.append((true, strands_bound, primal))
        return False

    out = run_admm(P, tol=1e-14, max_iter=200, check_every=1, stop=stop, stop_strands=True,
                   r0=np.zeros(3 * P.n_contacts))
    assert len(rows) == out.iterations == 200
    R = np.array(rows)
    assert np.all(R[:, 1] >= R[:, 0] - eps), "the strand certificate fell below the true error"
    assert np.all(R[:, 2] >= R[:, 0] - eps)
    far = R[:, 0] > 1e3 * eps
    assert far.sum() >= 20
    ratio = R[far, 1] / R[far, 0]
    assert ratio.min() >= 1.0 - 1e-9
    assert ratio[:5].max() <= 1.2  # tight where the error is large
    assert np.median(ratio) <= 5.0
    assert np.median(R[far, 2] / R[far, 1]) >= 1.5  # and tighter than the primal certificate


@pytest.mark.parametrize("model", ["superhelix", "clothoid"])
def test_inversion_with_admm_reports_the_smaller_bound_and_its_source(monkeypatch, model):
    """solve_inverse_problem on a dense groom through the strand-split ADMM: the reported q0 bound is the smaller
    of the two certificates (source "strands" here), and it bounds the true distance to clarabel's q0; for the
    Super-Helix (diagonal D) and the clothoid (dense D blocks, the strand certificate through D_apply)."""
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    groom, head = example_groom(60)
    params = dict(contacts="all", contact_radius=3e-4, stabilize="none", model=model)
    ref = invert_groom(groom, head=head, params=InversionParams(solver="clarabel", **params))
    assert ref.report["solve"]["q0_error_bound"] < 1e-6
    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    import groomtool.inverse_problem as ip

    seen = []
    bound_fn = ip.rest_curvature_error_bound

    def spy(problem, cp, r, u=None, line_search=True, strands=None, **known):
        out = bound_fn(problem, cp, r, u, line_search, strands, **known)
        if strands is not None:
            alone = bound_fn(problem, cp, r, u, line_search, HTr=known.get("HTr"))
            assert out["q0_error_bound"] <= alone["q0_error_bound"]
            seen.append((out["q0_error_bound"], alone["q0_error_bound"], out["q0_bound_source"]))
        return out

    monkeypatch.setattr(ip, "rest_curvature_error_bound", spy)
    res = invert_groom(groom, head=head, params=InversionParams(**params))
    solve = res.report["solve"]
    assert solve["solver"] == "admm" and solve["status"] == "solved" and solve["stopped_on"] == "q0_tolerance"
    assert solve["q0_bound_source"] == "strands"
    assert solve["q0_error_bound"] <= 1e-3
    true = np.linalg.norm(res.rest_curvatures - ref.rest_curvatures) / np.linalg.norm(ref.rest_curvatures)
    assert true <= solve["q0_error_bound"] + ref.report["solve"]["q0_error_bound"]
    assert len(seen) >= 2 and seen[0][2] == "strands" and seen[0][0] < seen[0][1]
