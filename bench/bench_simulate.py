"""Benchmark of the forward simulator and of ``groom check`` (the issue's done-criteria).

1. USC-HairSalon styles (../shared/data/usc, metres, y up) inverted with all contacts against the USC
   head, then ``check_groom``: 1 s simulated at dt = 1/240 from the groomed shape, inverted vs naive
   (q0 = q).  Criteria: inverted max tip drift < 1 mm and < 2 % of the naive one; curly styles keep
   their curvature profile within 1 %.
2. Time per step of a 1,000-strand groom with contacts: the bundled example groom (example_groom(1000),
   its ellipsoidal head), inverted with all contacts, simulated from rest (inverted, warm-started from
   the inversion's forces as groom check does) and sagging (naive).  The example strands lie 0.24 mm
   above the head (a fibre radius plus 0.2 mm), so the contact radius is 0.3 mm for them to rest on it.

3. Stage breakdown per step of the README example's ``groom check`` runs (``--example-dir``: the output
   directory of ``groom example example && groom invert example/example.obj --head example/head.obj
   --contacts all --contact-radius 5e-4 -o example/out``), steps after the first (kernels loaded).

    python bench/bench_simulate.py [--quick] [--strands 1000] [--steps 5] [--styles 00002 00014 ...]
    python bench/bench_simulate.py --keep-styles --keep-big --example-dir example/out --example-steps 12

Prints a table and writes bench/results/simulate.md and simulate.json.  BLAS is pinned to one thread
(the per-strand systems are 30-200 dofs: threads only add contention).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "usc"
RESULTS = ROOT / "bench" / "results"

# styles whose strands are all stable in isolation (stiffness ratio < 1 at E = 3 GPa), straight and curly,
# then two long styles with strands that only contacts could hold (reported, not counted)
STYLES = ["00002", "00004", "00042", "00092", "00098", "00206", "00014", "00027", "00033", "00144", "00187",
          "00218", "00254"]
LONG_STYLES = ["00001", "00003"]


def hair_classes() -> dict:
    out = {}
    path = DATA / "hair_classes.txt"
    if path.is_file():
        for line in path.read_text().split("\n"):
            if line.strip():
                key, cls = line.split()
                out.setdefault(key.replace("strands", ""), []).append(cls)
    return out


def run_style(style: str, classes: dict, seconds: float, dt: float) -> dict:
    from groomtool.check import check_groom
    from groomtool.invert import InversionParams, invert_groom
    from groomtool.io import load_groom, load_head

    groom = load_groom(DATA / "cstrands" / f"cstrands{style}.data")
    head = load_head(DATA / "head_model.obj")
    t0 = time.perf_counter()
    result = invert_groom(groom, head, InversionParams(contacts="all"))
    invert_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        result.save(tmp)
        report = check_groom(tmp, seconds=seconds, dt=dt)
    inv, nai = report["inverted"], report["naive"]
    kinds = classes.get(style, ["?"])
    return {
        "style": style, "class": "/".join(kinds), "curly": any("curly" in k for k in kinds),
        "strands": report["strands"], "elements": report["elements"],
        "max_length_m": float(groom.lengths().max()),
        "inversion_contacts": result.report.get("contacts", {}).get("total", 0),
        "unstable_in_isolation": int(result.report["stability"]["unstable_strands"]),
        "inverted_max_tip_drift_m": inv["max_tip_drift_m"], "inverted_mean_tip_drift_m": inv["mean_tip_drift_m"],
        "naive_max_tip_drift_m": nai["max_tip_drift_m"], "naive_mean_tip_drift_m": nai["mean_tip_drift_m"],
        "drift_ratio": report["drift_ratio"],
        "inverted_curvature_change": inv["curvature_profile_change"]["max"],
        "naive_curvature_change": nai["curvature_profile_change"]["max"],
        "sim_contacts_per_step": inv["contacts_per_step"]["mean"],
        "inverted_ms_per_step": 1e3 * inv["timings_s"]["per_step"], "naive_ms_per_step": 1e3 * nai["timings_s"]["per_step"],
        "solver_failures": inv["solver"]["failures"] + nai["solver"]["failures"],
        "invert_s": invert_s,
    }


def criteria(row: dict) -> dict:
    ok_drift = row["inverted_max_tip_drift_m"] < 1e-3 and row["inverted_max_tip_drift_m"] < 0.02 * row["naive_max_tip_drift_m"]
    ok_curl = (not row["curly"]) or row["inverted_curvature_change"] < 0.01
    return {"drift_ok": bool(ok_drift), "curls_ok": bool(ok_curl)}


EXAMPLE_CONTACT_RADIUS = 3e-4  # m: covers the example groom's 0.24 mm lift above its head


def time_big_groom(n_strands: int, steps: int) -> dict:
    """Per-step time of an n-strand groom with all contacts: inverted (at rest) and naive (sagging)."""
    from groomtool.examples import example_groom
    from groomtool.invert import InversionParams, SolverFailure, invert_groom
    from groomtool.simulate import SimulationParams, Simulator

    groom, head = example_groom(n_strands)
    t0 = time.perf_counter()
    out = {"groom": f"example_groom({n_strands})", "strands": n_strands}
    # the SOCQP's optimality to 5e-4 only (its Gauss-Seidel is slow on these ~20k contacts): the
    # equilibrium is exact for whatever forces it returns, and they are inside the cones
    params = InversionParams(contacts="all", contact_radius=EXAMPLE_CONTACT_RADIUS, solver_tolerance=5e-4)
    try:
        result = invert_groom(groom, head, params)
        out["inversion"] = {"converged": True, "contacts": result.report["contacts"]["total"],
                            "solve": {k: result.report["solve"][k] for k in ("solver", "iterations", "residual")},
                            "equilibrium_max_relative_residual": result.report["equilibrium"]["max_relative_residual"]}
        rest = result.rest_curvatures
    except SolverFailure as exc:  # measure the stepping anyway, from the isolated inversion
        out["inversion"] = {"converged": False, "message": str(exc)}
        result = invert_groom(groom, head, InversionParams(contacts="none"))
        rest = result.rest_curvatures
    warm = (result.contacts, result.forces) if result.contacts is not None else None
    out["invert_s"] = time.perf_counter() - t0
    helix = result.helix
    out["elements"] = int(helix.n_elements.sum())
    out["max_elements"] = int(helix.max_elements)
    material = result.material
    for name, q0 in (("inverted", rest), ("naive", helix.curvatures.copy())):
        sim = Simulator(helix, q0, material, result.gravity, head=head, warm_start=warm if name == "inverted" else None,
                        params=SimulationParams(dt=1 / 240, contacts="all", contact_radius=EXAMPLE_CONTACT_RADIUS))
        tips0 = sim.tips()
        per_step, contacts, iters = [], [], []
        for _ in range(steps):
            t = time.perf_counter()
            system = sim.step()
            per_step.append(time.perf_counter() - t)
            contacts.append(system.stats.get("contacts", 0))
            iters.append(system.stats.get("solver_iterations", 0))
        stages = {k: v / steps for k, v in sim.timings.items()}
        out[name] = {"s_per_step_mean": float(np.mean(per_step)), "s_per_step_first": float(per_step[0]),
                     "s_per_step_last": float(per_step[-1]), "contacts_mean": float(np.mean(contacts)),
                     "solver_iterations_mean": float(np.mean(iters)), "stages_s_per_step": stages,
                     "modified_step_matrices_per_step": sim.modified_strands / steps,
                     "max_tip_drift_m": float(np.linalg.norm(sim.tips() - tips0, axis=1).max())}
    return out


def example_stages(outdir, steps: int, skin=None, cpu_time: bool = True) -> dict:
    """Per-step stages of groom check's two runs on an inversion output directory (steps after the first).
    ``cpu_time``: every timer (the simulator's stages included) reads the process CPU time instead of
    the wall clock (the machine is shared; BLAS and numba run on one thread here)."""
    if cpu_time:
        time.perf_counter = time.process_time
    from groomtool.check import load_inverted
    from groomtool.simulate import SimulationParams, Simulator

    inv = load_inverted(outdir)
    out = {"dir": str(outdir), "strands": int(inv.helix.n_strands), "elements": int(inv.helix.n_elements.sum()),
           "steps": steps}
    for name, q0 in (("inverted", inv.rest_curvatures), ("naive", inv.helix.curvatures.copy())):
        params = SimulationParams(contacts=inv.contacts, contact_radius=inv.contact_radius, detection_skin=skin)
        t = time.perf_counter()
        sim = Simulator(inv.helix, q0, inv.material, inv.gravity, head=inv.head, params=params,
                        stiffness=inv.stiffness() if name == "inverted" else None,
                        warm_start=inv.contact_forces if name == "inverted" else None)
        setup = time.perf_counter() - t
        t = time.perf_counter()
        sim.step()
        first = time.perf_counter() - t
        sim.timings.clear()
        per, sweeps, contacts = [], [], []
        tips0 = sim.tips()
        for _ in range(steps):
            t = time.perf_counter()
            system = sim.step()
            per.append(time.perf_counter() - t)
            sweeps.append(int(system.stats.get("solver_iterations", 0)))
            contacts.append(int(system.stats.get("contacts", 0)))
        out[name] = {"setup_s": setup, "first_step_s": first, "s_per_step_mean": float(np.mean(per)),
                     "s_per_step_median": float(np.median(per)), "sweeps": sweeps, "contacts_mean": float(np.mean(contacts)),
                     "stages_s_per_step": {k: v / steps for k, v in sim.timings.items()},
                     "detection_passes": sim.tracker.passes if sim.tracker else 0,
                     "max_tip_drift_m": float(np.linalg.norm(sim.tips() - tips0, axis=1).max()),
                     "modified_step_matrices_per_step": sim.modified_strands / (steps + 1),
                     "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    return out


def whole_check(outdir, label: str) -> dict:
    """``groom check OUTDIR`` in full (1 s, both runs, check_groom), every timer on the process CPU time: per run
    the total, the stages, the solves out of budget and the drifts, as check.json gives them."""
    time.perf_counter = time.process_time
    from groomtool.check import check_groom

    t = time.process_time()
    report = check_groom(outdir)
    out = {"dir": str(outdir), "code": label, "cpu_s": time.process_time() - t, "strands": report["strands"],
           "steps": report["steps"]}
    for run in ("inverted", "naive"):
        r = report[run]
        out[run] = {"total_s": r["timings_s"]["total"], "stages_s": {k: v for k, v in r["timings_s"].items()
                                                                     if k not in ("total", "steps", "per_step")},
                    "failed_solves": r["solver"]["failures"], "worst_failed_residual": r["solver"]["worst_failed_residual"],
                    "mean_sweeps": r["solver"]["mean_iterations"], "max_tip_drift_m": r["max_tip_drift_m"]}
    return out


def check_markdown(checks: list) -> list[str]:
    lines = ["", "## The README example: `groom check example/out` in full (1 s, both runs)", "",
             "CPU seconds (every timer on process time); one row per measured code. Command: "
             "`python bench/bench_simulate.py --keep-styles --keep-big --check-dir example/out --check-label LABEL` "
             "(rows accumulate in simulate.json).", "",
             "| code | run | CPU s | failed solves / 240 (worst residual) | mean sweeps | max tip drift (m) | stages (s) |",
             "|---|---|---|---|---|---|---|"]
    for c in checks:
        for run in ("inverted", "naive"):
            r = c[run]
            stages = ", ".join(f"{k} {v:.1f}" for k, v in sorted(r["stages_s"].items(), key=lambda kv: -kv[1]))
            lines.append(f"| {c['code']} | {run} | {r['total_s']:.1f} | {r['failed_solves']} "
                         f"({r['worst_failed_residual']:.1e}) | {r['mean_sweeps']:.0f} | {r['max_tip_drift_m']:.2e} | {stages} |")
    return lines


def inversion_of(outdir) -> dict:
    """How an inversion output directory was made (its report.json): input, units, contacts, radius, stabilisation."""
    path = Path(outdir) / "report.json"
    if not path.is_file():
        return {}
    r = json.loads(path.read_text())
    p = r.get("parameters", {})
    return {"input": r.get("input"), "units": r.get("input_units", "m"), "contacts": p.get("contacts"),
            "contact_radius_m": p.get("contact_radius_m"), "stabilize": p.get("stabilize")}


def stage_list(stages: dict) -> str:
    """'solve 0.069, contact_setup 0.058, ...': the stages of a step, slowest first."""
    return ", ".join(f"{k} {v:.3f}" for k, v in sorted(stages.items(), key=lambda kv: -kv[1]))


def timing_markdown(timings: dict) -> list[str]:
    """Per-step CPU time of inversion output directories (--timing-dirs), both runs of groom check."""
    lines = ["", "## Time per step of groom check's runs on inversion outputs (CPU time, steps after the first)", "",
             "| groom | strands | elements | run | s/step mean (median) | contacts | GS sweeps | modified step "
             "matrices per step | peak RSS (MB) | stages (s/step) |", "|---|---|---|---|---|---|---|---|---|---|"]
    made = []
    for name, t in timings.items():
        inv = t.get("inversion") or {}
        if inv:
            radius = f" --contact-radius {inv['contact_radius_m']:g}" if inv.get("contact_radius_m") else ""
            made.append(f"- {name}: `groom invert {inv['input']} --units {inv['units']} --head HEAD --contacts "
                        f"{inv['contacts']}{radius}` (stabilize {inv['stabilize']}), then `python bench/bench_simulate.py "
                        f"--keep-styles --keep-big --timing-dirs '{name}=OUT' --steps {t['steps']}`")
        for run in ("inverted", "naive"):
            b = t.get(run)
            if not b:
                continue
            stages = stage_list(b["stages_s_per_step"])
            sw = b["sweeps"]
            lines.append(f"| {name} | {t['strands']} | {t['elements']} | {run} | {b['s_per_step_mean']:.3f} "
                         f"({b['s_per_step_median']:.3f}) | {b['contacts_mean']:.0f} | {min(sw)}-{max(sw)} | "
                         f"{b.get('modified_step_matrices_per_step', float('nan')):.0f} | "
                         f"{b.get('peak_rss_mb', float('nan')):.0f} | {stages} |")
    if made:
        made.append("- inputs: example.obj and head.obj of `groom example --strands 1000 DIR`; harolongo's HEAD is "
                    "../shared/data/digital-salon/Retopologised_Female_Head_01_mod.obj")
    return lines + ([""] + made if made else [])


def example_markdown(example, before=None) -> list[str]:
    lines = ["", "## The README example: stages per step of groom check's runs", "",
             f"{example['strands']} strands, {example['elements']} elements, contact radius 0.5 mm, all contacts; "
             f"{example['steps']} steps after the first per run (the first loads the kernels); OpenBLAS one thread; "
             "**CPU time** (process_time: the machine is shared with other jobs, so wall-clock times are noisy; "
             "'before' and 'after' were measured one after the other, at the same load). "
             + (f"'before' is {before.get('code', 'the previous code')}, " if before else "")
             + f"'after' {example.get('code', 'this code')}, measured on the same machine under the same load.", "",
             "A few steps after the first miss the naive run's hard contact solves (from about step 27): the "
             "whole check's cost is in the table 'groom check example/out in full' below.", "",
             "Command: `python bench/bench_simulate.py --keep-styles --keep-big --example-dir example/out "
             f"--example-steps {example['steps']} --example-before BEFORE.json --example-label LABEL` (BEFORE.json: example_stages "
             "run on the previous code).", "",
             "| code | run | s/step mean (median) | contacts | GS sweeps per step | stages (s/step) |", "|---|---|---|---|---|---|"]
    for label, ex in (("before", before), ("after", example)):
        if not ex:
            continue
        for name in ("inverted", "naive"):
            b = ex[name]
            stages = stage_list(b["stages_s_per_step"])
            sw = b["sweeps"]
            lines.append(f"| {label} | {name} | {b['s_per_step_mean']:.3f} ({b['s_per_step_median']:.3f}) | "
                         f"{b['contacts_mean']:.0f} | {min(sw)}-{max(sw)} | {stages} |")
    return lines


def markdown(rows, big, meta, example=None, before=None, timings=None, checks=None) -> str:
    lines = ["# groom check and forward simulation: benchmark", "",
             f"{meta['date']} on {meta['machine']} ({meta['cpus']} CPUs), Python {meta['python']}; "
             f"{meta['seconds']:g} s simulated at dt = 1/{round(1 / meta['dt'])} s; material: E = 3 GPa, r = 40 um, "
             "rho = 1300 kg/m^3, mu = 0.3; contact radius 50 um; inversion with contacts all against the USC head.", "",
             "## USC styles: inverted vs naive after 1 s", "",
             "| style | class | strands | elements | longest (m) | contacts (inv.) | unstable alone | inverted max drift (m) | "
             "naive max drift (m) | ratio | curvature change inv. / naive | ms/step inv. / naive | criteria |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = criteria(r)
        verdict = "ok" if c["drift_ok"] and c["curls_ok"] else ("drift FAIL" if not c["drift_ok"] else "curls FAIL")
        lines.append(
            f"| {r['style']} | {r['class']} | {r['strands']} | {r['elements']} | {r['max_length_m']:.3f} | "
            f"{r['inversion_contacts']} | {r['unstable_in_isolation']} | {r['inverted_max_tip_drift_m']:.2e} | "
            f"{r['naive_max_tip_drift_m']:.2e} | {r['drift_ratio']:.1e} | "
            f"{100 * r['inverted_curvature_change']:.2e} % / {100 * r['naive_curvature_change']:.1f} % | "
            f"{r['inverted_ms_per_step']:.0f} / {r['naive_ms_per_step']:.0f} | {verdict} |")
    if big:
        lines += ["", f"## Time per step: {big['groom']} with all contacts (contact radius 0.3 mm), "
                  "measured before the simulator work of issue 15 (kept for comparison: `--keep-big`)", "",
                  f"{big['strands']} strands, {big['elements']} elements (up to {big['max_elements']} per strand); "
                  f"inversion: {json.dumps(big['inversion'])}", "",
                  "| run | s/step (mean) | first / last | contacts | GS sweeps | modified step matrices | stages (s/step) |",
                  "|---|---|---|---|---|---|---|"]
        for name in ("inverted", "naive"):
            b = big[name]
            stages = ", ".join(f"{k} {v:.2f}" for k, v in b["stages_s_per_step"].items())
            lines.append(f"| {name} | {b['s_per_step_mean']:.2f} | {b['s_per_step_first']:.2f} / {b['s_per_step_last']:.2f} | "
                         f"{b['contacts_mean']:.0f} | {b['solver_iterations_mean']:.0f} | "
                         f"{b['modified_step_matrices_per_step']:.0f} | {stages} |")
    if example:
        lines += example_markdown(example, before)
    if timings:
        lines += timing_markdown(timings)
    if checks:
        lines += check_markdown(checks)
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="three styles, 100 strands for the timing")
    ap.add_argument("--styles", nargs="*", default=None)
    ap.add_argument("--strands", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--dt", type=float, default=1 / 240)
    ap.add_argument("--no-long", action="store_true", help="skip the long styles with isolation-unstable strands")
    ap.add_argument("--no-styles", action="store_true", help="only the timing of the large groom")
    ap.add_argument("--keep-styles", action="store_true", help="reuse the style rows of simulate.json")
    ap.add_argument("--keep-big", action="store_true", help="reuse the large-groom timing of simulate.json")
    ap.add_argument("--example-dir", default=None, help="an inversion of the README example: stage breakdown")
    ap.add_argument("--example-steps", type=int, default=12)
    ap.add_argument("--example-before", default=None,
                    help="a JSON of example_stages measured on the previous code, shown as 'before'")
    ap.add_argument("--example-label", default=None, help="what the measured code is (e.g. a commit), in the table")
    ap.add_argument("--check-dir", default=None, help="an inversion of the README example: groom check in full")
    ap.add_argument("--check-label", default="this code", help="what the measured code is, in the check table")
    ap.add_argument("--timing-dirs", nargs="*", default=None, metavar="NAME=DIR",
                    help="inversion output directories to time both runs of (steps: --steps), e.g. harolongo=out")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if not DATA.is_dir():
        print(f"USC data not found at {DATA}", file=sys.stderr)
        return 1
    styles = args.styles or (STYLES[:1] + STYLES[6:8] if args.quick else STYLES + ([] if args.no_long else LONG_STYLES))
    classes = hair_classes()
    rows = []
    if args.keep_styles and (RESULTS / "simulate.json").is_file():
        rows = json.loads((RESULTS / "simulate.json").read_text())["styles"]
        styles = []
    elif args.no_styles:
        styles = []
    for style in styles:
        t = time.perf_counter()
        row = run_style(style, classes, args.seconds, args.dt)
        rows.append(row)
        c = criteria(row)
        print(f"{style} {row['class']:<14} inverted {row['inverted_max_tip_drift_m']:.2e} m  naive "
              f"{row['naive_max_tip_drift_m']:.2e} m  ratio {row['drift_ratio']:.1e}  curv {row['inverted_curvature_change']:.1e}"
              f"  unstable {row['unstable_in_isolation']}  {'ok' if all(c.values()) else 'FAIL'}  ({time.perf_counter() - t:.0f} s)",
              flush=True)
    previous = json.loads((RESULTS / "simulate.json").read_text()) if (RESULTS / "simulate.json").is_file() else {}
    n_big = 100 if args.quick else args.strands
    if args.keep_big:
        big = previous.get("big")
    else:
        big = time_big_groom(n_big, args.steps) if n_big else None
    example = example_stages(args.example_dir, args.example_steps) if args.example_dir else previous.get("example")
    if args.example_dir and args.example_label:
        example["code"] = args.example_label
    timings = dict(previous.get("timings") or {})
    for t in timings.values():
        if not t.get("inversion"):
            t["inversion"] = inversion_of(t["dir"])
    for spec in args.timing_dirs or []:
        name, _, path = spec.partition("=")
        timings[name] = example_stages(path, args.steps)
        timings[name]["inversion"] = inversion_of(path)
        print(f"{name}: " + ", ".join(f"{run} {timings[name][run]['s_per_step_mean']:.2f} s/step"
                                       for run in ("inverted", "naive")), flush=True)
    before = json.loads(Path(args.example_before).read_text()) if args.example_before else previous.get("example_before")
    checks = list(previous.get("checks") or [])
    if args.check_dir:
        checks.append(whole_check(args.check_dir, args.check_label))
        print(f"groom check {args.check_dir}: " + ", ".join(f"{run} {checks[-1][run]['total_s']:.0f} s CPU, "
                                                          f"{checks[-1][run]['failed_solves']} failed solves"
                                                          for run in ("inverted", "naive")), flush=True)
    if big and not args.keep_big:
        for name in ("inverted", "naive"):
            print(f"{big['groom']} {name}: {big[name]['s_per_step_mean']:.2f} s/step, {big[name]['contacts_mean']:.0f} contacts",
                  flush=True)
    meta = {"date": time.strftime("%Y-%m-%d"), "machine": platform.machine(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "seconds": args.seconds, "dt": args.dt}
    RESULTS.mkdir(parents=True, exist_ok=True)
    stable = [r for r in rows if r["style"] not in LONG_STYLES]
    summary = {"styles_checked": len(stable),
               "styles_passing": sum(all(criteria(r).values()) for r in stable),
               "max_inverted_drift_m": max((r["inverted_max_tip_drift_m"] for r in stable), default=0.0),
               "max_drift_ratio": max((r["drift_ratio"] for r in stable), default=0.0),
               "max_curly_curvature_change": max((r["inverted_curvature_change"] for r in stable if r["curly"]), default=0.0)}
    (RESULTS / "simulate.json").write_text(json.dumps({"meta": meta, "summary": summary, "styles": rows, "big": big,
                                                       "example": example, "example_before": before,
                                                       "timings": timings, "checks": checks},
                                                      indent=2, default=float) + "\n")
    (RESULTS / "simulate.md").write_text(markdown(rows, big, meta, example, before, timings, checks))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
