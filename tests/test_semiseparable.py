"""groomtool.semiseparable against dense linear algebra: the factor is the dense Cholesky factor, the solves and
products the dense ones, on random block-semiseparable matrices and on matrices built the way the strands' are
(D^-1 + sum_e J_e^T J_e / rho_e with rigid Jacobians upstream of each point)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool import semiseparable as ss
from reference.semiseparable import dense_lower, dense_strand, factor, matvec


def _random_strands(rng, sizes, r):
    """Random generators and diagonal blocks made positive definite by a shift of each strand's diagonal."""
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    E = int(offsets[-1])
    later = rng.normal(size=(E, r, 3))
    earlier = rng.normal(size=(E, r, 3))
    diag = rng.normal(size=(E, 3, 3))
    diag = diag + diag.transpose(0, 2, 1)
    for s in range(len(sizes)):
        e0, e1 = offsets[s], offsets[s + 1]
        if e1 == e0:
            continue
        lam = np.linalg.eigvalsh(dense_strand(diag, later, earlier, e0, e1))[0]
        diag[e0:e1] += (abs(lam) + rng.uniform(0.1, 2.0)) * np.eye(3)
    return diag, later, earlier, offsets


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 12), min_size=1, max_size=5),
       r=st.integers(1, 9))
def test_factor_is_the_dense_cholesky_factor_and_solves_match(seed, sizes, r):
    rng = np.random.default_rng(seed)
    diag, later, earlier, offsets = _random_strands(rng, sizes, r)
    f = factor(diag, later, earlier, offsets)
    assert f.ok.all()
    E = int(offsets[-1])
    rhs = rng.normal(size=(3 * E, 2))
    x = f.solve(rhs)
    y = matvec(diag, later, earlier, offsets, rhs[:, 0])
    for s in range(len(sizes)):
        e0, e1 = int(offsets[s]), int(offsets[s + 1])
        if e1 == e0:
            continue
        A = dense_strand(diag, later, earlier, e0, e1)
        sl = slice(3 * e0, 3 * e1)
        L = np.linalg.cholesky(A)
        np.testing.assert_allclose(dense_lower(f.L, f.W, later, e0, e1), L, rtol=0, atol=1e-10 * np.abs(L).max())
        ref = np.linalg.solve(A, rhs[sl])
        np.testing.assert_allclose(x[sl], ref, rtol=0, atol=1e-9 * np.abs(ref).max())
        np.testing.assert_allclose(y[sl], A @ rhs[sl, 0], rtol=0, atol=1e-12 * np.abs(A).max() * np.abs(rhs).max() * A.shape[0])
        z = rhs[sl, 1].copy()
        ss.solve_lower_strand(f.L, f.W, later, e0, e1, z)
        np.testing.assert_allclose(z, np.linalg.solve(L, rhs[sl, 1]), rtol=0, atol=1e-9 * np.abs(z).max())
        ss.solve_upper_strand(f.L, f.W, later, e0, e1, z)
        np.testing.assert_allclose(z, ref[:, 1], rtol=0, atol=1e-9 * np.abs(ref).max())
        w = rhs[sl, 1].copy()
        ss.apply_upper_strand(f.L, f.W, later, e0, e1, w)
        np.testing.assert_allclose(w, L.T @ rhs[sl, 1], rtol=0, atol=1e-10 * np.abs(L).max() * np.abs(rhs).sum())
        ss.apply_lower_strand(f.L, f.W, later, e0, e1, w)  # L L^T y = A y
        np.testing.assert_allclose(w, A @ rhs[sl, 1], rtol=0, atol=1e-10 * np.abs(A).max() * np.abs(rhs).sum())
    assert x.shape == rhs.shape
    np.testing.assert_allclose(f.solve(rhs[:, 0]), x[:, 0], rtol=0, atol=0)


def _hair_like(rng, E, n_ends, rho_scale=1.0):
    """D^-1 + sum_e J_e^T J_e / rho_e of one strand, dense, and its generators: an end on element b has the rigid
    block P_e G_j on every element j < b and its own 3 x 3 block on b (docs/solvers.md section 12)."""
    G = rng.normal(size=(E, 6, 3))
    d_inv = rng.uniform(0.5, 2.0, size=3 * E)
    ends = []
    for _ in range(n_ends):
        b = int(rng.integers(0, E))
        P = rng.normal(size=(3, 6))
        own = rng.normal(size=(3, 3))
        ends.append((b, P, own, rho_scale * rng.uniform(0.01, 1.0)))
    J = np.zeros((3 * n_ends, 3 * E))
    for i, (b, P, own, rho) in enumerate(ends):
        for j in range(b):
            J[3 * i:3 * i + 3, 3 * j:3 * j + 3] = P @ G[j] / np.sqrt(rho)
        J[3 * i:3 * i + 3, 3 * b:3 * b + 3] = own / np.sqrt(rho)
    A = np.diag(d_inv) + J.T @ J
    diag = np.zeros((E, 3, 3))
    later = np.zeros((E, 6, 3))
    S = np.zeros((6, 6))  # sum over ends beyond element k of P^T P / rho
    for k in range(E - 1, -1, -1):
        diag[k] = np.diag(d_inv[3 * k:3 * k + 3]) + G[k].T @ S @ G[k]
        later[k] = S @ G[k]
        for b, P, own, rho in ends:
            if b == k:
                diag[k] += own.T @ own / rho
                later[k] += P.T @ own / rho
        for b, P, own, rho in ends:
            if b == k:
                S += P.T @ P / rho
    return A, diag, later, G


@pytest.mark.parametrize("E,n_ends,rho_scale", [(1, 3, 1.0), (7, 0, 1.0), (20, 30, 1.0), (40, 12, 1e-3),
                                                (40, 80, 1e3)])
def test_hair_like_matrix_generators_factor_and_solve(E, n_ends, rho_scale):
    rng = np.random.default_rng(E * 1000 + n_ends)
    A, diag, later, G = _hair_like(rng, E, n_ends, rho_scale)
    offsets = np.array([0, E])
    np.testing.assert_allclose(dense_strand(diag, later, G, 0, E), A, rtol=0, atol=1e-12 * np.abs(A).max())
    f = factor(diag, later, G, offsets)
    assert f.ok.all()
    y = rng.normal(size=3 * E)
    ref = np.linalg.solve(A, y)
    np.testing.assert_allclose(f.solve(y), ref, rtol=0, atol=1e-9 * np.abs(ref).max() * np.linalg.cond(A) ** 0.5)


def test_a_strand_that_is_not_positive_definite_is_flagged_and_the_others_are_solved():
    rng = np.random.default_rng(3)
    diag, later, earlier, offsets = _random_strands(rng, [4, 5, 3], 4)
    diag[offsets[1] + 2] -= 1e6 * np.eye(3)  # the middle strand: an indefinite pivot
    f = factor(diag, later, earlier, offsets)
    assert f.ok.tolist() == [True, False, True]
    y = rng.normal(size=3 * int(offsets[-1]))
    x = f.solve(y)
    assert np.isnan(x[3 * offsets[1]:3 * offsets[2]]).all()
    for s in (0, 2):
        e0, e1 = int(offsets[s]), int(offsets[s + 1])
        sl = slice(3 * e0, 3 * e1)
        np.testing.assert_allclose(x[sl], np.linalg.solve(dense_strand(diag, later, earlier, e0, e1), y[sl]), rtol=1e-9)
