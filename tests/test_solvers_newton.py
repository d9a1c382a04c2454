"""Subspace Newton steps between Gauss-Seidel sweeps (solvers/subspace_newton.py, issue 22), against a dense
restatement of the reduced system and against clarabel's optimum on random problems."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from groomtool.solvers import solve_coulomb, solve_socqp
from groomtool.solvers.gauss_seidel import AssembledOperator
from groomtool.solvers.subspace_newton import (
    SLIP,
    STICK,
    TAKEOFF,
    SubspaceNewton,
    classify,
    face_bases,
    reduced_slots,
)


def random_problem(seed, m, dofs_per_contact=2.0, gamma=1e-2, mu=None):
    """W = H C H^T + gamma I (C SPD, H dense: every contact couples with every other), b in general position."""
    rng = np.random.default_rng(seed)
    n = max(2, int(dofs_per_contact * 3 * m))
    H = rng.normal(size=(3 * m, n))
    L = rng.normal(size=(n, n)) / np.sqrt(n)
    C = L @ L.T + 0.05 * np.eye(n)
    W = H @ C @ H.T / n + gamma * np.eye(3 * m)
    W = 0.5 * (W + W.T)
    b = rng.normal(size=3 * m)
    if mu is None:
        mu = rng.uniform(0.1, 1.5, m)
        mu[rng.random(m) < 0.15] = 0.0
    return sp.csr_matrix(W), b, np.broadcast_to(np.asarray(mu, float), (m,)).copy()


def reference(W, b, mu):
    """clarabel's optimum, polished by plain Gauss-Seidel (no Newton) to residual 1e-12."""
    ref = solve_socqp(W, b, mu, method="clarabel", polish=False)
    assume(ref.status == "Solved")
    pol = solve_socqp(W, b, mu, tol=1e-12, r0=ref.r, newton=None, max_iter=20000)
    assume(pol.converged)
    return ref, pol.r


def dense_reduced(W, r, u, mu):
    """B^T (W + Lambda) B written out: per contact the tangent basis of its face and the slip curvature."""
    m = len(mu)
    cols, curv = [], np.zeros(m)
    Wd = W.toarray()
    for i in range(m):
        rn, rt = r[3 * i], r[3 * i + 1:3 * i + 3]
        nt = np.linalg.norm(rt)
        if rn <= 0:
            continue
        if mu[i] == 0:
            e = np.zeros(3 * m)
            e[3 * i] = 1
            cols.append(e)
        elif nt >= mu[i] * rn * (1 - 1e-8):
            w = rt / nt
            e1 = np.zeros(3 * m)
            e1[3 * i + 1:3 * i + 3] = (-w[1], w[0])
            e2 = np.zeros(3 * m)
            e2[3 * i:3 * i + 3] = np.r_[1.0, mu[i] * w] / np.hypot(1, mu[i])
            cols += [e1, e2]
            lam = max(0.0, (mu[i] * u[3 * i] - w @ u[3 * i + 1:3 * i + 3]) / (1 + mu[i] ** 2))
            curv[i] = lam / nt
        else:
            for a in range(3):
                e = np.zeros(3 * m)
                e[3 * i + a] = 1
                cols.append(e)
    Bd = np.array(cols).T if cols else np.zeros((3 * m, 0))
    Lam = np.zeros((3 * m, 3 * m))
    for i in range(m):
        if curv[i]:
            w = r[3 * i + 1:3 * i + 3] / np.linalg.norm(r[3 * i + 1:3 * i + 3])
            Lam[3 * i + 1:3 * i + 3, 3 * i + 1:3 * i + 3] = curv[i] * (np.eye(2) - np.outer(w, w))
    return Bd, Bd.T @ (Wd + Lam) @ Bd


def slots_dense(cptr, cidx, cblk, B):
    """The slot system as a dense matrix over the non-padded coordinates, and the matching 3m x k basis."""
    S = len(cptr) - 1
    A = np.zeros((2 * S, 2 * S))
    for q in range(S):
        for p in range(cptr[q], cptr[q + 1]):
            j = cidx[p]
            A[2 * q:2 * q + 2, 2 * j:2 * j + 2] = cblk[p]
            if j != q:
                A[2 * j:2 * j + 2, 2 * q:2 * q + 2] = cblk[p].T
    keep = np.array([np.any(B[q, :, a] != 0) for q in range(S) for a in range(2)], dtype=bool)
    return A[np.ix_(keep, keep)], keep


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 9), sweeps=st.integers(1, 8))
def test_reduced_system_is_the_faces_newton_system(seed, m, sweeps):
    """reduced_slots == B^T (W + Lambda) B formed densely, on iterates with every kind of contact; the slot
    bases are orthonormal and tangent to the faces (n . e = 0 on slipping contacts)."""
    W, b, mu = random_problem(seed, m)
    op = AssembledOperator.from_sparse(W, b, mu)
    r = np.zeros((m, 3))
    for _ in range(sweeps):
        op.sweep(0, 1.0, r)
    u = (W @ r.reshape(-1) + b).reshape(m, 3)
    kind = np.empty(m, dtype=np.int64)
    curv = np.empty(m)
    counts = classify(r, u, op.mu, kind, curv)
    assert sum(counts) == m
    slot_ptr, B = face_bases(r, op.mu, kind)
    cptr, cidx, cblk = reduced_slots(op.W.indptr, op.W.indices, op.W.blocks, curv, slot_ptr, B)
    A, keep = slots_dense(cptr, cidx, cblk, B)
    Bd, ref = dense_reduced(W, r.reshape(-1), u.reshape(-1), mu)
    if Bd.size == 0:  # every contact takes off: no slot
        assert keep.size == 0 and counts[0] == m
        return
    basis = np.zeros((3 * m, 2 * slot_ptr[-1]))
    for i in range(m):
        for q in range(slot_ptr[i], slot_ptr[i + 1]):
            basis[3 * i:3 * i + 3, 2 * q:2 * q + 2] = B[q]
    basis = basis[:, keep]
    assert basis.shape == Bd.shape
    np.testing.assert_allclose(basis.T @ basis, np.eye(basis.shape[1]), atol=1e-12)
    # same tangent spaces (the bases may differ by a rotation within each face)
    Q = Bd.T @ basis
    np.testing.assert_allclose(Q @ Q.T, np.eye(Q.shape[0]), atol=1e-10)
    scale = max(1.0, np.abs(ref).max())
    np.testing.assert_allclose(Q @ A @ Q.T, ref, rtol=0, atol=1e-10 * scale)
    for i in range(m):
        if kind[i] == SLIP and mu[i] > 0:
            n = np.r_[-mu[i], r[i, 1:] / np.linalg.norm(r[i, 1:])]
            for q in range(slot_ptr[i], slot_ptr[i + 1]):
                assert np.abs(n @ B[q]).max() <= 1e-12
        assert (slot_ptr[i + 1] - slot_ptr[i]) == {TAKEOFF: 0, STICK: 2, SLIP: 1}[int(kind[i])]


def planted(seed, m, kinds):
    """A problem whose optimum is planted: per contact (kind 0 take-off, 1 stick, 2 slip) r* and u* = W r* + b
    satisfying the SOC law strictly (take-off: u* inside the dual cone; stick: r* inside the cone, u* = 0; slip:
    r* = a (1, mu w), u* = lambda (mu, -w), a, lambda > 0).  W is SPD, so r* is the unique optimum."""
    rng = np.random.default_rng(seed)
    W, _, mu = random_problem(seed, m)
    mu = rng.uniform(0.2, 1.5, m)
    r = np.zeros((m, 3))
    u = np.zeros((m, 3))
    for i, k in enumerate(kinds):
        phi = rng.uniform(0, 2 * np.pi)
        w = np.array([np.cos(phi), np.sin(phi)])
        if k == 0:
            u[i] = np.r_[1.0, rng.uniform(0, 0.5) / mu[i] * w] * rng.uniform(0.5, 2)
        elif k == 1:
            r[i] = np.r_[1.0, rng.uniform(0, 0.5) * mu[i] * w] * rng.uniform(0.5, 2)
        else:
            r[i] = np.r_[1.0, mu[i] * w] * rng.uniform(0.5, 2)
            u[i] = np.r_[mu[i], -w] * rng.uniform(0.5, 2)
    b = u.reshape(-1) - W @ r.reshape(-1)
    return W, b, mu, r


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), kinds=st.lists(st.sampled_from([0, 1]), min_size=1, max_size=12),
       eps=st.sampled_from([1e-1, 1e-4]))
def test_one_step_is_exact_when_no_contact_slips(seed, kinds, eps):
    """With every contact sticking or taking off at the optimum, the face problem is a linear system: from a
    point on the optimum's faces, one step with exact CG lands on the (planted) optimum."""
    m = len(kinds)
    W, b, mu, R = planted(seed, m, kinds)
    stick = np.array(kinds) == 1
    rng = np.random.default_rng(seed + 1)
    r0 = R.copy()
    r0[stick] += eps * R[stick, :1] * rng.uniform(-0.2, 0.2, (stick.sum(), 3))
    op = AssembledOperator.from_sparse(W, b, mu)
    sn = SubspaceNewton(op, cg_iter=(10 * m + 10, 10 * m + 10), cg_rtol=1e-15)
    out = sn.step(r0, op.velocity(r0))
    if not stick.any():  # r0 = r* already: no step lowers f
        assert out is None
        return
    assert out is not None and sn.last["alpha"] == 1.0
    err0 = np.abs(r0 - R).max()
    err1 = np.abs(out[0] - R).max()
    assert err1 <= 1e-9 * np.abs(R).max() and err1 <= 1e-3 * err0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), kinds=st.lists(st.sampled_from([0, 1, 2]), min_size=1, max_size=10).filter(
    lambda k: 2 in k))
def test_step_converges_quadratically_on_slipping_faces(seed, kinds):
    """Slipping contacts moved along their cone's boundary by t = 1e-3 (rotated and scaled): one step with exact
    CG brings them back to O(t^2) of the planted optimum (the SQP step with the constraint's curvature;
    without that term the error stays O(t))."""
    m = len(kinds)
    W, b, mu, R = planted(seed, m, kinds)
    slip = np.array(kinds) == 2
    t = 1e-3
    r0 = R.copy()
    for i in np.flatnonzero(slip):
        c, s_ = np.cos(t), np.sin(t)
        r0[i] = np.r_[R[i, 0], np.array([[c, -s_], [s_, c]]) @ R[i, 1:]] * (1 + t)
    op = AssembledOperator.from_sparse(W, b, mu)
    sn = SubspaceNewton(op, cg_iter=(10 * m + 10, 10 * m + 10), cg_rtol=1e-15)
    out = sn.step(r0, op.velocity(r0))
    assert out is not None
    big = np.abs(R).max()
    err0 = np.abs(r0 - R).max() / big
    err1 = np.abs(out[0] - R).max() / big
    assert err0 >= 1e-4 and err1 <= 50 * err0**2


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 14), redundancy=st.sampled_from([0.3, 1.0, 3.0]),
       gamma=st.sampled_from([1e-3, 1e-2, 1e-1]))
def test_gauss_seidel_with_newton_steps_reaches_clarabels_optimum(seed, m, redundancy, gamma):
    """solve_socqp with a Newton step at every check from the first sweep on (the most Newton it can take) and
    with its defaults: converged to 1e-10, objective and forces at clarabel's optimum, in the cones."""
    W, b, mu = random_problem(seed, m, dofs_per_contact=redundancy, gamma=gamma)
    ref, rs = reference(W, b, mu)
    f_ref = 0.5 * rs @ (W @ rs + 2 * b)  # clarabel's optimum polished to residual 1e-12
    assert f_ref == pytest.approx(ref.objective, rel=1e-6, abs=1e-8 * np.abs(b).max() ** 2 / gamma)
    for opts in (dict(newton=1, newton_every=1, check_every=1), {}):
        res = solve_socqp(W, b, mu, tol=1e-10, **opts)
        assert res.converged and res.residual <= 1e-10
        assert res.cone_violation <= 1e-12 * max(1.0, np.abs(rs).max())
        assert res.objective == pytest.approx(f_ref, rel=1e-9, abs=1e-12 * np.abs(b).max() ** 2 / gamma)
        np.testing.assert_allclose(res.r, rs, rtol=0, atol=1e-6 * max(1.0, np.abs(rs).max()))
        if opts and res.iterations > 1:  # one sweep solves a single contact: no check before it converged
            steps = res.info["newton"]
            assert steps and all(s[0] >= 1 for s in steps)


def test_newton_is_off_where_it_does_not_apply():
    """Only the SOC law on the assembled W takes Newton steps: the Coulomb law, over-relaxation and the
    matrix-free form run exactly as before."""
    W, b, mu = random_problem(5, 30)
    c = solve_coulomb(W, b, mu, method="gs", newton=1)
    assert "newton" not in c.info
    o = solve_socqp(W, b, mu, omega=1.3, newton=1, max_iter=50)
    assert "newton" not in o.info
    on = solve_socqp(W, b, mu, newton=1, check_every=1, newton_every=1)
    off = solve_socqp(W, b, mu, newton=None)
    assert on.info["newton"] and "newton" not in off.info
    assert on.objective == pytest.approx(off.objective, rel=1e-9)
