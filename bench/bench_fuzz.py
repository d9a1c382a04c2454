"""Fuzz every reader with many mutated files; count outcomes into bench/results/fuzz.{md,json}.

Each file is a small valid seed (tests/test_fuzz_readers.py: OBJ three ways, .data, .hair, PLY ascii
and both binary orders, a hand-written .usda and one of our USD exports, a head OBJ) with 1 to 4 mutations: bytes flipped, set, inserted or
deleted, truncation, 4-byte integers and text tokens replaced, lines duplicated or dropped.  The
files are read in worker processes, so a crash (a signal) or a hang (no answer in HANG_S seconds) is
counted against the file being read and the worker restarted after it.

Outcomes: ok (a valid groom or head), error (a GroomError naming the file), other (any other
exception, or an error not naming the file), hang, crash.  Done when other = hang = crash = 0.

    .venv/bin/python bench/bench_fuzz.py                 # 12,000 files
    .venv/bin/python bench/bench_fuzz.py --files 500 --out /tmp/fuzz
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import select
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
import test_fuzz_readers as fz  # noqa: E402  (the mutation engine and seeds, shared with the test)

HANG_S = 60  # a worker silent this long on one file: a hang


def file_plan(name: str, index: int, seed: int):
    """(ops, repair, strand_length) of mutated file ``index`` of seed ``name``; deterministic."""
    rng = np.random.default_rng([seed, fz.NAMES.index(name), index])
    ops = [(fz.KINDS[int(rng.integers(len(fz.KINDS)))], float(rng.random()), int(rng.integers(0, 2**16)))
           for _ in range(int(rng.integers(1, 5)))]
    return ops, bool(rng.random() < 0.5), [None, 3, 7][int(rng.integers(3))]


def worker(name: str, seed: int, start: int, count: int) -> None:
    """Read files start .. start+count-1 of ``name``; one BEGIN and one END line per file."""
    import warnings

    warnings.simplefilter("ignore")
    suffix, data = fz.seeds()[name]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"fuzz{suffix}"
        for i in range(start, start + count):
            ops, repair, strand_length = file_plan(name, i, seed)
            path.write_bytes(fz.mutate(data, ops))
            print(f"BEGIN {i}", flush=True)
            t = time.perf_counter()
            try:
                result = fz.outcome(name, path, repair=repair, strand_length=strand_length)
                detail = ""
            except fz.Hang:
                result, detail = "hang", ""
            except Exception as exc:  # noqa: BLE001 - what the bench counts
                result, detail = "other", f"{type(exc).__name__}: {str(exc)[:200]}"
            ms = (time.perf_counter() - t) * 1e3
            print(f"END {i} {result} {ms:.3f} {json.dumps(detail)}", flush=True)


def run_format(name: str, n_files: int, seed: int):
    """Outcome counts, slow-file times and examples of the bad outcomes for ``name``."""
    counts, times, examples = Counter(), [], defaultdict(list)
    next_index = 0
    while next_index < n_files:
        cmd = [sys.executable, __file__, "--worker", name, "--seed", str(seed), "--start", str(next_index),
               "--count", str(n_files - next_index)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
        current = None
        while True:
            ready, _, _ = select.select([proc.stdout], [], [], HANG_S)
            if not ready:  # silent: hang on the current file
                proc.kill()
                proc.wait()
                counts["hang"] += 1
                examples["hang"].append({"index": current, "plan": file_plan(name, current, seed)})
                next_index = current + 1
                break
            line = proc.stdout.readline()
            if not line:  # the worker ended
                code = proc.wait()
                if current is not None:  # died while reading a file: a crash
                    counts["crash"] += 1
                    examples["crash"].append({"index": current, "exit": code, "plan": file_plan(name, current, seed)})
                    next_index = current + 1
                else:
                    next_index = n_files
                break
            words = line.split(" ", 4)
            if words[0] == "BEGIN":
                current = int(words[1])
            elif words[0] == "END":
                i, result, ms, detail = int(words[1]), words[2], float(words[3]), json.loads(words[4])
                counts[result] += 1
                times.append(ms)
                if result not in ("ok", "error") and len(examples[result]) < 10:
                    examples[result].append({"index": i, "detail": detail, "plan": file_plan(name, i, seed)})
                current = None
                next_index = i + 1
    return counts, times, examples


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--files", type=int, default=12_000, help="mutated files in all, spread over the seeds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "fuzz"), help="writes OUT.md and OUT.json")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    p.add_argument("--start", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args.worker, args.seed, args.start, args.count)
        return 0

    names = list(fz.NAMES)
    try:
        import pxr  # noqa: F401
    except ImportError:
        names = [n for n in names if not n.startswith("usda")]
        print("usd-core not installed: no .usda files", file=sys.stderr)
    per = -(-args.files // len(names))
    rows, total, report = [], Counter(), {}
    t0 = time.perf_counter()
    for name in names:
        t = time.perf_counter()
        counts, times, examples = run_format(name, per, args.seed)
        wall = time.perf_counter() - t
        total.update(counts)
        report[name] = {"files": per, "counts": dict(counts), "wall_s": round(wall, 2),
                        "median_ms": round(float(np.median(times)), 3) if times else None,
                        "max_ms": round(float(np.max(times)), 1) if times else None, "examples": examples}
        rows.append(f"| {name} | {per:,} | {counts['ok']:,} | {counts['error']:,} | {counts['other']} | "
                    f"{counts['hang']} | {counts['crash']} | {report[name]['median_ms']} | {report[name]['max_ms']} |")
        print(rows[-1], flush=True)
    wall = time.perf_counter() - t0
    n = sum(total.values())
    md = [
        "# Fuzzed readers (bench/bench_fuzz.py)",
        "",
        f"{n:,} mutated files (seed {args.seed}) read by `load_groom` / `load_head` in worker processes, "
        f"{wall:.0f} s on {platform.processor() or platform.machine()} ({os.cpu_count()} cores, shared).",
        "ok: a valid groom (or head); error: a GroomError naming the file; other: any other exception or an "
        "error not naming the file; hang: no answer in "
        f"{fz.HANG_SECONDS} s; crash: the process died.",
        "",
        "| seed file | files | ok | error | other | hang | crash | median ms | max ms |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        f"| **all** | {n:,} | {total['ok']:,} | {total['error']:,} | {total['other']} | {total['hang']} | "
        f"{total['crash']} | | |",
        "",
        "Mutations per file: 1 to 4 of byte flip / set / insert / delete, truncation, a 4-byte integer "
        "(header fields) or a text token replaced by an edge value (-1, 0, 2^31, 1e30, nan, ...), a line "
        "duplicated or dropped (header edits). Reader options drawn too: repair on or off, strand_length "
        "none, 3 or 7. Examples of every outcome other than ok and error are in fuzz.json.",
        "",
        "Found by this fuzzing while issue 17 was fixed (each now a GroomError, kept by "
        "tests/test_fuzz_readers.py): a non-UTF-8 .usda (pxr's own error message failed to decode), a "
        "head OBJ read as 2D vertices, USD attributes of an unregistered value type (5 of 1,200 .usda "
        "files in the first full run), groom primvars of the wrong length in our USD export.",
        "",
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text("\n".join(md))
    out.with_suffix(".json").write_text(json.dumps({"files": n, "seed": args.seed, "wall_s": round(wall, 1),
                                                   "totals": dict(total), "per_seed": report}, indent=1) + "\n")
    print("\n".join(md))
    return 0 if total["other"] + total["hang"] + total["crash"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
