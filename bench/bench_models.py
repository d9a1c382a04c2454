"""Elements needed by the Super-Helix and the Super Space Clothoid for the same fit tolerance (issue 20, first part).

Data: USC-HairSalon guide strands (../shared/data/usc/cstrands/*.data, 5 strands x 100 vertices per style).
Styles: the ``--straight`` straightest and ``--curly`` curliest of all styles by mean turning per metre of
their strands of at least 15 cm (sum of the polyline's vertex angles / length), plus ``--extra`` (default
style 3, XL curly, the guides of usc10k), ``--strands`` strands of each (the longest); and ``--harolongo``
random strands of digital-salon/harolongo.data (21 vertices, cm -> m).

Per strand, at ``--tolerance`` (m, max distance vertex -> fitted curve):
- production: ``groomtool.fit.fit_groom`` (floating tangents, adaptive N; its own error measure);
- helix-LS and clothoid-LS: the smallest N found by ``fit.least_squares.min_elements_ls`` (doubling/halving from the
  production N, then bisection) for which ``fit.least_squares.fit_polyline_ls`` -- the same least-squares procedure for
  both models -- reaches the tolerance, its error measured as the distance to the curve sampled 32 times
  per element; plus the largest jump of the bending curvature (kappa1, kappa2) at the helix's joints.

The LS fitter is a prototype (a local Levenberg-Marquardt with an iteration cap): a failure to reach the
tolerance at some N can be the optimiser's, not the model's.  Writes bench/results/models.md and models.json.

    python bench/bench_models.py [--tolerance 5e-4] [--straight 2] [--curly 3] [--strands 2] [--harolongo 4]
    python bench/bench_models.py --report-only      # models.md from models.json

Production fits (``--production``): whole grooms through the production fits of both models --
``fit_groom`` (Super-Helix) and ``fit.clothoid_fit.fit_clothoid_groom`` (Super Space Clothoid, started from
that helix fit) -- and the isolated inversion of each (``invert_groom`` with ``model``, stabilize "none"): elements
for the same tolerance, fit and inversion CPU, fit error, equilibrium residual and the largest jump of the
bending curvature at element joints.  Writes bench/results/models_production.json (one entry per groom, merged
with earlier runs) and the section of models.md built from it.

    python bench/bench_models.py --production usc-straight usc-curly harolongo

Every USC style inverted with ``--model clothoid`` and contacts (``--usc-contacts``: head and strand/strand, the
USC head mesh): per style the fit error, the contacts, the solve and the equilibrium residual
(bench/results/models_usc_contacts.json and its summary in models.md).

    python bench/bench_models.py --usc-contacts
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

from groomtool.fit import fit_groom  # noqa: E402
from groomtool.groom import Groom  # noqa: E402
from groomtool.io import read_data  # noqa: E402
from groomtool.fit import least_squares as ls  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "usc" / "cstrands"
RESULTS = ROOT / "bench" / "results"
HAROLONGO = ROOT.parent / "shared" / "data" / "digital-salon" / "harolongo.data"


def turning_per_metre(strand: np.ndarray) -> float:
    d = np.diff(strand, axis=0)
    n = np.linalg.norm(d, axis=1)
    keep = n > 1e-9
    d, n = d[keep], n[keep]
    t = d / n[:, None]
    ang = np.arccos(np.clip(np.einsum("ik,ik->i", t[1:], t[:-1]), -1.0, 1.0))
    return float(ang.sum() / n.sum())


def pick_styles(n_straight: int, n_curly: int, min_length: float = 0.15):
    rows = []
    for f in sorted(DATA.glob("*.data")):
        strands = [s for s in read_data(f, repair=True).strands() if np.linalg.norm(np.diff(s, axis=0), axis=1).sum() >= min_length]
        if len(strands) < 2:
            continue
        rows.append((float(np.mean([turning_per_metre(s) for s in strands])), f.name))
    rows.sort()
    return [(name, c, "straight") for c, name in rows[:n_straight]] + [(name, c, "curly") for c, name in rows[len(rows) - n_curly:]]


def helix_curvature_jump(rod) -> float:
    q = rod.curvatures[0, :rod.n_elements[0]]
    return float(np.linalg.norm(np.diff(q[:, 1:], axis=0), axis=1).max()) if len(q) > 1 else 0.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tolerance", type=float, default=5e-4)
    ap.add_argument("--straight", type=int, default=2)
    ap.add_argument("--curly", type=int, default=3)
    ap.add_argument("--strands", type=int, default=2)
    ap.add_argument("--harolongo", type=int, default=4, help="random harolongo strands (cm -> m) added")
    ap.add_argument("--extra", nargs="*", default=["cstrands00003.data"],
                    help="styles added as curly (default: style 3, XL curly, the guides of usc10k)")
    ap.add_argument("--report-only", action="store_true", help="rewrite models.md from models.json")
    ap.add_argument("--production", nargs="*", default=None, metavar="GROOM",
                    help="production-fit comparison on whole grooms: usc-straight, usc-curly (the --straight / "
                         "--curly styles merged into one groom), usc-all (every style), harolongo")
    ap.add_argument("--usc-contacts", action="store_true",
                    help="every USC style through groom invert --model clothoid --contacts all with the USC head")
    args = ap.parse_args()
    if args.usc_contacts:
        usc_contacts(args)
        data = json.loads((RESULTS / "models.json").read_text())
        write_report(data["meta"], data["rows"])
        return
    if args.production is not None:
        for name in args.production:
            production(name, args)
        data = json.loads((RESULTS / "models.json").read_text())
        write_report(data["meta"], data["rows"])
        return
    if args.report_only:
        data = json.loads((RESULTS / "models.json").read_text())
        write_report(data["meta"], data["rows"])
        return
    tol = args.tolerance
    rows = []
    styles = pick_styles(args.straight, args.curly)
    for name in args.extra:
        if name not in [s[0] for s in styles]:
            strands = list(read_data(DATA / name, repair=True).strands())
            styles.append((name, float(np.mean([turning_per_metre(s) for s in strands])), "curly"))
    jobs = []
    for name, turning, kind in styles:
        strands = list(read_data(DATA / name, repair=True).strands())
        lengths = [np.linalg.norm(np.diff(s, axis=0), axis=1).sum() for s in strands]
        jobs += [(name, turning, kind, int(k), strands[k], lengths[k]) for k in np.argsort(lengths)[::-1][:args.strands]]
    if args.harolongo:
        haro = list(read_data(HAROLONGO, scale=0.01, repair=True).strands())
        pick = np.random.default_rng(0).choice(len(haro), args.harolongo, replace=False)
        for k in pick:
            X = haro[k]
            jobs.append(("harolongo", turning_per_metre(X), "harolongo", int(k), X,
                         float(np.linalg.norm(np.diff(X, axis=0), axis=1).sum())))
    for name, turning, kind, k, X, length in jobs:
        row = {"style": name, "kind": kind, "style_turning_per_m": turning, "strand": int(k),
               "length_m": float(length), "vertices": len(X), "strand_turning_per_m": turning_per_metre(X)}
        t0 = time.process_time()
        prod = fit_groom(Groom.from_strands([X]), tolerance=tol)
        row["production"] = {"n": int(prod.n_elements[0]), "max_error_m": float(prod.max_error[0]),
                             "cpu_s": time.process_time() - t0}
        for model in ("helix", "clothoid"):
            t0 = time.process_time()
            n, fit, fits = ls.min_elements_ls(X, tol, model, start=int(prod.n_elements[0]))
            rec = {"n": n, "max_error_m": fit.max_error, "mean_error_m": fit.mean_error, "fits": fits,
                   "cpu_s": time.process_time() - t0}
            if model == "helix":
                rec["max_bending_jump_per_m"] = helix_curvature_jump(fit.rod)
            row[model + "_ls"] = rec
        rows.append(row)
        print(json.dumps(row), flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"tolerance_m": tol, "args": vars(args), "machine": f"{os.cpu_count()} CPUs, load average "
            + ", ".join(f"{x:.1f}" for x in os.getloadavg()), "numpy": np.__version__, "python": platform.python_version()}
    (RESULTS / "models.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    write_report(meta, rows)


def bending_jump(rod, model: str) -> float:
    """Largest jump of the bending curvature (kappa1, kappa2) across an element joint (1/m): the helix's between
    consecutive elements; the clothoid's Omega is evaluated at both sides of every joint from its two elements'
    start values and slopes (a_j + b_j l_j against a_{j+1})."""
    if model == "superhelix":
        q = rod.curvatures
        jump = np.linalg.norm(np.diff(q[..., 1:], axis=1), axis=2)
        valid = np.arange(q.shape[1] - 1)[None, :] < (rod.n_elements - 1)[:, None]
    else:
        a, b = rod.starts_and_slopes()
        end = a + b * rod.lengths[..., None]
        jump = np.linalg.norm((a[:, 1:] - end[:, :-1])[..., 1:], axis=2)
        valid = np.arange(a.shape[1] - 1)[None, :] < (rod.n_elements - 1)[:, None]
    return float(jump[valid].max()) if valid.any() else 0.0


def production_groom(name: str, args) -> Groom:
    if name == "harolongo":
        return read_data(HAROLONGO, scale=0.01, repair=True)
    if name in ("usc-straight", "usc-curly"):
        styles = [s for s, _, kind in pick_styles(args.straight, args.curly) if kind == name[4:]]
    elif name == "usc-all":
        styles = [f.name for f in sorted(DATA.glob("*.data"))]
    else:
        styles = [name]
    strands = [s for st in styles for s in read_data(DATA / st, repair=True).strands()]
    return Groom.from_strands(strands, source=f"{name}: {len(styles)} styles ({', '.join(styles[:6])}"
                                              f"{', ...' if len(styles) > 6 else ''})")


def production(name: str, args) -> None:
    from groomtool.fit.clothoid_fit import fit_clothoid_groom
    from groomtool.invert import InversionParams, invert_groom

    groom = production_groom(name, args)
    tol = args.tolerance
    rec = {"groom": name, "source": groom.source, "strands": int(len(groom.offsets) - 1),
           "vertices": int(len(groom.points)), "tolerance_m": tol,
           "machine": f"{os.cpu_count()} CPUs, load average " + ", ".join(f"{x:.1f}" for x in os.getloadavg())}
    t0 = time.process_time()
    hf = fit_groom(groom, tolerance=tol)
    t_h = time.process_time() - t0
    t0 = time.process_time()
    cf = fit_clothoid_groom(groom, tolerance=tol, helix_fit=hf)
    t_c = time.process_time() - t0
    for model, fit, cpu in (("superhelix", hf, t_h), ("clothoid", cf, t_c)):
        rod = fit.helix
        rec[model] = {"elements": int(rod.n_elements.sum()),
                      "unknowns": int(3 * (rod.n_elements.sum() + (rod.n_strands if model == "clothoid" else 0))),
                      "elements_per_strand": [int(rod.n_elements.min()), float(rod.n_elements.mean()),
                                              int(rod.n_elements.max())],
                      "fit_max_error_m": float(fit.max_error.max()), "fit_mean_error_m": float(fit.mean_error.mean()),
                      "over_tolerance": int((~fit.converged).sum()), "fit_cpu_s": cpu,
                      "max_bending_jump_per_m": bending_jump(rod, model)}
        if model == "clothoid":
            rec[model]["fit_cpu_s_after_helix_fit"] = cpu
            rec[model]["fit_cpu_s"] = cpu + t_h
            rec[model]["passes"] = fit.passes
    print(json.dumps(rec), flush=True)
    # the isolated inversion of each model (its fit included in the report's timings; stability included)
    for model in ("superhelix", "clothoid"):
        t0 = time.process_time()
        res = invert_groom(groom, None, InversionParams(tolerance=tol, model=model, discrete_rest_data=False))
        cpu = time.process_time() - t0
        t = res.report["timings_s"]
        rec[model]["invert_cpu_s"] = cpu
        rec[model]["invert_stages_wall_s"] = {k: round(v, 3) for k, v in t.items()}
        rec[model]["equilibrium_max_relative_residual"] = res.report["equilibrium"]["max_relative_residual"]
        rec[model]["unstable_isolated"] = res.report["stability"]["unstable_strands"]
        print(model, json.dumps(rec[model]), flush=True)
    path = RESULTS / "models_production.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    data[name] = rec
    path.write_text(json.dumps(data, indent=1))


def usc_contacts(args) -> None:
    from groomtool.invert import InversionParams, invert_groom
    from groomtool.io import load_head

    head = load_head(DATA.parent / "head_model.obj")
    out = []
    for f in sorted(DATA.glob("*.data")):
        groom = read_data(f, repair=True)
        t0 = time.process_time()
        rec = {"style": f.name, "strands": int(len(groom.offsets) - 1)}
        try:
            res = invert_groom(groom, head, InversionParams(tolerance=args.tolerance, model="clothoid", contacts="all",
                                                            discrete_rest_data=False))
        except Exception as exc:  # recorded, not hidden
            rec["error"] = f"{type(exc).__name__}: {exc}"
            out.append(rec)
            print(json.dumps(rec), flush=True)
            continue
        r = res.report
        rec.update({"elements": r["elements"], "helix_elements": r["fit"]["helix_elements"],
                    "fit_max_error_m": r["fit"]["max_error_m"], "over_tolerance": r["fit"]["strands_over_tolerance"],
                    "contacts": r["contacts"]["total"], "strand_strand": r["contacts"]["strand_strand"],
                    "solve": r["solve"]["status"], "residual": r["equilibrium"]["max_relative_residual"],
                    "stiffened": r["stability"]["stabilization"]["stiffened_strands"],
                    "unstable_with_contacts": r["stability"]["unstable_with_contacts"],
                    "cpu_s": time.process_time() - t0})
        out.append(rec)
        print(json.dumps(rec), flush=True)
    meta = {"tolerance_m": args.tolerance, "machine": f"{os.cpu_count()} CPUs, load average "
            + ", ".join(f"{x:.1f}" for x in os.getloadavg())}
    (RESULTS / "models_usc_contacts.json").write_text(json.dumps({"meta": meta, "styles": out}, indent=1))


def usc_contacts_section() -> list:
    path = RESULTS / "models_usc_contacts.json"
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    st = data["styles"]
    ok = [s for s in st if "error" not in s]
    lines = ["", "## Every USC style inverted as clothoids with contacts (`--usc-contacts`)", "",
             "Command: `python bench/bench_models.py --usc-contacts` (invert_groom, model clothoid, contacts all with "
             f"usc/head_model.obj, tolerance {data['meta']['tolerance_m'] * 1e3:.2f} mm; {data['meta']['machine']}).", ""]
    if not ok:
        return lines + [f"{len(st)} styles, none inverted."]
    res = np.array([s["residual"] for s in ok])
    el = sum(s["elements"] for s in ok)
    hel = sum(s["helix_elements"] for s in ok)
    lines += ["| styles | inverted | errors | strands | clothoid elements (helix fit's) | fit max error (mm) | "
              "strands over tol | contacts (strand/strand) | solves not 'solved' | max equilibrium residual | "
              "styles with residual >= 1e-8 | stiffened strands | unstable with contacts | CPU s (all) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
              f"| {len(st)} | {len(ok)} | {len(st) - len(ok)} | {sum(s['strands'] for s in ok)} | {el} ({hel}, "
              f"ratio {el / hel:.2f}) | {max(s['fit_max_error_m'] for s in ok) * 1e3:.3f} | "
              f"{sum(s['over_tolerance'] for s in ok)} | {sum(s['contacts'] for s in ok)} "
              f"({sum(s['strand_strand'] for s in ok)}) | {sum(s['solve'] != 'solved' for s in ok)} | {res.max():.1e} | "
              f"{int((res >= 1e-8).sum())} | {sum(s['stiffened'] for s in ok)} | "
              f"{sum(s['unstable_with_contacts'] for s in ok)} | {sum(s['cpu_s'] for s in ok):.0f} |"]
    for s in st:
        if "error" in s:
            lines.append(f"- {s['style']}: {s['error']}")
    return lines


def production_section() -> list:
    path = RESULTS / "models_production.json"
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    lines = ["", "## Production fits of whole grooms (`--production`)", "",
             "Both production fits at the same tolerance: `fit_groom` (Super-Helix, floating tangents) and "
             "`fit.clothoid_fit.fit_clothoid_groom` (Super Space Clothoid: starts from that helix fit, Levenberg-"
             "Marquardt per strand, N grown until within tolerance); fit CPU of the clothoid includes the helix fit "
             "it starts from. Inversion: `invert_groom` isolated (no contacts, stabilisation on, no discrete rest data), "
             "fit included. Jump: the largest change of the bending curvature (kappa1, kappa2) across an element joint. "
             "CPU seconds (time.process_time) on a shared 2-CPU box.", "",
             "Command: `python bench/bench_models.py --production " + " ".join(data) + "`", "",
             "| groom | strands | model | elements (per strand min/mean/max) | unknowns | fit max / mean error (mm) | "
             "over tol | fit CPU s | inversion CPU s (fit incl.) | equilibrium residual | max bending jump (1/m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, rec in data.items():
        for model in ("superhelix", "clothoid"):
            m = rec[model]
            e = m["elements_per_strand"]
            fit_cpu = f"{m['fit_cpu_s']:.1f}"
            if model == "clothoid":
                fit_cpu += f" ({m['fit_cpu_s_after_helix_fit']:.1f} after the helix fit)"
            lines.append(f"| {name} | {rec['strands']} | {model} | {m['elements']} ({e[0]}/{e[1]:.1f}/{e[2]}) | "
                         f"{m['unknowns']} | {m['fit_max_error_m'] * 1e3:.3f} / {m['fit_mean_error_m'] * 1e3:.3f} | "
                         f"{m['over_tolerance']} | {fit_cpu} | {m.get('invert_cpu_s', float('nan')):.1f} | "
                         f"{m.get('equilibrium_max_relative_residual', float('nan')):.1e} | "
                         f"{m['max_bending_jump_per_m']:.3g} |")
        c, h = rec["clothoid"], rec["superhelix"]
        lines.append(f"| {name} | | clothoid / helix | {c['elements'] / h['elements']:.2f} | "
                     f"{c['unknowns'] / h['unknowns']:.2f} | | | | | | |")
    return lines


def write_report(meta, rows) -> None:
    tol = meta["tolerance_m"]
    lines = ["# Elements needed: Super-Helix vs Super Space Clothoid (bench/bench_models.py)", "",
             f"tolerance {tol * 1e3:.2f} mm (max distance vertex -> fitted curve); {meta['machine']} (shared box: "
             "CPU times indicative); USC cstrands styles picked by mean turning per metre; arguments "
             f"{meta.get('args', {})}.", "",
             "Production: fit_groom (floating tangents; starts at ceil(L / 2 cm) elements and only grows, so its N is "
             "not minimal). helix-LS, clothoid-LS: the smallest N found for the same least-squares prototype fit "
             "(fit.least_squares.fit_polyline_ls; a local optimiser with an iteration cap: see docs/clothoid.md).", "",
             "| style | kind | strand | L (m) | turning (rad/m) | production helix N (err mm) | helix-LS N (err mm) | "
             "clothoid-LS N (err mm) | clothoid / helix-LS | helix-LS max bending jump (1/m) | CPU s: helix-LS / clothoid-LS |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(rec):
        return f"{rec['n'] if rec['n'] is not None else '>256'} ({rec['max_error_m'] * 1e3:.3f})"

    for r in rows:
        h, c = r["helix_ls"], r["clothoid_ls"]
        ratio = f"{c['n'] / h['n']:.2f}" if h["n"] and c["n"] else "-"
        lines.append(f"| {r['style']} | {r['kind']} | {r['strand']} | {r['length_m']:.3f} | {r['strand_turning_per_m']:.0f} | "
                     f"{r['production']['n']} ({r['production']['max_error_m'] * 1e3:.3f}) | {fmt(h)} | {fmt(c)} | {ratio} | "
                     f"{h['max_bending_jump_per_m']:.1f} | {h['cpu_s']:.1f} / {c['cpu_s']:.1f} |")
    lines += ["", "| kind | strands | production helix elements | helix-LS elements (unknowns 3N) | "
              "clothoid-LS elements (unknowns 3(N+1)) | clothoid / helix-LS elements | per strand: min - max |",
              "|---|---|---|---|---|---|---|"]
    for kind in ("straight", "curly", "harolongo"):
        sel = [r for r in rows if r["kind"] == kind and r["helix_ls"]["n"] and r["clothoid_ls"]["n"]]
        if sel:
            nh = sum(r["helix_ls"]["n"] for r in sel)
            nc = sum(r["clothoid_ls"]["n"] for r in sel)
            npd = sum(r["production"]["n"] for r in sel)
            ratios = [r["clothoid_ls"]["n"] / r["helix_ls"]["n"] for r in sel]
            lines.append(f"| {kind} | {len(sel)} | {npd} | {nh} ({3 * nh}) | {nc} ({3 * (nc + len(sel))}) | "
                         f"{nc / nh:.2f} | {min(ratios):.2f} - {max(ratios):.2f} |")
    lines += kept_lines()
    lines += production_section()
    lines += usc_contacts_section()
    lines += kept_sections()
    (RESULTS / "models.md").write_text("\n".join(lines) + "\n")


GENERATED = ("## Production fits of whole grooms", "## Every USC style inverted as clothoids")


def _existing() -> list:
    path = RESULTS / "models.md"
    return path.read_text().splitlines() if path.is_file() else []


def kept_lines() -> list:
    """Notes written by hand under the prototype's tables (lines starting "Unfinished:"), kept on a rewrite."""
    return [""] + [line for line in _existing() if line.startswith("Unfinished:")] if any(
        line.startswith("Unfinished:") for line in _existing()) else []


def kept_sections() -> list:
    """Sections of models.md this script does not write (e.g. the no-sag check of groom check), kept on a rewrite."""
    out, keep = [], False
    for line in _existing():
        if line.startswith("## "):
            keep = not line.startswith(GENERATED)
            if keep:
                out.append("")
        if keep:
            out.append(line)
    while out and not out[-1].strip():
        out.pop()
    return out


if __name__ == "__main__":
    main()
