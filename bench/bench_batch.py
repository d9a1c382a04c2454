"""Benchmark of ``groom batch`` (issue 21): the USC-HairSalon styles with the USC head, ``--contacts all``,
on a Dask LocalCluster of N one-thread worker processes against a serial loop.

Each run is a fresh process timed from outside (its start-up, imports and numba cache loading count, as
they do for a user):

1. serial: one Python process calling the batch's own task function (``groomtool.batch.invert_one``)
   for every style in turn, BLAS/numba pinned to one thread like the workers;
2. batch: ``groom batch STYLES --head head_model.obj --contacts all -o OUT --workers N --no-resume -q``;
3. (``--shell-loop``) today's practice: one ``groom invert`` process per style.

The outputs of 1 and 2 are compared (rest curvatures of every style, and the status of those that
fail); memory per worker is each worker's peak RSS (``worker_peak_rss_mib`` in the batch summary). CPU
counts every descendant (this process is their subreaper: the workers' forkserver outlives ``groom batch``
by a moment) and is split into the workers' (``worker_cpu_s``), the batch process's (``client_cpu_s``) and
the rest.

    python bench/bench_batch.py [--styles 40] [--workers 2] [--repeat 2] [--shell-loop] [--name batch]
    (--styles 0: all 343)
    python bench/bench_batch.py --example-grooms 12 [--example-strands 40] --name batch.examples
    (grooms whose inversion takes seconds, where Dask's fixed costs are small)

Prints a table and writes bench/results/<name>.md and <name>.json.  The machine's load average is
recorded before and after: on a shared machine the speed-up is a lower bound.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "usc"
RESULTS = ROOT / "bench" / "results"
PYTHON = sys.executable
GROOM = str(Path(sys.executable).with_name("groom"))

SERIAL = r"""
import json, resource, sys, time
from pathlib import Path
from groomtool.batch import invert_one
from groomtool.api import inversion_params
paths, out, head = json.loads(sys.argv[1]), sys.argv[2], sys.argv[3]
params = inversion_params(**json.loads(sys.argv[4]))
rows = [invert_one(p, out, head, params, {"units": "m"}) for p in paths]
json.dump({"rows": rows, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024},
          open(Path(out) / "serial.json", "w"), default=str)
"""


def one_thread_env() -> dict:
    from groomtool.batch import THREAD_ENV

    return {**os.environ, **THREAD_ENV}


def become_subreaper() -> bool:
    """Make this process the reaper of its orphaned descendants (Linux prctl PR_SET_CHILD_SUBREAPER), so that
    their CPU counts in RUSAGE_CHILDREN: the batch's forkserver (and the workers forked from it) outlive the
    `groom batch` process by a moment and are not waited for by it."""
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def reap_orphans(timeout: float = 30.0) -> None:
    """Wait for every descendant that was handed to this process (see become_subreaper)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.05)


def timed(cmd, env=None) -> tuple[float, float, subprocess.CompletedProcess]:
    """Wall time and CPU time (user + system of the process and every descendant, the batch's worker
    processes and their forkserver included: this process is their subreaper)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    reap_orphans()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc


def styles(n: int) -> list[Path]:
    every = sorted((DATA / "cstrands").glob("cstrands*.data"))
    if n <= 0 or n >= len(every):
        return every
    pick = np.unique(np.linspace(0, len(every) - 1, n).round().astype(int))  # spread over the data set
    return [every[i] for i in pick]


def compare(serial_rows, batch_dir: Path, serial_dir: Path) -> dict:
    """Same status per style, and the same rest curvatures where both wrote them."""
    out = {"styles": len(serial_rows), "same_status": 0, "compared": 0, "max_rel_diff": 0.0}
    batch = {r["name"]: r for r in json.loads((batch_dir / "batch_summary.json").read_text())["grooms"]}
    for r in serial_rows:
        b = batch[r["name"]]
        out["same_status"] += b["status"] == r["status"]
        if r["status"] == b["status"] == "ok":
            with np.load(serial_dir / r["name"] / "rest.npz") as s, np.load(batch_dir / r["name"] / "rest.npz") as t:
                q_s, q_t = s["rest_curvatures"], t["rest_curvatures"]
            scale = max(np.abs(q_s).max(), 1e-300)
            out["max_rel_diff"] = max(out["max_rel_diff"], float(np.abs(q_s - q_t).max() / scale))
            out["compared"] += 1
    return out


def run_serial(paths, head, out: Path, params: dict) -> dict:
    out.mkdir(parents=True)
    wall, cpu, proc = timed([PYTHON, "-c", SERIAL, json.dumps([str(p) for p in paths]), str(out), head,
                             json.dumps(params)], env=one_thread_env())
    if proc.returncode:
        raise RuntimeError(proc.stderr[-3000:])
    serial = json.loads((out / "serial.json").read_text())
    statuses = [r["status"] for r in serial["rows"]]
    return {"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": serial["peak_rss_mib"],
            "task_s": sum(r["wall_s"] for r in serial["rows"]),
            "counts": {s: statuses.count(s) for s in sorted(set(statuses))}, "rows": serial["rows"]}


def run_batch_cli(paths, head, out: Path, workers: int, params: dict) -> dict:
    extra = ["--contact-radius", str(params["contact_radius"])] if "contact_radius" in params else []
    wall, cpu, proc = timed([GROOM, "batch", *map(str, paths), "--head", head, "--contacts", "all", *extra, "-o",
                             str(out), "--workers", str(workers), "--no-resume", "-q"])
    if proc.returncode not in (0, 1, 2):
        raise RuntimeError(proc.stderr[-3000:])
    summary = json.loads((out / "batch_summary.json").read_text())
    per_worker: dict = {}
    worker_cpu: dict = {}
    for r in summary["grooms"]:
        if r.get("worker") and r.get("worker_peak_rss_mib"):
            per_worker[r["worker"]] = max(per_worker.get(r["worker"], 0.0), r["worker_peak_rss_mib"])
        if r.get("worker") and r.get("worker_cpu_s"):
            worker_cpu[r["worker"]] = max(worker_cpu.get(r["worker"], 0.0), r["worker_cpu_s"])
    return {"wall_s": wall, "cpu_s": cpu, "exit_code": proc.returncode,
            "counts": {k: v for k, v in summary["counts"].items() if v},
            "inside_wall_s": summary["wall_s"], "task_s": sum(r["wall_s"] or 0 for r in summary["grooms"]),
            "worker_peak_rss_mib": list(per_worker.values()),
            "worker_cpu_s": list(worker_cpu.values()), "client_cpu_s": summary.get("client_cpu_s"),
            "tasks_per_worker": [sum(r.get("worker") == w for r in summary["grooms"]) for w in per_worker]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--styles", type=int, default=40, help="number of USC styles, spread over the set (0: all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2, help="serial and batch runs, alternated (default 2)")
    ap.add_argument("--shell-loop", action="store_true", help="also time one `groom invert` process per style")
    ap.add_argument("--name", default="batch", help="results file stem under bench/results (default batch)")
    ap.add_argument("--example-grooms", type=int, default=0, metavar="N",
                    help="instead of USC styles: N grooms of the bundled example (example_groom, seeds 0..N-1, "
                         "--example-strands strands each, contact radius 0.5 mm as in the README): tasks of seconds")
    ap.add_argument("--example-strands", type=int, default=40)
    args = ap.parse_args()
    if not become_subreaper():
        print("warning: not a subreaper: the batch's CPU misses its forkserver and workers", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        tmp = Path(tmp)
        if args.example_grooms:
            from groomtool.examples import example_groom
            from groomtool.io import save_groom

            (tmp / "inputs").mkdir()
            paths = []
            for seed in range(args.example_grooms):
                groom, mesh = example_groom(n_strands=args.example_strands, seed=seed)
                paths.append(tmp / "inputs" / f"example{seed:02d}.obj")
                save_groom(groom, paths[-1])
            mesh.export(tmp / "inputs" / "head.obj")
            head = str(tmp / "inputs" / "head.obj")
            params = {"contacts": "all", "contact_radius": 5e-4}
            what = (f"{len(paths)} grooms of the bundled example (`example_groom(n_strands={args.example_strands}, "
                    f"seed=k)`, k < {len(paths)}), `--contacts all --contact-radius 5e-4` against the example's head")
        else:
            if not (DATA / "head_model.obj").is_file():
                print(f"no USC data at {DATA}", file=sys.stderr)
                return 1
            paths = styles(args.styles)
            head = str(DATA / "head_model.obj")
            params = {"contacts": "all"}
            what = (f"{len(paths)} USC-HairSalon styles "
                    f"{'(all)' if len(paths) == 343 else '(spread evenly over the 343)'}, `--contacts all` against "
                    "head_model.obj")
        result = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "machine": platform.machine(),
                  "cpus": os.cpu_count(), "python": platform.python_version(), "styles": len(paths), "what": what,
                  "workers": args.workers, "load_average": [os.getloadavg()[0]], "serial": [], "batch": []}
        print(f"{what}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
        for k in range(args.repeat):
            s = run_serial(paths, head, tmp / f"serial{k}", params)
            b = run_batch_cli(paths, head, tmp / f"batch{k}", args.workers, params)
            if k == 0:
                result["agreement"] = compare(s["rows"], tmp / "batch0", tmp / "serial0")
            del s["rows"]
            result["serial"].append(s)
            result["batch"].append(b)
            result["load_average"].append(os.getloadavg()[0])
            print(f"run {k + 1}: serial {s['wall_s']:7.1f} s wall {s['cpu_s']:7.1f} s CPU | groom batch --workers "
                  f"{args.workers} {b['wall_s']:7.1f} s wall {b['cpu_s']:7.1f} s CPU | speed-up "
                  f"{s['wall_s'] / b['wall_s']:.2f}x | load {os.getloadavg()[0]:.1f}", flush=True)
        if args.shell_loop:
            t = time.perf_counter()
            failed = 0
            for p in paths:
                extra = ["--contact-radius", str(params["contact_radius"])] if "contact_radius" in params else []
                proc = subprocess.run([GROOM, "invert", str(p), "--head", head, "--contacts", "all", *extra, "-o",
                                       str(tmp / "shell" / p.stem), "-q"], capture_output=True, text=True)
                failed += proc.returncode != 0
            result["shell_loop"] = {"wall_s": time.perf_counter() - t, "failed": failed}
            print(f"shell loop of groom invert     {result['shell_loop']['wall_s']:8.1f} s")
    best_s = min(r["wall_s"] for r in result["serial"])
    best_b = min(r["wall_s"] for r in result["batch"])
    result["speed_up_best"] = best_s / best_b
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=2, default=str) + "\n")
    (RESULTS / f"{args.name}.md").write_text(markdown(result))
    print(markdown(result))
    return 0


def markdown(r: dict) -> str:
    lines = [
        "# groom batch: benchmark",
        "",
        f"{r['date']} on {r['machine']} ({r['cpus']} CPUs), Python {r['python']}; "
        + r.get("what", f"{r['styles']} USC-HairSalon styles, `--contacts all` against head_model.obj")
        + ", default material and tolerances. The machine is shared with other jobs: 1-minute load average "
        + " / ".join(f"{x:.1f}" for x in r["load_average"]) + " (before, after each pair of runs), so the "
        "wall times depend on what the others left of the 2 cores; CPU times do not.",
        "",
        "Each run is a fresh process timed from outside: start-up, imports and numba cache loading count. "
        "CPU = user + system of the process and all its descendants (the workers).",
        "",
        "| run | wall (s) | CPU (s) | speed-up (wall) | sum of task times (s) | peak memory |",
        "|---|---|---|---|---|---|",
    ]
    for k, (s, b) in enumerate(zip(r["serial"], r["batch"])):
        lines.append(f"| {k + 1}: serial loop, one process (`invert_one` per groom, 1 BLAS/numba thread) | "
                     f"{s['wall_s']:.1f} | {s['cpu_s']:.1f} | 1.00x | {s['task_s']:.1f} | {s['peak_rss_mib']:.0f} MiB |")
        lines.append(f"| {k + 1}: `groom batch --workers {r['workers']}` (LocalCluster, 1 thread per worker) | "
                     f"{b['wall_s']:.1f} | {b['cpu_s']:.1f} | {s['wall_s'] / b['wall_s']:.2f}x | {b['task_s']:.1f} | "
                     + ", ".join(f"{v:.0f}" for v in b["worker_peak_rss_mib"]) + " MiB per worker |")
    if "shell_loop" in r:
        s0 = min(x["wall_s"] for x in r["serial"])
        lines.append(f"| shell loop of `groom invert` (one process per style) | {r['shell_loop']['wall_s']:.1f} | | "
                     f"{s0 / r['shell_loop']['wall_s']:.2f}x | | |")
    a = r["agreement"]
    b0 = r["batch"][0]
    lines += ["", "CPU, where it goes (s): serial process | batch: workers (sum of each worker's CPU at its last "
              "task) + batch process (scheduler, nannies, client) + the rest (the workers' forkserver, the workers "
              "after their last task):", ""]
    for k, (s, b) in enumerate(zip(r["serial"], r["batch"])):
        if b.get("worker_cpu_s") and b.get("client_cpu_s") is not None:
            w, c = sum(b["worker_cpu_s"]), b["client_cpu_s"]
            lines.append(f"- run {k + 1}: serial {s['cpu_s']:.1f} | batch {b['cpu_s']:.1f} = workers {w:.1f} ("
                         + " + ".join(f"{x:.1f}" for x in b["worker_cpu_s"]) + f") + batch process {c:.1f} + rest "
                         f"{b['cpu_s'] - w - c:.1f}")
    lines += [
        "",
        f"Best walls: speed-up {r['speed_up_best']:.2f}x. Statuses: serial {r['serial'][0]['counts']}, batch "
        f"{b0['counts']} (exit code {b0['exit_code']}); tasks per worker {b0['tasks_per_worker']}.",
        f"Agreement (run 1): {a['same_status']}/{a['styles']} grooms with the same status; rest curvatures of "
        f"{a['compared']} grooms compared, max difference {a['max_rel_diff']:.1e} relative to the largest.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
