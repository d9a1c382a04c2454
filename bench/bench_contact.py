"""Benchmark of contact detection (strand/strand + strand/head) on the real grooms, one core.

    /work/venv/bin/python bench/bench_contact.py [--data ../shared/data] [--quick] [--rows LABEL,...]

Prints tables and writes bench/results/contact.md and contact.json.  Every detection row runs in
its own process (NUMBA_NUM_THREADS=1) so that its peak memory is its own; times are wall clock and
process CPU time (the two differ when the machine is shared).  ``--rows`` re-runs only the rows
with those labels (``row_label``, e.g. ``harolongo_fitted@50um-head``) and merges them into the
existing contact.json (the other rows, the head query comparison and the distance study are kept).
The ``-head`` rows time the strand/head pass alone, ``detect_head_contacts`` against the previous
implementation ``detect_head_contacts_reference`` (tests/reference/contact.py; alternating, 3 times each,
a fresh HeadSurface each time, built outside the timing), and check that both return the same contacts
bit for bit.

``--kernels [--commits A,B,...]`` times the detection kernels alone (CPU, best of ``--rounds``
alternating rounds, every commit's ``src/groomtool`` extracted with ``git archive`` and run in its own
process) on the workloads of ``kernel_workloads`` (the example grooms as the simulator samples them,
with simulator-like per-strand thresholds, and harolongo's head pass), checks that every commit
returns the same contacts, and writes its table into contact.md (section "Detection kernels") and
contact.json ("kernels"); a full run keeps that section.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ["NUMBA_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # reference.contact: the implementations the tests compare with
DEFAULT_DATA = REPO.parent / "shared" / "data"
HAROLONGO = ("digital-salon/harolongo.data", "digital-salon/Retopologised_Female_Head_01_mod.obj", 0.01)
USC_HEAD = "usc/head_model.obj"


# ----------------------------------------------------------------------------------------- data
def read_data(path: Path, scale: float = 1.0) -> list[np.ndarray]:
    """USC-HairSalon .data: int32 strand count, then per strand int32 count and float32 xyz."""
    raw = path.read_bytes()
    n = int(np.frombuffer(raw, "<i4", 1, 0)[0])
    pos, strands = 4, []
    for _ in range(n):
        c = int(np.frombuffer(raw, "<i4", 1, pos)[0])
        strands.append(np.frombuffer(raw, "<f4", 3 * c, pos + 4).reshape(c, 3).astype(np.float64) * scale)
        pos += 4 + 12 * c
    return strands


def ragged(strands):
    from groomtool.groom import Groom

    g = Groom.from_strands(strands)
    return g.points, g.offsets, g.arc_lengths()


def load_mesh(path: Path, scale: float = 1.0):
    import trimesh

    mesh = trimesh.load(path, process=False)
    mesh.apply_scale(scale)
    return mesh


def fitted_samples(data: Path):
    """harolongo as `groom invert --contacts all` sees it: fitted Super-Helices sampled at 8 points per
    element (points, offsets, arc)."""
    from groomtool.fit import fit_groom
    from groomtool.invert import InversionParams
    from groomtool.io import load_groom
    from groomtool.rods import superhelix as sh

    params = InversionParams(contacts="all")
    helix = fit_groom(load_groom(data / HAROLONGO[0], units="cm"), tolerance=params.tolerance).helix
    pts, offsets, _, arc = sh.sample(helix, params.samples_per_element)
    return pts, offsets, arc


def usc10k_samples(data: Path):
    """usc10k (bench_fit.py: 10,000 strands grown from cstrands00003's guides on roots10k) fitted and
    sampled as `groom invert --contacts all` does (points, offsets, arc)."""
    from groomtool.fit import fit_groom
    from groomtool.groom import Groom
    from groomtool.invert import InversionParams
    from groomtool.rods import superhelix as sh

    guides = read_data(data / "usc" / "cstrands" / "cstrands00003.data")
    roots = np.array([line.split()[1:4] for line in open(data / "usc" / "roots10k.obj") if line.startswith("v ")],
                     dtype=np.float64)
    guide_roots = np.array([g[0] for g in guides])
    nearest = np.argmin(((roots[:, None] - guide_roots[None]) ** 2).sum(-1), axis=1)
    groom = Groom.from_strands([guides[k] - guide_roots[k] + r for k, r in zip(nearest, roots)])
    params = InversionParams(contacts="all")
    helix = fit_groom(groom, tolerance=params.tolerance).helix
    pts, offsets, _, arc = sh.sample(helix, params.samples_per_element)
    return pts, offsets, arc


def groups_for(spec: dict, data: Path):
    """[((points, offsets, arc), mesh)] for a row spec; USC gives one group per style."""
    if spec["dataset"] == "harolongo_fitted":
        return [(fitted_samples(data), load_mesh(data / HAROLONGO[1], HAROLONGO[2]))]
    if spec["dataset"] == "usc10k_fitted":
        return [(usc10k_samples(data), load_mesh(data / USC_HEAD))]
    return [(ragged(strands), mesh) for strands, mesh in _polyline_groups(spec, data)]


def _polyline_groups(spec: dict, data: Path):
    if spec["dataset"] == "harolongo":
        strands = read_data(data / HAROLONGO[0], HAROLONGO[2])
        if spec.get("subset"):
            rng = np.random.default_rng(0)
            keep = np.sort(rng.choice(len(strands), spec["subset"], replace=False))
            strands = [strands[k] for k in keep]
        return [(strands, load_mesh(data / HAROLONGO[1], HAROLONGO[2]))]
    mesh = load_mesh(data / USC_HEAD)
    files = sorted((data / "usc" / "cstrands").glob("*.data"))
    return [(read_data(f), mesh) for f in files]


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


# ------------------------------------------------------------------------------------ one row
def run_row(spec: dict, data: Path) -> dict:
    from groomtool.contact import HeadSurface, detect_contacts

    prepared = groups_for(spec, data)
    (pts, off, arc), mesh = prepared[0]
    k = off[min(3, len(off) - 1)]
    detect_contacts(pts[:k], off[:4], arc[:k], spec["radius"], head=HeadSurface(mesh))  # loads the numba cache
    base = rss_mb()
    totals: dict = {}
    wall0, cpu0 = time.perf_counter(), time.process_time()
    n_inside = 0
    for (pts, off, arc), mesh in prepared:
        stats: dict = {}
        c = detect_contacts(pts, off, arc, spec["radius"], head=mesh, stats=stats)  # USC: one head, built once
        n_inside += int(np.sum(c.distance[c.is_head] < 0))
        stats["strands"] = len(off) - 1
        for k, v in stats.items():
            totals[k] = totals.get(k, 0) + v
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {**spec, **totals, "head_contacts_inside": n_inside, "wall_s": wall, "cpu_s": cpu,
            "peak_rss_mb": peak, "rss_before_mb": base, "groups": len(prepared)}


def run_head_row(spec: dict, data: Path, repeats: int = 3) -> dict:
    """The strand/head pass alone: bounded (``detect_head_contacts``) vs every vertex queried
    (``detect_head_contacts_reference``), CPU seconds of each repetition, and whether they agree."""
    from groomtool.contact import HeadSurface, detect_head_contacts
    from reference.contact import detect_head_contacts_reference

    prepared = groups_for(spec, data)
    meshes = {id(mesh): mesh for _, mesh in prepared}
    (pts, off, arc), mesh = prepared[0]
    k = off[min(3, len(off) - 1)]
    for fn in (detect_head_contacts, detect_head_contacts_reference):  # loads the numba cache
        fn(pts[:k], off[:4], arc[:k], HeadSurface(mesh), spec["radius"])
    fields = ("strand_a", "s_a", "strand_b", "s_b", "point_a", "point_b", "normal", "frame", "distance")
    cpu: dict = {"bounded": [], "reference": []}
    results: dict = {}
    totals: dict = {}
    for _ in range(repeats):
        for name, fn in (("reference", detect_head_contacts_reference), ("bounded", detect_head_contacts)):
            surfaces = {key: HeadSurface(m) for key, m in meshes.items()}  # fresh: lazy set-up is timed
            out, stats_all = [], {}
            cpu0 = time.process_time()
            for (p, o, a), m in prepared:
                stats: dict = {}
                out.append(fn(p, o, a, surfaces[id(m)], spec["radius"], stats=stats))
                for key, v in stats.items():
                    stats_all[key] = stats_all.get(key, 0) + v
            cpu[name].append(time.process_time() - cpu0)
            results[name] = out
            totals[name] = stats_all
    identical = all(np.array_equal(getattr(x, f), getattr(y, f), equal_nan=True)
                    for x, y in zip(results["bounded"], results["reference"]) for f in fields)
    new = totals["bounded"]
    inside = sum(int(np.sum(c.distance < 0)) for c in results["bounded"])
    return {**spec, **new, "strands": sum(len(o) - 1 for (_, o, _), _ in prepared),
            "head_contacts_inside": inside, "identical": bool(identical), "groups": len(prepared),
            "cpu_s_bounded": cpu["bounded"], "cpu_s_reference": cpu["reference"],
            "reference_head_vertices_queried": totals["reference"]["head_vertices_queried"],
            "reference_time_head_vertices": totals["reference"]["time_head_vertices"],
            "reference_time_head_refine": totals["reference"]["time_head_refine"]}


def row_label(spec: dict) -> str:
    name = spec["dataset"] + (f"-{spec['subset']}" if spec.get("subset") else "") + f"@{spec['radius'] * 1e6:g}um"
    return name + ("-head" if spec.get("head_only") else "")


def run_in_child(spec: dict, data: Path) -> dict:
    out = subprocess.run([sys.executable, __file__, "--data", str(data), "--row", json.dumps(spec)],
                         capture_output=True, text=True, check=True, env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    return json.loads(out.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- kernel timings
KERNELS = (("detect", "_close_pairs_kernel"), ("detect", "_local_minima_kernel"), ("detect", "_local_minima_unsorted"),
           ("detect", "_sorted_pairs"), ("head", "_strand_bounds_kernel"), ("head", "_head_minima_bounded_kernel"))


def kernel_workloads(data: Path) -> dict:
    """name -> (kind, points, offsets, arc, radius, kwargs, head mesh): the example grooms (README: 200
    strands; 1,000) fitted and sampled as the simulator samples them (8 points per element), with the
    simulator's kind of thresholds (r_c = 0.5 mm plus per-strand margins and half the skin: 1.05 to 3
    r_c for strand/strand, 1 to 4 r_c for the head) and the inversion's (r_c = 0.5 mm); harolongo as
    ``groom invert`` samples it, head pass at 50 um."""
    from groomtool.examples import example_groom
    from groomtool.fit import fit_groom
    from groomtool.invert import InversionParams
    from groomtool.rods import superhelix as sh

    out = {}
    rc = 5e-4
    for n in (200, 1000):
        groom, mesh = example_groom(n)
        helix = fit_groom(groom, tolerance=InversionParams().tolerance).helix
        pts, off, _, arc = sh.sample(helix, 8)
        rng = np.random.default_rng(0)
        rs = rc * rng.uniform(1.05, 3.0, n)
        rh = rc * rng.uniform(1.0, 4.0, n)
        out[f"example{n}-sim-strand"] = ("strand", pts, off, arc, rs, dict(min_self_arc=np.pi * rs.max(),
                                                                          merge_arc=4 * rs.max()), None)
        out[f"example{n}-sim-head"] = ("head", pts, off, arc, rh, dict(min_root_arc=np.pi * rh.max(),
                                                                      merge_arc=4 * rh.max()), mesh)
        out[f"example{n}@0.5mm-strand"] = ("strand", pts, off, arc, rc, {}, None)
    if (data / HAROLONGO[0]).is_file():
        pts, off, arc = fitted_samples(data)
        out["harolongo_fitted@50um-head"] = ("head", pts, off, arc, 5e-5, {},
                                             load_mesh(data / HAROLONGO[1], HAROLONGO[2]))
    return out


def run_kernel_row(data: Path, cache: Path) -> dict:
    """Time the kernels of the groomtool on the path (best of 3 calls after a warm one) on every workload;
    the workloads are built once and kept in ``cache`` (an .npz per workload, shared by the commits)."""
    import pickle

    import groomtool
    from groomtool.contact import HeadSurface, detect_head_contacts, detect_strand_contacts
    from groomtool.contact import detect as det
    from groomtool.contact import head as hd

    if cache.is_file():
        work = pickle.loads(cache.read_bytes())
    else:
        work = kernel_workloads(data)
        cache.write_bytes(pickle.dumps(work))
    acc: dict = {}
    for mod_name, name in KERNELS:
        mod = det if mod_name == "detect" else hd
        fn = getattr(mod, name, None)
        if fn is None:
            continue

        def timed(*a, _fn=fn, _name=name):
            t = time.process_time()
            r = _fn(*a)
            acc[_name] = acc.get(_name, 0.0) + time.process_time() - t
            return r
        setattr(mod, name, timed)
    rows = {}
    for label, (kind, pts, off, arc, radius, kw, mesh) in work.items():
        surface = HeadSurface(mesh) if mesh is not None else None
        best: dict = {}
        for rep in range(4):
            acc.clear()
            t = time.process_time()
            if kind == "strand":
                c = detect_strand_contacts(pts, off, arc, radius, **kw)
            else:
                c = detect_head_contacts(pts, off, arc, surface, radius, **kw)
            total = time.process_time() - t
            if rep == 0:  # warm (numba cache, capacity estimate)
                digest = [float(np.sum(np.nan_to_num(getattr(c, f)))) for f in ("s_a", "s_b", "distance")]
                n = len(c)
                continue
            for k, v in {**acc, "total": total}.items():
                best[k] = min(best.get(k, np.inf), v)
        rows[label] = {"cpu_s": best, "contacts": n, "digest": digest}
    return {"groomtool": str(Path(groomtool.__file__).parent), "rows": rows}


def kernels_main(args) -> None:
    import tempfile

    commits = args.commits.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="bench_kernels_"))
    cache = tmp / "workloads.pkl"
    trees = {}
    for c in commits:
        trees[c] = tmp / c.replace("/", "_")
        trees[c].mkdir()
        archive = subprocess.run(["git", "-C", str(REPO), "archive", c, "src/groomtool"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(trees[c])], input=archive.stdout, check=True)
        subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", c], capture_output=True, text=True)
    results: dict = {c: [] for c in commits}
    for rnd in range(args.rounds):
        for c in commits:
            env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                   "PYTHONPATH": str(trees[c] / "src")}
            out = subprocess.run([sys.executable, __file__, "--data", str(args.data), "--kernel-row", str(cache)],
                                 capture_output=True, text=True, check=True, env=env)
            results[c].append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"round {rnd + 1} {c} done", flush=True)
    labels = list(results[commits[0]][0]["rows"])
    table = {}
    for c in commits:
        table[c] = {}
        for label in labels:
            per = [r["rows"][label] for r in results[c]]
            keys = set().union(*(p["cpu_s"] for p in per))
            table[c][label] = {"cpu_ms": {k: 1e3 * min(p["cpu_s"].get(k, np.inf) for p in per) for k in keys},
                               "contacts": per[0]["contacts"], "digest": per[0]["digest"]}
    same = {label: all(table[c][label]["digest"] == table[commits[0]][label]["digest"]
                       and table[c][label]["contacts"] == table[commits[0]][label]["contacts"] for c in commits)
            for label in labels}
    shas = {c: subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", c], capture_output=True,
                              text=True).stdout.strip() for c in commits}
    lines = ["# Contact detection kernels, before/after", "",
             f"`bench/bench_contact.py --kernels --commits {args.commits}`: CPU ms per call (best of {args.rounds} "
             "alternating rounds x 3 calls, one process per commit and round, NUMBA_NUM_THREADS=1, "
             f"load average at the end {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores). Same contacts: "
             "count and sums of s_a, s_b, distance equal for every commit (the tests check every field).", ""]
    cols = ["_close_pairs_kernel", "_local_minima_kernel", "_local_minima_unsorted", "_sorted_pairs",
            "_strand_bounds_kernel", "_head_minima_bounded_kernel", "total"]
    lines.append("| workload | commit | contacts | " + " | ".join(c.strip("_") for c in cols) + " |")
    lines.append("|---|---|---:|" + "---:|" * len(cols))
    for label in labels:
        for c in commits:
            row = table[c][label]
            vals = [f"{row['cpu_ms'][k]:.1f}" if k in row["cpu_ms"] else "" for k in cols]
            lines.append(f"| {label} | {shas[c]} | {row['contacts']:,} | " + " | ".join(vals) + " |")
    lines += ["", "Same contacts on every workload: " + ("yes" if all(same.values()) else f"NO: {same}")]
    merge_kernel_section(args.out, lines, {"commits": shas, "table": table, "same": same, "raw": results})
    print("\n".join(lines))


KERNEL_SECTION = "## Detection kernels, before/after"


def kernel_section(md: str) -> str:
    """The kernels section of a contact.md text ('' if none)."""
    if KERNEL_SECTION not in md:
        return ""
    rest = md[md.index(KERNEL_SECTION):]
    end = rest.find("\n## ", 1)
    return rest if end < 0 else rest[:end + 1]


def merge_kernel_section(out: Path, lines: list, data: dict) -> None:
    """Put the kernel table into contact.md (replacing its section) and contact.json ("kernels")."""
    md_path, json_path = out / "contact.md", out / "contact.json"
    md = md_path.read_text() if md_path.is_file() else "# Contact detection benchmark\n"
    section = "\n".join([KERNEL_SECTION] + lines[1:]) + "\n"
    old = kernel_section(md)
    md = md.replace(old, section) if old else md.rstrip("\n") + "\n\n" + section
    md_path.write_text(md)
    js = json.loads(json_path.read_text()) if json_path.is_file() else {}
    js["kernels"] = data
    json_path.write_text(json.dumps(js, indent=1, default=float))


# ------------------------------------------------------------------------ head query comparison
def head_query_comparison(data: Path, n_points: int = 20000) -> dict:
    """Own BVH signed distance vs trimesh.proximity.closest_point on harolongo vertices near the head."""
    import trimesh

    from groomtool.contact import HeadSurface

    strands = read_data(data / HAROLONGO[0], HAROLONGO[2])
    mesh = load_mesh(data / HAROLONGO[1], HAROLONGO[2])
    pts = np.concatenate(strands)
    lo, hi = mesh.bounds
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    pts = pts[np.random.default_rng(0).choice(len(pts), min(n_points, len(pts)), replace=False)]
    t0 = time.perf_counter()
    head = HeadSurface(mesh)
    t_build = time.perf_counter() - t0
    head.query(pts[:10])
    t0 = time.perf_counter()
    d = head.query(pts)[0]
    t_own = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, d_tm, _ = trimesh.proximity.closest_point(mesh, pts)
    t_tm = time.perf_counter() - t0
    diff = d_tm - np.abs(d)
    return {"points": len(pts), "own_build_s": t_build, "own_us_per_point": 1e6 * t_own / len(pts),
            "trimesh_us_per_point": 1e6 * t_tm / len(pts), "speedup": t_tm / t_own,
            "max_own_minus_trimesh_m": float(np.max(-diff)), "trimesh_farther_fraction": float(np.mean(diff > 1e-9)),
            "max_trimesh_excess_m": float(np.max(diff))}


# ---------------------------------------------------------------------------- distance study
def distance_study(data: Path) -> dict:
    """Distributions behind the default radius: nearest other strand, head gaps."""
    from groomtool.contact import HeadSurface, close_segment_pairs, root_gaps
    from groomtool.contact.detect import strand_segments
    from reference.contact import vertex_signed_distances

    out = {}
    pct = [1, 5, 10, 25, 50, 75, 90]
    for name, groups in (("harolongo", _polyline_groups({"dataset": "harolongo"}, data)),
                         ("usc", _polyline_groups({"dataset": "usc"}, data))):
        probe = 1e-2 if name == "usc" else 2e-4  # pairs found up to 2 * probe
        nearest, gaps, strand_min = [], [], []
        head = HeadSurface(groups[0][1])
        for strands, _ in groups:
            pts, off, arc = ragged(strands)
            pairs = close_segment_pairs(pts, off, arc, probe)
            _, seg_strand = strand_segments(off)
            best = np.full(len(off) - 1, np.inf)
            other = seg_strand[pairs.i] != seg_strand[pairs.j]
            np.minimum.at(best, seg_strand[pairs.i][other], pairs.distance[other])
            np.minimum.at(best, seg_strand[pairs.j][other], pairs.distance[other])
            nearest.append(best)
            gaps.append(root_gaps(pts[off[:-1]], head))
            vd = vertex_signed_distances(pts, off, head, np.inf)
            for k in range(len(off) - 1):
                sl = slice(off[k], off[k + 1])
                beyond = arc[sl] > 0.01  # past the first centimetre
                if np.any(beyond):
                    strand_min.append(np.min(vd[sl][beyond]))
        nearest, gaps, strand_min = np.concatenate(nearest), np.concatenate(gaps), np.array(strand_min)
        near_um = np.quantile(nearest, np.array(pct) / 100, method="inverted_cdf") * 1e6
        out[name] = {
            "nearest_other_strand_probe_m": 2 * probe,
            "nearest_other_strand_um_percentiles": dict(zip(pct, [round(x, 1) for x in near_um.tolist()])),
            "strands_without_neighbour_within_probe": float(np.mean(~np.isfinite(nearest))),
            "root_gap_mm_percentiles": dict(zip(pct, np.round(np.percentile(gaps, pct) * 1e3, 3).tolist())),
            "roots_inside_fraction": float(np.mean(gaps < 0)),
            "strand_min_head_distance_mm_percentiles": dict(zip(pct, np.round(np.percentile(strand_min, pct) * 1e3, 3).tolist())),
            "strands_within_head_mm": {str(r): float(np.mean(strand_min < r * 1e-3)) for r in (0.05, 0.5, 1, 2, 5)},
        }
    return out


# ------------------------------------------------------------------------------------- report
STAGES = [("time_head_prepare", "head prep"), ("time_strand_pairs", "s/s pairs"), ("time_strand_dedup", "s/s dedup"),
          ("time_strand_frames", "s/s frames"), ("time_head_vertices", "head verts"), ("time_head_refine", "head refine")]


def head_table(rows: list[dict]) -> str:
    head = ["data", "strands", "r_c (um)", "vertices in box", "exact queries", "bounded", "late", "inside",
            "candidates", "s/h contacts (inside)", "identical", "head verts s", "head refine s",
            "cpu s bounded", "cpu s reference", "speedup"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        name = r["dataset"] if r["dataset"] != "usc" else f"usc cstrands ({r['groups']} styles)"
        new, ref = min(r["cpu_s_bounded"]), min(r["cpu_s_reference"])
        cells = [name, f"{r['strands']:,}", f"{r['radius'] * 1e6:g}", f"{r['head_vertices_in_box']:,}",
                 f"{r['head_vertices_queried']:,}", f"{r['head_vertices_bounded']:,}", f"{r['head_vertices_late']:,}",
                 f"{r['head_vertices_inside']:,}", f"{r['head_candidates']:,}",
                 f"{r['head_contacts']:,} ({r['head_contacts_inside']:,})", "yes" if r["identical"] else "**NO**",
                 f"{r['time_head_vertices']:.2f} ({r['reference_time_head_vertices']:.2f})",
                 f"{r['time_head_refine']:.2f} ({r['reference_time_head_refine']:.2f})",
                 " / ".join(f"{x:.2f}" for x in r["cpu_s_bounded"]),
                 " / ".join(f"{x:.2f}" for x in r["cpu_s_reference"]),
                 f"{ref / new:.1f}x"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    head = ["data", "strands", "segments", "r_c (um)", "group pairs", "candidates", "close pairs", "s/s contacts",
            "s/h contacts (inside)"] + [s for _, s in STAGES] + ["total wall s", "total cpu s", "peak MB (+run)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        name = r["dataset"] + (f" ({r['subset']} random strands)" if r.get("subset") else "")
        if r["dataset"] == "usc":
            name = f"usc cstrands ({r['groups']} styles)"
        cells = [name, f"{r['strands']:,}", f"{r['segments']:,}", f"{r['radius'] * 1e6:g}", f"{r['group_pairs']:,}",
                 f"{r['candidates']:,}", f"{r['close_pairs']:,}", f"{r['strand_contacts']:,}",
                 f"{r['head_contacts']:,} ({r['head_contacts_inside']:,})"]
        cells += [f"{r[k]:.2f}" for k, _ in STAGES]
        cells += [f"{r['wall_s']:.2f}", f"{r['cpu_s']:.2f}",
                  f"{r['peak_rss_mb']:.0f} (+{r['peak_rss_mb'] - r['rss_before_mb']:.0f})"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    ap.add_argument("--quick", action="store_true", help="default radius only, no distance study")
    ap.add_argument("--rows", help="re-run only these row labels (comma-separated) and merge them into contact.json")
    ap.add_argument("--row", help=argparse.SUPPRESS)
    ap.add_argument("--kernels", action="store_true", help="time the detection kernels of --commits (before/after)")
    ap.add_argument("--commits", default="HEAD", help="commits to compare with --kernels (comma-separated)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds of --kernels")
    ap.add_argument("--kernel-row", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.kernel_row:
        print(json.dumps(run_kernel_row(args.data, args.kernel_row), default=float))
        return
    if args.kernels:
        kernels_main(args)
        return
    if args.row:
        spec = json.loads(args.row)
        print(json.dumps(run_head_row(spec, args.data) if spec.get("head_only") else run_row(spec, args.data)))
        return
    if not (args.data / HAROLONGO[0]).is_file():
        sys.exit(f"real data not found under {args.data}")

    from groomtool.contact import DEFAULT_CONTACT_RADIUS

    radii = [DEFAULT_CONTACT_RADIUS] if args.quick else [25e-6, 40e-6, DEFAULT_CONTACT_RADIUS, 100e-6, 200e-6]
    specs = [{"dataset": "harolongo", "radius": r} for r in radii]
    specs += [{"dataset": "harolongo", "radius": DEFAULT_CONTACT_RADIUS, "subset": n} for n in (1000, 2000, 4000)]
    specs += [{"dataset": "harolongo_fitted", "radius": DEFAULT_CONTACT_RADIUS}]
    specs += [{"dataset": "usc", "radius": r} for r in ([DEFAULT_CONTACT_RADIUS] if args.quick else [DEFAULT_CONTACT_RADIUS, 1e-3])]
    specs += [{"dataset": d, "radius": DEFAULT_CONTACT_RADIUS, "head_only": True}
              for d in ("harolongo_fitted", "usc10k_fitted", "usc")]
    previous = None
    if args.rows:
        wanted = set(args.rows.split(","))
        unknown = wanted - {row_label(sp) for sp in specs}
        if unknown:
            sys.exit(f"unknown row labels {sorted(unknown)}; known: {[row_label(sp) for sp in specs]}")
        previous = json.loads((args.out / "contact.json").read_text())
        old_rows = {row_label(r): r for r in previous["rows"]}
        specs = [sp for sp in specs if row_label(sp) in wanted or row_label(sp) in old_rows]
    rows = []
    for spec in specs:
        if previous is not None and row_label(spec) not in wanted:
            rows.append(old_rows[row_label(spec)])
            continue
        rows.append(run_in_child(spec, args.data))
        r = rows[-1]
        if spec.get("head_only"):
            print(f"{row_label(spec):28s} head only: s/h {r['head_contacts']:>6,}  identical {r['identical']}  "
                  f"cpu bounded {min(r['cpu_s_bounded']):6.2f} s  reference {min(r['cpu_s_reference']):6.2f} s",
                  flush=True)
            continue
        print(f"{r['dataset']:9s} {r.get('subset') or r['strands']:>6} r_c={r['radius'] * 1e6:5.0f} um  "
              f"s/s {r['strand_contacts']:>8,}  s/h {r['head_contacts']:>6,}  wall {r['wall_s']:6.2f} s  "
              f"cpu {r['cpu_s']:6.2f} s  peak {r['peak_rss_mb']:.0f} MB", flush=True)
    if previous is not None:
        comparison, study = previous["head_query"], previous["distance_study"]
        for s in (study or {}).values():  # JSON made the percentile keys strings
            pcts = s["nearest_other_strand_um_percentiles"]
            s["nearest_other_strand_um_percentiles"] = {int(k): v for k, v in pcts.items()}
    else:
        comparison = head_query_comparison(args.data)
        study = None if args.quick else distance_study(args.data)
    env = {"python": platform.python_version(), "numpy": np.__version__,
           "numba": __import__("numba").__version__, "trimesh": __import__("trimesh").__version__,
           "cpu": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
           "load_average_at_end": os.getloadavg(), "numba_threads": 1}

    args.out.mkdir(parents=True, exist_ok=True)
    old_json = json.loads((args.out / "contact.json").read_text()) if (args.out / "contact.json").is_file() else {}
    old_kernels = kernel_section((args.out / "contact.md").read_text()) if (args.out / "contact.md").is_file() else ""
    (args.out / "contact.json").write_text(json.dumps({"rows": rows, "head_query": comparison,
                                                        "distance_study": study, "environment": env,
                                                        **({"kernels": old_json["kernels"]} if "kernels" in old_json
                                                           else {})}, indent=1))
    md = ["# Contact detection benchmark", "",
          "Generated by `bench/bench_contact.py` (one core: NUMBA_NUM_THREADS=1; each row in its own process; "
          "numba functions already compiled and cached). Stage columns are wall seconds. "
          f"Machine: {env['cpus']} CPUs, load average at the end {tuple(round(x, 2) for x in env['load_average_at_end'])} "
          "(shared machine: wall > cpu means other work competed for the cores).", "",
          "harolongo: 7,905 strands x 21 vertices (cm -> m) with its head mesh (21,510 faces); harolongo_fitted: "
          "the same strands as `groom invert --contacts all` samples them (fitted Super-Helices, 8 points per "
          "element, 2.7 M segments; roots not snapped); usc10k_fitted: 10,000 strands grown from cstrands00003's "
          "guides on usc/roots10k.obj (as in bench_fit.py), sampled the same way (3.0 M points); "
          "usc: 343 five-strand styles, each run separately against the USC head (13,832 faces), totals.", "",
          table([r for r in rows if not r.get("head_only")]), "",
          "group pairs: pairs of segment groups (runs of consecutive segments of a strand) whose boxes (inflated "
          "by r_c) overlap; candidates: segment pairs given the exact test (boxes overlap, lines closer than 2 r_c); "
          "close pairs: segment pairs closer than 2 r_c; "
          "contacts: one per local minimum after merging. s/h inside: head contacts with the axis inside the mesh.", "",
          "## Strand/head pass alone: bounded vs every vertex queried", "",
          "`detect_head_contacts` (distance bounds along each strand, docs/contact.md) against the previous "
          "implementation `detect_head_contacts_reference` (tests/reference/contact.py: every vertex in the inflated "
          "box queried), alternating, "
          "each with a fresh HeadSurface built outside the timing (so the bounded pass pays its own mesh checks). "
          "cpu s: process CPU seconds of each of the 3 repetitions; speedup: best reference / best bounded. "
          "head verts / head refine: wall seconds of the last run, bounded (reference). exact queries: vertices whose "
          "signed distance was computed (the reference computes all vertices in box); bounded: left with a lower "
          "bound; late: bounds the minima pass replaced by exact values; identical: every field of the contacts equal "
          "bit for bit.", "",
          head_table([r for r in rows if r.get("head_only")]), "",
          "## Head distance query: own BVH vs trimesh", "",
          f"{comparison['points']:,} harolongo vertices inside the head's box: own {comparison['own_us_per_point']:.2f} us/point "
          f"(BVH build {comparison['own_build_s'] * 1e3:.0f} ms incl. pseudo-normals), trimesh.proximity.closest_point "
          f"{comparison['trimesh_us_per_point']:.1f} us/point: {comparison['speedup']:.0f}x. trimesh's nearest point is "
          f"farther than the true one for {100 * comparison['trimesh_farther_fraction']:.1f} % of the points "
          f"(by up to {comparison['max_trimesh_excess_m'] * 1e6:.1f} um); ours is never farther "
          f"(max own - trimesh: {comparison['max_own_minus_trimesh_m']:.1e} m).", ""]
    if study:
        md += ["## Distance distributions (for the default radius)", ""]
        for name, s in study.items():
            md += [f"### {name}", "",
                   f"- nearest other strand, axis to axis (um), per strand, percentiles {list(s['nearest_other_strand_um_percentiles'])}: "
                   f"{list(s['nearest_other_strand_um_percentiles'].values())} (inf: none within "
                   f"{s['nearest_other_strand_probe_m'] * 1e3:g} mm; {100 * s['strands_without_neighbour_within_probe']:.0f} % of strands)",
                   f"- root signed gap to the head (mm), same percentiles: {list(s['root_gap_mm_percentiles'].values())}; "
                   f"roots inside the mesh: {100 * s['roots_inside_fraction']:.0f} %",
                   f"- per strand, smallest signed vertex distance to the head beyond the first cm (mm): "
                   f"{list(s['strand_min_head_distance_mm_percentiles'].values())}",
                   "- strands coming within X mm of the head (beyond the first cm): "
                   + ", ".join(f"{x} mm: {100 * f:.0f} %" for x, f in s["strands_within_head_mm"].items()), ""]
    (args.out / "contact.md").write_text("\n".join(md) + "\n" + ("\n" + old_kernels if old_kernels else ""))
    print()
    print(table([r for r in rows if not r.get("head_only")]))
    print(head_table([r for r in rows if r.get("head_only")]))
    print(json.dumps(comparison, indent=1))
    if study:
        print(json.dumps(study, indent=1))


if __name__ == "__main__":
    main()
