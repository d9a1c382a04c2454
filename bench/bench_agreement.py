"""Agreement of the Gauss-Seidel (GS) and clarabel contact solvers on every USC-HairSalon style with the head.

Issue goal: "GS and clarabel objectives within 1e-6 relative on every USC style with head".  For each style
of ../shared/data/usc/cstrands (343 styles of 5 guide strands, metres, y up) and the USC head mesh, the
inverse contact problem of ``groom invert --contacts all`` is built ONCE with the pipeline's own functions
(groomtool.invert: fit_groom -> kinematics, sample -> detect_contacts(head, strand_strand) ->
contact_jacobian -> gravity_force -> build_inverse_problem, the ContactProblem of inverse_problem.solve_inverse_problem) and solved
with both solvers (solve_contact_problem, method "clarabel" and "gs", tol 1e-8, max_iter 5000, as
inverse_problem.solve_inverse_problem does).  Reported per style and solver: status, iterations, the solvers' common residual
(residual.py), wall time (SolveResult.time_s, set-up included; best of --repeat runs, after a numba
warm-up), the cone violation (inverse_problem.cone_violation, newtons) and two objective differences:

* ``rel_phys``    |f_gs - f_cl| / max(|f_cl|, tiny), f = InverseProblem.objective(r) in physical units
                  (the issue's criterion).  f = w f^2 J + 1/2 ||d||^2 where J is the SOCQP objective in
                  solver units and 1/2 ||d||^2 the contact-free part (r = 0), which usually dominates;
* ``rel_contact`` |J_gs - J_cl| / max(|J_cl|, |J_gs|, J_scale), the difference of the contact part alone
                  (J <= 0, the decrease of f that the contacts buy): the stricter figure.  J_scale =
                  1/2 sum_i rho_i ||b_i||^2 (rho_i = 3 / tr W_ii), the decrease the contacts would buy one by
                  one without cones: a floor for styles whose optimum is r = 0 (J = 0: no contact is loaded),
                  where clarabel's interior point returns J ~ 1e-10 and GS exactly 0.

Two series: the default contact radius (50 um; styles without contacts are counted apart) and a "wisp"
radius of 2 mm (more head contacts).  clarabel is skipped above --clarabel-max contacts (20,000).
When a style has rel_contact > 1e-6, clarabel is re-run at a tighter tolerance of its own
(clarabel_socqp.solve_factored, --tight-tol) to tell solver accuracy from disagreement.
One thread (numba, BLAS).  Writes bench/results/agreement.md and agreement.json.

    python bench/bench_agreement.py                       # both series, every style (a few minutes)
    python bench/bench_agreement.py --styles 20 --radius 2e-3 --out /tmp/agreement   # quick look
    python bench/bench_agreement.py --data DIR            # DIR holds usc/cstrands and usc/head_model.obj
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from groomtool.contact import DEFAULT_CONTACT_RADIUS, detect_contacts  # noqa: E402
from groomtool.contact.head import as_head_surface  # noqa: E402
from groomtool.contact.jacobian import contact_jacobian  # noqa: E402
from groomtool.fit import fit_groom  # noqa: E402
from groomtool.inverse_problem import build_inverse_problem, cone_violation  # noqa: E402
from groomtool.invert import InversionParams  # noqa: E402
from groomtool.io import load_head, read_data  # noqa: E402
from groomtool.rods import superhelix as sh  # noqa: E402
from groomtool.solvers import solve_contact_problem  # noqa: E402
from groomtool.solvers.clarabel_socqp import solve_factored  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RESULTS = HERE / "results"
TINY = np.finfo(float).tiny
CRITERION = 1e-6
WISP_RADIUS = 2e-3
BUCKETS = ((1, 10), (10, 100), (100, 1000), (1000, 10_000), (10_000, None))
SOLVERS = ("clarabel", "gs")


# ----------------------------------------------------------------------------------------------
# one style
# ----------------------------------------------------------------------------------------------
def build(path: Path, head, radius: float, params: InversionParams):
    """The inverse problem of ``invert_groom`` with contacts="all": (helix, contacts, InverseProblem,
    ContactProblem, build seconds).  ContactProblem as in inverse_problem.solve_inverse_problem."""
    material = params.material
    groom = read_data(path, repair=True)  # cstrands00356 needs the repair (a duplicated vertex)
    gravity = groom.gravity(material.gravity)
    t0 = time.perf_counter()
    helix = fit_groom(groom, tolerance=params.tolerance, relative_tolerance=params.relative_tolerance).helix
    kin = sh.kinematics(helix)
    pts, offsets, _, arc = sh.sample(helix, params.samples_per_element, kin)
    contacts = detect_contacts(pts, offsets, arc, radius=radius, head=head, strand_strand=True)
    H = contact_jacobian(helix, contacts, kin)
    mu = np.full(len(contacts.strand_a), material.friction)
    F = sh.gravity_force(helix, material.linear_density, gravity, kin)
    problem = build_inverse_problem(helix, F, H, material, gravity, params.guess, params.gamma, mu)
    cp = problem.contact_problem(helix)
    return helix, contacts, problem, cp, time.perf_counter() - t0


def solve(problem, cp, method: str, params: InversionParams, repeat: int, **options) -> dict:
    """Best-of-``repeat`` wall time; the solvers are deterministic, the last result is kept.  clarabel runs
    with polish=False (its own interior point, independent of GS) unless ``options`` say otherwise."""
    if method == "clarabel":
        options.setdefault("polish", False)
    times = []
    for _ in range(max(1, repeat)):
        res = solve_contact_problem(cp, law="soc", method=method, tol=params.solver_tolerance,
                                    max_iter=params.max_sweeps, **options)
        times.append(res.time_s)
    forces = np.asarray(res.r).reshape(-1, 3) * problem.f_scale
    return {
        "status": str(res.status), "converged": bool(res.converged), "iterations": int(res.iterations),
        "residual": float(res.residual), "time_s": float(min(times)),
        "setup_s": res.info.get("setup_s"), "solve_s": res.info.get("solve_s"), "form": res.info.get("form"),
        "objective": problem.objective(forces.ravel()), "objective_solver_units": float(res.objective),
        "cone_violation_N": cone_violation(forces, problem.mu),
        # loaded contacts: r_N above 1e-6 of the largest free reaction (clarabel's interior point leaves
        # r_N ~ 1e-10 on unloaded ones)
        "active": int(np.count_nonzero(res.r.reshape(-1, 3)[:, 0] > 1e-6 * cp.residual_scale())),
        "polish_sweeps": int(res.info.get("polish_sweeps", 0)),
        "_r": np.asarray(res.r),
    }


def rel(a: float, b: float) -> float:
    """|a - b| / max(|b|, tiny)."""
    return abs(a - b) / max(abs(b), TINY)


def j_scale(cp) -> float:
    """1/2 sum_i rho_i ||b_i||^2, rho_i = 3 / tr W_ii (solver units): the objective scale of the contact part."""
    b = np.asarray(cp.b).reshape(-1, 3)
    return 0.5 * float(np.sum(cp.rho() * np.einsum("ij,ij->i", b, b)))


def rel_contact(j_gs: float, j_cl: float, scale: float) -> float:
    return abs(j_gs - j_cl) / max(abs(j_cl), abs(j_gs), scale, TINY)


def tight_clarabel(problem, cp, gs_row: dict, tol: float) -> dict:
    """clarabel at its own tolerance ``tol`` (its gap / feasibility tolerances; inverse_problem.solve_inverse_problem leaves its
    default 1e-9): does the difference to GS shrink with clarabel's residual?"""
    t0 = time.perf_counter()
    out = solve_factored(cp, tol=tol, max_iter=400)
    t = time.perf_counter() - t0
    r = np.asarray(out.r)
    forces = r.reshape(-1, 3) * problem.f_scale
    J = cp.objective(r)
    return {"tol": tol, "status": out.status, "iterations": out.iterations, "residual": cp.residual(r),
            "time_s": t, "objective": problem.objective(forces.ravel()), "objective_solver_units": J,
            "rel_phys": rel(gs_row["objective"], problem.objective(forces.ravel())),
            "rel_contact": rel_contact(gs_row["objective_solver_units"], J, j_scale(cp))}


def run_style(path: Path, head, radius: float, params: InversionParams, args) -> dict:
    row: dict = {"style": path.stem.removeprefix("cstrands"), "radius_m": radius}
    try:
        helix, contacts, problem, cp, build_s = build(path, head, radius, params)
    except Exception as exc:  # noqa: BLE001 - a bench row, not a crash
        row["error"] = f"build: {type(exc).__name__}: {exc}"
        return row
    m = len(problem.mu)
    strand_b = np.asarray(contacts.strand_b)
    row.update(strands=int(helix.n_strands), elements=int(helix.n_elements.sum()), contacts=m,
               head_contacts=int(np.count_nonzero(strand_b < 0)),
               strand_contacts=int(np.count_nonzero(strand_b >= 0)), build_s=build_s,
               contact_free_objective=0.5 * float(problem.d @ problem.d))
    if m == 0:
        return row
    for method in SOLVERS:
        if method == "clarabel" and m > args.clarabel_max:
            row["clarabel"] = {"status": "skipped", "reason": f"{m} contacts > {args.clarabel_max}"}
            continue
        try:
            row[method] = solve(problem, cp, method, params, args.repeat)
        except Exception as exc:  # noqa: BLE001
            row[method] = {"status": "error", "error": f"{type(exc).__name__}: {exc}"}
    cl, gs = row.get("clarabel", {}), row.get("gs", {})
    if "objective" in cl and "objective" in gs:
        row["rel_phys"] = rel(gs["objective"], cl["objective"])
        row["j_scale"] = j_scale(cp)
        row["rel_contact"] = rel_contact(gs["objective_solver_units"], cl["objective_solver_units"], row["j_scale"])
        rc, rg = cl["_r"].reshape(-1, 3), gs["_r"].reshape(-1, 3)
        row["force_diff"] = float(np.max(np.linalg.norm(rc - rg, axis=1))
                                  / max(float(np.max(np.linalg.norm(rc, axis=1))), cp.residual_scale(), TINY))
        # what the inversion uses: clarabel's point polished by Gauss-Seidel to the tolerance (solvers.api)
        pol = solve(problem, cp, "clarabel", params, 1, polish=True)
        row["clarabel_polished"] = {k: pol[k] for k in ("status", "converged", "residual", "polish_sweeps",
                                                         "time_s", "cone_violation_N")}
        row["clarabel_polished"]["rel_contact"] = rel_contact(gs["objective_solver_units"],
                                                              pol["objective_solver_units"], row["j_scale"])
        if args.tight_tol and row["rel_contact"] > CRITERION:
            try:
                row["clarabel_tight"] = tight_clarabel(problem, cp, gs, args.tight_tol)
            except Exception as exc:  # noqa: BLE001
                row["clarabel_tight"] = {"status": "error", "error": f"{type(exc).__name__}: {exc}"}
    for method in SOLVERS:
        row.get(method, {}).pop("_r", None)
    return row


# ----------------------------------------------------------------------------------------------
# summaries
# ----------------------------------------------------------------------------------------------
def warm_up(head, params, data: Path, style: str = "cstrands00003.data") -> None:
    """Compile / load numba's caches before anything is timed."""
    path = data / "usc" / "cstrands" / style
    if not path.exists():
        path = sorted((data / "usc" / "cstrands").glob("*.data"))[0]
    _, _, problem, cp, _ = build(path, head, WISP_RADIUS, params)
    if len(problem.mu):
        for method in SOLVERS:
            solve_contact_problem(cp, law="soc", method=method, tol=1e-8, max_iter=50)


def summarize(rows: list[dict]) -> dict:
    withc = [r for r in rows if r.get("contacts")]
    both = [r for r in withc if "rel_phys" in r]
    counts = np.array([r["contacts"] for r in withc]) if withc else np.zeros(0)

    def worst(key, method):
        vals = [r[method][key] for r in withc if isinstance(r.get(method), dict) and key in r[method]]
        return max(vals) if vals else None

    failures = {m: [r["style"] for r in withc if not r.get(m, {}).get("converged")
                    and r.get(m, {}).get("status") != "skipped"] for m in SOLVERS}
    return {
        "styles": len(rows),
        "errors": [r["style"] for r in rows if "error" in r],
        "styles_with_contacts": len(withc),
        "styles_without_contacts": sum(1 for r in rows if r.get("contacts") == 0),
        "total_contacts": int(counts.sum()),
        "head_contacts": int(sum(r["head_contacts"] for r in withc)),
        "strand_contacts": int(sum(r["strand_contacts"] for r in withc)),
        "max_contacts": int(counts.max()) if len(counts) else 0,
        "median_contacts": float(np.median(counts)) if len(counts) else 0.0,
        "compared": len(both),
        "clarabel_skipped": [r["style"] for r in withc if r.get("clarabel", {}).get("status") == "skipped"],
        "max_rel_phys": max((r["rel_phys"] for r in both), default=None),
        "above_phys": [r["style"] for r in both if r["rel_phys"] > CRITERION],
        "max_rel_contact": max((r["rel_contact"] for r in both), default=None),
        "above_contact": [r["style"] for r in both if r["rel_contact"] > CRITERION],
        "max_force_diff": max((r["force_diff"] for r in both), default=None),
        "worst_residual": {m: worst("residual", m) for m in SOLVERS},
        "worst_cone_violation_N": {m: worst("cone_violation_N", m) for m in SOLVERS},
        "max_iterations": {m: worst("iterations", m) for m in SOLVERS},
        "failures": failures,
        "tight": [{"style": r["style"], **r["clarabel_tight"]} for r in both if "clarabel_tight" in r],
        "polished_not_converged": [r["style"] for r in both if not r["clarabel_polished"]["converged"]],
        "polished_worst_residual": max((r["clarabel_polished"]["residual"] for r in both), default=None),
        "polished_max_rel_contact": max((r["clarabel_polished"]["rel_contact"] for r in both), default=None),
        "polished_max_sweeps": max((r["clarabel_polished"]["polish_sweeps"] for r in both), default=None),
    }


def crossover(rows: list[dict]) -> list[dict]:
    out = []
    for lo, hi in BUCKETS:
        sel = [r for r in rows if r.get("contacts", 0) >= lo and (hi is None or r["contacts"] < hi)]
        item = {"bucket": f"{lo:,}-{hi:,}" if hi else f">= {lo:,}", "styles": len(sel)}
        for m in SOLVERS:
            t = [r[m]["time_s"] for r in sel if "time_s" in r.get(m, {})]
            item[f"{m}_median_s"] = float(np.median(t)) if t else None
            item[f"{m}_max_s"] = float(np.max(t)) if t else None
        out.append(item)
    return out


def fmt(x, f="{:.1e}"):
    return "-" if x is None else f.format(x)


def styles_list(styles, n=12):
    if not styles:
        return "0"
    more = f", ... (+{len(styles) - n})" if len(styles) > n else ""
    return f"{len(styles)} ({', '.join(styles[:n])}{more})"


def markdown(meta: dict, series: list[dict]) -> str:
    lines = [
        "# GS / clarabel agreement on the USC-HairSalon styles (generated by bench/bench_agreement.py)",
        "",
        f"{meta['date']}; `{meta['command']}`; run time {meta['run_s']:.0f} s.",
        f"Machine: {meta['machine']}, {meta['cpus']} CPUs, shared: load average at the start "
        f"{', '.join(f'{x:.2f}' for x in meta['load_start'])}, at the end "
        f"{', '.join(f'{x:.2f}' for x in meta['load_end'])}. One thread (numba, BLAS). Python {meta['python']}, "
        f"numpy {meta['numpy']}.",
        "",
        f"Problem: `groom invert --contacts all` with the USC head, built once per style with the pipeline's "
        f"functions (fit tolerance {meta['tolerance_m'] * 1e3:.1f} mm, gamma {meta['gamma']}, guess "
        f"{meta['guess']}, friction {meta['friction']}); both solvers on the same ContactProblem as inverse_problem.solve_inverse_problem "
        f"(tol {meta['solver_tolerance']:.0e}, max_iter {meta['max_iterations']}). \"clarabel\" is its own interior "
        "point (`polish=False`, default tolerance 1e-9), independent of GS; \"clarabel + polish\" is what the "
        "inversion uses (Gauss-Seidel sweeps from clarabel's optimum until the residual meets tol). "
        "Times: SolveResult.time_s (set-up included), "
        f"best of {meta['repeat']}.",
        "",
        "* **rel. objective (criterion)**: |f_gs - f_cl| / |f_cl|, f = InverseProblem.objective (physical units). "
        "f includes the contact-free part 1/2 ||d||^2 (r = 0), which usually dominates;",
        "* **rel. contact part**: |J_gs - J_cl| / max(|J_cl|, |J_gs|, J_scale), J the SOCQP objective in solver "
        "units (f = w_scale f_scale^2 J + 1/2 ||d||^2, J <= 0): the stricter figure. J_scale = 1/2 sum_i rho_i "
        "||b_i||^2 (rho_i = 3 / tr W_ii) floors the denominator for styles whose optimum is r = 0 (no contact "
        "loaded: GS returns J = 0 exactly, clarabel's interior point J ~ 1e-10);",
        "* **force diff**: max_i ||r_gs,i - r_cl,i|| / max(max_i ||r_cl,i||, max_i rho_i ||b_i||) (solver units); "
        "active contacts: r_N > 1e-6 max_i rho_i ||b_i||;",
        "* **residual**: residual.py (max-norm natural map, relative), the measure GS stops on; cone violation in "
        "newtons (inverse_problem.cone_violation).",
        "",
        "## Summary",
        "",
        "| | " + " | ".join(s["label"] for s in series) + " |",
        "|---|" + "---|" * len(series),
    ]

    def line(name, fn):
        lines.append(f"| {name} | " + " | ".join(fn(s["summary"]) for s in series) + " |")

    line("styles", lambda s: f"{s['styles']}" + (f" ({len(s['errors'])} errors: {', '.join(s['errors'])})"
                                                  if s["errors"] else ""))
    line("styles with contacts / no contacts", lambda s: f"{s['styles_with_contacts']} / {s['styles_without_contacts']}")
    line("total contacts (head / strand-strand)", lambda s: f"{s['total_contacts']:,} ({s['head_contacts']:,} / "
                                                            f"{s['strand_contacts']:,})")
    line("contacts per style with contacts: max / median", lambda s: f"{s['max_contacts']:,} / {s['median_contacts']:g}")
    line("styles compared (clarabel skipped)", lambda s: f"{s['compared']} ({len(s['clarabel_skipped'])})")
    line("max rel. objective diff (criterion)", lambda s: fmt(s["max_rel_phys"]))
    line(f"styles above {CRITERION:.0e} (criterion)", lambda s: styles_list(s["above_phys"]))
    line("max rel. contact-part diff", lambda s: fmt(s["max_rel_contact"]))
    line(f"styles above {CRITERION:.0e} (contact part)", lambda s: styles_list(s["above_contact"]))
    line("max force diff", lambda s: fmt(s["max_force_diff"]))
    line("worst residual clarabel / GS", lambda s: f"{fmt(s['worst_residual']['clarabel'])} / "
                                                   f"{fmt(s['worst_residual']['gs'])}")
    line("worst cone violation (N) clarabel / GS", lambda s: f"{fmt(s['worst_cone_violation_N']['clarabel'])} / "
                                                             f"{fmt(s['worst_cone_violation_N']['gs'])}")
    line("max iterations clarabel / GS sweeps", lambda s: f"{fmt(s['max_iterations']['clarabel'], '{}')} / "
                                                          f"{fmt(s['max_iterations']['gs'], '{}')}")
    line("solver failures clarabel / GS", lambda s: f"{styles_list(s['failures']['clarabel'])} / "
                                                    f"{styles_list(s['failures']['gs'])}")
    line("clarabel + polish: worst residual / not converged", lambda s: f"{fmt(s['polished_worst_residual'])} / "
                                                                      f"{styles_list(s['polished_not_converged'])}")
    line("clarabel + polish: max sweeps / max rel. contact-part diff to GS",
         lambda s: f"{fmt(s['polished_max_sweeps'], '{}')} / {fmt(s['polished_max_rel_contact'])}")

    lines += ["", "## Time vs contacts (crossover for `--solver auto`)", "",
              "Median (max) wall time per solve, set-up included, one thread.", "",
              "| series | contacts | styles | clarabel median (max) s | GS median (max) s | clarabel / GS |",
              "|---|---|---|---|---|---|"]
    for s in series:
        for b in s["crossover"]:
            if not b["styles"]:
                lines.append(f"| {s['label']} | {b['bucket']} | 0 | - | - | - |")
                continue
            c, g = b["clarabel_median_s"], b["gs_median_s"]
            ratio = f"{c / g:.1f}" if c and g else "-"
            lines.append(f"| {s['label']} | {b['bucket']} | {b['styles']} | {fmt(c, '{:.4f}')} "
                         f"({fmt(b['clarabel_max_s'], '{:.4f}')}) | {fmt(g, '{:.4f}')} "
                         f"({fmt(b['gs_max_s'], '{:.4f}')}) | {ratio} |")

    allrows = [(s["label"], r) for s in series for r in s["rows"] if "rel_phys" in r]
    worst = sorted(allrows, key=lambda x: (x[1]["rel_contact"], x[1]["rel_phys"]), reverse=True)[:10]
    lines += ["", "## The 10 worst styles (both series, by the contact-part difference)", "",
              "| series | style | contacts (head) | rel. objective | rel. contact part | force diff | "
              "clarabel residual / iters / s | GS residual / sweeps / s | active contacts cl / GS |",
              "|---|---|---|---|---|---|---|---|---|"]
    for label, r in worst:
        cl, gs = r["clarabel"], r["gs"]
        lines.append(f"| {label} | {r['style']} | {r['contacts']} ({r['head_contacts']}) | {r['rel_phys']:.1e} | "
                     f"{r['rel_contact']:.1e} | {r['force_diff']:.1e} | {cl['residual']:.1e} / {cl['iterations']} / "
                     f"{cl['time_s']:.4f} | {gs['residual']:.1e} / {gs['iterations']} / {gs['time_s']:.4f} | "
                     f"{cl['active']} / {gs['active']} |")

    tight = [(s["label"], t) for s in series for t in s["summary"]["tight"]]
    if tight:
        lines += ["", f"## Styles above {CRITERION:.0e} in the contact part: clarabel re-run at its own tolerance "
                  f"{tight[0][1].get('tol', 0):.0e}", "",
                  "clarabel_socqp.solve_factored(tol=...) directly: does a tighter interior point close the gap?", "",
                  "| series | style | status | iterations | residual | rel. objective | rel. contact part |",
                  "|---|---|---|---|---|---|---|"]
        for label, t in tight:
            if "residual" not in t:
                lines.append(f"| {label} | {t['style']} | {t.get('status')} | {t.get('error', '')} | | | |")
                continue
            lines.append(f"| {label} | {t['style']} | {t['status']} | {t['iterations']} | {t['residual']:.1e} | "
                         f"{t['rel_phys']:.1e} | {t['rel_contact']:.1e} |")
    if meta.get("notes"):
        lines += ["", "## Notes", ""] + [f"* {n}" for n in meta["notes"]]
    return "\n".join(lines) + "\n"


def notes(series: list[dict], params: InversionParams) -> list[str]:
    """Facts read off the rows, for the markdown."""
    out = []
    for s in series:
        rows = [r for r in s["rows"] if "rel_phys" in r]
        if not rows:
            continue
        loose = [r for r in rows if r["clarabel"]["residual"] > params.solver_tolerance]
        empty = [b["bucket"] for b in s["crossover"] if not b["styles"]]
        out.append(f"{s['label']}: clarabel reports Solved but its residual (residual.py) is above the "
                   f"{params.solver_tolerance:.0e} that GS reaches on {len(loose)} of {len(rows)} styles (median "
                   f"{np.median([r['clarabel']['residual'] for r in rows]):.1e}, worst "
                   f"{max(r['clarabel']['residual'] for r in rows):.1e}); GS returns r = 0 after 0 sweeps on "
                   f"{sum(1 for r in rows if r['gs']['iterations'] == 0)} styles whose optimum is r = 0.")
        if empty:
            out.append(f"{s['label']}: no style in the buckets {', '.join(empty)} (5 guide strands per style, at most "
                       f"{s['summary']['max_contacts']} contacts): these styles say nothing about the crossover near "
                       "AUTO_CLARABEL_MAX_CONTACTS; see bench/results/solvers.md for larger problems.")
    return out


# ----------------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA, help="folder with usc/cstrands/*.data and usc/head_model.obj")
    ap.add_argument("--styles", type=int, default=None, help="only the first N styles (sorted)")
    ap.add_argument("--radius", type=float, action="append", default=None,
                    help=f"contact radius in metres, repeatable (default: {DEFAULT_CONTACT_RADIUS:g} and {WISP_RADIUS:g})")
    ap.add_argument("--repeat", type=int, default=3, help="solves per solver and style; the fastest is reported")
    ap.add_argument("--clarabel-max", type=int, default=20_000, help="skip clarabel above this many contacts")
    ap.add_argument("--tight-tol", type=float, default=1e-12,
                    help="clarabel's own tolerance for the re-run of styles above 1e-6 (0: no re-run)")
    ap.add_argument("--out", default=str(RESULTS / "agreement"), help="output stem (.md and .json)")
    args = ap.parse_args()

    t_start = time.perf_counter()
    load_start = os.getloadavg()
    styles = sorted((args.data / "usc" / "cstrands").glob("cstrands*.data"))
    if not styles:
        sys.exit(f"no styles under {args.data / 'usc' / 'cstrands'}: pass --data DIR")
    if args.styles:
        styles = styles[: args.styles]
    head = as_head_surface(load_head(args.data / "usc" / "head_model.obj"))
    params = InversionParams(contacts="all", solver_tolerance=1e-8)
    radii = args.radius or [DEFAULT_CONTACT_RADIUS, WISP_RADIUS]
    warm_up(head, params, args.data)

    series = []
    for radius in radii:
        label = f"radius {radius * 1e3:g} mm" if radius >= 1e-3 else f"radius {radius * 1e6:g} um"
        rows = []
        t0 = time.perf_counter()
        for k, path in enumerate(styles):
            rows.append(run_style(path, head, radius, params, args))
            if (k + 1) % 20 == 0 or k + 1 == len(styles):
                done = [r for r in rows if "rel_phys" in r]
                print(f"[{label}] {k + 1}/{len(styles)} styles, {sum(r.get('contacts', 0) for r in rows)} contacts, "
                      f"max rel diff {max((r['rel_phys'] for r in done), default=0):.1e} (contact part "
                      f"{max((r['rel_contact'] for r in done), default=0):.1e}), {time.perf_counter() - t0:.0f} s",
                      flush=True)
        series.append({"label": label, "radius_m": radius, "rows": rows, "summary": summarize(rows),
                       "crossover": crossover(rows), "run_s": time.perf_counter() - t0})

    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "command": " ".join(["python bench/bench_agreement.py", *sys.argv[1:]]),
        "python": platform.python_version(), "numpy": np.__version__,
        "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "load_start": list(load_start), "load_end": list(os.getloadavg()),
        "tolerance_m": params.tolerance, "gamma": params.gamma, "guess": params.guess,
        "friction": params.material.friction, "solver_tolerance": params.solver_tolerance,
        "max_iterations": params.max_sweeps, "repeat": args.repeat, "clarabel_max": args.clarabel_max,
        "run_s": time.perf_counter() - t_start, "data": str(args.data),
    }
    meta["notes"] = notes(series, params)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "series": series}, indent=1))
    md = markdown(meta, series)
    out.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
