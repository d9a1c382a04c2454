"""Benchmark of the floating-tangent fit (groomtool.fit) and the isolated inversion on real grooms.

Grooms (../shared/data, see MANIFEST.md there):
- harolongo: digital-salon/harolongo.data, 7,905 strands x 21 vertices, centimetres;
- usc10k: a 10,000-strand groom grown from USC-HairSalon guide strands: for each of the 10,000 scalp
  roots of usc/roots10k.obj, the guide strand of cstrands00003.data (style 3, XL curly: 5 guides of
  100 vertices) whose root is nearest, translated so that its root sits on the scalp root.

For each: fit_groom (default tolerance 0.5 mm), then the isolated inversion q0 = q - K^-1 F(q)
(gravity only, groomtool.rods.superhelix.gravity_force, default Material).  One thread (BLAS pinned),
wall and CPU time per stage, peak traced memory (a separate run: tracemalloc slows numpy down), and the
CPU time of the process's first fit (it loads the numba kernels from their cache).  Writes
bench/results/fit.md and fit.json.

    python bench/bench_fit.py [--tolerance 5e-4] [--twist-budget 0.25] [--repeat 2]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import groomtool.fit.fitter as fitter  # noqa: E402
from groomtool.groom import Groom  # noqa: E402
from groomtool.io import read_data  # noqa: E402
from groomtool.material import Material  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
STAGES = ("prepare", "sample", "relax", "helix", "assemble", "error", "merge")




def harolongo() -> Groom:
    return Groom.from_strands(list(read_data(DATA / "digital-salon" / "harolongo.data", scale=0.01).strands()), source="harolongo")


def usc10k(style: str = "cstrands00003.data") -> Groom:
    guides = list(read_data(DATA / "usc" / "cstrands" / style).strands())
    roots = np.array([line.split()[1:4] for line in open(DATA / "usc" / "roots10k.obj") if line.startswith("v ")],
                     dtype=np.float64)
    guide_roots = np.array([g[0] for g in guides])
    nearest = np.argmin(((roots[:, None] - guide_roots[None]) ** 2).sum(-1), axis=1)
    strands = [guides[k] - guide_roots[k] + r for k, r in zip(nearest, roots)]
    return Groom.from_strands(strands, source=f"usc10k ({style} on roots10k)")


def fit_and_invert(groom: Groom, tolerance: float, twist_budget: float):
    """The timed work: fit_groom, then q0 = q - K^-1 F(q).  Returns (result, q0, seconds)."""
    material = Material()
    times = {}
    wall, cpu = time.perf_counter(), time.process_time()
    fitter._clock = time.process_time                       # stage timings in CPU seconds
    res = fitter.fit_groom(groom, tolerance=tolerance, twist_budget=twist_budget)
    times["fit"] = (time.process_time() - cpu, time.perf_counter() - wall)
    wall, cpu = time.perf_counter(), time.process_time()
    F = sh.gravity_force(res.helix, material.linear_density, groom.gravity())
    K = sh.stiffness(res.helix, material.stiffness_diag)
    q0 = res.helix.curvatures - np.divide(F, K, out=np.zeros_like(F), where=K > 0)
    times["inversion"] = (time.process_time() - cpu, time.perf_counter() - wall)
    return res, q0, times


def peak_memory(groom: Groom, tolerance: float, twist_budget: float):
    """Peak traced memory (MB) of the fit and of the inversion, separately (tracemalloc slows the run)."""
    material = Material()
    tracemalloc.start()
    res = fitter.fit_groom(groom, tolerance=tolerance, twist_budget=twist_budget)
    fit_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    F = sh.gravity_force(res.helix, material.linear_density, groom.gravity())
    inv_peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    del F
    return fit_peak / 2**20, inv_peak / 2**20


def run(groom: Groom, tolerance: float, twist_budget: float, repeat: int) -> dict:
    runs = [fit_and_invert(groom, tolerance, twist_budget) for _ in range(repeat)]
    res, q0, times = min(runs, key=lambda r: r[2]["fit"][0] + r[2]["inversion"][0])
    assert np.isfinite(q0).all()
    fit_mb, inv_mb = peak_memory(groom, tolerance, twist_budget)
    helix = res.helix
    q = helix.curvatures[helix.element_mask]
    twist = np.abs(q[:, 0])
    bend = np.linalg.norm(q[:, 1:], axis=1)
    return {
        "groom": groom.source, "strands": groom.n_strands, "vertices": groom.n_points,
        "elements": int(helix.n_elements.sum()),
        "elements_per_strand": [int(helix.n_elements.min()), float(helix.n_elements.mean()),
                                int(helix.n_elements.max())],
        "passes": res.passes, "not_converged": int((~res.converged).sum()),
        "max_error_mm": 1e3 * float(res.max_error.max()), "mean_error_mm": 1e3 * float(res.mean_error.mean()),
        "max_relative_error": float(res.relative_max_error.max()),
        "twist_median_p90": [float(np.median(twist)), float(np.percentile(twist, 90))],
        "bend_median_p90": [float(np.median(bend)), float(np.percentile(bend, 90))],
        "stage_cpu_s": {k: round(res.timings.get(k, 0.0), 3) for k in STAGES},
        "fit_cpu_s": times["fit"][0], "fit_wall_s": times["fit"][1], "fit_first_cpu_s": runs[0][2]["fit"][0],
        "inversion_cpu_s": times["inversion"][0], "inversion_wall_s": times["inversion"][1],
        "fit_peak_MB": fit_mb, "inversion_peak_MB": inv_mb,
    }


def table(rows) -> str:
    head = ("| groom | strands | vertices | elements (min/mean/max) | passes | max / mean error (mm) | "
            "twist / bend median (1/m) | " + " | ".join(STAGES) + " | fit CPU (wall) s | first fit CPU s "
            "| inversion CPU (wall) s "
            "| peak MB fit / inversion |")
    sep = "|" + "---|" * (head.count("|") - 1)
    out = [head, sep]
    for r in rows:
        e = r["elements_per_strand"]
        out.append(
            f"| {r['groom']} | {r['strands']} | {r['vertices']} | {r['elements']} ({e[0]}/{e[1]:.1f}/{e[2]}) | "
            f"{r['passes']} | {r['max_error_mm']:.3f} / {r['mean_error_mm']:.3f} | "
            f"{r['twist_median_p90'][0]:.1f} / {r['bend_median_p90'][0]:.1f} | "
            + " | ".join(f"{r['stage_cpu_s'][k]:.2f}" for k in STAGES)
            + f" | {r['fit_cpu_s']:.2f} ({r['fit_wall_s']:.2f}) | {r['fit_first_cpu_s']:.2f}"
            f" | {r['inversion_cpu_s']:.2f} ({r['inversion_wall_s']:.2f})"
            f" | {r['fit_peak_MB']:.0f} / {r['inversion_peak_MB']:.0f} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tolerance", type=float, default=5e-4)
    ap.add_argument("--twist-budget", type=float, default=0.25)
    ap.add_argument("--repeat", type=int, default=2, help="runs per groom; the fastest (CPU) is kept")
    ap.add_argument("--out", default=str(RESULTS / "fit"))
    args = ap.parse_args()
    rows = []
    for make in (harolongo, usc10k):
        groom = make()
        rows.append(run(groom, args.tolerance, args.twist_budget, args.repeat))
        print(json.dumps(rows[-1]))
    env = {"python": platform.python_version(), "numpy": np.__version__, "machine": platform.machine(),
           "cpus": os.cpu_count(), "load_average": os.getloadavg(),
           "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "tolerance_m": args.tolerance, "twist_budget": args.twist_budget}
    md = (f"# Fit benchmark (bench/bench_fit.py)\n\n"
          f"tolerance {args.tolerance * 1e3:.2f} mm, twist_budget {args.twist_budget}; one thread; best of "
          f"{args.repeat} runs; stage times are CPU seconds; first fit: the process's first run (harolongo's "
          f"includes loading the numba kernels from their cache).\nMachine: {env['cpus']} CPUs, load average "
          f"{', '.join(f'{x:.1f}' for x in env['load_average'])} (shared: wall times are inflated), "
          f"numpy {env['numpy']}, peak RSS {env['peak_rss_MB']:.0f} MB.\n\n" + table(rows) + "\n")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(md)
    out.with_suffix(".json").write_text(json.dumps({"environment": env, "results": rows}, indent=1))
    print(md)


if __name__ == "__main__":
    main()
