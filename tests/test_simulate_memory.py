"""The simulator's memory layout (issue 15): packed step-matrix factors, unstable-mode corrections in exact-size
arenas (no buffer of the whole groom that doubles), and what a step at rest keeps."""

import numpy as np

from groomtool.material import Material
from groomtool.rods import superhelix as sh
from groomtool.simulate import SimulationParams, Simulator, simulate
from groomtool.simulate_linalg import (StepCorrections, StrandFactors, _corrections_apply, factor_step_matrix,
                                       packed_size)

GRAVITY = np.array([0.0, -9.81, 0.0])


def unstable_strands(rng, sizes, n_pad):
    """(A, B) padded (S, n_pad, n_pad): A SPD, B strongly indefinite (every strand needs a correction)."""
    S = len(sizes)
    A = np.zeros((S, n_pad, n_pad))
    B = np.zeros((S, n_pad, n_pad))
    for s, n in enumerate(sizes):
        X = rng.normal(size=(n, n))
        A[s, :n, :n] = X @ X.T + n * np.eye(n)
        Y = rng.normal(size=(n, n))
        B[s, :n, :n] = -2.0 * n * (Y + Y.T) / 2.0
    return A, B


def test_packed_factors_solve_apply_and_inverse_like_dense_ones():
    """StrandFactors keeps the lower triangles only (sum n (n + 1) / 2): factor() unpacks them, set_factor packs, and
    solve, apply and leading_inverse are those of the dense P L L^T P."""
    rng = np.random.default_rng(1)
    n_el = np.array([3, 1, 5, 4])
    f = StrandFactors(n_el)
    assert len(f.data) == int(np.sum(packed_size(3 * n_el)))
    dense = []
    for s, n in enumerate(3 * n_el):
        X = rng.normal(size=(n, n))
        L = np.linalg.cholesky(X @ X.T + n * np.eye(n))
        f.set_factor(s, L + np.triu(rng.normal(size=(n, n)), 1))  # above the diagonal ignored
        np.testing.assert_array_equal(f.factor(s), L)
        dense.append(L[::-1, ::-1] @ L[::-1, ::-1].T)  # Mhat = P L L^T P
    x = rng.normal(size=(len(n_el), 15))
    y, z = f.solve(x), f.apply(x)
    for s, (n, M) in enumerate(zip(3 * n_el, dense)):
        np.testing.assert_allclose(y[s, :n], np.linalg.solve(M, x[s, :n]), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(z[s, :n], M @ x[s, :n], rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(y[s, n:], x[s, n:])
        for k in (1, n // 2, n):
            np.testing.assert_allclose(f.leading_inverse(s, k), np.linalg.inv(M)[:k, :k], rtol=1e-10, atol=1e-14)
    # right-hand sides on the leading dofs only (H^T r up to a strand's farthest contact), and zero ones: the solve
    # skips the zeros towards the tip (or the whole strand) with the same result
    lead = x.copy()
    lead[:, 4:] = 0.0
    lead[2] = 0.0
    y = f.solve(lead)
    for s, (n, M) in enumerate(zip(3 * n_el, dense)):
        np.testing.assert_allclose(y[s, :n], np.linalg.solve(M, lead[s, :n]), rtol=1e-12, atol=1e-14)
    assert np.all(y[2] == 0.0)


def test_corrections_are_kept_in_exact_arenas_per_call_and_regrouped_by_range():
    """Each factor_step_matrix call with new corrected strands adds one arena of exactly their packed size (the
    range's kept ones moved into it); a strand corrected again is overwritten in place; arenas left empty are
    released; get() gives the symmetric C."""
    rng = np.random.default_rng(2)
    n_el = np.array([2, 4, 3, 4, 2, 3])
    A, B = unstable_strands(rng, 3 * n_el, 12)
    corr = StepCorrections(len(n_el))
    out = StrandFactors(n_el)
    for a, b in ((0, 3), (3, 6)):  # the simulator's chunks
        _, modified = factor_step_matrix(A[a:b], B[a:b], n_el[a:b], corr, out=out, first=a)
        assert modified == b - a
    live = int(np.sum(packed_size(3 * n_el)))
    assert corr.nbytes() == 8 * live and sum(a is not None for a in corr.arenas) == 2
    kept = [corr.get(s) for s in range(len(n_el))]
    for C in kept:
        assert np.array_equal(C, C.T)
    # a range's strands decomposed anew: in place, no new arena
    factor_step_matrix(A[3:6], 3.0 * B[3:6], n_el[3:6], corr, out=out, first=3)
    assert corr.nbytes() == 8 * live and len(corr.arenas) == 2
    assert not np.array_equal(corr.get(4), kept[4]) and np.array_equal(corr.get(0), kept[0])
    # a call over a range spanning both arenas: regrouped into one, the old ones released
    factor_step_matrix(A, B, n_el, corr, out=out)
    assert corr.nbytes() == 8 * live and sum(a is not None for a in corr.arenas) == 1
    for s in (0, 1, 2):
        np.testing.assert_array_equal(corr.get(s), kept[s])
    # the packed C applied like the dense one (bit for bit: the same order of summation)
    x = rng.normal(size=(len(n_el), 12))
    got = np.zeros_like(x)
    for data, start in corr.by_arena():
        _corrections_apply(data, start, corr.size, np.ones(len(n_el), bool), x, got)
    for s, n in enumerate(3 * n_el):
        C = corr.get(s)
        want = np.array([sum(C[i, k] * x[s, k] for k in range(n)) for i in range(n)])
        np.testing.assert_array_equal(got[s, :n], want)


def test_a_step_at_rest_keeps_no_geometry_and_simulate_holds_no_old_system():
    """The kept assembly (AtRestSystem) holds factors, contacts and H but not the assembly's helix, kinematics or
    free rates; a run with reuse on has the tips of one without to round-off."""
    n = 6
    roots = np.zeros((2, 3))
    roots[1, 0] = 0.01
    frames = np.repeat(np.eye(3)[None], 2, axis=0)
    rng = np.random.default_rng(0)
    helix = sh.SuperHelix(roots, frames, np.full((2, n), 0.02), 0.3 * rng.normal(size=(2, n, 3)))
    material = Material(young_modulus=1e7)
    params = SimulationParams(contacts="none", reuse_rotation=1e-7)
    sim = Simulator(helix, helix.curvatures, material, np.zeros(3), params=params)
    sim.step()
    sim.step()
    assert sim.reused_steps == 1
    kept = sim._at_rest.system
    assert kept.kin is None and kept.helix is None and kept.v_free is None and kept.factors is sim._factors
    res = simulate(helix, helix.curvatures, material, GRAVITY, seconds=5 / 240, params=params)
    ref = simulate(helix, helix.curvatures, material, GRAVITY, seconds=5 / 240,
                   params=SimulationParams(contacts="none", reuse_rotation=0.0))
    np.testing.assert_allclose(res.tips, ref.tips, rtol=0, atol=1e-12)
