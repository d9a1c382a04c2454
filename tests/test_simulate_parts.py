"""The simulator's parts: per-strand linear algebra against dense references, detection kept while
nothing moved against fresh detection, SimulationParams as the only carrier of options, the progress
estimate, and groom check's per-strand materials and strand subsets."""

import json
import shutil

import numpy as np
import scipy.linalg
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool.check import check_groom, choose_strands, load_inverted
from groomtool.invert import InversionParams, invert_groom
from reference import dynamics as ref
from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator, simulate
from groomtool.simulate_linalg import StepCorrections, cho_inverse, factor_step_matrix, strand_chunks
from groomtool.simulate_progress import StepProgress

GRAVITY = np.array([0.0, -9.81, 0.0])


# --------------------------------------------------------------------------- linear algebra
def dense_factor_reference(A, B, n_elements):
    """The step matrix as first written: batched Cholesky test of A/2 + B, generalized eigh on failures."""
    import scipy.linalg

    M = A + B
    modified = 0
    for s in range(len(A)):
        n = 3 * int(n_elements[s])
        a, b = A[s, :n, :n], B[s, :n, :n]
        try:
            np.linalg.cholesky(0.5 * a + b)
        except np.linalg.LinAlgError:
            lam, V = scipy.linalg.eigh(b, a)
            d = np.where(lam >= 0.0, 1.0 + lam, 1.0 + 0.5 * np.abs(lam))
            AV = a @ V
            M[s, :n, :n] = (AV * d) @ AV.T
            modified += 1
    return M, modified


def random_strands(rng, S: int, n: int, scale: float, length_range) -> sh.SuperHelix:
    """S random strands of 1..n elements (lengths in length_range, curvatures ~ scale), random roots/frames."""
    counts = rng.integers(1, n + 1, size=S)
    lengths = rng.uniform(*length_range, size=(S, n)) * (np.arange(n)[None, :] < counts[:, None])
    q = rng.normal(size=(S, n, 3)) * scale * (lengths > 0)[..., None]
    frames = np.stack([frame(rng.normal(size=3), rng.normal(size=3)) for _ in range(S)])
    return sh.SuperHelix(rng.normal(size=(S, 3)) * 0.05, frames, lengths, q, counts)


def padded_factors(factors, n_pad):
    """Factors F_s = P L_s P with F_s F_s^T = Mhat_s (upper triangular: StrandFactors stores them tip first),
    padded to (S, n_pad, n_pad) with the identity."""
    out = np.zeros((len(factors.sizes), n_pad, n_pad))
    for s, n in enumerate(factors.sizes):
        out[s, :n, :n] = factors.factor(s)[::-1, ::-1]
        out[s, np.arange(n, n_pad), np.arange(n, n_pad)] = 1.0
    return out


def whole_inverse(factors, s):
    """Mhat_s^-1 in full: the leading block of every dof."""
    return factors.leading_inverse(s, int(factors.sizes[s]))


def dense_factors(A, B, n_elements, *args, **kw):
    """factor_step_matrix's factors padded to (S, n, n) (padding the identity), and its count."""
    factors, modified = factor_step_matrix(A, B, n_elements, *args, **kw)
    return padded_factors(factors, A.shape[1]), modified


def cho_inverse_by_triangular_solves(L, n):
    """Reference (L L^T)^-1 on the first n dofs: X = L^-1 column by column, then X^T X."""
    X = np.zeros((n, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        X[:, j] = scipy.linalg.solve_triangular(L[:n, :n], e, lower=True)
    return X.T @ X


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), unstable=st.floats(0.0, 3.0))
def test_factor_step_matrix_matches_the_dense_reference(seed, unstable):
    rng = np.random.default_rng(seed)
    N = 6
    n_elements = rng.integers(1, N + 1, size=4)
    S, n = len(n_elements), 3 * N
    A = np.zeros((S, n, n))
    B = np.zeros((S, n, n))
    for s, k in enumerate(n_elements):
        m = 3 * int(k)
        X = rng.normal(size=(m, m))
        A[s, :m, :m] = X @ X.T + m * np.eye(m)
        Y = rng.normal(size=(m, m))
        B[s, :m, :m] = -unstable * m * (Y + Y.T) / 2.0
        A[s, m:, m:] = np.eye(n - m)
    factors, modified = factor_step_matrix(A, B, n_elements)
    chol = padded_factors(factors, n)
    ref, ref_modified = dense_factor_reference(A, B, n_elements)
    assert modified == ref_modified
    got = chol @ np.swapaxes(chol, -1, -2)
    assert np.abs(got - ref).max() <= 1e-10 * np.abs(ref).max()
    assert np.allclose(np.tril(chol, -1), 0.0)  # tip first: F = P L P is upper triangular (StrandFactors)
    rhs = rng.normal(size=(S, n)) * np.repeat(np.arange(N)[None, :] < n_elements[:, None], 3, axis=1)
    x = factors.solve(rhs)
    assert np.abs(np.einsum("sij,sj->si", ref, x) - rhs).max() <= 1e-9 * np.abs(rhs).max()
    for s in range(S):
        m = 3 * int(n_elements[s])
        inv = whole_inverse(factors, s)
        assert np.abs(inv @ ref[s, :m, :m] - np.eye(m)).max() <= 1e-9
        k = int(rng.integers(1, m + 1))  # the leading block a contact problem on the first k dofs needs
        lead = factors.leading_inverse(s, k)
        assert np.abs(lead - inv[:k, :k]).max() <= 1e-10 * np.abs(inv).max()


@pytest.mark.parametrize("seed, strength", [(0, 1.0), (1, 1.0), (0, 1e4), (1, 1e4)])
def test_step_matrix_from_the_gravity_generators_matches_the_dense_jacobian(seed, strength):
    """factor_step_matrix on (U, G, Dg) (never stored densely) gives the factors of the dense dF/dq."""
    from groomtool.rods import dynamics as dyn

    rng = np.random.default_rng(seed)
    S = 4
    helix = random_strands(rng, S, 7, 20.0, (0.01, 0.04))
    counts = helix.n_elements
    mat = Material()
    M = dyn.mass_matrix(helix, dyn.Inertia.from_material(mat))
    K = sh.stiffness(helix, mat.stiffness_diag)
    h = 1 / 240
    g = np.array([0.0, -9.81, 0.0])
    dense = sh.gravity_force_jacobian(helix, mat.linear_density, g)
    parts = sh.gravity_force_jacobian_parts(helix, mat.linear_density, g, sh.kinematics(helix))
    kw = dict(stiffness=K, k_scale=h * h, b_scale=-h * h * strength)  # 1e4: strong enough to modify strands
    ref, mod_ref = dense_factors(M, dense, counts, **kw)
    got, mod = dense_factors(M, parts, counts, **kw)
    assert mod == mod_ref and (mod > 0 or strength == 1.0)
    assert np.abs(got - ref).max() <= 1e-10 * np.abs(ref).max()


def test_kept_step_corrections_are_the_fresh_ones_at_rest_and_bound_every_mode():
    """A kept correction reproduces the fresh factor when nothing changed, is reused while A/2 + B + C stays
    positive definite (no mode's step factor below 1/2), and is not used once the strand is stable."""
    rng = np.random.default_rng(11)
    m = 12
    X = rng.normal(size=(m, m))
    A = (X @ X.T + m * np.eye(m))[None]
    Y = rng.normal(size=(m, m))
    B = (-2.0 * m * (Y + Y.T) / 2.0)[None]
    n_elements = np.array([m // 3])
    corrections = StepCorrections(1)
    fresh, modified = dense_factors(A, B, n_elements)
    assert modified == 1
    first, _ = dense_factors(A, B, n_elements, corrections)
    assert corrections.get(0) is not None and np.allclose(first, fresh, rtol=0, atol=1e-14 * np.abs(fresh).max())
    kept = corrections.get(0).copy()
    again, modified = dense_factors(A, B, n_elements, corrections)
    assert modified == 1 and np.array_equal(corrections.get(0), kept)  # the same C: no new decomposition
    assert np.allclose(again, first, rtol=0, atol=1e-13 * np.abs(first).max())
    # a small drift: the kept C is reused and still bounds every mode
    B2 = B * 1.01
    drifted, _ = dense_factors(A, B2, n_elements, corrections)
    assert np.array_equal(corrections.get(0), kept)
    Mhat = drifted[0] @ drifted[0].T
    assert np.allclose(Mhat, A[0] + B2[0] + kept, rtol=0, atol=1e-12 * np.abs(Mhat).max())
    L = np.linalg.cholesky(A[0])
    Li = np.linalg.inv(L)
    assert np.linalg.eigvalsh(Li @ Mhat @ Li.T).min() > 0.5
    # a large change: decomposed anew; a stable strand: correction dropped
    factor_step_matrix(A, 3.0 * B, n_elements, corrections)
    assert not np.array_equal(corrections.get(0), kept)
    stable, modified = dense_factors(A, 0.0 * B, n_elements, corrections)
    assert modified == 0 and corrections.get(0) is not None  # kept, unused while not needed
    assert np.allclose(stable[0] @ stable[0].T, A[0], rtol=0, atol=1e-12 * np.abs(A[0]).max())


def test_strand_chunks_cover_the_groom_within_the_memory_bound():
    n_elements = np.array([3, 40, 7, 40, 1, 12, 33] * 5)
    chunks = strand_chunks(n_elements, max_bytes=2 * (3 * 40) ** 2 * 8)
    assert chunks[0][0] == 0 and chunks[-1][1] == len(n_elements)
    assert all(b1 == a2 for (_, b1), (a2, _) in zip(chunks[:-1], chunks[1:]))
    for a, b in chunks:
        assert b > a and (b - a == 1 or (b - a) * (3 * n_elements[a:b].max()) ** 2 * 8 <= 2 * (3 * 40) ** 2 * 8)
    assert strand_chunks(n_elements) == [(0, len(n_elements))]


def test_cho_inverse_matches_the_triangular_solves():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(30, 30))
    L = np.linalg.cholesky(X @ X.T + 30 * np.eye(30))
    for n in (30, 21, 3):
        ref = cho_inverse_by_triangular_solves(L, n)
        assert np.abs(cho_inverse(L, n) - ref).max() <= 1e-12 * np.abs(ref).max()
        assert np.allclose(cho_inverse(L, n) @ (L[:n, :n] @ L[:n, :n].T), np.eye(n), atol=1e-10)


# --------------------------------------------------------------------------- detection kept
def frame(tangent, normal):
    t = np.asarray(tangent, float) / np.linalg.norm(tangent)
    n = np.asarray(normal, float) - np.dot(normal, t) * t
    n /= np.linalg.norm(n)
    return np.stack([t, n, np.cross(t, n)], axis=1)


def crossing_strands():
    """Two straight strands crossing just above each other over a sphere: strand/strand and head contacts."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    n = 6
    roots = [[-0.03, 0.05 + 3e-5, 0.0], [0.0, 0.05 + 3e-5 + 9e-5, -0.03]]
    frames = [frame([1, 0, 0], [0, 1, 0]), frame([0, 0, 1], [0, 1, 0])]
    helix = sh.SuperHelix(np.array(roots), np.array(frames), np.full((2, n), 0.01), np.zeros((2, n, 3)))
    return helix, sphere


def keys(contacts):
    return {(int(a), int(b)): None for a, b in zip(contacts.strand_a, contacts.strand_b)}


def test_contact_problem_on_the_moved_dofs_is_the_full_delassus():
    """The simulator's contact problem keeps each strand's dofs up to its farthest contact only
    (D_s = (Mhat_s^-1)[:k_s, :k_s]): its W equals H Mhat^-1 H^T with the whole H and the whole inverses."""
    import scipy.sparse as sp

    helix, sphere = crossing_strands()
    params = SimulationParams(dt=1 / 240, contacts="all", contact_radius=50e-6)
    sim = Simulator(helix, helix.curvatures, Material(), GRAVITY, head=sphere, params=params)
    for _ in range(3):
        sim.step()
    system = sim.assemble()
    assert system.problem is not None
    full_inverse = sp.block_diag([whole_inverse(system.factors, s) for s in range(helix.n_strands)]).toarray()
    H = system.H.toarray()
    W_full = H @ full_inverse @ H.T
    W = system.problem.assemble_W().toarray()
    assert np.abs(W - W_full).max() <= 1e-12 * np.abs(W_full).max()
    assert system.problem.H.shape[1] < system.H.shape[1]  # some dofs were left out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_moved_dofs_restricts_H_to_each_strands_leading_dofs_and_drops_immovable_contacts(seed):
    """simulate_linalg.moved_dofs against a dense reference: rows of contacts whose H rows all vanish dropped, strand
    s's columns cut to its largest touched dof + 1 and packed one strand after the other."""
    import scipy.sparse as sp

    from groomtool.simulate_linalg import moved_dofs

    rng = np.random.default_rng(seed)
    sizes = 3 * rng.integers(1, 6, size=5)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    m = 12
    dense = np.zeros((3 * m, offsets[-1]))
    for i in range(m):
        if i % 5 == 3:
            continue  # an immovable contact: no entry
        for strand in rng.choice(5, size=rng.integers(1, 3), replace=False):
            upto = rng.integers(1, sizes[strand] + 1)  # a contact moves a strand's leading dofs
            dense[3 * i:3 * i + 3, offsets[strand]:offsets[strand] + upto] = rng.normal(size=(3, upto))
    dense[3 * 7:3 * 7 + 3] *= 1e-12  # below 1e-9 of the largest: dropped too
    keep, H, k, H_moved = moved_dofs(sp.csr_matrix(dense), offsets)
    want_keep = np.array([np.abs(dense[3 * i:3 * i + 3]).max() > 1e-9 * np.abs(dense).max() for i in range(m)])
    assert keep.tolist() == want_keep.tolist() and not keep[3] and not keep[7]
    rows = dense[np.repeat(keep, 3)]
    assert np.array_equal(H.toarray(), rows)
    want_k = [int(np.max(np.flatnonzero(np.any(rows[:, a:b] != 0, axis=0)), initial=-1)) + 1
              for a, b in zip(offsets[:-1], offsets[1:])]
    assert k.tolist() == want_k
    want = np.hstack([rows[:, a:a + kk] for a, kk in zip(offsets[:-1], want_k)])
    assert np.array_equal(H_moved.toarray(), want)
    assert moved_dofs(sp.csr_matrix(np.zeros((6, offsets[-1]))), offsets) is None


def test_kept_contacts_match_a_fresh_detection_and_save_passes():
    helix, sphere = crossing_strands()
    params = SimulationParams(dt=1 / 240, contacts="all", contact_radius=50e-6)
    kept = Simulator(helix, helix.curvatures, Material(), GRAVITY, head=sphere, params=params)
    fresh = Simulator(helix, helix.curvatures, Material(), GRAVITY, head=sphere,
                      params=SimulationParams(dt=1 / 240, contacts="all", contact_radius=50e-6, detection_skin=0.0))
    for _ in range(40):
        a, b = kept.step(), fresh.step()
        # same physics: the same contacts (strand pairs, distances) and the same motion
        assert len(a.contacts) == len(b.contacts)
        assert keys(a.contacts) == keys(b.contacts)
        order_a = np.lexsort((a.contacts.s_a, a.contacts.strand_b, a.contacts.strand_a))
        order_b = np.lexsort((b.contacts.s_a, b.contacts.strand_b, b.contacts.strand_a))
        assert np.abs(a.contacts.distance[order_a] - b.contacts.distance[order_b]).max() < 1e-6
    assert np.abs(kept.tips() - fresh.tips()).max() < 1e-5
    assert fresh.tracker.reused == 0
    assert kept.tracker.reused > 0 and kept.tracker.passes < fresh.tracker.passes


def test_kept_contacts_at_rest_are_the_detections_own():
    helix, sphere = crossing_strands()
    sim = Simulator(helix, helix.curvatures, Material(), GRAVITY, head=sphere,
                    params=SimulationParams(contacts="all", contact_radius=50e-6))
    first = sim.tracker.initial
    kin = sh.kinematics(sim.helix())
    again = sim.tracker.detect(sim.helix(), kin, 0.0, (0.0, 0.0))
    assert sim.tracker.reused == 1 and sim.tracker.passes == 1
    assert len(again) == len(first) and len(first) >= 2
    for name in ("point_a", "point_b", "normal", "frame", "distance", "s_a"):
        assert np.allclose(getattr(again, name), getattr(first, name), rtol=0, atol=1e-12)


def test_head_contacts_are_detected_again_only_for_the_strands_that_moved():
    """Strand by strand head candidates (simulate_contacts module docstring): after one strand moved by more than
    the skin, only its head contacts are detected again, and every strand's contacts are a fresh detection's."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    n, top, lift = 6, 0.1, 0.05 + 3e-5
    roots, frames = [], []
    for a in np.linspace(0.0, 1.5 * np.pi, 4):  # four strands leaving the top of the sphere, 90 degrees apart
        radial = np.array([np.sin(top) * np.cos(a), np.cos(top), np.sin(top) * np.sin(a)])
        roots.append(lift * radial)
        frames.append(frame([np.cos(top) * np.cos(a), -np.sin(top), np.cos(top) * np.sin(a)], radial))
    curv = np.zeros((4, n, 3))
    curv[:, :, 2] = -1.0 / lift  # bent along the sphere, 10-30 um above its facets
    helix = sh.SuperHelix(np.array(roots), np.array(frames), np.full((4, n), 0.01), curv)
    params = SimulationParams(dt=1 / 240, contacts="head", contact_radius=50e-6)
    sim = Simulator(helix, helix.curvatures, Material(), GRAVITY, head=sphere, params=params)
    tracker = sim.tracker
    first = tracker.initial
    assert set(first.strand_a.tolist()) == {0, 1, 2, 3} and np.all(first.strand_b < 0)
    assert tracker.head_redetections == 4
    moved_curv = curv.copy()
    moved_curv[2, :, 2] -= 0.5  # strand 2 bends in: its tip moves by ~1 mm, far beyond the skin (50 um)
    moved = sh.SuperHelix(helix.root_positions, helix.root_frames, helix.lengths, moved_curv)
    zero = (np.zeros(4), np.zeros(4))
    found = tracker.detect(moved, sh.kinematics(moved), 0.0, zero)
    assert tracker.head_redetections == 5  # strand 2 only
    every_step = SimulationParams(dt=1 / 240, contacts="head", contact_radius=50e-6, detection_skin=0.0)
    fresh_sim = Simulator(moved, moved.curvatures, Material(), GRAVITY, head=sphere, params=every_step)
    fresh = fresh_sim.tracker.initial
    assert found.strand_a.tolist() == fresh.strand_a.tolist()
    for name in ("s_a", "distance", "point_a", "normal"):
        assert np.allclose(getattr(found, name), getattr(fresh, name), rtol=0, atol=1e-9), name
    again = tracker.detect(moved, sh.kinematics(moved), 0.0, zero)  # nothing moved since: kept for every strand
    assert tracker.head_redetections == 5 and len(again) == len(found)


# --------------------------------------------------------------------------- options
def test_simulate_never_modifies_the_params_and_takes_dt_from_them():
    n = 4
    helix = sh.SuperHelix([0.0, 0.0, 0.0], np.eye(3), np.full((1, n), 0.01), np.zeros((1, n, 3)))
    params = SimulationParams(dt=0.01, contacts="none")
    result = simulate(helix, helix.curvatures, Material(), GRAVITY, seconds=0.05, params=params)
    assert result.timings["steps"] == 5 and result.stats["dt"] == 0.01
    result = simulate(helix, helix.curvatures, Material(), GRAVITY, seconds=0.05, params=params, dt=0.025)
    assert result.timings["steps"] == 2
    assert params.dt == 0.01 and params.contacts == "none"
    with pytest.raises(ValueError, match="detection_skin"):
        SimulationParams(detection_skin=-1.0)


def test_progress_estimate_leaves_out_the_first_step_and_estimates_each_run_from_its_own_steps():
    bar = StepProgress([("inverted", 10), ("naive", 10)], enabled=False)
    assert bar.estimate_s() is None
    bar.step(30.0)  # compiling
    assert bar.estimate_s() is None
    for _ in range(3):
        bar.step(0.1)
    assert bar.estimate_s() == pytest.approx(0.1 * 6)  # this run's 6 steps left; the naive run is not guessed
    bar.next_run()
    bar.step(0.2)  # the first step of the second run is left out as well
    assert bar.estimate_s() is None
    bar.step(1.0)  # the naive run's own rate, not the inverted run's
    assert bar.estimate_s() == pytest.approx(1.0 * 8)


def test_progress_estimate_is_not_thrown_by_a_few_slow_early_steps():
    """A sagging groom's second and third steps take several times its later ones: the estimate is the median of the
    measured steps (a mean of 1.0, 0.3, 0.25 s would announce 0.52 s a step)."""
    bar = StepProgress([("naive", 24)], enabled=False)
    for seconds in (30.0, 1.0, 0.3, 0.25):
        bar.step(seconds)
    assert bar.step_time_s() == pytest.approx(0.3)
    assert bar.estimate_s() == pytest.approx(0.3 * 20)
    bar.step(0.2)
    assert bar.step_time_s() == pytest.approx(0.275)  # an even count: the mean of the middle two


def test_progress_announces_each_run_and_names_the_runs_to_come():
    import io

    stream = io.StringIO()
    bar = StepProgress([("inverted", 10), ("naive", 10)], enabled=True, stream=stream)
    for seconds in (5.0, 0.05, 0.05, 0.05):
        bar.step(seconds)
    bar.next_run()
    for seconds in (2.0, 0.5, 0.5, 0.5):
        bar.step(seconds)
    bar.close()
    text = stream.getvalue()
    assert "estimated run time of inverted: ~0.3 s more for 6 steps (50 ms/step); then naive (10 steps)" in text
    assert "estimated run time of naive: ~3.0 s more for 6 steps (500 ms/step)" in text


# --------------------------------------------------------------------------- groom check
def hanging_groom(n=3, length=0.12):
    from groomtool.groom import Groom

    strands = []
    for k in range(n):
        s = np.linspace(0.0, length, 40)
        radius = 0.05 + 0.003 * k
        angle = s / radius
        strands.append(np.stack([radius * np.sin(angle), radius * (np.cos(angle) - 1.0), 0.01 * k + 0 * s], axis=1))
    return Groom.from_strands(strands, up="y", source="hanging")


@pytest.fixture(scope="module")
def inverted_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("inverted")
    invert_groom(hanging_groom(), None, InversionParams(contacts="none")).save(out)
    return out


PER_STRAND = ("strand_young_modulus", "strand_shear_modulus", "stiffness_factor")


def with_arrays(src, dst, drop=PER_STRAND, **extra):
    """A copy of an inversion directory whose rest.npz lacks ``drop`` and carries ``extra`` arrays."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in src.iterdir():
        if f.is_file() and f.name != "rest.npz":
            shutil.copy(f, dst / f.name)
    arrays = {k: v for k, v in np.load(src / "rest.npz", allow_pickle=False).items() if k not in drop}
    arrays.update(extra)
    np.savez(dst / "rest.npz", **arrays)
    return dst


def test_per_strand_materials_are_read_and_used_by_the_inverted_run_only(inverted_dir, tmp_path):
    plain_dir = with_arrays(inverted_dir, tmp_path / "plain")  # a rest.npz written before per-strand materials
    plain = load_inverted(plain_dir)
    assert plain.strand_stiffness is None and plain.stiffness() is None
    E = plain.material.young_modulus
    young = np.array([E, 2.0 * E, E])
    shear = np.array([E / 3.0, 2.0 * E / 3.0, E / 2.0])
    folder = with_arrays(inverted_dir, tmp_path / "stiffened", strand_young_modulus=young, strand_shear_modulus=shear,
                         stiffness_factor=np.array([1.0, 2.0, 1.0]))
    inv = load_inverted(folder)
    I = plain.material.second_moment
    expected = np.stack([shear * 2 * I, young * I, young * I], axis=1)
    assert np.allclose(inv.strand_stiffness, expected, rtol=1e-14)
    K = inv.stiffness()
    assert np.allclose(K[1], inv.helix.lengths[1][:, None] * expected[1], rtol=1e-14)
    assert np.allclose(K[0], sh.stiffness(inv.helix, plain.material.stiffness_diag)[0], rtol=1e-14)

    base = check_groom(plain_dir, seconds=0.05, dt=1 / 120)
    report = check_groom(folder, seconds=0.05, dt=1 / 120)
    assert report["per_strand_materials"] and not base["per_strand_materials"]
    unit = check_groom(with_arrays(inverted_dir, tmp_path / "ones", stiffness_factor=np.ones(3)), seconds=0.05,
                       dt=1 / 120)
    assert not unit["per_strand_materials"]  # factors of one: the scalar material
    assert unit["inverted"]["max_tip_drift_m"] == pytest.approx(base["inverted"]["max_tip_drift_m"], abs=1e-15)
    # the inversion's rest curvatures balance gravity at E: at 2E strand 1 is out of equilibrium and
    # moves; the naive run (scalar material) is unchanged
    assert base["inverted"]["max_tip_drift_m"] < 1e-9
    assert report["inverted"]["max_tip_drift_m"] > 1e-6
    assert report["naive"]["max_tip_drift_m"] == pytest.approx(base["naive"]["max_tip_drift_m"], rel=1e-12)


def test_only_a_stiffness_factor_scales_the_scalar_material(inverted_dir, tmp_path):
    folder = with_arrays(inverted_dir, tmp_path / "factor", stiffness_factor=np.array([1.0, 1.5, 3.0]))
    inv = load_inverted(folder)
    d = inv.material.stiffness_diag
    assert np.allclose(inv.strand_stiffness, np.array([1.0, 1.5, 3.0])[:, None] * d[None, :], rtol=1e-14)
    bad = with_arrays(inverted_dir, tmp_path / "bad", strand_young_modulus=np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="strand_young_modulus"):
        load_inverted(bad)


def test_strand_subset_takes_the_contact_partners(inverted_dir):
    inv = load_inverted(inverted_dir)
    from types import SimpleNamespace

    inv.contact_forces = (SimpleNamespace(strand_a=np.array([0, 1, 2]), s_a=np.zeros(3), strand_b=np.array([1, -1, 2]),
                                          s_b=np.array([0.0, np.nan, 0.05])), np.ones((3, 3)))
    for seed in range(6):
        chosen, simulated = choose_strands(inv, 1, seed=seed)
        assert len(chosen) == 1
        expected = {0, 1} if chosen[0] in (0, 1) else {2}
        assert set(simulated.tolist()) == expected
    sub = inv.subset(np.array([0, 1]))
    assert sub.helix.n_strands == 2 and len(sub.contact_forces[1]) == 2
    assert sub.contact_forces[0].strand_b.tolist() == [1, -1]


def test_check_command_with_a_subset(inverted_dir, capsys):
    from test_check import parser  # noqa: F401 - same CLI wiring

    from groomtool.cli import simulate_cmd

    args = parser().parse_args(["check", str(inverted_dir), "--strands", "2", "--seed", "1", "--seconds", "0.02",
                                "--dt", "0.01"])
    assert simulate_cmd.cmd_check(args) == 0
    out = capsys.readouterr().out
    assert "2 of 3 strands" in out and "contact solves failed" in out
    report = json.loads((inverted_dir / "check.json").read_text())
    assert report["subset"]["checked"] == 2 and len(report["subset"]["checked_strands"]) == 2
    # unstable strands among the simulated partners but none among the checked: said so, no crash
    from groomtool.check import summary

    report["unstable_in_isolation"] = 1
    report["inverted"]["max_tip_drift_unstable_strands_m"] = None
    assert f"1 of the {report['strands']} simulated strands are unstable" in summary(report)
    assert "none of them is among the checked strands" in summary(report)
    # a failed solve is explained with the tolerance and the budget it missed (check.json's contact_solve)
    assert report["contact_solve"] == {"tolerance": 1e-6, "max_sweeps": 500}
    report["naive"]["solver"].update(failures=2, failed_steps=[3, 5], worst_failed_residual=3e-6)
    text = summary(report)
    assert "naive: 2 of" in text and "steps 3, 5" in text
    assert "did not reach residual 1e-06 in 500 sweeps" in text


# --------------------------------------------------------------------------- mass matrix assembly
def batched_mass_reference(helix, inertia, order=4):
    """dynamics.mass_matrix as first written: the blocks assembled with batched dense products and masks."""

    kin = sh.kinematics(helix)
    pts = ref.element_points(helix, kin, order)
    S, N = helix.lengths.shape
    rhoS = inertia.linear
    II = ref.world_inertia(pts, inertia)
    w = pts.w[..., None, None]
    B, Theta = ref._upstream_blocks(helix, kin)
    m0 = ref._suffix_beyond(helix.lengths)[..., None, None]
    m1 = ref._suffix_beyond(np.einsum("snq,snqa->sna", pts.w, pts.x))
    m2 = ref._suffix_beyond(np.einsum("snq,snqa,snqb->snab", pts.w, pts.x, pts.x))
    IId = ref._suffix_beyond(np.sum(w * II, axis=2))
    E = np.sum(w * pts.J_own, axis=2)
    G = np.sum(w * (sh.skew(pts.x) @ pts.J_own), axis=2)
    Gr = np.sum(w * (II @ pts.Jw_own), axis=2)
    own = rhoS * np.sum(w * (np.swapaxes(pts.J_own, -1, -2) @ pts.J_own), axis=2)
    own += np.sum(w * (np.swapaxes(pts.Jw_own, -1, -2) @ II @ pts.Jw_own), axis=2)
    m1x = sh.skew(m1)
    tr = np.trace(m2, axis1=-2, axis2=-1)[..., None, None]
    down_top = rhoS * (m0 * B - m1x @ Theta)
    down_bottom = rhoS * (m1x @ B + (tr * np.eye(3) - m2) @ Theta) + IId @ Theta
    left = np.concatenate([np.swapaxes(B, -1, -2), np.swapaxes(Theta, -1, -2)], axis=-1)
    right = np.concatenate([down_top + rhoS * E, down_bottom + rhoS * G + Gr], axis=-2)
    right_down = np.concatenate([down_top, down_bottom], axis=-2)
    full = left.reshape(S, 3 * N, 6) @ right.transpose(0, 2, 1, 3).reshape(S, 6, 3 * N)
    blk = np.arange(3 * N) // 3
    M = full * (blk[:, None] < blk[None, :])
    M = M + np.swapaxes(M, -1, -2)
    diag = left @ right_down + own
    idx = np.arange(N)
    Mb = M.reshape(S, N, 3, N, 3)
    Mb[:, idx, :, idx, :] = diag.transpose(1, 0, 2, 3)
    mask = np.repeat(helix.element_mask, 3, axis=1)
    return M * (mask[:, :, None] & mask[:, None, :])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 9), scale=st.floats(0.0, 60.0))
def test_mass_matrix_kernel_matches_the_batched_assembly(seed, n, scale):
    from groomtool.rods import dynamics as dyn

    rng = np.random.default_rng(seed)
    helix = random_strands(rng, 3, n, scale, (0.002, 0.03))
    inertia = dyn.Inertia.from_material(Material())
    M = dyn.mass_matrix(helix, inertia)
    ref = batched_mass_reference(helix, inertia)
    assert np.abs(M - ref).max() <= 1e-10 * np.abs(ref).max()
    assert np.abs(M - np.swapaxes(M, -1, -2)).max() <= 1e-12 * np.abs(M).max()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 9), scale=st.floats(0.0, 60.0), moving=st.booleans())
def test_inertia_kernel_matches_the_numpy_quadrature(seed, n, scale, moving):
    """The compiled one-pass M and A against the vectorised numpy version over every Gauss point."""
    from groomtool.rods import dynamics as dyn

    rng = np.random.default_rng(seed)
    helix = random_strands(rng, 3, n, scale, (0.002, 0.03))
    inertia = dyn.Inertia(0.01, (3e-3, 1e-3, 2e-3))
    rates = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    motion = None
    if moving:
        motion = {key: rng.normal(size=(helix.n_strands, 3)) for key in ("root_velocity", "root_angular_velocity",
                                                            "root_acceleration", "root_angular_acceleration")}
    M, A = dyn.inertia_terms(helix, inertia, rates=rates, order=5, root_motion=motion)
    M_ref = ref.mass_matrix_numpy(helix, inertia, order=5)
    A_ref = ref.velocity_terms_numpy(helix, rates, inertia, order=5, root_motion=motion)
    assert np.abs(M - M_ref).max() <= 1e-10 * np.abs(M_ref).max()
    assert np.abs(A - A_ref).max() <= 1e-10 * max(np.abs(A_ref).max(), 1e-300)
    assert np.array_equal(dyn.mass_matrix(helix, inertia, order=5), M)
    assert np.array_equal(dyn.velocity_terms(helix, rates, inertia, order=5, root_motion=motion), A)
    speeds = np.linalg.norm(ref.node_motion(helix, rates).V, axis=-1).max(axis=1)  # per strand, over its nodes
    np.testing.assert_allclose(dyn.strand_node_speeds(helix, rates), speeds, rtol=1e-12, atol=1e-300)


def test_subset_of_touching_strands_starts_in_equilibrium(tmp_path):
    """Three strands side by side (axes 90 um apart, r_c = 50 um) inverted with their contacts: a subset
    of an outer strand and its partner keeps the left-out strand's forces and stays put."""
    from groomtool.groom import Groom

    strands = []
    for k in range(3):
        s = np.linspace(0.0, 0.1, 40)
        angle = s / 0.05
        strands.append(np.stack([0.05 * np.sin(angle), 0.05 * (np.cos(angle) - 1.0), 9e-5 * k + 0 * s], axis=1))
    groom = Groom.from_strands(strands, up="y", source="touching")
    invert_groom(groom, None, InversionParams(contacts="all", contact_radius=50e-6)).save(tmp_path)
    inv = load_inverted(tmp_path)
    assert inv.contact_forces is not None and np.any(inv.contact_forces[1][:, 0] > 0)
    seed = next(k for k in range(50) if len(choose_strands(inv, 1, seed=k)[1]) == 2)
    chosen, simulated = choose_strands(inv, 1, seed=seed)
    assert chosen[0] in (0, 2) and 1 in simulated
    sub = inv.subset(simulated)
    assert sub.boundary_force is not None and np.abs(sub.boundary_force).max() > 0
    report = check_groom(tmp_path, seconds=0.02, dt=1 / 240, strands=1, seed=seed)
    assert report["subset"]["simulated_with_partners"] == 2
    assert report["inverted"]["max_tip_drift_m"] < 1e-9
    assert report["inverted"]["solver"]["failures"] == 0


def test_speculative_margins_are_per_strand():
    """A fast strand widens only its own pairs' thresholds: 2 r_c + m_a + m_b (strand/strand), r_c + m_a
    (head), each m = min(cap, 1.5 h |v|max of the strand)."""
    from groomtool.contact import Contacts
    from groomtool.simulate_contacts import ContactTracker, contact_thresholds

    params = SimulationParams(dt=0.01)
    rc = 1e-4
    tracker = ContactTracker(params, rc, None, None, np.ones((3, 2)), np.ones((3, 2), bool))
    m_h, m_s = tracker.margins(np.array([0.0, 0.001, 10.0]))  # at rest, slow, fast (capped)
    np.testing.assert_allclose(m_s, [0.0, 1.5e-5, 2 * rc])
    np.testing.assert_allclose(m_h, [0.0, 1.5e-5, 100 * rc])
    n = 4
    z = np.zeros((n, 3))
    contacts = Contacts(np.array([0, 0, 1, 2]), np.zeros(n), np.array([1, -1, 2, -1]), np.zeros(n), z, z, z,
                        np.zeros((n, 3, 3)), np.zeros(n), rc)
    np.testing.assert_allclose(contact_thresholds(contacts, rc, (m_h, m_s)),
                               [2 * rc + 1.5e-5, rc, 2 * rc + 1.5e-5 + 2 * rc, rc + 100 * rc])
    # one number for all strands (the previous form) still works
    np.testing.assert_allclose(contact_thresholds(contacts, rc, (1e-5, 2e-5)), [2 * rc + 4e-5, rc + 1e-5,
                                                                                2 * rc + 4e-5, rc + 1e-5])
