"""blocks.pack_HD: H D per contact (the Gauss-Seidel's matrix-free panels) against the sparse product,
for diagonal, dense and mixed D blocks, unequal strand sizes and strands without contacts."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool.solvers import ContactProblem


def dense_panels(packed, n):
    """The packed rows as a dense (3m, n) matrix."""
    m = len(packed.ptr) - 1
    out = np.zeros((3 * m, n))
    for i in range(m):
        for t in range(packed.ptr[i], packed.ptr[i + 1]):
            out[3 * i:3 * i + 3, packed.cols[t]] += packed.vals[t]
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 30), n_strands=st.integers(1, 6),
       kinds=st.lists(st.sampled_from(["dense", "diag"]), min_size=6, max_size=6))
def test_pack_HD_equals_the_sparse_product(seed, m, n_strands, kinds):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 12, size=n_strands)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    n = int(offsets[-1])
    H = sp.random(3 * m, n, density=0.3, random_state=rng, format="csr")
    blocks = []
    for s, k in enumerate(sizes):
        if kinds[s] == "dense":
            X = rng.normal(size=(k, k))
            blocks.append(X @ X.T + k * np.eye(k))
            blocks[-1][0, -1] = blocks[-1][-1, 0] = blocks[-1][0, -1] + (1.0 if k > 1 else 0.0)  # not diagonal
        else:
            blocks.append(rng.uniform(0.5, 2.0, size=k))
    P = ContactProblem(H, blocks, offsets, 0.0, np.zeros(3 * m), 0.3)
    D = sp.block_diag([b if b.ndim == 2 else np.diag(b) for b in P.D_blocks]).toarray()
    Hp, G = P.packed()
    ref = H.toarray() @ D
    got = dense_panels(G, n)
    assert np.abs(got - ref).max() <= 1e-13 * max(np.abs(ref).max(), 1.0)
    assert np.array_equal(dense_panels(Hp, n), H.toarray())
    # a dense strand's panel covers all its dofs; a diagonal one only the contact's own columns
    for i in range(m):
        cols = G.cols[G.ptr[i]:G.ptr[i + 1]]
        assert np.all(np.diff(cols) > 0)
        touched = np.unique(np.searchsorted(offsets, H[3 * i:3 * i + 3].indices, side="right") - 1)
        expect = sum(int(sizes[s]) if P.D_blocks[s].ndim == 2 else
                     len(np.unique(H[3 * i:3 * i + 3].indices[(H[3 * i:3 * i + 3].indices >= offsets[s])
                                                             & (H[3 * i:3 * i + 3].indices < offsets[s + 1])]))
                     for s in touched)
        assert len(cols) == expect


def test_assembled_w_is_kept_for_a_problem_with_another_free_velocity():
    """AssembledOperator.from_problem keeps W's upper blocks in the problem's cache (per order): the problem of
    with_free_velocity (a simulator step at rest) reuses them with its own b, and its velocities are W r + b'."""
    from groomtool.solvers.gauss_seidel import AssembledOperator

    rng = np.random.default_rng(5)
    m, sizes = 12, np.array([5, 7, 4])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    H = sp.random(3 * m, int(offsets[-1]), density=0.4, random_state=rng, format="csr")
    blocks = [np.diag(rng.uniform(0.5, 2.0, k)) + 0.1 for k in sizes]
    P = ContactProblem(H, blocks, offsets, 0.01, rng.normal(size=3 * m), 0.3)
    order = rng.permutation(m)
    first = AssembledOperator.from_problem(P, order)
    other = P.with_free_velocity(rng.normal(size=3 * m))
    second = AssembledOperator.from_problem(other, order)
    assert second.W is first.W
    assert AssembledOperator.from_problem(other, None).W is not first.W  # another order: assembled anew
    D = sp.block_diag(P.D_blocks).toarray()
    W = H.toarray() @ D @ H.toarray().T + 0.02 * np.eye(3 * m)
    r = rng.normal(size=3 * m)
    np.testing.assert_allclose(second.to_external(second.velocity(second.to_internal(r))),
                               W @ r + other.b, rtol=0, atol=1e-12 * np.abs(W @ r).max())
