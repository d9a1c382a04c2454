"""H as an operator (prefix/suffix sums, contact/operator.py) against the CSR H of contact/jacobian.py and against
finite differences of the contact points."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.linalg import LinearOperator, aslinearoperator, lsqr

from groomtool.contact.jacobian import contact_jacobian
from groomtool.contact.operator import ContactJacobianOperator, contact_velocities, point_velocities
from groomtool.rods import superhelix as sh
from test_contact_jacobian import _positions, _random_contacts, _random_groom


@given(seed=st.integers(0, 10_000), scale=st.sampled_from([0.0, 1e-6, 5.0, 40.0]),
       n_strands=st.integers(1, 6), max_elements=st.integers(1, 9), m=st.integers(1, 40))
@settings(max_examples=40, deadline=None)
def test_operator_products_equal_the_csr_H(seed, scale, n_strands, max_elements, m):
    """H v and H^T r of the operator equal the CSR H's on every kind of contact (pairs, self, head, roots, tips,
    nodes) to round-off."""
    rng = np.random.default_rng(seed)
    helix = _random_groom(rng, n_strands, max_elements, scale)
    contacts = _random_contacts(rng, helix, m)
    H = contact_jacobian(helix, contacts)
    op = ContactJacobianOperator(helix, contacts)
    assert op.shape == H.shape
    v = rng.normal(size=H.shape[1])
    r = rng.normal(size=H.shape[0])
    Hv = H @ v
    Htr = H.T @ r
    assert np.abs(op @ v - Hv).max() <= 1e-13 * max(1.0, np.abs(H).max() * np.abs(v).sum())
    assert np.abs(op.T @ r - Htr).max() <= 1e-13 * max(1.0, np.abs(H).max() * np.abs(r).sum())


def test_point_velocities_are_the_derivative_of_the_points():
    """dC(s)/dt for rates v equals the central difference of C(s) along q + eps v (independent of H)."""
    rng = np.random.default_rng(11)
    helix = _random_groom(rng, 4, 7, 20.0)
    strand = rng.integers(4, size=30)
    s = rng.uniform(0.0, 1.0, 30) * helix.strand_lengths[strand]
    v = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    eps = 1e-6
    xp, _ = sh.evaluate(helix.with_curvatures(helix.curvatures + eps * v), strand, s)
    xm, _ = sh.evaluate(helix.with_curvatures(helix.curvatures - eps * v), strand, s)
    fd = (xp - xm) / (2 * eps)
    got = point_velocities(helix, sh.kinematics(helix), strand, s, v)
    assert np.abs(got - fd).max() <= 1e-6 * np.abs(fd).max()


def test_contact_velocities_equal_finite_differences_of_relative_positions():
    rng = np.random.default_rng(5)
    helix = _random_groom(rng, 5, 8, 10.0)
    contacts = _random_contacts(rng, helix, 25)
    v_flat = rng.normal(size=3 * int(helix.flat_offsets()[-1]))
    v = helix.from_flat(v_flat.reshape(-1, 3))
    eps = 1e-6
    dp = (_positions(helix.with_curvatures(helix.curvatures + eps * v), contacts)
          - _positions(helix.with_curvatures(helix.curvatures - eps * v), contacts)) / (2 * eps)
    ref = np.einsum("pij,pj->pi", contacts.frame, dp)
    for rates in (v_flat, v):  # flat (H's columns) or padded
        got = contact_velocities(helix, contacts, rates)
        assert got.shape == ref.shape
        assert np.abs(got - ref).max() <= 1e-6 * np.abs(ref).max()


def test_padding_rates_are_ignored_and_untouched_strands_cost_nothing():
    """Rates on padding elements (not dofs) do not change H v; a contact-free strand's rates do not either."""
    rng = np.random.default_rng(9)
    helix = _random_groom(rng, 4, 6, 5.0)
    contacts = _random_contacts(rng, helix, 12)
    v = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    base = contact_velocities(helix, contacts, v)
    noisy = v + rng.normal(size=v.shape) * ~helix.element_mask[..., None]
    assert np.array_equal(contact_velocities(helix, contacts, noisy), base)
    involved = set(contacts.strand_a.tolist()) | set(contacts.strand_b[contacts.strand_b >= 0].tolist())
    free = [k for k in range(4) if k not in involved]
    if free:
        other = v.copy()
        other[free] += 1.0
        assert np.array_equal(contact_velocities(helix, contacts, other), base)


def test_operator_works_with_scipy_solvers():
    """As a scipy LinearOperator (matvec, rmatvec): a least-squares solve with lsqr matches one with the CSR H."""
    rng = np.random.default_rng(2)
    helix = _random_groom(rng, 3, 5, 10.0)
    contacts = _random_contacts(rng, helix, 4)
    H = contact_jacobian(helix, contacts)
    u = rng.normal(size=H.shape[0])
    op = ContactJacobianOperator(helix, contacts)
    a = lsqr(LinearOperator(op.shape, matvec=op.matvec, rmatvec=op.rmatvec), u, atol=1e-14, btol=1e-14)[0]
    b = lsqr(aslinearoperator(H), u, atol=1e-14, btol=1e-14)[0]
    assert np.allclose(a, b, atol=1e-8 * max(1.0, np.abs(b).max()))
