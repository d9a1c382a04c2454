"""H against finite differences of the contact points' positions, and H^T r against its point-wise twin."""

from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from groomtool.contact.jacobian import contact_jacobian, generalized_contact_force
from groomtool.rods import superhelix as sh
from reference.contact import contact_jacobian_reference, generalized_contact_force_reference


def _helix(seed=0):
    rng = np.random.default_rng(seed)
    n = np.array([4, 6, 3])
    lengths = np.zeros((3, 6))
    q = np.zeros((3, 6, 3))
    for i, k in enumerate(n):
        lengths[i, :k] = rng.uniform(0.01, 0.04, k)
        q[i, :k] = rng.normal(size=(k, 3)) * 20
    return sh.SuperHelix(0.05 * rng.normal(size=(3, 3)), Rotation.random(3, random_state=seed).as_matrix(),
                         lengths, q, n)


def _contacts(helix, seed=0):
    rng = np.random.default_rng(seed)
    strand_a = np.array([0, 1, 2, 1])
    strand_b = np.array([1, -1, 0, 1])  # a strand pair, the head, another pair, a self contact
    L = helix.strand_lengths
    s_a = rng.uniform(0.1, 0.9, 4) * L[strand_a]
    s_b = np.where(strand_b >= 0, rng.uniform(0.1, 0.9, 4) * L[np.maximum(strand_b, 0)], np.nan)
    frames = Rotation.random(4, random_state=seed + 1).as_matrix()
    return SimpleNamespace(strand_a=strand_a, s_a=s_a, strand_b=strand_b, s_b=s_b, frame=frames)


def _positions(helix, contacts):
    pa, _ = sh.evaluate(helix, contacts.strand_a, contacts.s_a)
    has_b = contacts.strand_b >= 0
    pb = np.zeros_like(pa)
    pb[has_b], _ = sh.evaluate(helix, contacts.strand_b[has_b], contacts.s_b[has_b])
    return pa - pb  # the head does not move


def test_H_matches_finite_difference_of_relative_positions():
    helix = _helix()
    contacts = _contacts(helix)
    H = contact_jacobian(helix, contacts).toarray()
    rng = np.random.default_rng(3)
    qdot_flat = rng.normal(size=H.shape[1])
    qdot = helix.from_flat(qdot_flat.reshape(-1, 3))
    eps = 1e-6
    dp = (_positions(helix.with_curvatures(helix.curvatures + eps * qdot), contacts)
          - _positions(helix.with_curvatures(helix.curvatures - eps * qdot), contacts)) / (2 * eps)
    u_ref = np.einsum("pij,pj->pi", contacts.frame, dp).ravel()
    assert np.allclose(H @ qdot_flat, u_ref, atol=1e-7 * np.abs(u_ref).max())


def test_H_transpose_equals_pointwise_generalized_force():
    helix = _helix(1)
    contacts = _contacts(helix, 1)
    H = contact_jacobian(helix, contacts)
    r = np.random.default_rng(4).normal(size=(4, 3))
    via_h = helix.from_flat((H.T @ r.ravel()).reshape(-1, 3))
    pointwise = generalized_contact_force(helix, contacts, r)
    assert np.allclose(via_h, pointwise, atol=1e-14 * np.abs(pointwise).max())


def test_H_is_zero_downstream_of_the_contact():
    helix = _helix(2)
    contacts = _contacts(helix, 2)
    H = contact_jacobian(helix, contacts).toarray()
    offsets = helix.flat_offsets()
    elem, _ = sh.locate(helix, contacts.strand_a[:1], contacts.s_a[:1])
    first_dead = 3 * (offsets[contacts.strand_a[0]] + elem[0] + 1)
    last = 3 * offsets[contacts.strand_a[0] + 1]
    assert np.all(H[0:3, first_dead:last] == 0)


# --------------------------------------------------------------------------- direct CSR vs the reference
def _random_groom(rng, n_strands, max_elements, scale):
    """Strands of different element counts (padded), the root/tip both possible contact sites."""
    n = rng.integers(1, max_elements + 1, n_strands)
    n[rng.integers(n_strands)] = max_elements
    lengths = np.zeros((n_strands, max_elements))
    q = np.zeros((n_strands, max_elements, 3))
    for i, k in enumerate(n):
        lengths[i, :k] = rng.uniform(0.005, 0.04, k)
        q[i, :k] = rng.normal(size=(k, 3)) * scale
    roots = 0.1 * rng.normal(size=(n_strands, 3))
    frames = Rotation.random(n_strands, random_state=int(rng.integers(1 << 30))).as_matrix()
    return sh.SuperHelix(roots, frames, lengths, q, n)


def _random_contacts(rng, helix, m):
    """Strand pairs in both orders of strand index, self contacts (either side further along), head
    contacts, and arc lengths on the first and last elements, at nodes and at both ends."""
    S = helix.n_strands
    L = helix.strand_lengths
    starts = helix.element_starts
    strand_a = rng.integers(S, size=m)
    strand_b = rng.integers(S, size=m)
    kind = rng.integers(4, size=m)
    strand_b[kind == 0] = -1
    strand_b[kind == 1] = strand_a[kind == 1]

    def arc(strand):
        n = helix.n_elements[strand]
        pick = rng.integers(6, size=len(strand))
        last = starts[strand, n - 1]
        s = rng.uniform(0.0, 1.0, len(strand)) * L[strand]
        s = np.where(pick == 0, 0.0, s)  # the root
        s = np.where(pick == 1, L[strand], s)  # the tip
        s = np.where(pick == 2, rng.uniform(0.0, 1.0, len(strand)) * starts[strand, 1], s)  # first element
        s = np.where(pick == 3, last + rng.uniform(0.0, 1.0, len(strand)) * (L[strand] - last), s)  # last element
        node = starts[strand, rng.integers(0, n + 1)]
        return np.where(pick == 4, node, s)

    s_a = arc(strand_a)
    s_b = np.where(strand_b >= 0, arc(np.maximum(strand_b, 0)), np.nan)
    frames = Rotation.random(m, random_state=int(rng.integers(1 << 30))).as_matrix()
    return SimpleNamespace(strand_a=strand_a, s_a=s_a, strand_b=strand_b, s_b=s_b, frame=frames)


def _assert_same_as_reference(helix, contacts):
    H = contact_jacobian(helix, contacts)
    ref = contact_jacobian_reference(helix, contacts)
    assert isinstance(H, sp.csr_matrix)
    assert H.dtype == np.float64 and H.shape == ref.shape
    # sorted, duplicate-free columns in every row (checked from the arrays, not the cached flag)
    rows = np.repeat(np.arange(H.shape[0]), np.diff(H.indptr))
    assert np.all((np.diff(H.indices) > 0) | (np.diff(rows) > 0))
    Hc = H.copy()
    Hc.has_sorted_indices = False
    Hc.sort_indices()
    assert np.array_equal(Hc.indices, H.indices) and np.array_equal(Hc.data, H.data)
    # the same sparsity pattern and the same values
    ref.sum_duplicates()
    ref.sort_indices()
    assert np.array_equal(H.indptr, ref.indptr) and np.array_equal(H.indices, ref.indices)
    scale = np.abs(ref.data).max()
    assert np.abs(H.data - ref.data).max() <= 1e-12 * scale
    return H


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=40, deadline=None)
def test_H_equals_reference_on_random_grooms(seed, scale, n_strands, max_elements, m):
    rng = np.random.default_rng(seed)
    helix = _random_groom(rng, n_strands, max_elements, scale)
    _assert_same_as_reference(helix, _random_contacts(rng, helix, m))


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0]),
       n_strands=st.integers(1, 5), max_elements=st.integers(1, 9), m=st.integers(1, 25))
@settings(max_examples=30, deadline=None)
def test_generalized_force_by_suffix_sums_equals_dense_reference(seed, scale, n_strands, max_elements, m):
    """The O(S N + m) suffix-sum H^T r equals the dense point-Jacobian one and H^T r of the CSR H."""
    rng = np.random.default_rng(seed)
    helix = _random_groom(rng, n_strands, max_elements, scale)
    contacts = _random_contacts(rng, helix, m)
    r = rng.normal(size=(len(contacts.strand_a), 3))
    fast = generalized_contact_force(helix, contacts, r)
    ref = generalized_contact_force_reference(helix, contacts, r)
    tol = 1e-12 * max(1.0, np.abs(ref).max())
    assert np.abs(fast - ref).max() <= tol
    via_h = helix.from_flat((contact_jacobian(helix, contacts).T @ r.ravel()).reshape(-1, 3))
    assert np.abs(fast - via_h).max() <= tol
    assert not np.any(fast[~helix.element_mask])


def test_H_equals_reference_on_every_kind_of_contact():
    rng = np.random.default_rng(7)
    helix = _random_groom(rng, 5, 8, 20.0)
    n = helix.n_elements
    L = helix.strand_lengths
    short, long_ = int(np.argmin(n)), int(np.argmax(n))
    assert n[short] < n[long_]
    starts = helix.element_starts
    strand_a = np.array([short, long_, long_, long_, long_, short, long_, 3])
    strand_b = np.array([long_, short, -1, long_, long_, -1, long_, 3])
    s_a = np.array([L[short], 0.0, L[long_], 0.5 * starts[long_, 1], L[long_], 0.3 * L[short],
                    starts[long_, 2], 0.4 * L[3]])
    s_b = np.array([0.0, L[short], np.nan, L[long_], 0.5 * starts[long_, 1], np.nan, starts[long_, 2],
                    0.6 * L[3]])
    contacts = SimpleNamespace(strand_a=strand_a, s_a=s_a, strand_b=strand_b, s_b=s_b,
                               frame=Rotation.random(8, random_state=2).as_matrix())
    H = _assert_same_as_reference(helix, contacts)
    offsets = helix.flat_offsets()
    # head contact at the tip: the whole strand, nothing else
    assert H[6:9].nnz == 9 * n[long_]
    assert set(H[6:9].indices // 3) == set(range(offsets[long_], offsets[long_ + 1]))
    # root of one strand against the tip of a shorter strand (and the mirror): 1 + n[short] blocks
    assert H[0:3].nnz == 9 * (1 + n[short]) and H[3:6].nnz == 9 * (1 + n[short])
    # self contact first element vs last element: the union of the two ranges
    assert H[9:12].nnz == 9 * n[long_] and H[12:15].nnz == 9 * n[long_]
    # a self contact at the same point cancels exactly
    assert np.all(H[18:21].toarray() == 0)


def test_H_without_contacts_and_with_head_contacts_only():
    helix = _helix(4)
    none = SimpleNamespace(strand_a=np.zeros(0, int), s_a=np.zeros(0), strand_b=np.zeros(0, int),
                           s_b=np.zeros(0), frame=np.zeros((0, 3, 3)))
    H = contact_jacobian(helix, none)
    assert H.shape == (0, 3 * helix.n_elements.sum())
    heads = SimpleNamespace(strand_a=np.array([2, 0, 1]), s_a=np.array([0.0, 0.01, 1.0]),
                            strand_b=np.full(3, -1), s_b=np.full(3, np.nan),
                            frame=Rotation.random(3, random_state=5).as_matrix())
    _assert_same_as_reference(helix, heads)
