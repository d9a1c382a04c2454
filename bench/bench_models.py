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
    args = ap.parse_args()
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
    (RESULTS / "models.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
