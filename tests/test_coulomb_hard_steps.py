"""Coulomb problems that block Gauss-Seidel alone converges slowly on (issue 15): a stiff, loaded contact near
two strands' roots among redundant contacts (more contact rows than the dofs they move, W singular).  The
cluster Newton steps between the sweeps (solvers/cluster_newton.py) on small generated problems, checked
against the disjunctive statement of Coulomb's law (take-off | stick | slip), finite differences and the
explicit W = H D H^T + 2 gamma I."""

import numpy as np
import pytest
import scipy.sparse as sp

from groomtool.solvers import ContactProblem, solve_contact_problem
from groomtool.solvers.cluster_newton import coulomb_map, newton_cluster
from groomtool.solvers.gauss_seidel import AssembledOperator, MatrixFreeOperator, run_gauss_seidel
from reference.solvers import coulomb_contact_errors


def pair_rows(rng, m, n_s, stiff):
    """m contacts between two strands of n_s dofs each; contact i moves the first k_i dofs of both (a chain,
    root to tip), so 3m rows on 2 n_s dofs: W singular.  A separating velocity v exists (N_i . v = 1,
    T_i . v = 0 for every contact), so the Coulomb problem has a solution (Acary, Cadoux, Lemarechal & Malick
    2011).  Contact 0 is near the roots: its rows ``stiff`` times shorter (W_00 stiff^2 times smaller)."""
    H = np.zeros((3 * m, 2 * n_s))
    v = rng.normal(size=2 * n_s)
    for i in range(m):
        k = 2 + (i * (n_s - 2)) // max(m - 1, 1)
        sup = np.r_[np.arange(k), n_s + np.arange(k)]
        vs = np.zeros(2 * n_s)
        vs[sup] = v[sup]
        rows = np.zeros((3, 2 * n_s))
        rows[:, sup] = rng.normal(size=(3, 2 * k))
        rows[0] += (1.0 - rows[0] @ vs) / (vs @ vs) * vs
        rows[1:] -= np.outer(rows[1:] @ vs, vs) / (vs @ vs)
        H[3 * i:3 * i + 3] = rows
    H[0:3] *= stiff
    return H, v


def groom(seed, pairs=6, hard=(0,), m=12, n_s=8, stiff=1e-2, mu=0.3, gamma=0.0, diagonal=False):
    """``pairs`` independent strand pairs pressed together (b = H (-2 v + noise)); the pairs in ``hard`` have
    the stiff root contact."""
    rng = np.random.default_rng(seed)
    n = 2 * n_s * pairs
    Hs, blocks, bs = [], [], []
    for q in range(pairs):
        Hq, v = pair_rows(rng, m, n_s, stiff if q in hard else 1.0)
        H = np.zeros((3 * m, n))
        H[:, 2 * n_s * q:2 * n_s * (q + 1)] = Hq
        Hs.append(H)
        for _ in range(2):
            if diagonal:
                blocks.append(rng.uniform(0.5, 2.0, n_s))
            else:
                L = rng.normal(size=(n_s, n_s))
                blocks.append(L @ L.T / n_s + 0.1 * np.eye(n_s))
        bs.append(Hq @ (-2.0 * v + 0.5 * rng.normal(size=2 * n_s)))
    return ContactProblem(sp.csr_matrix(np.vstack(Hs)), blocks, np.arange(0, n + 1, n_s), gamma,
                          np.concatenate(bs), mu)


def dense_W(P):
    D = sp.block_diag([np.diag(d) if d.ndim == 1 else d for d in P.D_blocks]).toarray()
    H = P.H.toarray()
    return H @ D @ H.T + 2 * P.gamma * np.eye(H.shape[0])




@pytest.mark.parametrize("seed", [0, 2, 6, 7])
@pytest.mark.parametrize("form", ["matrix_free", "assembled"])
def test_cluster_steps_solve_the_stiff_pair_in_fewer_sweeps(seed, form):
    P = groom(seed)
    plain = solve_contact_problem(P, law="coulomb", method="gs", tol=1e-8, max_iter=5000, anderson=0,
                                  form=form, cluster=None)
    res = solve_contact_problem(P, law="coulomb", method="gs", tol=1e-8, max_iter=5000, anderson=0, form=form)
    assert plain.converged and res.converged
    assert res.residual <= 1e-8 and P.residual(res.r, law="coulomb") <= 1e-8
    # the disjunctive law, normalised by the largest force and velocity (the stiff contact's: 1e-6 here is the
    # natural map's 1e-8 at the soft contacts): at least as close as plain Gauss-Seidel's solution
    assert coulomb_contact_errors(P, res.r).max() <= max(1e-6, coulomb_contact_errors(P, plain.r).max())
    assert any(c[1] for c in res.info["cluster"])  # a cluster step was taken ...
    assert res.iterations < plain.iterations  # ... and it saved sweeps (plain: 630-2040 sweeps)
    # both reach the same motion: W = H D H^T, so the impulses H^T r agree where r may not (W singular)
    d = P.H.T @ (res.r - plain.r)
    assert np.linalg.norm(d) <= 1e-5 * np.linalg.norm(P.H.T @ plain.r)


def test_cluster_steps_never_raise_the_residual():
    P = groom(5)
    res = solve_contact_problem(P, law="coulomb", method="gs", tol=1e-8, max_iter=3000, anderson=0)
    hist = res.info["history"]
    accepted = [c for c in res.info["cluster"] if c[1]]
    assert accepted
    for sweep, _, size, iters, residual, _ in accepted:
        before = [h[1] for h in hist if h[0] == sweep]
        assert len(before) == 2 and before[1] == residual < before[0]  # the check, then the accepted point
        assert 0 < size <= P.n_contacts and iters >= 1


@pytest.mark.parametrize("seed", [0, 6, 7])
def test_newton_near_a_solution_converges_fast_on_a_singular_W(seed):
    """Levenberg-Marquardt alone on the whole problem (216 rows, 96 dofs) from 500 plain sweeps' point:
    locally fast where the sweeps crawl (it is not globally convergent on the nonsmooth natural map: from 100
    sweeps it stalls at 1e-4, which is why the solver keeps a step only if it lowers the residual)."""
    P = groom(seed)
    W = dense_W(P)
    assert np.linalg.matrix_rank(W) == 96 < W.shape[0]
    gs = solve_contact_problem(P, law="coulomb", method="gs", tol=1e-14, max_iter=500, anderson=0, cluster=None)
    assert gs.residual > 1e-8
    r, res, its = newton_cluster(W, P.b, gs.r, P.mu, P.rho(), P.residual_scale(), 1e-11, max_iter=40)
    assert res <= 1e-10 and 1 <= its <= 30
    assert P.residual(r, law="coulomb") <= 1e-10  # residual.py's measure agrees with the cluster's own
    assert coulomb_contact_errors(P, r).max() < 1e-8


@pytest.mark.parametrize("seed", range(4))
def test_coulomb_map_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(seed)
    k = 5
    A = rng.normal(size=(3 * k, 2 * k))
    W = A @ A.T  # singular, like the clusters
    c = rng.normal(size=3 * k)
    r = rng.normal(size=3 * k)
    r[0::3] = np.abs(r[0::3]) + 0.5
    mu = rng.uniform(0.1, 0.8, k)
    rho = rng.uniform(0.05, 0.5, k)
    F = np.empty(3 * k)
    J = np.empty((3 * k, 3 * k))
    coulomb_map(W, c, r, mu, rho, F, J, True)
    Fp, Fm = np.empty(3 * k), np.empty(3 * k)
    h = 1e-6
    for j in range(3 * k):
        e = np.zeros(3 * k)
        e[j] = h
        coulomb_map(W, c, r + e, mu, rho, Fp, J[:0], False)
        coulomb_map(W, c, r - e, mu, rho, Fm, J[:0], False)
        assert np.allclose((Fp - Fm) / (2 * h), J[:, j], rtol=1e-5, atol=1e-6)
    # F is the natural map: zero exactly at a solution, and F(r) = r - P_K(r - rho u_eff) contact by contact
    u = W @ r + c
    for i in range(k):
        ui = u[3 * i:3 * i + 3]
        z = r[3 * i:3 * i + 3] - rho[i] * (ui + mu[i] * np.linalg.norm(ui[1:]) * np.array([1.0, 0, 0]))
        nt = np.linalg.norm(z[1:])
        if nt <= mu[i] * z[0]:
            p = z
        elif mu[i] * nt <= -z[0]:
            p = np.zeros(3)
        else:
            a = (z[0] + mu[i] * nt) / (1 + mu[i] ** 2)
            p = np.r_[a, a * mu[i] * z[1:] / nt]
        assert np.allclose(F[3 * i:3 * i + 3], r[3 * i:3 * i + 3] - p, atol=1e-12)


@pytest.mark.parametrize("diagonal", [False, True])
def test_dense_blocks_and_neighbours_match_the_explicit_W(diagonal):
    P = groom(3, pairs=4, gamma=0.01, diagonal=diagonal)
    W = dense_W(P)
    m = P.n_contacts
    rng = np.random.default_rng(0)
    idx = np.sort(rng.choice(m, size=9, replace=False))
    rows = (3 * idx[:, None] + np.arange(3)).ravel()
    order = rng.permutation(m)
    ops = [MatrixFreeOperator(P), AssembledOperator.from_problem(P), AssembledOperator.from_problem(P, order)]
    # the contacts on the strands idx touches: pair q owns contacts 12q..12q+11
    expected = np.unique(np.concatenate([np.arange(12 * (i // 12), 12 * (i // 12) + 12) for i in idx]))
    for op in ops:
        inv = np.arange(m) if op.form == "matrix_free" or op.order is None else np.argsort(op.order)
        internal = np.sort(inv[idx])  # the same contacts in the operator's internal order
        blk = op.dense_block(internal)
        ext = op.order[internal] if op.form == "assembled" and op.order is not None else internal
        ext_rows = (3 * ext[:, None] + np.arange(3)).ravel()
        assert np.allclose(blk, W[np.ix_(ext_rows, ext_rows)], rtol=1e-12, atol=1e-12 * np.abs(W).max())
        nb = op.neighbours(internal)
        nb_ext = np.sort(op.order[nb]) if op.form == "assembled" and op.order is not None else nb
        assert np.array_equal(nb_ext, expected)
    assert np.allclose(ops[0].dense_block(idx), W[np.ix_(rows, rows)])


def test_soc_law_and_fixed_point_are_unchanged():
    """Cluster steps are for the Coulomb law only: the SOC solve is bit-identical with and without."""
    P = groom(1, gamma=0.01)
    a = solve_contact_problem(P, law="soc", method="gs", tol=1e-10)
    b = solve_contact_problem(P, law="soc", method="gs", tol=1e-10, cluster=None)
    assert np.array_equal(a.r, b.r) and a.iterations == b.iterations
    assert "cluster" not in a.info


def test_a_cluster_over_the_cap_is_not_tried():
    """A cluster bigger than max_contacts: no step, the run is plain Gauss-Seidel sweep for sweep."""
    from groomtool.solvers import cluster_newton

    P = groom(0)
    op = MatrixFreeOperator(P)
    saved = cluster_newton.CLUSTER_MAX
    try:
        cluster_newton.CLUSTER_MAX = 5
        out = run_gauss_seidel(op, "coulomb", tol=1e-8, max_sweeps=200, anderson=0)
    finally:
        cluster_newton.CLUSTER_MAX = saved
    plain = run_gauss_seidel(MatrixFreeOperator(P), "coulomb", tol=1e-8, max_sweeps=200, anderson=0, cluster=None)
    assert not any(c[1] for c in out.cluster) and all(c[2] == 0 for c in out.cluster)
    assert np.array_equal(out.r, plain.r)
