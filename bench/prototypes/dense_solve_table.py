"""MEASUREMENT (issue 16): residual and certified rest-curvature (q0) bound against CPU time for the existing
options of the contact solvers on one dense inverse problem (example_groom(1000) with its head, all contacts,
contact radius 0.3 mm: 67,805 contacts), the table of docs/solvers.md section 12.

    OPENBLAS_NUM_THREADS=1 python bench/prototypes/dense_solve_table.py --save /tmp/i16/ex1000.pkl   # build once
    OPENBLAS_NUM_THREADS=1 python bench/prototypes/dense_solve_table.py --problem /tmp/i16/ex1000.pkl \\
        --config default --cpu 90 [--json out.jsonl]

At every residual check (every 10 sweeps / iterations) the solver's ``stop`` hook computes the certified bound of
inverse_problem.rest_curvature_error_bound (without its line search, as the inversion's stopping rule does) on
the current forces; its CPU time is measured and subtracted from the time axis (it costs about one sweep per
check).  CPU time is time.process_time of this process (one thread).  The run ends at --cpu seconds or once the
bound is <= --target.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from groomtool.inverse_problem import rest_curvature_error_bound  # noqa: E402
from groomtool.solvers import solve_contact_problem  # noqa: E402

#: name -> (method, options for solve_contact_problem)
CONFIGS = {
    "default": ("gs", {}),  # what the inversion runs (form auto -> matrix-free here)
    "anderson0": ("gs", {"anderson": 0}),
    "anderson16": ("gs", {"anderson": 16}),
    "anderson3": ("gs", {"anderson": 3}),
    "symmetric": ("gs", {"symmetric": True}),
    "symmetric_anderson0": ("gs", {"symmetric": True, "anderson": 0}),
    "symmetric_at_1e-3": ("gs", {"symmetric": 1e-3}),
    "omega1.2": ("gs", {"omega": 1.2}),
    "omega1.5": ("gs", {"omega": 1.5}),
    "omega1.2_anderson0": ("gs", {"omega": 1.2, "anderson": 0}),
    "omega1.5_anderson0": ("gs", {"omega": 1.5, "anderson": 0}),
    "assembled": ("gs", {"form": "assembled"}),  # with the subspace Newton steps (assembled form only)
    "assembled_no_newton": ("gs", {"form": "assembled", "newton": None}),
    "matrix_free": ("gs", {"form": "matrix_free"}),
    "order_columns": ("gs", {"order": "columns"}),
    "order_columns_reversed": ("gs", {"order": "columns_reversed"}),
    "local_tol_1e-3": ("gs", {"local_tol_fraction": 1e-3}),
    "apgd": ("apgd", {}),
    "apgd_assembled": ("apgd", {"form": "assembled"}),
    "admm": ("admm", {}),  # solvers/admm.py with its defaults
    "admm_beta0.1": ("admm", {"beta": 0.1}),
    "admm_beta0.01": ("admm", {"beta": 0.01}),
    "admm_alpha1.8": ("admm", {"alpha": 1.8}),
    "admm_anderson0": ("admm", {"anderson": 0}),
}


def build(n_strands: int, radius: float) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from q0_bound import build as _build

    inv, cp, q0_free = _build(n_strands, radius)
    return {"inv": inv, "cp": cp, "q0_free": q0_free}


def run(data: dict, name: str, cpu: float, target: float) -> dict:
    inv, cp = data["inv"], data["cp"]
    method, options = CONFIGS[name]
    options = dict(options)
    form = options.pop("form", "auto")
    cp._cache.clear()  # every run packs / assembles its own operators (set-up counted)
    hook = {"cpu": 0.0}
    rows = []
    last = {"residual": float("nan"), "it": 0}
    t0 = time.process_time()

    def callback(it, residual):
        last["residual"], last["it"] = residual, it

    def stop(r, u):
        th = time.process_time()
        bound = rest_curvature_error_bound(inv, cp, r, u, line_search=False)["q0_error_bound"]
        hook["cpu"] += time.process_time() - th
        t = time.process_time() - t0 - hook["cpu"]
        rows.append((last["it"], t, last["residual"], bound))
        return bound <= target or t > cpu

    res = solve_contact_problem(cp, law="soc", method=method, form=form, tol=1e-12, max_iter=10**6,
                                callback=callback, stop=stop, **options)
    total = time.process_time() - t0 - hook["cpu"]

    def first(level):
        hit = [t for (_, t, _, b) in rows if b <= level]
        return round(hit[0], 1) if hit else None

    at60 = [row for row in rows if row[1] <= 60.0]
    out = {
        "config": name, "method": method, "options": {k: v for k, v in CONFIGS[name][1].items()},
        "form": res.info.get("form"), "status": res.status, "iterations": res.iterations,
        "cpu_s": round(total, 1), "setup_s": round(res.info.get("setup_s", 0.0), 2),
        "final_residual": res.residual, "final_bound": rows[-1][3] if rows else None,
        "bound_at_60s": at60[-1][3] if at60 else None, "residual_at_60s": at60[-1][2] if at60 else None,
        "iterations_at_60s": at60[-1][0] if at60 else None,
        "cpu_to_bound": {f"{lv:g}": first(lv) for lv in (5e-2, 2e-2, 1e-2, 5e-3, 2e-3, 1e-3)},
        "hook_cpu_s": round(hook["cpu"], 1),
        "history": rows[:: max(1, len(rows) // 40)] + rows[-1:],
    }
    newton = res.info.get("newton")
    if newton:
        out["newton_steps"] = len(newton)
        out["newton_accepted"] = int(sum(1 for s in newton if s[1]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", help="pickle written by --save")
    ap.add_argument("--save", help="build example_groom(--strands) and pickle it here")
    ap.add_argument("--strands", type=int, default=1000)
    ap.add_argument("--contact-radius", type=float, default=3e-4)
    ap.add_argument("--config", action="append", default=[], help=f"one of {sorted(CONFIGS)} (repeatable)")
    ap.add_argument("--cpu", type=float, default=90.0, help="CPU seconds per run (bound checks excluded)")
    ap.add_argument("--target", type=float, default=1e-3, help="stop once the relative q0 bound is this small")
    ap.add_argument("--json", help="append one JSON line per run")
    args = ap.parse_args()
    if args.save:
        data = build(args.strands, args.contact_radius)
        with open(args.save, "wb") as f:
            pickle.dump(data, f, protocol=5)
        cp = data["cp"]
        print(f"{cp.n_contacts:,} contacts, {cp.n_dofs:,} dofs, H nnz {cp.H.nnz:,} -> {args.save}")
    if not args.config:
        return
    with open(args.problem, "rb") as f:
        data = pickle.load(f)
    for name in args.config:
        out = run(data, name, args.cpu, args.target)
        print(json.dumps({k: v for k, v in out.items() if k != "history"}), flush=True)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
