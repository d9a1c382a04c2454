"""H against finite differences of the contact points' positions, and H^T r against its point-wise twin."""

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from groomtool.contact.jacobian import contact_jacobian, generalized_contact_force
from groomtool.rods import superhelix as sh


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
