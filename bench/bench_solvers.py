"""Benchmark of groomtool's contact solvers on synthetic hair-like problems (bench/problems.py).

    python bench/bench_solvers.py            # full run, writes bench/results/solvers.md and solvers.json
    python bench/bench_solvers.py --quick    # 1k and 10k only
    python bench/bench_solvers.py --shared   # the headline: the shared generator's problems, side by side with
                                             # so-bogus (../shared/bench/gen_hair_problem.py, issue 22)

Every measurement runs in its own subprocess with NUMBA_NUM_THREADS=1 (and BLAS on one thread), so the
times are one-core times and the peak memory is that run's own.  Reported per run:

* setup_s  -- building the solver's data (W's 3x3 blocks, packing, clarabel's matrices),
* solve_s  -- the iterations, wall clock; cpu_s -- process CPU time of setup + solve (the fairer figure
  on a shared machine: other processes' load does not count),
* sweeps / iterations, the final residual (residual.py: max-norm natural map, relative), so-bogus's own
  error figure for comparison, the objective,
* solver_peak_mb -- peak of Python/NumPy allocations during setup + solve (tracemalloc),
  rss_peak_mb -- the subprocess's peak resident memory (includes generating the problem).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
CACHE = Path(os.environ.get("GROOMTOOL_BENCH_CACHE", "/tmp/groomtool_bench_cache"))
BOGUS_30K_S = 13.1  # so-bogus, one core, 30k contacts, 20-element strands, gamma = 0.01, residual 1e-8
TARGET_30K_S = 2.6
# the side-by-side problems of issue 22: ../shared/bench/gen_hair_problem.py, seed 0
SHARED_GEN = Path(os.environ.get("GROOMTOOL_SHARED_GEN", HERE.parents[1] / "shared" / "bench" / "gen_hair_problem.py"))
BOGUS_SHARED_30K = {"cpu_s": 18.0, "sweeps": 925, "objective": -8.817132e3, "error": 8.8e-9}  # so-bogus, one thread
TARGET_SHARED_30K_CPU_S = 3.6  # 5x less CPU than so-bogus
CLARABEL_LIMIT_S = 60.0


# ----------------------------------------------------------------------------------------------
# child: one measurement
# ----------------------------------------------------------------------------------------------
def _problem(spec):
    sys.path.insert(0, str(HERE))
    from problems import make_hair_like

    import numpy as np
    import scipy.sparse as sp

    from groomtool.solvers import ContactProblem

    key = f"m{spec['m']}_{spec.get('variant', 'inverse')}_w{spec.get('window')}_s{spec.get('seed', 0)}"
    path = CACHE / f"{key}.npz"
    if path.exists():
        z = np.load(path, allow_pickle=False)
        H = sp.csr_matrix((z["Hd"], z["Hi"], z["Hp"]), shape=tuple(z["Hs"]))
        D = z["D"]
        blocks = D if D.ndim == 1 else list(D)
        return ContactProblem(H, blocks, z["off"], float(z["gamma"]), z["b"], z["mu"])
    P, _ = make_hair_like(spec["m"], variant=spec.get("variant", "inverse"), window=spec.get("window"),
                          seed=spec.get("seed", 0))
    CACHE.mkdir(parents=True, exist_ok=True)
    D = P.D_blocks
    D = np.concatenate(D) if all(d.ndim == 1 for d in D) else np.stack(D)
    np.savez(path, Hd=P.H.data, Hi=P.H.indices, Hp=P.H.indptr, Hs=np.array(P.H.shape), D=D, off=P.dof_offsets,
             gamma=P.gamma, b=P.b, mu=P.mu)
    return P


def run_child(spec: dict) -> dict:
    import resource
    import tracemalloc

    import numpy as np

    from groomtool.solvers import solve_contact_problem
    from groomtool.solvers.blocks import assemble_upper

    P = _problem(spec)
    law = spec.get("law", "soc")
    method = spec["method"]
    opts = dict(spec.get("options", {}))
    # warm the numba caches on a tiny problem so compilation never counts
    if method != "clarabel":
        sys.path.insert(0, str(HERE))
        from problems import make_hair_like

        tiny, _ = make_hair_like(40, variant=spec.get("variant", "inverse"))
        solve_contact_problem(tiny, law=law, method=method, max_iter=20, **opts)
        if method == "gs" and law == "soc":
            solve_contact_problem(tiny, law=law, method=method, max_iter=20, **dict(opts, newton=1, newton_every=1,
                                                                                    check_every=1))
        assemble_upper(tiny)
    tracemalloc.start()
    c0 = time.process_time()
    res = solve_contact_problem(P, law=law, method=method, tol=spec.get("tol", 1e-8), max_iter=spec.get("max_iter"),
                                **opts)
    cpu = time.process_time() - c0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    out = {
        "spec": spec,
        "m": P.n_contacts,
        "strands": P.n_strands,
        "status": res.status,
        "converged": res.converged,
        "residual": res.residual,
        "bogus_error": P.bogus_error(res.r, law=law),
        "iterations": res.iterations,
        "objective": res.objective,
        "cone_violation": res.cone_violation,
        "time_s": res.time_s,
        "setup_s": res.info.get("setup_s"),
        "solve_s": res.info.get("solve_s"),
        "cpu_s": cpu,
        "form": res.info.get("form"),
        "switched_to": res.info.get("switched_to"),
        "local_failures": res.info.get("local_failures"),
        "history": [(int(a), float(b), float(c)) for a, b, c in res.info.get("history", [])][:: max(1, len(res.info.get("history", [])) // 40)],
        "solver_peak_mb": peak / 2**20,
        "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "load": os.getloadavg(),
    }
    if spec.get("save_r"):
        np.save(spec["save_r"], res.r)
    return out


def shared_problem_path(m: int, pairing: str = "random", gamma: float = 0.01, seed: int = 0) -> Path:
    """The shared generator's problem file (made once, cached under CACHE)."""
    path = CACHE / f"shared_m{m}_{pairing}_g{gamma:g}_s{seed}.bin"
    if not path.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, str(SHARED_GEN), "--contacts", str(m), "--pairing", pairing, "--gamma",
                        str(gamma), "--seed", str(seed), "-o", str(path)], check=True, capture_output=True)
    return path


def run_shared_child(spec: dict) -> dict:
    """One solve_socqp(W, b, mu, **options) on a shared-generator problem: process CPU time and wall time
    of the call (its set-up included), sweeps, residual, so-bogus's error figure, objective, cone
    violation.  spec: m, pairing, gamma, seed, options, tol, max_iter, order ("reversed": contacts
    solved in the reverse of the file's order)."""
    sys.path.insert(0, str(HERE))
    import numpy as np
    import scipy.sparse as sp
    from problems import read_bogus_problem

    from groomtool.solvers import solve_socqp
    from groomtool.solvers import residual as _res

    W, b, mu = read_bogus_problem(shared_problem_path(spec["m"], spec.get("pairing", "random"), spec.get("gamma", 0.01),
                                                      spec.get("seed", 0)))
    opts = dict(spec.get("options", {}))
    if spec.get("stop") == "bogus":  # like for like: stop on so-bogus's own error (the caller's stop rule)
        import inspect

        from groomtool.solvers.gauss_seidel import run_gauss_seidel

        if "stop" not in inspect.signature(run_gauss_seidel).parameters:
            return {"spec": spec, "status": "error", "stderr": "this groomtool has no stop rule"}
        trace_ = np.asarray(sp.csr_matrix(W).diagonal()).reshape(-1, 3).sum(axis=1)
        bogus_tol = float(spec.get("bogus_tol", BOGUS_SHARED_30K["error"]))
        opts["stop"] = lambda r, u: _res.bogus_error(r.reshape(-1, 3), u.reshape(-1, 3), mu, trace_) <= bogus_tol
    if spec.get("order") == "reversed":
        opts["order"] = np.arange(b.size // 3)[::-1].copy()
    # warm the numba caches on a small principal block so compilation never counts (the second call takes
    # Newton steps whatever the options, so their kernels are loaded too)
    warm = {k: v for k, v in opts.items() if k not in ("order", "stop")}
    solve_socqp(W[:600, :600], b[:600], mu[:200], max_iter=30, **warm)
    solve_socqp(W[:600, :600], b[:600], mu[:200], max_iter=30, **dict(warm, newton=1, newton_every=1, check_every=1))
    c0 = time.process_time()
    w0 = time.perf_counter()
    res = solve_socqp(W, b, mu, tol=spec.get("tol", 1e-8), max_iter=spec.get("max_iter"), **opts)
    cpu = time.process_time() - c0
    wall = time.perf_counter() - w0
    r3 = res.r.reshape(-1, 3)
    u = (W @ res.r + b).reshape(-1, 3)
    trace = np.asarray(sp.csr_matrix(W).diagonal()).reshape(-1, 3).sum(axis=1)
    return {
        "spec": spec, "m": b.size // 3, "status": res.status, "converged": res.converged, "residual": res.residual,
        "bogus_error": _res.bogus_error(r3, u, mu, trace), "iterations": res.iterations, "objective": res.objective,
        "cone_violation": res.cone_violation, "cpu_s": cpu, "wall_s": wall, "setup_s": res.info.get("setup_s"),
        "solve_s": res.info.get("solve_s"), "threads": spec.get("threads", "one"),
        "history": [(int(a), float(b_), float(c)) for a, b_, c in res.info.get("history", [])][:: max(1, len(res.info.get("history", [])) // 40)],
        "load": os.getloadavg(),
    }


def child(spec: dict, timeout: float = 1800) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if spec.get("threads") == "default":  # the library's own defaults: whatever the machine gives
        env = {k: v for k, v in os.environ.items()
               if k not in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], capture_output=True, text=True,
                           env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"spec": spec, "status": "timeout", "time_s": time.perf_counter() - t}
    if p.returncode != 0:
        return {"spec": spec, "status": "error", "stderr": p.stderr[-2000:]}
    return json.loads(p.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------------------------
# parent: the tables
# ----------------------------------------------------------------------------------------------
def fmt(x, f="{:.2f}"):
    return "-" if x is None else f.format(x)


def row(r):
    s = r["spec"]
    label = s["method"] + ("" if s["method"] == "clarabel" else f" ({r.get('form')})")
    opts = s.get("options", {})
    if opts.get("anderson") == 0:
        label += " no-AA"
    if "newton" in opts and opts["newton"] is None:
        label += " no-Newton"
    if r.get("switched_to"):
        label += f" -> {r['switched_to']}"
    if s.get("tol", 1e-8) != 1e-8:
        label += f", tol {s['tol']:.0e}"
    return (
        f"| {s['m']:,} | {s.get('variant', 'inverse')} | {'random' if s.get('window') is None else 'local'} | "
        f"{s.get('law', 'soc')} | {label} | {r.get('status')} | {fmt(r.get('setup_s'))} | {fmt(r.get('solve_s'))} | "
        f"{fmt(r.get('cpu_s'))} | {r.get('iterations', '-')} | {fmt(r.get('residual'), '{:.1e}')} | "
        f"{fmt(r.get('bogus_error'), '{:.1e}')} | {fmt(r.get('solver_peak_mb'), '{:.0f}')} | "
        f"{fmt(r.get('rss_peak_mb'), '{:.0f}')} |"
    )


HEADER = (
    "| contacts | D | contact graph | law | method (form) | status | setup s | solve s | cpu s | sweeps/iters | "
    "residual | bogus err | solver MB | RSS MB |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--child")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", type=str, default=None)
    ap.add_argument("--skip-clarabel", action="store_true")
    ap.add_argument("--reuse-clarabel", action="store_true",
                    help="keep the clarabel series of the existing solvers.json instead of re-running it")
    ap.add_argument("--from-json", action="store_true", help="rewrite solvers.md from solvers.json")
    ap.add_argument("--target", type=int, default=0, metavar="N",
                    help="only re-measure the 30k target row N times and merge it into solvers.json")
    ap.add_argument("--shared", action="store_true",
                    help="only the shared generator's rows (issue 22): run them and merge them into solvers.json")
    ap.add_argument("--shared-only", type=str, default=None, metavar="K,K",
                    help="--shared: re-run only these SHARED_EXPERIMENTS (indices) at 30k and merge them")
    ap.add_argument("--threads-check", type=int, default=0, metavar="N",
                    help="--shared: N alternated pairs of one-thread / default-thread 30k runs (CPU and wall)")
    ap.add_argument("--repeat", type=int, default=3, help="--shared: processes per headline row (median reported)")
    ap.add_argument("--add", action="append", default=[], metavar="SPEC",
                    help="run one more spec (JSON) and append it to solvers.json")
    args = ap.parse_args()
    if args.child:
        spec = json.loads(args.child)
        print(json.dumps(run_shared_child(spec) if spec.get("gen") == "shared" else run_child(spec)))
        return
    if args.shared:
        run_shared(args)
        return
    if args.from_json or args.target or args.add:
        data = json.loads((RESULTS / "solvers.json").read_text())
        for spec in args.add:
            data["runs"].append(child(json.loads(spec)))
            print(row(data["runs"][-1]), flush=True)
        if args.target:
            spec = {"m": 30000, "method": "gs", "options": {"form": "assembled"}}
            tries = []
            for _ in range(args.target):
                tries.append(child(spec))
                print(row(tries[-1]), flush=True)
            data["target"] = {"date": time.strftime("%Y-%m-%d %H:%M"), "runs": tries, "load_at_end": os.getloadavg()}
        (RESULTS / "solvers.json").write_text(json.dumps(data, indent=1))
        write_markdown(data["meta"], data["runs"], data.get("clarabel", []), data.get("target"), data.get("shared"))
        return

    sizes = [1000, 10000] if args.quick else [1000, 10000, 30000, 100000]
    if args.sizes:
        sizes = [int(s) for s in args.sizes.split(",")]
    RESULTS.mkdir(parents=True, exist_ok=True)
    runs = []

    def go(spec, timeout=1800, repeat=1):
        """Run a spec (repeat times, keeping the run of least CPU time: the machine may be shared)."""
        tries = [child(spec, timeout) for _ in range(repeat)]
        ok = [t for t in tries if "cpu_s" in t]
        r = min(ok, key=lambda t: t["cpu_s"]) if ok else tries[0]
        if repeat > 1 and ok:
            r["cpu_s_all"] = [t["cpu_s"] for t in ok]
            r["solve_s_all"] = [t["solve_s"] for t in ok]
        runs.append(r)
        print(row(r) if "spec" in r and r.get("status") not in ("error",) else r, flush=True)
        return r

    print(HEADER)
    # main table: SOCQP, inverse variant (D = K^-2), random contact graph
    for m in sizes:
        go({"m": m, "method": "gs", "options": {"form": "assembled"}}, repeat=3 if m == 30000 else 1)
        go({"m": m, "method": "gs", "options": {"form": "matrix_free"}})
        go({"m": m, "method": "gs", "options": {"form": "assembled", "newton": None}})  # Anderson only
        go({"m": m, "method": "gs", "options": {"form": "assembled", "anderson": 0, "newton": None},
            "max_iter": 5000})  # plain Gauss-Seidel
        go({"m": m, "method": "apgd", "options": {"form": "assembled"}})
    # a looser tolerance, for the comparison with so-bogus's own error figure
    if 30000 in sizes:
        go({"m": 30000, "method": "gs", "options": {"form": "assembled"}, "tol": 1e-4})
    # sensitivity at 30k (or the largest size <= 30k): dense D (dynamics) and a local contact graph
    mid = max([m for m in sizes if m <= 30000] or [sizes[0]])
    for extra in ({"variant": "dynamics"}, {"window": 2}):
        go(dict({"m": mid, "method": "gs", "options": {"form": "assembled"}}, **extra))
        go(dict({"m": mid, "method": "gs", "options": {"form": "matrix_free"}}, **extra))
    # Coulomb (forward simulator): dense D, and the inverse variant's stiffer coupling
    for m in [s for s in sizes if s <= 30000]:
        go({"m": m, "method": "auto", "law": "coulomb", "variant": "dynamics"})
    for m in [s for s in sizes if s <= 30000]:
        go({"m": m, "method": "auto", "law": "coulomb"})

    # clarabel scaling (factored form): both contact graphs, both of its direct solvers; a series stops at
    # the first size that is not solved within the limit
    cl_runs = []
    if args.reuse_clarabel and (RESULTS / "solvers.json").exists():
        old = json.loads((RESULTS / "solvers.json").read_text())
        cl_runs = old.get("clarabel", [])
        runs += [r for r in old["runs"] if r.get("spec", {}).get("method") == "clarabel"]
    elif not args.skip_clarabel:
        for window in (None, 2):
            for solver in ("qdldl", "faer"):
                for m in [1000, 3000, 10000, 30000]:
                    if m > max(sizes):
                        break
                    spec = {"m": m, "method": "clarabel",
                            "options": {"time_limit": CLARABEL_LIMIT_S, "linear_solver": solver}}
                    if window is not None:
                        spec["window"] = window
                    r = go(spec, timeout=CLARABEL_LIMIT_S * 4 + 300)
                    gs = next((x for x in runs if x.get("m") == m and x["spec"]["method"] == "gs"
                               and x.get("form") == "assembled" and x["spec"].get("window") == window
                               and x["spec"].get("tol", 1e-8) == 1e-8
                               and x["spec"].get("options", {}).get("anderson") is None
                               and "variant" not in x["spec"]), None)
                    if gs is None and r.get("status") == "Solved":
                        gs_spec = {"m": m, "method": "gs", "options": {"form": "assembled"}}
                        if window is not None:
                            gs_spec["window"] = window
                        gs = go(gs_spec)
                    if gs is not None and r.get("objective") is not None and gs.get("objective") is not None:
                        r["gs_objective"] = gs["objective"]
                        r["objective_rel_diff"] = abs(r["objective"] - gs["objective"]) / abs(gs["objective"])
                    cl_runs.append(r)
                    if r.get("status") != "Solved" or (r.get("time_s") or 0) > CLARABEL_LIMIT_S:
                        break

    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "python": sys.version.split()[0],
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_at_end": os.getloadavg(),
    }
    old = json.loads((RESULTS / "solvers.json").read_text()) if (RESULTS / "solvers.json").exists() else {}
    shared = old.get("shared")  # the shared generator's rows are re-measured by --shared only
    out = {"meta": meta, "runs": runs, "clarabel": cl_runs}
    if shared:
        out["shared"] = shared
    (RESULTS / "solvers.json").write_text(json.dumps(out, indent=1))
    write_markdown(meta, runs, cl_runs, shared=shared)


SHARED_EXPERIMENTS = [  # 30k, random pairing, gamma 0.01: what was tried for the sweep count (issue 22)
    ({"options": {"newton": None}}, "no Newton steps (Anderson only: the previous default)"),
    ({"options": {"anderson": 0}}, "Newton steps, no Anderson"),
    ({"options": {"newton_cg": [100, 100]}}, "Newton with 100 CG iterations at every step"),
    ({"options": {"newton_cg": [50, 150]}}, "Newton with 50 / 150 CG iterations"),
    ({"options": {"newton": 40}}, "first Newton step after 40 sweeps"),
    ({"options": {"newton_every": 20}}, "Newton steps 20 sweeps apart"),
    ({"stop": "bogus"}, "stopped on so-bogus's own error <= 8.8e-9 (like for like)"),
    ({"tol": 1e-4}, "tolerance 1e-4"),
    ({"tol": 1e-10}, "tolerance 1e-10"),
]
# measured before the subspace Newton steps (2026-11-24 21:15, Anderson only), kept in docs/solvers.md section 10:
# plain Gauss-Seidel 3,000 sweeps to 9e-7, Anderson memory 3 / 16, symmetric sweeps, omega 1.3, reverse order


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2] if len(xs) % 2 else 0.5 * (xs[len(xs) // 2 - 1] + xs[len(xs) // 2])


def run_shared(args):
    """The shared generator's rows (issue 22), merged into solvers.json under "shared"."""
    base = {"gen": "shared", "gamma": 0.01, "seed": 0}
    sizes = [int(x) for x in args.sizes.split(",")] if args.sizes else [1000, 10000, 30000, 100000]
    rows = []

    def go(spec, label, repeat=1):
        tries = [child(spec, timeout=3600) for _ in range(repeat)]
        ok = [t for t in tries if "cpu_s" in t]
        if not ok:
            print(label, tries[0], flush=True)
            return
        r = dict(ok[len(ok) // 2])  # the runs are deterministic: same sweeps and residual in every process
        r["label"] = label
        r["cpu_s_all"] = [t["cpu_s"] for t in ok]
        r["wall_s_all"] = [t["wall_s"] for t in ok]
        r["cpu_s"] = _median(r["cpu_s_all"])
        r["wall_s"] = _median(r["wall_s_all"])
        rows.append(r)
        print(shared_row(r), flush=True)

    print(SHARED_HEADER)
    if args.threads_check:
        # one-thread and default-thread runs of the 30k headline, alternated so that both see the same load
        path = RESULTS / "solvers.json"
        data = json.loads(path.read_text())
        pairs = []
        for k in range(args.threads_check):  # which goes first alternates too
            if k % 2:
                dft = child(dict(base, m=30000, pairing="random", threads="default"))
                one = child(dict(base, m=30000, pairing="random"))
            else:
                one = child(dict(base, m=30000, pairing="random"))
                dft = child(dict(base, m=30000, pairing="random", threads="default"))
            pairs.append({k: {"cpu_s": t.get("cpu_s"), "wall_s": t.get("wall_s")} for k, t in (("one", one), ("default", dft))})
            print(pairs[-1], flush=True)
        data["shared"]["threads_check"] = {"date": time.strftime("%Y-%m-%d %H:%M"), "pairs": pairs,
                                           "load_at_end": os.getloadavg()}
        path.write_text(json.dumps(data, indent=1))
        write_markdown(data["meta"], data["runs"], data.get("clarabel", []), data.get("target"), data["shared"])
        return
    if args.shared_only:
        path = RESULTS / "solvers.json"
        data = json.loads(path.read_text())
        for k in (int(x) for x in args.shared_only.split(",")):
            extra, label = SHARED_EXPERIMENTS[k]
            data["shared"]["runs"] = [r for r in data["shared"]["runs"] if r.get("label") != label]
            go(dict(base, m=30000, pairing="random", **extra), label, repeat=args.repeat)
        data["shared"]["runs"] += rows
        data["shared"]["load_at_end"] = os.getloadavg()
        path.write_text(json.dumps(data, indent=1))
        write_markdown(data["meta"], data["runs"], data.get("clarabel", []), data.get("target"), data["shared"])
        return
    for m in sizes:
        for pairing in ("random", "local"):
            spec = dict(base, m=m, pairing=pairing)
            go(spec, "defaults", repeat=args.repeat if (m == 30000 and pairing == "random") else 1)
            if m == 30000 and pairing == "random":
                go(dict(spec, threads="default"), "defaults, default threads", repeat=args.repeat)
    if 30000 in sizes:
        for extra, label in SHARED_EXPERIMENTS:
            go(dict(base, m=30000, pairing="random", **extra), label)
    path = RESULTS / "solvers.json"
    data = json.loads(path.read_text()) if path.exists() else {"meta": {}, "runs": [], "clarabel": []}
    data["shared"] = {"date": time.strftime("%Y-%m-%d %H:%M"), "runs": rows, "load_at_end": os.getloadavg(),
                      "cpus": os.cpu_count()}
    path.write_text(json.dumps(data, indent=1))
    write_markdown(data["meta"], data["runs"], data.get("clarabel", []), data.get("target"), data["shared"])


SHARED_HEADER = (
    "| contacts | pairing | run | threads | status | CPU s (median) | wall s (median) | sweeps | residual | "
    "so-bogus err | objective | rel. to so-bogus obj. | cone viol. |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def shared_row(r):
    s = r["spec"]
    rel = "-"
    if s["m"] == 30000 and s.get("pairing", "random") == "random" and s.get("gamma") == 0.01 and s.get("seed", 0) == 0:
        rel = f"{(r['objective'] - BOGUS_SHARED_30K['objective']) / abs(BOGUS_SHARED_30K['objective']):+.1e}"
    n = len(r.get("cpu_s_all", [1]))
    return (
        f"| {s['m']:,} | {s.get('pairing', 'random')} | {r['label']} | {'default' if s.get('threads') == 'default' else '1'} | "
        f"{r['status']} | {r['cpu_s']:.2f}{f' (n={n})' if n > 1 else ''} | {r['wall_s']:.2f} | {r['iterations']} | "
        f"{r['residual']:.1e} | {r['bogus_error']:.1e} | {r['objective']:.6e} | {rel} | {r['cone_violation']:.1e} |"
    )


def shared_markdown(shared):
    rows = shared["runs"]
    lines = [
        "## Side by side with so-bogus: the shared generator (headline, issue 22)",
        "",
        f"{shared['date']}: problems of `../shared/bench/gen_hair_problem.py --contacts m --pairing p --gamma 0.01 "
        "--seed 0` (20-element strands, m/5 strands, 20 % body contacts), solved by `solve_socqp(W, b, mu)` with its "
        "defaults (tolerance 1e-8 on residual.py's max-norm residual, much stricter than so-bogus's error), one "
        "process per run. Threads '1': NUMBA/OMP/OPENBLAS/MKL_NUM_THREADS=1; 'default': none set. CPU s = "
        "time.process_time() of the call (set-up included), the figure to compare on this machine: "
        f"{shared.get('cpus', '?')} cores shared with several other agents' jobs (load average at the end "
        f"{', '.join(f'{x:.1f}' for x in shared['load_at_end'])}), so wall times are inflated by the load.",
        "",
        f"so-bogus on the 30k random problem (one thread, -O3 -march=native): {BOGUS_SHARED_30K['cpu_s']} s CPU, "
        f"{BOGUS_SHARED_30K['sweeps']} sweeps, its error {BOGUS_SHARED_30K['error']:.1e}, objective "
        f"{BOGUS_SHARED_30K['objective']:.6e}.  Target: under {TARGET_SHARED_30K_CPU_S} s CPU to that accuracy "
        "(objective within 1e-6 relative, cone violation < 1e-8); 100k within 4x of the 30k time per contact.",
        "",
        SHARED_HEADER,
    ]
    lines += [shared_row(r) for r in rows]
    head = [r for r in rows if r["spec"]["m"] == 30000 and r["spec"].get("pairing") == "random" and r["label"] == "defaults"
            and r["spec"].get("threads") != "default"]
    big = [r for r in rows if r["spec"]["m"] == 100000 and r["spec"].get("pairing") == "random" and r["label"] == "defaults"]
    tc = shared.get("threads_check")
    if tc:
        lines += ["", f"One thread against the default threads, 30k, alternated pairs of processes ({tc['date']}, load "
                  f"average at the end {', '.join(f'{x:.1f}' for x in tc['load_at_end'])}):", "",
                  "| pair | CPU s, 1 thread | wall s, 1 thread | CPU s, default | wall s, default | wall default / 1 thread |",
                  "|---|---|---|---|---|---|"]
        for k, pr in enumerate(tc["pairs"]):
            o, d = pr["one"], pr["default"]
            lines.append(f"| {k + 1} | {o['cpu_s']:.2f} | {o['wall_s']:.2f} | {d['cpu_s']:.2f} | {d['wall_s']:.2f} | "
                         f"{d['wall_s'] / o['wall_s']:.2f} |")
    if head:
        h = head[0]
        lines += ["", f"30k CPU times of the {len(h['cpu_s_all'])} processes: "
                  + ", ".join(f"{x:.2f}" for x in h["cpu_s_all"]) + " s; wall " + ", ".join(f"{x:.2f}" for x in h["wall_s_all"])
                  + f" s.  so-bogus / groomtool CPU: {BOGUS_SHARED_30K['cpu_s'] / h['cpu_s']:.1f}x."]
        if big:
            per = (big[0]["cpu_s"] / 100000) / (h["cpu_s"] / 30000)
            lines.append(f"100k / 30k CPU time per contact: {per:.2f}x.")
    return lines


def write_markdown(meta, runs, cl_runs, target=None, shared=None):
    lines = [
        "# Contact solver benchmark (generated by bench/bench_solvers.py)",
        "",
    ]
    if shared:
        lines += shared_markdown(shared) + ["", "## groomtool's own generator (bench/problems.py)", ""]
    lines += [
        f"{meta['date']}, Python {meta['python']}, {meta['cpus']} CPUs (shared machine; load average at the end "
        f"{', '.join(f'{x:.1f}' for x in meta['load_at_end'])}). One core: NUMBA_NUM_THREADS=1, BLAS on one thread.",
        "Problems: bench/problems.py (S = m/4 strands of 20 elements, gamma = 0.01 relative to mean diag(W) = 1,"
        " mu in [0.2, 0.4]).  Tolerance: residual (residual.py) <= 1e-8.  gs: the defaults (Anderson and, on the"
        " assembled form, subspace Newton steps); no-Newton: Anderson only; no-AA no-Newton: plain Gauss-Seidel.",
        "",
        "## Runs",
        "",
        HEADER,
    ]
    lines += [row(r) for r in runs if "spec" in r and r.get("status") not in ("error",)]
    gs30 = [r for r in runs if r.get("m") == 30000 and r["spec"]["method"] == "gs" and r.get("form") == "assembled"
            and not r["spec"].get("options", {}).get("anderson") == 0 and "variant" not in r["spec"] and "window" not in r["spec"]]
    if gs30:
        r = gs30[0]
        lines += [
            "",
            "## Target (30,000 contacts, SOCQP, one core)",
            "",
            f"so-bogus: {BOGUS_30K_S} s (925 sweeps); target {TARGET_30K_S} s.  groomtool GS (assembled, Anderson, "
            f"subspace Newton steps: the defaults): "
            f"setup {r['setup_s']:.2f} s + solve {r['solve_s']:.2f} s (cpu {r['cpu_s']:.2f} s), {r['iterations']} sweeps, "
            f"residual {r['residual']:.1e}, bogus-style error {r['bogus_error']:.1e}.",
        ]
        if r.get("cpu_s_all"):
            lines.append(f"CPU times of the {len(r['cpu_s_all'])} repeats: "
                         + ", ".join(f"{x:.2f}" for x in r["cpu_s_all"]) + " s; solve (wall): "
                         + ", ".join(f"{x:.2f}" for x in r["solve_s_all"]) + " s.")
    if target:
        ok = [t for t in target["runs"] if "cpu_s" in t]
        lines += [
            "",
            f"Re-measured {target['date']} ({len(ok)} separate processes, load average at the end "
            f"{', '.join(f'{x:.1f}' for x in target['load_at_end'])}):",
            "",
            "| run | setup s | solve s (wall) | setup + solve s | cpu s (process) | sweeps | residual |",
            "|---|---|---|---|---|---|---|",
        ]
        for k, t in enumerate(ok):
            lines.append(f"| {k + 1} | {t['setup_s']:.2f} | {t['solve_s']:.2f} | {t['setup_s'] + t['solve_s']:.2f} | "
                         f"{t['cpu_s']:.2f} | {t['iterations']} | {t['residual']:.1e} |")
        if ok:
            best = min(ok, key=lambda t: t["setup_s"] + t["solve_s"])
            cpus = sorted(t["cpu_s"] for t in ok)
            lines.append(f"\nBest setup + solve {best['setup_s'] + best['solve_s']:.2f} s; CPU time min "
                         f"{cpus[0]:.2f} s, median {cpus[len(cpus) // 2]:.2f} s.")
    if cl_runs:
        lines += ["", "## clarabel scaling (factored SOCQP, one thread, limit "
                  f"{CLARABEL_LIMIT_S:.0f} s; a series stops at its first failure)", "",
                  "| contacts | contact graph | linear solver | status | iterations | solve s (clarabel) | total s | cpu s | "
                  "residual (residual.py) | rel. objective diff vs GS |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in cl_runs:
            sp_ = r["spec"]
            lines.append(f"| {sp_['m']:,} | {'random' if sp_.get('window') is None else 'local'} | "
                         f"{sp_['options']['linear_solver']} | {r.get('status')} | {r.get('iterations', '-')} | "
                         f"{fmt(r.get('solve_s'))} | {fmt(r.get('time_s'))} | {fmt(r.get('cpu_s'))} | "
                         f"{fmt(r.get('residual'), '{:.1e}')} | {fmt(r.get('objective_rel_diff'), '{:.1e}')} |")
    (RESULTS / "solvers.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
