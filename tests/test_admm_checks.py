"""The strand-split ADMM's checks through the structured split's generators (run_admm(stop_products=True),
admm_structured.StructuredSplit.check_products): the same residual and certified bounds as with the CSR H, and no
run stops on them without the check redone with H on its returned forces."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_admm_structured import _hair_problem

from groomtool.solvers import residual as _res
from groomtool.solvers.admm import run_admm
from groomtool.solvers.certificate import error_bound, error_bound_with_strands


def _bounds(P, r, u, h, HTr=None, c=None):
    forces = error_bound(P, r, u, line_search=False, HTr=HTr)["bound"]
    strands = error_bound_with_strands(P, r, h, HTr=HTr, c=c)["bound"]
    return forces, strands


@given(seed=st.integers(0, 10_000), mu=st.sampled_from([0.0, 0.3, 2.0]), check_every=st.integers(1, 7))
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_checks_through_the_generators_equal_the_csr_checks(seed, mu, check_every):
    """At every check of a run: the bounds from the generators' u, H^T r and H D h + b equal those from H (to
    round-off), and so does u (against W r + b from H)."""
    P, geometry = _hair_problem(seed, mu=mu)
    seen = []

    def stop(r, u, h, HTr=None, c=None):
        assert HTr is not None and c is not None  # no call with H: this stop never says stop
        u_ref = P.velocity(r)
        assert np.abs(u - u_ref).max() <= 1e-11 * max(1.0, np.abs(u_ref).max())
        got = _bounds(P, r, u, h, HTr, c)
        ref = _bounds(P, r, u_ref, h)
        y = np.linalg.norm(np.sqrt(P.D_data) * (P.H.T @ r))
        # square roots of gaps: the gaps agree to their round-off, a sum over the dofs and contacts of terms of the
        # size of |y|^2 (near convergence the gaps themselves are round-off: ~4e-13 |y|^2 on seed 2049, mu 0)
        roundoff = 32 * np.finfo(float).eps * (P.n_dofs + P.n_contacts) * y * y
        for a, b in zip(got, ref):
            assert abs(a * a - b * b) <= 1e-8 * b * b + roundoff
        seen.append(got)
        return False

    out = run_admm(P, tol=0.0, max_iter=40, check_every=check_every, stop=stop, stop_strands=True,
                   stop_products=True, geometry=geometry, warm_sweeps=0)
    assert out.iterations == 40 and not out.stopped_by_rule
    assert len(seen) == 40 // check_every + (40 % check_every > 0)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_stop_is_confirmed_with_H_on_the_returned_forces(seed):
    """A stop from a check through the generators is redone with H's products on the same forces; the run stops
    only when that one says so (a rule that says stop only on the generators' numbers never stops the run), and the
    returned forces are those of the confirming call; the last call of a run stopped by the rule is one with H."""
    P, geometry = _hair_problem(seed)
    calls = []

    def never_with_H(r, u, h, HTr=None, c=None):
        calls.append((HTr is not None, r))
        return HTr is not None

    out = run_admm(P, tol=0.0, max_iter=30, check_every=5, stop=never_with_H, stop_strands=True,
                   stop_products=True, geometry=geometry, warm_sweeps=0)
    assert out.iterations == 30 and not out.stopped_by_rule
    assert [f for f, _ in calls] == [True, False] * 6
    for (_, r1), (_, r2) in zip(calls[::2], calls[1::2]):
        assert np.array_equal(r1, r2)
    tol = 5e-2  # the relative strand bound after a few iterations

    def strands_bound(r, u, h, HTr=None, c=None):
        calls.append((HTr is not None, r, u))
        y = np.sqrt(P.D_data) * (P.H.T @ r if HTr is None else HTr)
        return error_bound_with_strands(P, r, h, HTr=HTr, c=c)["bound"] <= tol * np.linalg.norm(y)

    calls.clear()
    out = run_admm(P, tol=0.0, max_iter=5000, check_every=1, stop=strands_bound, stop_strands=True,
                   stop_products=True, geometry=geometry, warm_sweeps=0)
    assert out.stopped_by_rule and out.iterations < 5000
    fast, r_last, u_last = calls[-1]
    assert not fast and calls[-2][0] and np.array_equal(r_last, out.r)
    assert np.array_equal(u_last, P.velocity(out.r))  # u from H: W r + b
    emax, _ = _res.residual_max_rms(_res.law_code("soc"), out.r.reshape(-1, 3), u_last.reshape(-1, 3), P.mu,
                                    P.rho())
    assert out.residual == emax / _res.residual_scale(P.b, P.rho())


def test_inversion_certifies_its_forces_with_H_and_reuses_the_stopping_check(monkeypatch):
    """invert_groom on example_groom(60) with all contacts through ADMM: it stops on the q0 tolerance, and the
    written bound (the final certificate, which reuses the stopping check's products with H) equals the certificate
    computed from scratch with H on the written forces, and is within the tolerance."""
    import groomtool.inverse_problem as ip
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    bound_fn = ip.rest_curvature_error_bound
    finals = []

    def spy(problem, cp, r, u=None, line_search=True, strands=None, **known):
        out = bound_fn(problem, cp, r, u, line_search, strands, **known)
        if line_search:  # the final certificate
            fresh = bound_fn(problem, cp, r, None, True, strands)
            finals.append((bool(known), out["q0_error_bound"], fresh["q0_error_bound"]))
        return out

    monkeypatch.setattr(ip, "rest_curvature_error_bound", spy)
    groom, head = example_groom(60)
    res = invert_groom(groom, head=head, params=InversionParams(contacts="all", contact_radius=3e-4,
                                                                stabilize="none"))
    solve = res.report["solve"]
    assert solve["solver"] == "admm" and solve["status"] == "solved" and solve["stopped_on"] == "q0_tolerance"
    assert len(finals) == 1
    reused, written, fresh = finals[0]
    assert reused  # the stopping check's products with H served the final certificate
    assert abs(written - fresh) <= 1e-12 * fresh
    assert solve["q0_error_bound"] == written <= 1e-3
