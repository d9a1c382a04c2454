"""The matrix-free Gauss-Seidel's kept products (ContactProblem.velocity / dof_velocity through the packed panels)
and run_gauss_seidel's quick checks, against direct products and an exact check after every sweep."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from groomtool.solvers.gauss_seidel import MatrixFreeOperator, run_gauss_seidel

_spec = importlib.util.spec_from_file_location("bench_problems", Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def dynamics(m, seed):
    return problems.make_hair_like(m, variant="dynamics", seed=seed)[0]


def test_packed_velocity_is_W_r_plus_b_and_follows_r_and_b():
    P = dynamics(150, 4)
    W = P.assemble_W().toarray()
    rng = np.random.default_rng(0)
    r = rng.normal(size=3 * P.n_contacts)
    direct = W @ r + P.b
    np.testing.assert_allclose(P.velocity(r), direct, rtol=0, atol=1e-12 * np.abs(direct).max())
    P.packed()  # from here on through the packed panels, the last product kept
    u = P.velocity(r)
    np.testing.assert_allclose(u, direct, rtol=0, atol=1e-12 * np.abs(direct).max())
    u[:] = 0.0  # the caller's copy: the kept product is not modified
    np.testing.assert_allclose(P.velocity(r), direct, rtol=0, atol=1e-12 * np.abs(direct).max())
    r[5] += 1.0  # r modified in place: not the kept product's r any more
    np.testing.assert_allclose(P.velocity(r), W @ r + P.b, rtol=0, atol=1e-12 * np.abs(direct).max())
    Q = P.with_free_velocity(rng.normal(size=3 * P.n_contacts))  # shares the cache, another b
    np.testing.assert_allclose(Q.velocity(r), W @ r + Q.b, rtol=0, atol=1e-12 * np.abs(direct).max())
    np.testing.assert_allclose(P.velocity(r), W @ r + P.b, rtol=0, atol=1e-12 * np.abs(direct).max())
    # v = D H^T r: the kept one only for the same r
    D = np.zeros((P.n_dofs, P.n_dofs))
    for s, blk in enumerate(P.D_blocks):
        a, b = P.dof_offsets[s], P.dof_offsets[s + 1]
        D[a:b, a:b] = blk if blk.ndim == 2 else np.diag(blk)
    for x in (r, r + 1.0):
        v = P.dof_velocity(x.reshape(-1, 3))
        ref = D @ (P.H.T @ x)
        np.testing.assert_allclose(v, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("law", ["soc", "coulomb"])
def test_quick_checks_stop_where_an_exact_check_after_every_sweep_stops(law):
    P = dynamics(300, 11)
    P.b = np.random.default_rng(1).normal(size=3 * P.n_contacts)
    tol = 1e-6
    every = run_gauss_seidel(MatrixFreeOperator(P), law, tol=tol, max_sweeps=400, check_every=1, anderson=0,
                             cluster=None, newton=None)
    assert every.converged and 3 <= every.sweeps < 100
    sparse = run_gauss_seidel(MatrixFreeOperator(P), law, tol=tol, max_sweeps=400, check_every=100, anderson=0,
                              cluster=None, newton=None)
    assert sparse.sweeps == 100  # without quick checks: the first check
    quick = run_gauss_seidel(MatrixFreeOperator(P), law, tol=tol, max_sweeps=400, check_every=100, anderson=0,
                             cluster=None, newton=None, quick_check=1)
    assert quick.converged and quick.residual <= tol
    assert quick.sweeps == every.sweeps
    assert quick.history[-1][0] == quick.sweeps and len(quick.history) == 2  # only the exact check that stopped it
    np.testing.assert_allclose(quick.r, every.r, rtol=0, atol=1e-10 * np.abs(every.r).max())
    two = run_gauss_seidel(MatrixFreeOperator(P), law, tol=tol, max_sweeps=400, check_every=100, anderson=0,
                           cluster=None, newton=None, quick_check=2)
    assert two.converged and two.sweeps in (every.sweeps, every.sweeps + 1) and two.sweeps % 2 == 0


def test_dense_block_strand_by_strand_is_the_explicit_W():
    """MatrixFreeOperator.dense_block (summed strand by strand) against W = H D H^T + 2 gamma I, on random clusters of
    a problem whose contacts touch one or two strands of dense D blocks."""
    P = dynamics(200, 7)
    P.gamma = 0.003
    W = P.assemble_W().toarray()
    op = MatrixFreeOperator(P)
    rng = np.random.default_rng(2)
    for size in (1, 5, 40, 200):
        idx = np.sort(rng.choice(P.n_contacts, size=size, replace=False))
        rows = (3 * idx[:, None] + np.arange(3)).ravel()
        ref = W[np.ix_(rows, rows)]
        np.testing.assert_allclose(op.dense_block(idx), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
