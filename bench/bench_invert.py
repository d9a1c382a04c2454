"""End-to-end inversion on whole real grooms with their heads: the stage breakdown of `groom invert`.

Grooms (../shared/data, see MANIFEST.md there):
- harolongo: digital-salon/harolongo.data (7,905 strands, centimetres) with its head
  digital-salon/Retopologised_Female_Head_01_mod.obj, roots snapped onto the head (96 % lie inside it);
- example<N> (e.g. example1000): groomtool.examples.example_groom(N) with its head, contact radius 0.3 mm (issue
  16's dense case);
- usc10k: 10,000 strands grown from cstrands00003's guides on usc/roots10k.obj (as in bench_fit.py) with
  the USC head usc/head_model.obj.

Each (groom, contact mode) runs `groomtool.invert.invert_groom` in its own subprocess with one thread
(numba, BLAS) and reports the wall seconds of every stage (report.json's timings_s), the process CPU time,
the peak resident memory, the contact counts and the solver's outcome.  A solve that does not reach its
tolerance within --max-sweeps keeps its feasible forces (status `feasible`, its residual and the certified
rest-curvature error bound q0_error_bound; the later stages run); with --strict invert raises SolverFailure
instead (the stages up to the solve are still timed).  Loading the files is timed apart (`load`).  Writes bench/results/invert.md
and invert.json.

    python bench/bench_invert.py                          # both grooms, contacts head and all
    python bench/bench_invert.py --grooms harolongo --modes all --max-sweeps 300
    python bench/bench_invert.py --grooms example1000 --modes all --admm dense   # ADMM with dense strand factors
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = ROOT.parent / "shared" / "data"
RESULTS = HERE / "results"
STAGES = ("snap_roots", "fit", "kinematics", "contacts", "jacobian", "solve", "rest_curvatures", "discrete_rest_data",
          "equilibrium_check", "stability", "stability_with_contacts")


EXAMPLE_CONTACT_RADIUS = 3e-4  #: issue 16's dense case: example_groom(1000), all contacts at 0.3 mm (67,805)


def _load(name: str):
    sys.path.insert(0, str(HERE))
    from bench_fit import harolongo, usc10k

    from groomtool.io import load_head

    if name == "harolongo":
        return harolongo(), load_head(DATA / "digital-salon" / "Retopologised_Female_Head_01_mod.obj", units="cm"), True
    if name == "usc10k":
        return usc10k(), load_head(DATA / "usc" / "head_model.obj"), False
    if name.startswith("example"):  # example<N>: groomtool.examples.example_groom(N) with its head (issue 16)
        from groomtool.examples import example_groom

        groom, head = example_groom(int(name[len("example"):]))
        return groom, head, False
    raise ValueError(f"unknown groom {name!r}")


def run_child(spec: dict) -> dict:
    import resource

    from groomtool.invert import InversionParams, SolverFailure, invert_groom

    t0, c0 = time.perf_counter(), time.process_time()
    groom, head, snap = _load(spec["groom"])
    load_s = time.perf_counter() - t0
    extra = {k: spec[k] for k in ("q0_tolerance", "strict", "contact_radius") if k in spec}
    params = InversionParams(contacts=spec["mode"], snap_roots=snap, max_sweeps=spec["max_sweeps"],
                             solver=spec.get("solver", "auto"), **extra)
    if spec.get("admm") == "dense":  # the strand-split ADMM with dense strand factors (as before issue 16's O(n_s) x-step)
        sys.modules["groomtool.invert"].admm_geometry = lambda *args: None
    c1 = time.process_time()
    out: dict = {"spec": spec, "load_s": load_s, "strands": groom.n_strands}
    try:
        result = invert_groom(groom, head=head, params=params)
        report = result.report
        out["converged"] = report.get("solve", {}).get("status", "solved") == "solved"
    except SolverFailure as exc:
        report = exc.report
        out["converged"] = False
        out["failure"] = str(exc)
    out["cpu_s"] = time.process_time() - c1
    out["load_cpu_s"] = c1 - c0
    out["rss_peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["timings_s"] = report.get("timings_s", {})
    out["contacts"] = report.get("contacts")
    out["solve"] = {k: v for k, v in report.get("solve", {}).items() if not isinstance(v, (list, dict))}
    out["elements"] = report.get("elements")
    out["equilibrium"] = report.get("equilibrium")
    out["stability"] = {k: report.get("stability", {}).get(k) for k in ("unstable_strands", "unstable_with_contacts")}
    return out


def child(spec: dict, timeout: float) -> dict:
    """One row, run in its own process; stamped with when it ran and the machine's load then (``measured``:
    rows appended later keep their own)."""
    out = _child(spec, timeout)
    out["measured"] = f"{time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.1f}"
    return out


def _child(spec: dict, timeout: float) -> dict:
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"spec": spec, "error": f"timeout after {timeout:.0f} s", "wall_s": time.perf_counter() - t}
    if p.returncode != 0:
        return {"spec": spec, "error": p.stderr[-1500:]}
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - t
    return out


def _f(x, f="{:.2f}"):
    return "-" if x is None else f.format(x)


def _radius(spec: dict) -> str:
    out = f" (r_c {1e3 * spec['contact_radius']:g} mm)" if "contact_radius" in spec else ""
    return out + (" [ADMM: dense strand factors]" if spec.get("admm") == "dense" else "")


def markdown(meta: dict, runs: list[dict]) -> str:
    lines = [
        "# End-to-end inversion on whole grooms (generated by bench/bench_invert.py)",
        "",
        f"Last written {meta['date']}, Python {meta['python']}, {meta['cpus']} CPUs (shared machine; load average at "
        f"the end of that run {', '.join(f'{x:.1f}' for x in meta['load_at_end'])}; each row's own date and 1-minute "
        f"load in its `measured` column, '-' for rows from before that column). One thread (numba, BLAS), each run in its own "
        f"process, numba caches warm. Solver: `auto` unless the row says otherwise (Gauss-Seidel for sparse contacts, "
        f"clarabel + Gauss-Seidel polish for dense ones up to 10,000 contacts, beyond that Gauss-Seidel until issue 16, "
        f"since then the strand-split ADMM `admm`: docs/solvers.md sections 9 and 12; `sweeps / its` then counts ADMM "
        f"iterations), "
        f"tolerance 1e-8, at most the row's sweep budget (a row that is not converged stopped there, or earlier "
        f"when its rate projected more than twice the budget over the last fifth of the run: `stalled`); since issue 16 such a "
        f"run keeps its feasible forces (`feasible`, later stages run) unless `--strict`. `q0 bound`: the certified relative "
        f"rest-curvature error of the forces written (docs/solvers.md section 11); the solve stops once it is below "
        f"--q0-tolerance (1e-3 by default, `solved (q0)`).",
        "",
        "Stage columns are wall seconds of `invert_groom` (report.json `timings_s`); `cpu` is the process CPU "
        "time of invert_groom (loading excluded).",
        "",
        "| groom | contacts mode | strands | elements | contacts (head / s-s) | solver (asked) | status | sweeps / its (budget) | "
        "residual | q0 bound | " + " | ".join(STAGES) + " | total s | cpu s | peak MB | measured |",
        "|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(STAGES) + "---|---|---|---|",
    ]
    for r in runs:
        s = r["spec"]
        if "error" in r:
            lines.append(f"| {s['groom']} | {s['mode']} | error: {r['error'][:200]!r} ({r.get('measured', '-')}) |")
            continue
        c = r.get("contacts") or {}
        sv = r.get("solve") or {}
        t = r["timings_s"]
        its = sv.get("iterations")
        if sv.get("polish_sweeps"):
            its = f"{its} + {sv['polish_sweeps']} polish"
        if r["converged"]:
            status = "solved (q0)" if sv.get("stopped_on") == "q0_tolerance" else "solved"
        elif sv.get("status") == "feasible":
            status = f"feasible ({sv.get('stopped_with')})"
        else:
            status = f"NOT converged ({sv.get('status')})"
        if sv.get("projected_sweeps"):
            status += f", projected {sv['projected_sweeps']:,.0f} sweeps"
        lines.append(
            f"| {s['groom']}{_radius(s)} | {s['mode']} | {r['strands']:,} | {_f(r.get('elements'), '{:,}')} | "
            + (f"{c.get('total', 0):,} ({c.get('strand_head', 0):,} / {c.get('strand_strand', 0):,})" if c else "-")
            + f" | {sv.get('solver', '-')} ({s.get('solver', 'auto')}) | {status} | "
            f"{its if its is not None else '-'} ({s['max_sweeps']}) | "
            f"{_f(sv.get('residual'), '{:.1e}')} | {_f(sv.get('q0_error_bound'), '{:.1e}')} | "
            + " | ".join(_f(t.get(k)) for k in STAGES)
            + f" | {_f(sum(v for k, v in t.items() if k != 'total'))} | {_f(r['cpu_s'])} | {r['rss_peak_mb']:.0f} | "
            f"{r.get('measured', '-')} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child")
    ap.add_argument("--grooms", default="harolongo,usc10k")
    ap.add_argument("--modes", default="none,head,all")
    ap.add_argument("--max-sweeps", type=int, default=500)
    ap.add_argument("--solver", default="auto", choices=["auto", "gs", "clarabel", "admm"])
    ap.add_argument("--q0-tolerance", type=float, default=None, help="(default: invert's own)")
    ap.add_argument("--strict", action="store_true")
    ap.add_argument("--admm", default="structured", choices=["structured", "dense"],
                    help="the strand-split ADMM's strand systems: semiseparable factors (Super-Helices, the default) or "
                         "the dense Cholesky factors (as before)")
    ap.add_argument("--append", action="store_true", help="add the rows to the existing results file")
    ap.add_argument("--timeout", type=float, default=1800)
    ap.add_argument("--out", type=Path, default=RESULTS / "invert")
    ap.add_argument("--from-json", action="store_true", help="rewrite the .md from the .json")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(run_child(json.loads(args.child))))
        return
    if args.from_json:
        data = json.loads(args.out.with_suffix(".json").read_text())
        args.out.with_suffix(".md").write_text(markdown(data["meta"], data["runs"]))
        return
    runs = []
    if args.append and args.out.with_suffix(".json").exists():
        runs = json.loads(args.out.with_suffix(".json").read_text())["runs"]
    for groom in args.grooms.split(","):
        for mode in args.modes.split(","):
            spec = {"groom": groom, "mode": mode, "max_sweeps": args.max_sweeps, "solver": args.solver}
            if args.q0_tolerance is not None:
                spec["q0_tolerance"] = args.q0_tolerance or None
            if args.strict:
                spec["strict"] = True
            if args.admm == "dense":
                spec["admm"] = "dense"
            if groom.startswith("example"):
                spec["contact_radius"] = EXAMPLE_CONTACT_RADIUS
            runs.append(child(spec, args.timeout))
            r = runs[-1]
            print(json.dumps({k: r.get(k) for k in ("spec", "converged", "cpu_s", "timings_s", "contacts", "error")}),
                  flush=True)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "python": sys.version.split()[0], "cpus": os.cpu_count(),
            "machine": platform.machine(), "load_at_end": os.getloadavg(), "max_sweeps": args.max_sweeps}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "runs": runs}, indent=1))
    args.out.with_suffix(".md").write_text(markdown(meta, runs))
    print(markdown(meta, runs))


if __name__ == "__main__":
    main()
