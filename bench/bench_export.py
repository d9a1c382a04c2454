"""Time the discrete rest-data export (Cosserat/PyElastica + Discrete Elastic Rods) on one core.

Cases: 1,900 strands x 100 vertices with point loads (real USC-HairSalon guide strands from
../shared/data when present, cycled to 1,900, else synthetic), and a synthetic 10,000 x 100 groom.
Point loads: 5 per strand at random arc lengths (a stand-in for contact forces).

    /work/venv/bin/python bench/bench_export.py [--repeat 3]

Prints a table and writes bench/results/export.md and export.json.  Times are best-of-N wall and
CPU seconds after a warm-up call (numba compiled and cached); the machine load is recorded too.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from groomtool import Material  # noqa: E402
from groomtool.io import read_data  # noqa: E402
from groomtool.rods.cosserat import cosserat_rest_data  # noqa: E402
from groomtool.rods.der import der_rest_data  # noqa: E402
from groomtool.rods.discrete import arc_lengths, prepare_rods  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
USC_DIR = ROOT.parent / "shared" / "data" / "usc" / "cstrands"
GRAVITY = np.array([0.0, -9.81, 0.0])  # USC data is y-up




def usc_groom(n_strands: int):
    """USC guide strands (100 vertices each), cycled to n_strands, each copy shifted by 1 mm."""
    files = sorted(USC_DIR.glob("cstrands*.data"))
    # a guide strand that repeats a vertex is repaired to fewer than 100 vertices on reading: leave it out
    pool = [s for f in files for s in read_data(f, repair=True).strands()
            if len(s) == 100 and np.all(np.linalg.norm(np.diff(s, axis=0), axis=1) > 0)]
    strands = [pool[i % len(pool)] + 1e-3 * (i // len(pool)) for i in range(n_strands)]
    return np.concatenate(strands), np.arange(n_strands + 1) * 100, f"USC-HairSalon cstrands ({len(pool)} real)"


def synthetic_groom(n_strands: int, n_vertices: int = 100, seed: int = 0):
    """Smooth wavy strands rooted on a 9 cm sphere, hanging out and down, 10-50 cm long."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0, 2 * np.pi, n_strands)
    z = rng.uniform(0.1, 1.0, n_strands)
    root_dir = np.stack([np.sqrt(1 - z**2) * np.cos(phi), z, np.sqrt(1 - z**2) * np.sin(phi)], 1)
    roots = 0.09 * root_dir
    L = rng.uniform(0.1, 0.5, n_strands)
    s = np.linspace(0.0, 1.0, n_vertices)[None, :, None]
    out = root_dir[:, None, :] * np.minimum(s * L[:, None, None], 0.05)          # leave the scalp
    down = np.array([0.0, -1.0, 0.0]) * np.maximum(s * L[:, None, None] - 0.05, 0.0)
    side = np.cross(root_dir, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side, axis=1, keepdims=True) + 1e-12
    k = rng.uniform(20, 60, n_strands)[:, None, None]
    amp = rng.uniform(0.0, 0.01, n_strands)[:, None, None]
    wave = amp * np.sin(k * s * L[:, None, None] + rng.uniform(0, 6.3, n_strands)[:, None, None]) * side[:, None]
    P = roots[:, None] + out + down + wave
    return P.reshape(-1, 3), np.arange(n_strands + 1) * n_vertices, "synthetic wavy"


def point_loads(points, offsets, per_strand: int = 5, seed: int = 1):
    rng = np.random.default_rng(seed)
    S = len(offsets) - 1
    L = arc_lengths(points, offsets)[offsets[1:] - 1]
    strand = np.repeat(np.arange(S), per_strand)
    where = rng.uniform(0.0, 1.0, len(strand)) * L[strand]
    force = 2e-6 * rng.standard_normal((len(strand), 3))   # ~ the weight of 3 cm of hair
    return strand, where, force


def timed(fn, repeat):
    best_wall, best_cpu, out = np.inf, np.inf, None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        best_wall = min(best_wall, time.perf_counter() - w)
        best_cpu = min(best_cpu, time.process_time() - c)
    return best_wall, best_cpu, out


def run_case(name, points, offsets, source, loads, repeat, mat):
    args = (points, offsets, mat, GRAVITY)
    kw = {"point_forces": loads}
    cos_w, cos_c, cos = timed(lambda: cosserat_rest_data(*args, **kw), repeat)
    der_w, der_c, der = timed(lambda: der_rest_data(*args, **kw), repeat)

    def both():
        rod = prepare_rods(points, offsets)
        return cosserat_rest_data(*args, **kw, rod=rod), der_rest_data(*args, **kw, rod=rod)

    both_w, both_c, _ = timed(both, repeat)
    return {
        "case": name, "source": source, "strands": len(offsets) - 1, "vertices": int(len(points)),
        "point_loads": 0 if loads is None else len(loads[0]),
        "cosserat_wall_s": cos_w, "cosserat_cpu_s": cos_c, "der_wall_s": der_w, "der_cpu_s": der_c,
        "both_shared_wall_s": both_w, "both_shared_cpu_s": both_c,
        "cosserat_force_rel": cos["cosserat_residual"]["force_rel"],
        "cosserat_torque_rel": cos["cosserat_residual"]["torque_rel"],
        "der_force_rel": der["der_residual"]["force_rel"],
        "der_worst_strand_rel": der["der_residual"]["per_strand_max"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    mat = Material()

    t0 = time.perf_counter()
    warm = synthetic_groom(4, 10)
    cosserat_rest_data(*warm[:2], mat, GRAVITY, point_forces=point_loads(*warm[:2]))
    der_rest_data(*warm[:2], mat, GRAVITY, point_forces=point_loads(*warm[:2]))
    first_call = time.perf_counter() - t0

    g1 = usc_groom(1900) if USC_DIR.is_dir() else synthetic_groom(1900)
    g2 = synthetic_groom(10_000, seed=2)
    rows = [
        run_case("1,900 x 100 + point loads", g1[0], g1[1], g1[2], point_loads(g1[0], g1[1]), args.repeat, mat),
        run_case("10,000 x 100", g2[0], g2[1], g2[2], None, args.repeat, mat),
        run_case("10,000 x 100 + point loads", g2[0], g2[1], g2[2], point_loads(g2[0], g2[1]), args.repeat, mat),
    ]
    machine = {"python": platform.python_version(), "numpy": np.__version__, "cpu": platform.processor()
               or platform.machine(), "cpus": os.cpu_count(), "load_avg_1min": os.getloadavg()[0],
               "first_call_s (numba load/compile)": first_call}

    header = ("| case | strands x vertices | Cosserat wall / CPU s | DER wall / CPU s | both (shared prep) wall / "
              "CPU s | Cosserat residual (F, T) | DER residual (all, worst strand) |")
    lines = [header, "|" + "---|" * 7]
    for r in rows:
        lines.append(
            f"| {r['case']} ({r['source']}) | {r['strands']} x {r['vertices'] // r['strands']} | "
            f"{r['cosserat_wall_s']:.3f} / {r['cosserat_cpu_s']:.3f} | {r['der_wall_s']:.3f} / {r['der_cpu_s']:.3f} | "
            f"{r['both_shared_wall_s']:.3f} / {r['both_shared_cpu_s']:.3f} | "
            f"{r['cosserat_force_rel']:.1e}, {r['cosserat_torque_rel']:.1e} | "
            f"{r['der_force_rel']:.1e}, {r['der_worst_strand_rel']:.1e} |")
    table = "\n".join(lines)
    print(table)
    print(f"machine: {machine}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    md = ["# Rest-data export benchmark (`bench/bench_export.py`)", "",
          "One core (numba and BLAS pinned to one thread), best of "
          f"{args.repeat} after a warm-up; CPU = process time.  Residuals: Cosserat = PyElastica's static "
          "force / torque balance re-evaluated term by term; DER = ||grad E - f_ext|| / ||f_ext|| on the "
          "free dofs (stiff stretching: float64 floor ~1e-8, see docs/rest_data.md).", "", table, "",
          f"Machine: {machine['cpu']}, {machine['cpus']} CPUs, 1-min load average {machine['load_avg_1min']:.1f} "
          f"while measuring (shared machine: wall times inflate with the load, CPU times much less); "
          f"Python {machine['python']}, numpy {machine['numpy']}; first call incl. numba cache load "
          f"{first_call:.1f} s.", ""]
    (RESULTS / "export.md").write_text("\n".join(md))
    (RESULTS / "export.json").write_text(json.dumps({"rows": rows, "machine": machine}, indent=2))
    print(f"wrote {RESULTS / 'export.md'} and export.json")


if __name__ == "__main__":
    main()
