"""The step matrix per strand size: dense (M formed, O(N^2), LAPACK Cholesky, O(N^3)) against block semiseparable
(simulate_linalg.factor_step_generators: generators in O(N), factor in O(N r^2)), M v, the solves and the leading
blocks of Mhat^-1 the contact problem needs (StrandFactors.leading_inverse).

Strands of 8 cm in N = 10..96 elements, hanging down, gently curved (curvature ~ 5 1/m), at dt = 1/240 s with implicit gravity:
their step matrices need no unstable-mode correction (both paths then do the same work as in the simulator).  CPU
time (time.process_time) per strand, best of ``--repeat`` rounds of ``--strands`` strands, one BLAS thread.

    python bench/bench_step_matrix.py [--sizes 10 16 24 32 43 64 96] [--strands 200] [--repeat 3]
    python bench/bench_step_matrix.py --corrected   (rising strands of 30 cm: most on a correction)

Whole runs (``--whole DIR RUN STEPS``, RUN inverted or naive): a Simulator on an inversion directory with groom
check's parameters (as check.py builds it), every strand dense (simulate_linalg.DENSE_BELOW = 1e9) then structured
(0), each in its own process: CPU, the median later step, the simulator's stage timings per later step, drift and
peak RSS, one JSON line each.

    python bench/bench_step_matrix.py --whole /tmp/big/haro naive 6
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from groomtool.material import Material  # noqa: E402
from groomtool.rods import dynamics as dyn  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402
from groomtool.simulate_linalg import (StepCorrections, StrandFactors, factor_step_generators, factor_step_matrix,  # noqa: E402
                                       gravity_jacobian_left, mass_apply)

GRAVITY = np.array([0.0, -9.81, 0.0])
DT = 1 / 240


def strands(S: int, N: int, seed: int = 0, corrected: bool = False) -> sh.SuperHelix:
    """Hanging strands of 8 cm (none needs a correction), or with ``corrected`` rising strands of 30 cm (most do)."""
    rng = np.random.default_rng(seed)
    lengths = np.full((S, N), (0.3 if corrected else 0.08) / N)
    q = rng.normal(size=(S, N, 3)) * 5.0
    down = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the tangent (first column) along -y
    frames = np.repeat((-down if corrected else down)[None], S, axis=0)
    return sh.SuperHelix(rng.normal(size=(S, 3)) * 0.05, frames, lengths, q, np.full(S, N))


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def step_inputs(helix):
    """What both step-matrix paths take for ``helix`` with the default material: (inertia, kinematics, gravity's
    dF/dq generators, its left factor, element counts, the keyword arguments of dt^2 K and -dt^2 dF/dq)."""
    mat = Material()
    kin = sh.kinematics(helix)
    parts = sh.gravity_force_jacobian_parts(helix, mat.linear_density, GRAVITY, kin)
    kw = dict(stiffness=sh.stiffness(helix, mat.stiffness_diag), k_scale=DT * DT, b_scale=-DT * DT)
    return (dyn.Inertia.from_material(mat), kin, parts, gravity_jacobian_left(mat.linear_density, GRAVITY),
            helix.n_elements, kw)


def measure_corrected(N: int, S: int, repeat: int) -> dict:
    """Strands that (mostly) need the unstable-mode correction, with their kept corrections (a step after the first):
    factor_step_matrix on M against factor_step_generators (whose dense path skips the dense test of a/2 + b)."""
    helix = strands(S, N, corrected=True)
    inertia, kin, parts, left, counts, kw = step_inputs(helix)
    corr_d, corr_s = StepCorrections(S), StepCorrections(S)
    dense, structured = StrandFactors(counts), StrandFactors(counts)

    def dense_path():
        M, _ = dyn.inertia_terms(helix, inertia, kin)
        return factor_step_matrix(M, parts, counts, corr_d, out=dense, **kw)[1]

    def structured_path():
        gens, _ = dyn.inertia_generators(helix, inertia, kin)
        return factor_step_generators(gens, parts, left, counts, corr_s, out=structured, dense_below=0, **kw)

    fresh_d = best(dense_path, 1)  # the first call: every correction new (eigendecompositions)
    fresh_s = best(structured_path, 1)
    assert np.array_equal(dense.corrected, structured.corrected)
    return {"N": N, "corrected": int(dense.corrected.sum()), "fresh_dense_ms": 1e3 * fresh_d / S, "fresh_structured_ms": 1e3 * fresh_s / S,
            "kept_dense_ms": 1e3 * best(dense_path, repeat) / S,
            "kept_structured_ms": 1e3 * best(structured_path, repeat) / S}


def measure(N: int, S: int, repeat: int) -> dict:
    helix = strands(S, N)
    inertia, kin, parts, left, counts, kw = step_inputs(helix)
    dense = StrandFactors(counts)
    structured = StrandFactors(counts)

    def dense_path():
        M, _ = dyn.inertia_terms(helix, inertia, kin)
        factor_step_matrix(M, parts, counts, out=dense, **kw)

    def structured_path():
        gens, _ = dyn.inertia_generators(helix, inertia, kin)
        factor_step_generators(gens, parts, left, counts, out=structured, dense_below=0, **kw)

    dense_path()
    structured_path()
    assert not dense.corrected.any() and structured.structured.all()
    gens, _ = dyn.inertia_generators(helix, inertia, kin)
    n = 3 * N
    rhs = np.random.default_rng(1).normal(size=(S, n))
    half = n // 2
    M, _ = dyn.inertia_terms(helix, inertia, kin)
    v = rhs.reshape(S, N, 3)
    row = {"N": N, "strands": S,
           "dense_ms": 1e3 * best(dense_path, repeat) / S,
           "structured_ms": 1e3 * best(structured_path, repeat) / S,
           "mass_dense_ms": 1e3 * best(lambda: dyn.inertia_terms(helix, inertia, kin), repeat) / S,
           "generators_ms": 1e3 * best(lambda: dyn.inertia_generators(helix, inertia, kin), repeat) / S,
           "factor_only_ms": 1e3 * best(lambda: factor_step_generators(gens, parts, left, counts, out=structured,
                                                                      dense_below=0, **kw), repeat) / S,
           "Mv_dense_us": 1e6 * best(lambda: np.einsum("sij,sj->si", M, rhs), repeat) / S,
           "Mv_generators_us": 1e6 * best(lambda: mass_apply(gens, v, counts), repeat) / S,
           "solve_dense_us": 1e6 * best(lambda: dense.solve(rhs), repeat) / S,
           "solve_structured_us": 1e6 * best(lambda: structured.solve(rhs), repeat) / S}
    for name, k in (("all", n), ("half", half)):
        row[f"leading_{name}_dense_us"] = 1e6 * best(lambda: [dense.leading_inverse(s, k) for s in range(S)],
                                                     repeat) / S
        row[f"leading_{name}_structured_us"] = 1e6 * best(
            lambda: [structured.leading_inverse(s, k) for s in range(S)], repeat) / S
    x_d, x_s = dense.solve(rhs), structured.solve(rhs)
    row["solve_rel_diff"] = float(np.abs(x_d - x_s).max() / np.abs(x_d).max())
    return row


def whole_run(directory: str, run: str, steps: int, dense_below: int) -> dict:
    """One simulation of an inversion directory (module docstring), strands below ``dense_below`` elements dense."""
    from threadpoolctl import threadpool_limits

    from groomtool import simulate_linalg
    from groomtool.check import load_inverted
    from groomtool.simulate import SimulationParams, Simulator

    simulate_linalg.DENSE_BELOW = dense_below
    inv = load_inverted(directory)
    params = SimulationParams(contacts=inv.contacts, contact_radius=inv.contact_radius)
    naive = run == "naive"
    kw = {} if naive else dict(stiffness=inv.stiffness(), warm_start=inv.contact_forces,
                               external_force=inv.boundary_force)
    t0 = time.process_time()
    with threadpool_limits(1):
        sim = Simulator(inv.helix, inv.helix.curvatures.copy() if naive else inv.rest_curvatures, inv.material,
                        inv.gravity, head=inv.head, params=params, **kw)
        start = sim.tips()
        cpu, first = [], {}
        for i in range(steps):
            t = time.process_time()
            sim.step()
            cpu.append(time.process_time() - t)
            if i == 0:
                first = dict(sim.timings)
    later = {k: round((v - first.get(k, 0.0)) / max(steps - 1, 1), 4) for k, v in sim.timings.items()}
    return {"dir": directory, "run": run, "steps": steps, "dense_below": dense_below,
            "cpu_s": round(time.process_time() - t0, 2), "first_step_s": round(cpu[0], 2),
            "median_later_step_s": round(float(np.median(cpu[1:])), 4) if steps > 1 else None,
            "later_stage_s_per_step": later, "max_tip_drift_m": float(np.abs(sim.tips() - start).max()),
            "modified_strand_steps": sim.modified_strands, "structured_strands": int(sim._factors.structured.sum()),
            "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 3),
            "load": round(os.getloadavg()[0], 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[10, 16, 24, 32, 43, 64, 96])
    ap.add_argument("--strands", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--corrected", action="store_true", help="strands that all need an unstable-mode correction")
    ap.add_argument("--whole", nargs=3, metavar=("DIR", "RUN", "STEPS"), default=None)
    ap.add_argument("--one", nargs=4, metavar=("DIR", "RUN", "STEPS", "DENSE_BELOW"), default=None,
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(whole_run(args.one[0], args.one[1], int(args.one[2]), int(args.one[3]))), flush=True)
        return 0
    if args.whole:
        for dense_below in (10**9, 0):
            subprocess.run([sys.executable, __file__, "--one", *args.whole, str(dense_below)], check=True)
        return 0
    print(f"load {os.getloadavg()[0]:.2f}")
    if args.corrected:
        cols = ["N", "corrected", "fresh_dense_ms", "fresh_structured_ms", "kept_dense_ms", "kept_structured_ms"]
        print("| " + " | ".join(cols) + " |")
        for N in args.sizes:
            row = measure_corrected(N, args.strands, args.repeat)
            print("| " + " | ".join(f"{row[c]:.3g}" if isinstance(row[c], float) else str(row[c]) for c in cols)
                  + " |", flush=True)
        print(f"load {os.getloadavg()[0]:.2f}")
        return 0
    cols = ["N", "dense_ms", "structured_ms", "mass_dense_ms", "generators_ms", "factor_only_ms", "Mv_dense_us", "Mv_generators_us",
            "solve_dense_us",
            "solve_structured_us", "leading_all_dense_us", "leading_all_structured_us", "leading_half_dense_us",
            "leading_half_structured_us", "solve_rel_diff"]
    print("| " + " | ".join(cols) + " |")
    for N in args.sizes:
        row = measure(N, args.strands, args.repeat)
        print("| " + " | ".join(f"{row[c]:.3g}" if isinstance(row[c], float) else str(row[c]) for c in cols) + " |",
              flush=True)
    print(f"load {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
