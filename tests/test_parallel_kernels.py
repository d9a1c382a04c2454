"""The compiled per-strand loops that run in parallel (numba prange over strands or points) give the same bits on one
thread and on two: each strand writes only its own outputs, nothing is summed across strands.  Every parallel kernel
is run through its public caller with numba.set_num_threads(1) and (2), and the outputs compared with
np.array_equal (skipped where numba has fewer than 2 threads: NUMBA_NUM_THREADS=1)."""

import numba
import numpy as np
import pytest

from groomtool.material import Material
from groomtool.rods import dynamics as dyn
from groomtool.rods import superhelix as sh
from groomtool.simulate_linalg import (StepCorrections, StrandFactors, factor_step_generators, gravity_jacobian_left,
                                       mass_apply)

GRAVITY = np.array([0.0, -9.81, 0.0])
DT = 1 / 24  # long, rising strands at a long step: many need the unstable-mode correction (the dense path)

pytestmark = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba has a single thread")


def strands(S: int = 37, N: int = 14, seed: int = 0) -> sh.SuperHelix:
    """S strands of 1 to N elements, half of them rising (unstable under gravity), the others hanging: more strands
    than STRANDS_PER_TASK, so several tasks."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, N + 1, size=S)
    counts[0] = N
    lengths = rng.uniform(0.005, 0.03, size=(S, N)) * (np.arange(N)[None, :] < counts[:, None])
    q = rng.normal(size=(S, N, 3)) * 8.0 * (lengths > 0)[..., None]
    down = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    frames = np.where((np.arange(S) % 2 == 0)[:, None, None], down, -down)
    return sh.SuperHelix(rng.normal(size=(S, 3)) * 0.05, frames, lengths, q, counts)


def on_threads(fn, n: int):
    """fn() with numba on n threads (the previous count restored)."""
    before = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        return fn()
    finally:
        numba.set_num_threads(before)


def assert_same_bits(fn):
    """fn() -> a list of arrays: bit for bit the same on one thread and on two."""
    one, two = on_threads(fn, 1), on_threads(fn, 2)
    assert len(one) == len(two) > 0
    for a, b in zip(one, two):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


def test_superhelix_kernels_give_the_same_bits_on_any_thread_count():
    """evaluate_positions (_position_kernel, more points than POINTS_PER_TASK), with the kinematics and gravity terms
    the step computes beside it (serial kernels)."""
    helix = strands()
    rng = np.random.default_rng(1)
    n_points = 3 * sh.POINTS_PER_TASK + 7
    which = rng.integers(0, helix.n_strands, n_points)
    s = rng.uniform(0.0, 1.0, n_points) * helix.lengths[which].sum(axis=1)

    def run():
        kin = sh.kinematics(helix)
        parts = sh.gravity_force_jacobian_parts(helix, 0.07, GRAVITY, kin)
        return [kin.z, kin.c, kin.dc, kin.Q, kin.p, kin.P, kin.D, kin.DP, kin.C, kin.R, kin.Theta,
                sh.gravity_force(helix, 0.07, GRAVITY, kin), *parts, sh.evaluate_positions(helix, which, s, kin)]

    assert_same_bits(run)


def test_inertia_kernels_give_the_same_bits_on_any_thread_count():
    """inertia_generators (_inertia_kernel: the mass generators and A, with a moving root) and the dense M from the
    generators (_dense_from_generators)."""
    helix = strands()
    inertia = dyn.Inertia.from_material(Material())
    rng = np.random.default_rng(2)
    rates = rng.normal(size=helix.curvatures.shape)
    root = {"root_angular_velocity": rng.normal(size=3), "root_acceleration": rng.normal(size=(helix.n_strands, 3)),
            "root_angular_acceleration": rng.normal(size=3)}

    def run():
        kin = sh.kinematics(helix)
        gens, A = dyn.inertia_generators(helix, inertia, kin, rates=rates, root_motion=root)
        _, A_still = dyn.inertia_generators(helix, inertia, kin, rates=rates, mass=False)
        return [gens.diag, gens.later, gens.earlier, A, A_still, gens.dense(helix.n_elements)]

    assert_same_bits(run)


def test_step_matrix_kernels_give_the_same_bits_on_any_thread_count():
    """factor_step_generators twice (fresh corrections, then kept ones: the dense path's _factor_kernel beside the
    serial structured factors), then StrandFactors.solve (_solve_kernel, with zero and tip-zero right-hand sides),
    apply and mass_apply."""
    helix = strands()
    mat = Material()
    inertia = dyn.Inertia.from_material(mat)
    counts = helix.n_elements
    S, N = helix.curvatures.shape[:2]
    rng = np.random.default_rng(3)
    rhs = rng.normal(size=(S, 3 * N)) * (np.arange(3 * N)[None, :] < 3 * counts[:, None])
    rhs[1] = 0.0
    rhs[2, :3] = 0.0  # a right-hand side zero on the first element (the tip end once reversed: a shorter solve)
    x = rng.normal(size=(S, N, 3))

    def run():
        kin = sh.kinematics(helix)
        gens, _ = dyn.inertia_generators(helix, inertia, kin)
        parts = sh.gravity_force_jacobian_parts(helix, mat.linear_density, GRAVITY, kin)
        K = sh.stiffness(helix, mat.stiffness_diag)
        left = gravity_jacobian_left(mat.linear_density, GRAVITY)
        out, corr = StrandFactors(counts), StepCorrections(S)
        kw = dict(stiffness=K, k_scale=DT * DT, b_scale=-DT * DT, out=out, dense_below=0)
        fresh = factor_step_generators(gens, parts, left, counts, corr, **kw)
        first = [out.data.copy(), out.L3.copy(), out.W.copy(), out.structured.copy(), out.corrected.copy()]
        kept = factor_step_generators(gens, parts, left, counts, corr, **kw)
        assert fresh > 0 and not out.structured.all() and out.structured.any()
        return first + [np.array([fresh, kept]), out.data, out.L3, out.W, out.V, out.structured, out.corrected,
                        out.solve(rhs), out.apply(rhs), mass_apply(gens, x, counts)]

    assert_same_bits(run)


@pytest.mark.parametrize("command", [["invert", "groom.obj"], ["check", "out"], ["simulate", "out"]])
def test_threads_option_sets_numbas_thread_count(command):
    """--threads N calls numba.set_num_threads(N) (1 to NUMBA_NUM_THREADS, else a user error); no --threads leaves
    numba's count; groom batch has no --threads (one thread per worker)."""
    from groomtool.cli.main import build_parser
    from groomtool.cli.options import UserError, set_threads

    parser = build_parser()
    before = numba.get_num_threads()
    try:
        set_threads(parser.parse_args(command + ["--threads", "1"]))
        assert numba.get_num_threads() == 1
        set_threads(parser.parse_args(command))
        assert numba.get_num_threads() == 1
        set_threads(parser.parse_args(command + ["--threads", "2"]))
        assert numba.get_num_threads() == 2
        for bad in (0, numba.config.NUMBA_NUM_THREADS + 1):
            with pytest.raises(UserError, match="--threads must be 1 to"):
                set_threads(parser.parse_args(command + ["--threads", str(bad)]))
    finally:
        numba.set_num_threads(before)
    with pytest.raises(SystemExit):
        parser.parse_args(["batch", "groom.obj", "--threads", "1"])
