"""The mass matrix's and the step matrix's semiseparable generators (dynamics.MassGenerators,
simulate_linalg.factor_step_generators) against dense references: the numpy quadrature of M, the dense dF/dq, the
dense Cholesky factors and solves of factor_step_matrix."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groomtool.material import Material
from groomtool.rods import dynamics as dyn
from groomtool.rods import superhelix as sh
from groomtool.simulate_linalg import (StepCorrections, StrandFactors, factor_step_generators, factor_step_matrix,
                                       gravity_jacobian_left, mass_apply)
from reference import dynamics as ref
from test_simulate import GRAVITY, frame


def random_strands(rng, S, n, scale, length_range, counts=None):
    counts = rng.integers(1, n + 1, size=S) if counts is None else np.asarray(counts)
    lengths = rng.uniform(*length_range, size=(S, n)) * (np.arange(n)[None, :] < counts[:, None])
    q = rng.normal(size=(S, n, 3)) * scale * (lengths > 0)[..., None]
    frames = np.stack([frame(rng.normal(size=3), rng.normal(size=3)) for _ in range(S)])
    return sh.SuperHelix(rng.normal(size=(S, 3)) * 0.05, frames, lengths, q, counts)


def dense_from_generators(diag, later, earlier, n):
    """The symmetric matrix with blocks diag_j and later_k^T earlier_j (k > j), by numpy blocks."""
    out = np.zeros((3 * n, 3 * n))
    for k in range(n):
        out[3 * k:3 * k + 3, 3 * k:3 * k + 3] = diag[k]
        for j in range(k):
            blk = later[k].T @ earlier[j]
            out[3 * k:3 * k + 3, 3 * j:3 * j + 3] = blk
            out[3 * j:3 * j + 3, 3 * k:3 * k + 3] = blk.T
    return out


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 12), scale=st.floats(0.0, 80.0),
       rot_scale=st.sampled_from([1.0, 10.0, 1e3]), short=st.booleans())
def test_mass_generators_rebuild_the_quadrature_mass_matrix(seed, n, scale, rot_scale, short):
    """M_kj = later_k^T earlier_j (k > j), M_jj = diag_j: the numpy quadrature's M to 1e-10 relative; the dense
    mass_matrix is the generators' (bit for bit), a moving root and rates leave them as they are, and M x from the
    generators is M's product."""
    rng = np.random.default_rng(seed)
    helix = random_strands(rng, 3, n, scale, (0.0005, 0.004) if short else (0.004, 0.04))
    inertia = dyn.Inertia.from_material(Material(), rot_scale)
    gens, _ = dyn.inertia_generators(helix, inertia, order=5)
    M_ref = ref.mass_matrix_numpy(helix, inertia, order=5)
    for s in range(helix.n_strands):
        m = int(helix.n_elements[s])
        got = dense_from_generators(gens.diag[s], gens.later[s], gens.earlier[s], m)
        want = M_ref[s, :3 * m, :3 * m]
        assert np.abs(got - want).max() <= 1e-10 * np.abs(want).max()
    M = dyn.mass_matrix(helix, inertia, order=5)
    assert np.array_equal(gens.dense(helix.n_elements), M)
    # a moving root changes A only: the generators of the pass that also computes A are the same
    motion = {key: rng.normal(size=(helix.n_strands, 3)) for key in ("root_velocity", "root_angular_velocity",
                                                                      "root_acceleration", "root_angular_acceleration")}
    rates = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    moving, A = dyn.inertia_generators(helix, inertia, rates=rates, order=5, root_motion=motion)
    for a, b in zip((moving.diag, moving.later, moving.earlier), (gens.diag, gens.later, gens.earlier)):
        assert np.array_equal(a, b)
    assert np.array_equal(A, dyn.velocity_terms(helix, rates, inertia, order=5, root_motion=motion))
    x = rng.normal(size=helix.curvatures.shape) * helix.element_mask[..., None]
    Mx = np.einsum("sij,sj->si", M, x.reshape(helix.n_strands, -1)).reshape(x.shape)
    assert np.abs(mass_apply(gens, x, helix.n_elements) - Mx).max() <= 1e-12 * np.abs(Mx).max()


def step_parts(helix, rot_scale=1.0):
    mat = Material()
    inertia = dyn.Inertia.from_material(mat, rot_scale)
    kin = sh.kinematics(helix)
    gens, _ = dyn.inertia_generators(helix, inertia, kin)
    parts = sh.gravity_force_jacobian_parts(helix, mat.linear_density, GRAVITY, kin)
    dense_jac = sh.gravity_force_jacobian(helix, mat.linear_density, GRAVITY, kin)
    K = sh.stiffness(helix, mat.stiffness_diag)
    return mat, gens, parts, dense_jac, K


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30), scale=st.floats(0.0, 60.0),
       rot_scale=st.sampled_from([1.0, 100.0]), dt=st.sampled_from([1 / 240, 1 / 24]),
       gravity=st.sampled_from([0.0, 1.0]), damping=st.booleans())
def test_structured_step_factor_is_the_dense_one(seed, n, scale, rot_scale, dt, gravity, damping):
    """factor_step_generators (no dense M) gives the dense factor_step_matrix's factors of a M + k K + b dF/dq to
    1e-10 relative (P L L^T P is Mhat: the dense dF/dq), its solves, products and leading inverses; a strand whose
    step matrix needs an unstable-mode correction takes the dense path, the same as factor_step_matrix's."""
    rng = np.random.default_rng(seed)
    helix = random_strands(rng, 4, n, scale, (0.005, 0.05))
    mat, gens, parts, dense_jac, K = step_parts(helix, rot_scale)
    counts = helix.n_elements
    M = gens.dense(counts)
    kw = dict(stiffness=K, a_scale=1.0 + (0.3 * dt if damping else 0.0), k_scale=dt * dt + (1e-3 * dt if damping else 0),
              b_scale=-dt * dt * gravity)
    ref_f, ref_mod = factor_step_matrix(M, dense_jac, counts, **kw)
    got = StrandFactors(counts)
    mod = factor_step_generators(gens, parts, gravity_jacobian_left(mat.linear_density, GRAVITY), counts, out=got,
                                 dense_below=0, **kw)
    assert mod == ref_mod
    assert np.array_equal(got.structured, ~ref_f.corrected)
    S, n_pad = len(counts), M.shape[1]
    Kd = K.reshape(S, -1)
    for s in range(S):
        m = 3 * int(counts[s])
        mhat = kw["a_scale"] * M[s, :m, :m] + np.diag(kw["k_scale"] * Kd[s, :m]) + kw["b_scale"] * dense_jac[s, :m, :m]
        L_ref, L_got = ref_f.factor(s), got.factor(s)
        assert np.abs(L_got - L_ref).max() <= 1e-10 * np.abs(L_ref).max()
        if got.structured[s]:
            F = L_got[::-1, ::-1]
            assert np.abs(F @ F.T - mhat).max() <= 1e-10 * np.abs(mhat).max()
        k = int(rng.integers(1, m + 1))
        lead = ref_f.leading_inverse(s, k)
        assert np.abs(got.leading_inverse(s, k) - lead).max() <= 1e-10 * np.abs(lead).max()
    mask = np.repeat(helix.element_mask, 3, axis=1)
    rhs = rng.normal(size=(S, n_pad)) * mask
    rhs[0, n_pad // 2:] = 0.0  # zero towards the tip: the forward solve starts at its first non-zero
    x_ref = ref_f.solve(rhs)
    assert np.abs(got.solve(rhs) - x_ref).max() <= 1e-10 * np.abs(x_ref).max()
    y_ref = ref_f.apply(rhs)
    assert np.abs(got.apply(rhs) - y_ref).max() <= 1e-10 * np.abs(y_ref).max()


def test_unstable_strands_take_the_dense_path_with_their_kept_corrections():
    """Long floppy strands at dt = 1/24 s need the unstable-mode correction: the generators' path
    sends them to the dense one (modified counted, corrections kept as factor_step_matrix keeps them), the stable
    ones stay structured; a mixed dense_below sends the short ones dense too."""
    rng = np.random.default_rng(5)
    helix = random_strands(rng, 6, 20, 5.0, (0.01, 0.03), counts=[20, 3, 20, 8, 15, 2])
    mat, gens, parts, dense_jac, K = step_parts(helix)
    counts = helix.n_elements
    M = gens.dense(counts)
    kw = dict(stiffness=K, k_scale=(1 / 24) ** 2, b_scale=-(1 / 24) ** 2)  # 1/24 s: 4 of the 6 need a correction
    corr_ref, corr_got = StepCorrections(6), StepCorrections(6)
    ref_f, ref_mod = factor_step_matrix(M, dense_jac, counts, corr_ref, **kw)
    assert 0 < ref_mod < 6
    got = StrandFactors(counts)
    left = gravity_jacobian_left(mat.linear_density, GRAVITY)
    mod = factor_step_generators(gens, parts, left, counts, corr_got, out=got, dense_below=3, **kw)
    assert mod == ref_mod
    assert np.array_equal(got.structured, ~ref_f.corrected & (counts >= 3))
    assert got.structured.any() and not got.structured.all()
    for s in range(6):
        assert np.abs(got.factor(s) - ref_f.factor(s)).max() <= 1e-10 * np.abs(ref_f.factor(s)).max()
        if ref_f.corrected[s]:
            assert np.abs(corr_got.get(s) - corr_ref.get(s)).max() <= 1e-10 * np.abs(corr_ref.get(s)).max()
    # again: the kept corrections serve (no new eigendecomposition needed), the same factors
    again = StrandFactors(counts)
    assert factor_step_generators(gens, parts, left, counts, corr_got, out=again, dense_below=3, **kw) == ref_mod
    for s in range(6):
        assert np.abs(again.factor(s) - ref_f.factor(s)).max() <= 1e-10 * np.abs(ref_f.factor(s)).max()


@pytest.mark.parametrize("first", [0, 2])
def test_generators_fill_a_range_of_the_groom_factors(first):
    """A chunk of strands factorised into a StrandFactors of the whole groom (first, as the simulator's chunks and
    partial assemblies): the other strands' factors untouched."""
    rng = np.random.default_rng(11)
    helix = random_strands(rng, 5, 9, 10.0, (0.005, 0.03))
    mat, gens, parts, dense_jac, K = step_parts(helix)
    counts = helix.n_elements
    kw = dict(stiffness=K, k_scale=1e-5, b_scale=-1e-5)
    whole, _ = factor_step_matrix(gens.dense(counts), dense_jac, counts, **kw)
    out = StrandFactors(counts)
    before = [out.factor(s).copy() for s in range(5)]
    sub = helix.subset(np.arange(first, first + 3))
    g_sub, _ = dyn.inertia_generators(sub, dyn.Inertia.from_material(mat))
    p_sub = sh.gravity_force_jacobian_parts(sub, mat.linear_density, GRAVITY, sh.kinematics(sub))
    factor_step_generators(g_sub, p_sub, gravity_jacobian_left(mat.linear_density, GRAVITY), counts[first:first + 3],
                           out=out, first=first, stiffness=K[first:first + 3, :sub.max_elements], k_scale=1e-5,
                           b_scale=-1e-5, dense_below=0)
    for s in range(5):
        if first <= s < first + 3:
            assert np.abs(out.factor(s) - whole.factor(s)).max() <= 1e-10 * np.abs(whole.factor(s)).max()
        else:
            assert np.array_equal(out.factor(s), before[s])
