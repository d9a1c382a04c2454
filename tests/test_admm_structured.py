"""The structured strand systems of the strand-split ADMM (solvers/admm_structured.py) against dense restatements:
M_s from the dense point Jacobians (superhelix.point_jacobians, not H), the x-step against the dense solve and the
dense StrandSplit, W_ii against the packed H, and the ADMM and the inversion through it against clarabel and the
dense path."""

import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference.semiseparable import dense_strand
from test_contact_jacobian import _random_contacts, _random_groom

from groomtool.contact.jacobian import contact_jacobian
from groomtool.rods import superhelix as sh
from groomtool.semiseparable import solve_strand
from groomtool.solvers import ContactProblem, solve_contact_problem
from groomtool.solvers.admm import StrandSplit, run_admm
from groomtool.solvers.admm_structured import HelixContacts, StructuredSplit


def _problem(rng, helix, contacts, kin, gamma=0.01, mu=0.3):
    H = contact_jacobian(helix, contacts, kin)
    D = rng.uniform(0.2, 3.0, H.shape[1]) * 10.0 ** rng.uniform(-2, 2)
    return ContactProblem(H=H, D_blocks=D, dof_offsets=3 * helix.flat_offsets(), gamma=gamma,
                          b=rng.normal(size=H.shape[0]), mu=mu)


def _dense_end_rows(split, kin):
    """J_e (3, n_s) of every end from the dense point Jacobians: sigma_e F_e dC(s_e)/dq."""
    J, _ = sh.point_jacobians(split.helix, split.end_strand, split.end_arc, kin)
    out = []
    for e in range(split.n_ends):
        n = split.helix.n_elements[split.end_strand[e]]
        out.append(split.sF[e] @ J[e, :n].transpose(1, 0, 2).reshape(3, 3 * n))
    return out


def _setup(seed, n_strands, max_elements, m, scale, self_contacts=True):
    rng = np.random.default_rng(seed)
    helix = _random_groom(rng, n_strands, max_elements, scale)
    contacts = _random_contacts(rng, helix, m)
    if not self_contacts:
        same = contacts.strand_a == contacts.strand_b
        contacts.strand_b = np.where(same, -1, contacts.strand_b)
    kin = sh.kinematics(helix)
    P = _problem(rng, helix, contacts, kin)
    split = StructuredSplit(P, HelixContacts(helix, contacts, kin))
    split.set_rho(rng.uniform(0.05, 3.0, P.n_contacts))
    return rng, helix, contacts, kin, P, split


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_generators_give_the_dense_strand_matrices(seed, scale, n_strands, max_elements, m):
    """diag, later and earlier = G rebuild M_s = D_s^-1 + sum_e J_e^T J_e / rho_e (J_e from the dense point
    Jacobians) on every kind of contact: strand pairs, self-contacts (two ends on one strand, also on one element),
    head, roots (element 0), tips, nodes, several ends on one element; and its factor solves M_s."""
    rng, helix, contacts, kin, P, split = _setup(seed, n_strands, max_elements, m, scale)
    rows = _dense_end_rows(split, kin)
    off = helix.flat_offsets()
    D = P.D_data
    for s in split.active:
        e0, e1 = off[s], off[s + 1]
        M = np.diag(1.0 / D[3 * e0:3 * e1])
        for q in range(split.strand_ptr[s], split.strand_ptr[s + 1]):
            e = split.ends_sorted[q]
            M += rows[e].T @ rows[e] / split.rho_end[e]
        A = dense_strand(split.diag_M, split.later, split.G, e0, e1)
        assert np.abs(A - M).max() <= 1e-10 * np.abs(M).max()
        y = rng.normal(size=3 * (e1 - e0))
        z = y.copy()
        solve_strand(split.L, split.W, split.later, e0, e1, z)
        assert np.abs(M @ z - y).max() <= 1e-9 * np.abs(M).max() * np.abs(z).max() + 1e-12


def test_every_kind_of_end_is_drawn():
    """The random contacts of the tests above hold every kind: self-contacts, two on one element, head, element 0,
    several ends on one element."""
    _, helix, contacts, kin, P, split = _setup(3, 3, 4, 40, 5.0)
    pair = split.partner >= 0
    assert np.any(pair & (split.elem == split.elem[np.maximum(split.partner, 0)]))  # a self-contact on one element
    assert np.any(contacts.strand_b < 0) and np.any(split.elem == 0)
    key = split.end_strand[split.ends_sorted] * 100 + split.elem  # (elem: in strand order)
    assert np.unique(key).size < key.size  # several ends on one element


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_contact_diagonal_is_H_D_H_transpose(seed, scale, n_strands, max_elements, m):
    """W_ii = H_i D H_i^T + 2 gamma I from the prefix sums equals the packed H's (self-contacts' cross terms
    included)."""
    _, _, _, _, P, split = _setup(seed, n_strands, max_elements, m, scale)
    ref = P.diagonal_blocks()
    assert np.abs(split.diag - ref).max() <= 1e-12 * np.abs(ref).max()


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_x_step_solves_each_strand_system(seed, scale, n_strands, max_elements, m):
    """x_s = (J_s D_s J_s^T + R_s)^-1 R_s w_s per strand (dense solve with the point Jacobians' rows); the
    strand sums and strand velocities are sum_e J_e^T x_e and J_e D_s sum_e' J_e'^T x_e'."""
    rng, helix, contacts, kin, P, split = _setup(seed, n_strands, max_elements, m, scale)
    rows = _dense_end_rows(split, kin)
    off = helix.flat_offsets()
    E = split.n_ends
    w = rng.normal(size=(E, 3))
    x = np.empty((E, 3))
    split.x_step(w, x)
    h = split.strand_sum(w)
    v = split.strand_velocity(w)
    ref_h = np.zeros(P.n_dofs)
    for s in range(helix.n_strands):
        ends = split.ends_sorted[split.strand_ptr[s]:split.strand_ptr[s + 1]]
        if not len(ends):
            continue
        J = np.concatenate([rows[e] for e in ends])
        Ds = np.diag(P.D_data[3 * off[s]:3 * off[s + 1]])
        R = np.repeat(split.rho_end[ends], 3)
        ws = w[ends].ravel()
        xs = np.linalg.solve(J @ Ds @ J.T + np.diag(R), R * ws)
        assert np.abs(x[ends].ravel() - xs).max() <= 1e-10 * max(1.0, np.abs(xs).max())
        g = J.T @ ws
        ref_h[3 * off[s]:3 * off[s + 1]] = g
        vs = J @ Ds @ g
        assert np.abs(v[ends].ravel() - vs).max() <= 1e-11 * max(1.0, np.abs(vs).max())
    assert np.abs(h - ref_h).max() <= 1e-12 * max(1.0, np.abs(ref_h).max())


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_check_products_equal_the_csr_products(seed, scale, n_strands, max_elements, m):
    """The checks' products through the generators equal the CSR H's: H^T s, sum_e J_e^T x_e (the strand sum),
    W s + b and H D h + b, on every kind of contact (head, self-contacts, several ends on one element)."""
    rng, helix, contacts, kin, P, split = _setup(seed, n_strands, max_elements, m, scale)
    s = rng.normal(size=(P.n_contacts, 3))
    x = rng.normal(size=(split.n_ends, 3))
    b = P.b.reshape(-1, 3)
    HTs, h, u, c = split.check_products(s, x, b)
    H = P.H.toarray()
    ref_HTs = H.T @ s.ravel()
    ref_h = split.strand_sum(x)
    ref_u = H @ (P.D_data * ref_HTs) + 2.0 * P.gamma * s.ravel() + P.b
    ref_c = H @ (P.D_data * ref_h) + P.b
    for got, ref in ((HTs, ref_HTs), (h, ref_h), (u, ref_u), (c, ref_c)):
        assert np.abs(got - ref).max() <= 1e-12 * max(1.0, np.abs(ref).max())


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 5.0, 40.0]), m=st.integers(1, 40))
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_x_step_equals_the_dense_strand_split(seed, scale, m):
    """Without self-contacts the ends are the dense StrandSplit's, in its order, and so are x, W_ii and the
    strand sums (1e-10)."""
    rng, helix, contacts, kin, P, split = _setup(seed, 5, 8, m, scale, self_contacts=False)
    dense = StrandSplit(P, split.rho_c)
    assert np.array_equal(dense.cend_ptr, split.cend_ptr) and np.array_equal(dense.end_strand, split.end_strand)
    E = split.n_ends
    w = rng.normal(size=(E, 3))
    x, xd = np.empty((E, 3)), np.empty((E, 3))
    split.x_step(w, x)
    dense.x_step(w, xd)
    assert np.abs(x - xd).max() <= 1e-10 * max(1.0, np.abs(xd).max())
    h = dense.strand_sum(w)
    assert np.abs(split.strand_sum(w) - h).max() <= 1e-12 * max(1.0, np.abs(h).max())


def _hair_problem(seed, n_strands=6, max_elements=8, m=60, mu=0.3):
    rng = np.random.default_rng(seed)
    helix = _random_groom(rng, n_strands, max_elements, 5.0)
    contacts = _random_contacts(rng, helix, m)
    kin = sh.kinematics(helix)
    H = contact_jacobian(helix, contacts, kin)
    D = rng.uniform(0.5, 2.0, H.shape[1])
    b = -(H @ rng.normal(size=H.shape[1])) - 0.05 * np.tile([1.0, 0.0, 0.0], m)
    P = ContactProblem(H=H, D_blocks=D, dof_offsets=3 * helix.flat_offsets(), gamma=0.01, b=b, mu=mu)
    return P, HelixContacts(helix, contacts, kin)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_admm_through_the_structured_split_reaches_clarabels_optimum(seed):
    """run_admm with the geometry (structured x-step, self-contacts as two ends) converges to clarabel's objective
    (1e-7 relative), also from the end state after a stiffness change (D scaled on some strands)."""
    P, geometry = _hair_problem(seed)
    ref = solve_contact_problem(P, "soc", "clarabel", polish=False)
    res = solve_contact_problem(P, "soc", "admm", tol=1e-10, max_iter=50_000, geometry=geometry, state_out=(out := {}))
    assert isinstance(out["state"].split, StructuredSplit)
    assert res.converged and abs(res.objective - ref.objective) <= 1e-7 * max(1.0, abs(ref.objective))
    g = np.ones(P.n_strands)
    g[::2] = 3.0
    D2 = P.D_data * np.repeat(g, np.diff(P.dof_offsets))
    P2 = ContactProblem(H=P.H, D_blocks=D2, dof_offsets=P.dof_offsets, gamma=P.gamma, b=P.b, mu=P.mu)
    ref2 = solve_contact_problem(P2, "soc", "clarabel", polish=False)
    state = out["state"]
    res2 = run_admm(P2, tol=1e-10, max_iter=50_000, initial_state=state, geometry=geometry)
    assert res2.from_state and isinstance(res2.state.split, StructuredSplit)
    assert res2.converged
    assert abs(P2.objective(res2.r) - ref2.objective) <= 1e-7 * max(1.0, abs(ref2.objective))
    reused = res2.state.split
    fresh = StructuredSplit(P2, geometry)  # the same rho, from scratch: the same W_ii and x-steps
    fresh.set_rho(reused.rho_c)
    assert np.abs(fresh.diag - reused.diag).max() <= 1e-13 * np.abs(fresh.diag).max()
    w = np.random.default_rng(seed).normal(size=(fresh.n_ends, 3))
    x, xr = np.empty_like(w), np.empty_like(w)
    fresh.x_step(w, x)
    reused.x_step(w, xr)
    assert np.abs(x - xr).max() <= 1e-12 * np.abs(x).max()


def _spy_admm(monkeypatch):
    """Record (split type, from_state) of every run_admm that solve_contact_problem makes."""
    import groomtool.solvers.api as api

    seen = []
    run = api.run_admm

    def spy(*args, **kwargs):
        out = run(*args, **kwargs)
        seen.append((type(out.state.split).__name__, out.from_state))
        return out

    monkeypatch.setattr(api, "run_admm", spy)
    return seen


def test_inversion_through_the_structured_split_agrees_with_the_dense_path(monkeypatch):
    """invert_groom on example_groom(60) with all contacts through ADMM (the clarabel threshold lowered): the
    Super-Helix geometry takes the structured split, and its q0 is within the runs' certified bounds of the dense
    path's (no geometry) and of clarabel's."""
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    inv = sys.modules["groomtool.invert"]  # (groomtool.invert is also a function's name)
    groom, head = example_groom(60)
    params = dict(contacts="all", contact_radius=3e-4, stabilize="none")
    ref = invert_groom(groom, head=head, params=InversionParams(solver="clarabel", **params))
    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    seen = _spy_admm(monkeypatch)
    structured = invert_groom(groom, head=head, params=InversionParams(**params))
    assert [k for k, _ in seen] == ["StructuredSplit"]
    monkeypatch.setattr(inv, "admm_geometry", lambda *args: None)
    dense = invert_groom(groom, head=head, params=InversionParams(**params))
    assert [k for k, _ in seen[1:]] == ["StrandSplit"]
    for res in (structured, dense):
        assert res.report["solve"]["solver"] == "admm" and res.report["solve"]["status"] == "solved"
    bounds = [r.report["solve"]["q0_error_bound"] for r in (structured, dense, ref)]
    assert max(bounds[:2]) <= 1e-3
    q0 = [r.rest_curvatures for r in (structured, dense, ref)]
    assert np.linalg.norm(q0[0] - q0[1]) / np.linalg.norm(q0[1]) <= 1.01 * (bounds[0] + bounds[1])
    assert np.linalg.norm(q0[0] - q0[2]) / np.linalg.norm(q0[2]) <= 1.01 * (bounds[0] + bounds[2])


def test_inversion_stiffening_rounds_reuse_the_structured_split(monkeypatch):
    """With stiffening (example_groom(150): a strand stiffened), every solve runs the structured split and each
    re-solve starts from the previous round's state and split (StructuredSplit.rebind)."""
    import groomtool.solver_choice as sc
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, invert_groom

    monkeypatch.setattr(sc, "AUTO_CLARABEL_MAX_CONTACTS", 100)
    seen = _spy_admm(monkeypatch)
    groom, head = example_groom(150)
    res = invert_groom(groom, head=head, params=InversionParams(contacts="all", contact_radius=3e-4))
    assert len(seen) >= 2 and all(k == "StructuredSplit" for k, _ in seen)
    assert not seen[0][1] and all(from_state for _, from_state in seen[1:])
    assert res.report["solve"]["status"] == "solved" and res.report["solve"]["q0_error_bound"] <= 1e-3
