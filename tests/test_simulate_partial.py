"""Partial steps (Simulator._partial_contacts): the contacts of the strands that did not move keep their rows (contact,
H row, w, W's diagonal block, the blocks between two of them, their H D panels); only the contacts of the moved strands
are found and evaluated again.  With the unmoved strands exactly where they were, the step's contact problem is a full
assembly's to round-off; keeping the rows of a moved strand's contacts is caught."""

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from groomtool import simulate as simulate_module
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator, State, match_contacts
from groomtool.solvers import ContactProblem
from groomtool.solvers.gauss_seidel import AssembledOperator, MatrixFreeOperator

GRAVITY = np.array([0.0, -9.81, 0.0])
R_C = 50e-6


def frame(tangent, normal):
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    n = np.asarray(normal, float) - np.dot(normal, t) * t
    n /= np.linalg.norm(n)
    return np.stack([t, n, np.cross(t, n)], axis=1)


def stacked_strands(angles=(0.0, 0.5, -0.45, 0.3, -0.25)):
    """Strands over a sphere along great circles through its top, each 2 r_c above the one before: strand k touches the
    head and strands k - 1 and k + 1 (crossing there), so one strand's moving leaves contacts of the others alone."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    n = 10
    roots, frames, qs = [], [], []
    for k, angle in enumerate(angles):
        t = np.array([np.cos(angle), 0.0, np.sin(angle)])
        roots.append(np.array([0.0, 0.05 + (1.4 + 2.0 * k) * R_C, 0.0]) - 0.02 * t)
        frames.append(frame(t, [0, 1, 0]))
        q = np.zeros((n, 3))
        q[:, 2] = -1.0 / (0.05 + (1.4 + 2.0 * k) * R_C)
        qs.append(q)
    return sh.SuperHelix(np.array(roots), np.array(frames), np.full((len(angles), n), 0.006), np.array(qs)), sphere


def partial_and_fresh(form: str, bend: float = 1e-3, strand: int = 1):
    """A full assembly kept (its W's cache filled for ``form``), then strand ``strand`` bent by ``bend`` (rad per m of
    curvature, far above reuse_rotation) with the others exactly where they were: (partial step, full assembly of the
    same state, the simulator)."""
    helix, sphere = stacked_strands()
    material = Material(friction=0.3)
    rng = np.random.default_rng(3)
    rates = 1e-2 * rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    params = SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=1e-7)
    sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params, initial_rates=rates)
    kept = sim.assemble()
    assert kept.contacts.n_strand_strand >= 4 and kept.contacts.n_strand_head >= 5
    if form == "assembled":
        AssembledOperator.from_problem(kept.problem)
    else:
        kept.problem.packed()
    kept.problem.diagonal_blocks()
    moved = helix.curvatures.copy()
    moved[strand] += bend * rng.normal(size=moved[strand].shape) * helix.element_mask[strand, :, None]
    sim.state = State(0.0, moved, rates)
    partial = sim.assemble()
    assert sim.partial_steps == 1 and sim.partial_strands == 1
    fresh_sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, initial_rates=rates,
                          params=SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=0.0))
    fresh_sim.state = State(0.0, moved, rates)
    return partial, fresh_sim.assemble(), sim


def discrepancy(partial, fresh, form: str) -> float:
    """The largest relative difference between the partial step's contact problem and the full assembly's (inf where
    the contact sets differ): contacts, H, w, b, W r (H D H^T and the solver's operator on the cached parts) for random
    r, W's diagonal blocks."""
    idx = match_contacts(fresh.contacts, partial.contacts, 1e-12)  # partial contact i is fresh contact idx[i]
    if len(idx) != len(fresh.contacts.strand_a) or np.any(idx < 0) or len(np.unique(idx)) != len(idx):
        return np.inf
    rows = (3 * idx[:, None] + np.arange(3)).ravel()

    def rel(a, b):
        return float(np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(np.asarray(b)).max(), 1e-300))

    worst = [rel(partial.contacts.frame, fresh.contacts.frame[idx]),
             rel(partial.contacts.point_a, fresh.contacts.point_a[idx]),
             abs(partial.H - fresh.H[rows]).max() / abs(fresh.H).max(),
             rel(partial.w, fresh.w[rows]),
             rel(partial.problem.b, fresh.problem.b[rows])]
    rng = np.random.default_rng(0)
    r = rng.normal(size=3 * len(idx))
    r_fresh = np.empty_like(r)
    r_fresh[rows] = r
    u_fresh = fresh.problem.velocity(r_fresh)[rows]
    worst.append(rel(partial.problem.velocity(r), u_fresh))
    worst.append(rel(partial.problem.diagonal_blocks(), fresh.problem.diagonal_blocks()[idx]))
    op = AssembledOperator.from_problem(partial.problem) if form == "assembled" else MatrixFreeOperator(partial.problem)
    worst.append(rel(op.velocity(r.reshape(-1, 3)).ravel(), u_fresh))
    discrepancy.parts = worst
    return max(worst)


@pytest.mark.parametrize("form", ["assembled", "matrix_free"])
def test_a_partial_step_keeps_the_unmoved_contacts_and_is_the_full_assembly(form):
    partial, fresh, sim = partial_and_fresh(form)
    kept_cache = sim._at_rest.system.problem._cache
    assert "diag" in kept_cache and ("upper" in kept_cache) == (form == "assembled")
    assert ("packed" in kept_cache) == (form == "matrix_free")  # carried, not rebuilt from H D
    assert discrepancy(partial, fresh, form) <= 1e-12
    # the contacts of the unmoved strands come first, as they were kept
    unmoved = (partial.contacts.strand_a != 1) & (partial.contacts.strand_b != 1)
    assert np.all(unmoved[:np.count_nonzero(unmoved)]) and np.count_nonzero(unmoved) >= 5


@pytest.mark.parametrize("form", ["assembled", "matrix_free"])
def test_keeping_a_moved_strands_contacts_is_caught(form, monkeypatch):
    """The kept rows are those of the contacts with no side on a moved strand: counting strand 1 as unmoved there keeps
    its old contacts beside the new ones, and the test above fails."""
    monkeypatch.setattr(simulate_module, "touching", lambda contacts, strands, n: np.zeros(len(contacts.strand_a), bool))
    partial, fresh, _ = partial_and_fresh(form)
    assert discrepancy(partial, fresh, form) > 1e-6


def random_problem(rng, sizes, contacts):
    """A ContactProblem with dense SPD blocks: contacts = [(strand, strand or -1)], each row touching the first dofs
    of its strands."""
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    H = np.zeros((3 * len(contacts), offsets[-1]))
    for i, (a, b) in enumerate(contacts):
        for s in (a, b):
            if s >= 0:
                k = rng.integers(1, sizes[s] + 1)
                H[3 * i:3 * i + 3, offsets[s]:offsets[s] + k] = rng.normal(size=(3, k))
    blocks = []
    for n in sizes:
        A = rng.normal(size=(n, n))
        blocks.append(A @ A.T + n * np.eye(n))
    return H, blocks, offsets


@pytest.mark.parametrize("form", ["assembled", "matrix_free"])
def test_carried_cache_is_the_rebuilt_one_and_a_stale_row_is_caught(form):
    """ContactProblem.carry_cache on its own: strand 2's D block changes and contacts on it (and a new one) come in;
    the cache carried for the others and computed for those is a fresh problem's to round-off, and claiming a contact
    on strand 2 kept (its old diagonal block and W_ij) is caught."""
    rng = np.random.default_rng(1)
    sizes = [6, 9, 12, 6]
    pairs = [(0, -1), (0, 1), (1, -1), (2, -1), (1, 2), (3, -1), (2, 3), (3, 0), (1, 3)]
    H, blocks, offsets = random_problem(rng, sizes, pairs)
    old = ContactProblem.from_dense_blocks(sp.csr_matrix(H), blocks, offsets, 0.0, np.zeros(H.shape[0]), 0.3)
    if form == "assembled":
        AssembledOperator.from_problem(old)
    else:
        old.packed()
    old.diagonal_blocks()
    # strand 2's block anew; contacts 3 and 4 (on it) re-evaluated, contact 1 dropped, a new contact (2, 0) at the end
    A = rng.normal(size=(12, 12))
    blocks_new = list(blocks)
    blocks_new[2] = A @ A.T + 12 * np.eye(12)
    keep = [0, 2, 3, 4, 5, 6, 7, 8]
    H2, _, _ = random_problem(rng, sizes, [(2, 0)])
    H_new = np.vstack([H[(3 * np.array(keep)[:, None] + np.arange(3)).ravel()], H2])
    H_new[6:9] = random_problem(rng, sizes, [(2, -1)])[0]  # contact 3 (strand 2) re-evaluated
    new = ContactProblem.from_dense_blocks(sp.csr_matrix(H_new), blocks_new, offsets, 0.0, np.zeros(H_new.shape[0]),
                                           0.3)
    on_2 = np.array([2 in pairs[c] for c in keep] + [True])
    rows = np.where(on_2, -1, np.array(keep + [-1]))
    new.carry_cache(old, rows, np.arange(offsets[-1]))
    fresh = ContactProblem.from_dense_blocks(sp.csr_matrix(H_new), blocks_new, offsets, 0.0, np.zeros(H_new.shape[0]),
                                             0.3)
    r = rng.normal(size=(len(keep) + 1, 3))

    def velocity(problem):
        op = AssembledOperator.from_problem(problem) if form == "assembled" else MatrixFreeOperator(problem)
        return op.velocity(r.copy()).ravel()

    assert ("upper" in new._cache) == (form == "assembled") and "diag" in new._cache
    scale = np.abs(fresh.velocity(r.ravel())).max()
    np.testing.assert_allclose(velocity(new), fresh.velocity(r.ravel()), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(new.diagonal_blocks(), fresh.diagonal_blocks(), rtol=0,
                               atol=1e-12 * np.abs(fresh.diagonal_blocks()).max())
    stale = ContactProblem.from_dense_blocks(sp.csr_matrix(H_new), blocks_new, offsets, 0.0, np.zeros(H_new.shape[0]),
                                             0.3)
    wrong = rows.copy()
    wrong[2] = keep[2]  # contact 4 of the old problem, on strand 2: its old parts of W carried
    stale.carry_cache(old, wrong, np.arange(offsets[-1]))
    assert np.abs(velocity(stale) - fresh.velocity(r.ravel())).max() > 1e-6 * scale


def test_contacts_that_turned_by_contact_rotation_are_made_anew_without_assembling_the_strand():
    """A strand turned by more than contact_rotation (reuse_rotation / 100) but less than reuse_rotation keeps its Mhat,
    A and dF/dq; its contacts, H rows and w are made anew (a partial step assembling no strand), as a full assembly
    makes them."""
    helix, sphere = stacked_strands()
    material = Material(friction=0.3)
    params = SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=1e-7)
    sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere, params=params)
    sim.assemble()
    moved = helix.curvatures.copy()
    moved[2, :, 2] += 5e-8 / helix.strand_lengths[2]  # strand 2 turned by 5e-8 rad
    sim.state = State(0.0, moved, np.zeros_like(moved))
    partial = sim.assemble()
    assert sim.partial_steps == 1 and sim.partial_strands == 0 and sim.refreshed_strands == 1
    fresh_sim = Simulator(helix, helix.curvatures, material, GRAVITY, head=sphere,
                          params=SimulationParams(dt=1 / 240, contacts="all", reuse_rotation=0.0))
    fresh_sim.state = State(0.0, moved, np.zeros_like(moved))
    fresh = fresh_sim.assemble()
    idx = match_contacts(fresh.contacts, partial.contacts, 1e-12)
    assert np.all(idx >= 0) and len(idx) == len(fresh.contacts.strand_a)
    rows = (3 * idx[:, None] + np.arange(3)).ravel()
    assert abs(partial.H - fresh.H[rows]).max() <= 1e-12 * abs(fresh.H).max()
    np.testing.assert_allclose(partial.contacts.point_a, fresh.contacts.point_a[idx], rtol=0, atol=1e-15)
    sim.state = State(0.0, moved.copy(), np.zeros_like(moved))
    sim.assemble()
    assert sim.reused_steps == 1  # made anew: at rest again


def test_a_partial_step_whose_candidates_cannot_serve_makes_every_contact_anew(monkeypatch):
    """Where the kept strand/strand candidates cannot serve the strands made anew (ContactTracker.contacts_of: a pair's
    e_a + e_b beyond the skin), the partial step makes all contacts anew (_full_contacts), as a full assembly does."""
    from groomtool.simulate_contacts import ContactTracker

    calls = []
    original = ContactTracker.contacts_of

    def far(self, *args, **kwargs):
        self._pair_excess[:] = self.cache.skin  # every strand as far as the skin from the pass
        out = original(self, *args, **kwargs)
        calls.append(out)
        return out

    monkeypatch.setattr(ContactTracker, "contacts_of", far)
    partial, fresh, sim = partial_and_fresh("assembled")
    assert calls == [None]
    assert discrepancy(partial, fresh, "assembled") <= 1e-12
    np.testing.assert_array_equal(partial.contacts.strand_a, fresh.contacts.strand_a)  # the full assembly's order
    assert np.all(sim._contacts_at == sim.state.curvatures)
