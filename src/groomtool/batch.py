"""Batch inversion of many grooms on Dask, from a laptop to a cluster (docs/batch.md).

    >>> from groomtool.batch import run_batch
    >>> summary = run_batch(["a.data", "b.data"], "out", head="head.obj", params={"contacts": "all"})  # doctest: +SKIP
    >>> summary.exit_code, summary.counts                                                              # doctest: +SKIP

Each groom runs the same inversion as ``groom invert`` in a ``dask.distributed`` task (small grooms are
grouped into tasks: ``plan_tasks``); its output set goes to ``OUTDIR/<groom stem>/`` (rest.npz,
rest_shape.obj, fitted.obj, report.json).

* **Where it runs**: a ``LocalCluster`` of ``workers`` processes with one thread each (default), a
  running scheduler (``scheduler="tcp://host:8786"``) or any ``distributed.Client`` (``client=``,
  e.g. one on a dask-jobqueue ``SLURMCluster``).
* **Threads**: numba and BLAS run one thread per worker (environment of the local workers, and
  ``threadpoolctl`` / ``numba.set_num_threads`` inside every task, which also holds on a cluster).
* **Complete output set**: the task writes with the project's writer (``io.results.write_result``),
  which stages the whole set beside the target and swaps it in (io/outset.py): ``OUTDIR/<stem>`` is
  the old complete set or the new one, never a mix, even when a worker is killed mid-write (its
  staging directory is removed by the retry's write or at the end of the batch). A groom's output is
  *complete* when ``OUTDIR/<stem>/report.json`` exists (the batch always writes it).
* **Resume**: a groom whose output set is complete is skipped (status ``skipped``, its figures read
  back from report.json and rest.npz); ``resume=False`` recomputes and replaces it.
* **Failures are isolated**: a groom that cannot be read (``input_error``), whose contact solve does
  not converge (``solver_failure``) or that raised anything else (``error``) is reported with its
  message and the batch goes on. A task whose worker dies (killed, over its memory limit) is rerun
  on another worker, up to ``retries`` times (Dask's ``allowed-failures``), then ``worker_lost``.
* **Summary**: ``OUTDIR/batch_summary.csv`` and ``.json``, one row per input in input order.
* **Exit code** (``BatchSummary.exit_code``): 0 all grooms inverted or skipped; 1 at least one
  input error, unexpected error or lost worker; 2 otherwise, i.e. only solver failures.
"""

from __future__ import annotations

import csv
import importlib.util
import io as _io
import json
import os
import sys
import time
import traceback
import uuid
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .groom import GroomError

STATUSES = ("ok", "skipped", "input_error", "solver_failure", "worker_lost", "error")
EXIT_OK, EXIT_USER_ERROR, EXIT_NOT_CONVERGED = 0, 1, 2
SUMMARY_NAME = "batch_summary"
COMPLETE_MARKER = "report.json"  # written last by io.results.write_result
DEFAULT_FORMATS = ("npz", "obj", "json")
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}

# Local cluster: less background polling than Dask's defaults (the statistical profiler every 10 ms, the
# event-loop tick every 20 ms, system and memory monitors): on a loaded 2-core machine they took
# ~7 % of a core, idle, out of the cores the inversions need (bench/results/batch.md).
LOCAL_CONFIG = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "100ms",
                "distributed.admin.system-monitor.interval": "2s",
                "distributed.worker.memory.monitor-interval": "500ms"}

# what the forkserver of the local workers imports once for all of them (_forkserver_context)
FORKSERVER_PRELOAD = ("distributed", "distributed.nanny", "distributed.worker", "groomtool.batch",
                      "groomtool.invert", "groomtool.io", "groomtool.io.results")

PRELOAD_ENV = "GROOMTOOL_BATCH_FORKSERVER"  # set only in the forkserver's environment: what to preload

# the summary's columns, in order (CSV header; the JSON rows carry these plus ``timings_s``)
COLUMNS = ("name", "input", "status", "strands", "elements", "contacts", "contacts_head", "contacts_strand",
           "solver", "solve_status", "solve_iterations", "residual", "q0_error_bound", "equilibrium_residual",
           "unstable_strands", "unstable_with_contacts", "q0_max", "q0_change_max", "fit_max_error_m",
           "load_s", "invert_s", "write_s", "wall_s", "worker", "worker_peak_rss_mib", "worker_cpu_s", "output", "error",
           "warnings")


@dataclass
class BatchSummary:
    """What :func:`run_batch` returns: one row per input (dicts with ``COLUMNS`` and ``timings_s``),
    the status counts, the exit code and where the summary files are."""

    rows: list[dict]
    outdir: Path
    wall_s: float
    workers: str
    counts: dict = field(default_factory=dict)
    exit_code: int = EXIT_OK
    csv_path: Path | None = None
    json_path: Path | None = None
    client_cpu_s: float | None = None  # CPU of this process (with a local cluster: its scheduler and nannies)

    def failed(self) -> list[dict]:
        return [r for r in self.rows if r["status"] not in ("ok", "skipped")]


# --------------------------------------------------------------------------------------------------
# one groom (runs in a worker)

_HEADS: dict = {}  # per worker process: (path, units, mtime) -> head mesh, loaded once


def _load_head_cached(path, units):
    from .io import load_head

    p = Path(path)
    key = (str(p), str(units), p.stat().st_mtime_ns)
    if key not in _HEADS:
        _HEADS.clear()
        _HEADS[key] = load_head(p, units=units)
    return _HEADS[key]


def _limit_threads():
    """One numba and one BLAS thread in this worker (whatever its environment says)."""
    from threadpoolctl import threadpool_limits

    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):  # pragma: no cover - numba is a dependency
        pass
    return threadpool_limits(limits=1)


def _empty_row(path, outdir) -> dict:
    row = {c: None for c in COLUMNS}
    row.update(name=Path(path).stem, input=str(path), output=str(Path(outdir) / Path(path).stem),
               timings_s={})
    return row


def _row_from_report(row: dict, report: dict) -> dict:
    row["strands"] = report.get("strands")
    row["elements"] = report.get("elements")
    c = report.get("contacts")
    if c:
        row.update(contacts=c.get("total"), contacts_head=c.get("strand_head"),
                   contacts_strand=c.get("strand_strand"))
    else:
        row.update(contacts=0, contacts_head=0, contacts_strand=0)
    s = report.get("solve")
    if s:
        row.update(solver=s.get("solver"), solve_status=s.get("status"), solve_iterations=s.get("iterations"),
                   residual=s.get("residual"), q0_error_bound=s.get("q0_error_bound"))
    if "equilibrium" in report:
        row["equilibrium_residual"] = report["equilibrium"].get("max_relative_residual")
    st = report.get("stability")
    if st:
        row["unstable_strands"] = st.get("unstable_strands")
        row["unstable_with_contacts"] = st.get("unstable_with_contacts")
    if "fit" in report:
        row["fit_max_error_m"] = report["fit"].get("max_error_m")
    timings = dict(report.get("timings_s") or {})
    row["timings_s"] = timings
    row["invert_s"] = timings.get("total")
    return row


def _q0_figures(rest, curvatures) -> tuple[float, float]:
    """max |q0| and max |q0 - q| over elements (1/m; the norm of (kappa1, kappa2, tau))."""
    rest = np.asarray(rest, dtype=np.float64).reshape(-1, 3)
    curvatures = np.asarray(curvatures, dtype=np.float64).reshape(-1, 3)
    if not len(rest):
        return 0.0, 0.0
    return (float(np.linalg.norm(rest, axis=1).max()),
            float(np.linalg.norm(rest - curvatures, axis=1).max()))


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"local:{os.getpid()}"


def _cpu_s() -> float | None:
    """CPU time (user + system) of this process so far."""
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return None
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _peak_rss_mib() -> float | None:
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def is_complete(out: Path) -> bool:
    """A groom's output set is complete when its report.json exists (written last, the directory
    only ever appears whole: see the module docstring)."""
    return (Path(out) / COMPLETE_MARKER).is_file()


def _extra_formats() -> tuple[str, ...]:
    """The formats written by the exporters (io/export.py) beside the default set: usd, abc, vtp, hair."""
    from .io.export import FORMATS

    return tuple(f for f in FORMATS if f not in DEFAULT_FORMATS)


def _write(result, target: Path, formats) -> None:
    """The output set, written by the project's writer as one atomic set (io/outset.py): the target
    directory is the old complete set or the new one, never a mix, even if the worker is killed."""
    from .io.results import write_result

    extra = [f for f in formats if f in _extra_formats()]
    if extra:
        from .io.export import export_formats

        def write_extra(stage):
            return export_formats(result, stage, extra)
    else:
        write_extra = None
    write_result(result, target, formats=tuple(f for f in formats if f in DEFAULT_FORMATS), extra=write_extra)


def invert_one(path, outdir, head=None, params=None, load_options=None, formats=DEFAULT_FORMATS) -> dict:
    """Invert one groom file and write its output set to ``outdir/<stem>/``; never raises for a bad
    groom: returns its summary row with ``status`` and ``error``.  This is the Dask task."""
    from .invert import InversionParams, SolverFailure, invert_groom
    from .io import load_groom

    t0 = time.perf_counter()
    path = Path(path)
    outdir = Path(outdir)
    row = _empty_row(path, outdir)
    row["worker"] = _worker_name()
    load_options = dict(load_options or {})
    units_name = load_options.pop("units_name", None)
    units = load_options.get("units", "m")
    caught = []
    try:
        with _limit_threads(), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                groom = load_groom(path, **load_options)
                mesh = _load_head_cached(head, units) if head is not None else None
            except (GroomError, OSError) as exc:
                row.update(status="input_error", error=str(exc))
                return row
            t1 = time.perf_counter()
            row["load_s"] = t1 - t0
            try:
                result = invert_groom(groom, head=mesh, params=params or InversionParams(), quiet=True)
            except SolverFailure as exc:
                _row_from_report(row, exc.report)
                row.update(status="solver_failure", solve_status=exc.status, residual=exc.residual,
                           error=f"{path}: {exc}")
                return row
            except GroomError as exc:
                row.update(status="input_error", error=str(exc))
                return row
            t2 = time.perf_counter()
            result.report["input_units"] = units_name or units
            _row_from_report(row, result.report)
            row["q0_max"], row["q0_change_max"] = _q0_figures(result.rest_curvatures, result.helix.curvatures)
            _write(result, outdir / path.stem, formats)
            row["write_s"] = time.perf_counter() - t2
            row["status"] = "ok"
    except Exception as exc:  # isolate anything else: the batch goes on
        row.update(status="error", error=f"{path}: {type(exc).__name__}: {exc}")
        row["traceback"] = traceback.format_exc(limit=8)
    finally:
        row["wall_s"] = time.perf_counter() - t0
        row["worker_peak_rss_mib"] = _peak_rss_mib()
        row["worker_cpu_s"] = _cpu_s()
        # warnings go to the summary, not to the terminal the progress bar is on
        row["warnings"] = "; ".join(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught)) or None
    return row


def invert_many(paths, outdir, head=None, params=None, load_options=None, formats=DEFAULT_FORMATS) -> list[dict]:
    """``invert_one`` for each groom of a task group, in order (the Dask task of ``run_batch``)."""
    return [invert_one(p, outdir, head, params, load_options, formats) for p in paths]


# estimated seconds of one groom's task (estimate_cost): COST_FIXED_S + COST_PER_STRAND_VERTEX_S x strands x
# vertices, fitted on 11 bundled-example grooms of 20-120 strands (1.7-10.3 k vertices; --contacts all;
# 0.36-2.97 s each, predicted within 0.25 s; bench/results/batch.cost_model.md); the fixed part is reading,
# writing and the per-groom set-up, the product the contact detection and solve that grow with both
COST_FIXED_S = 0.33
COST_PER_STRAND_VERTEX_S = 2.1e-6
VERTICES_PER_STRAND = 100  # where a format does not say how many strands (bare OBJ vertices, PLY)
BYTES_PER_VERTEX = {".obj": 48, ".data": 12, ".hair": 12}  # where the header cannot be read: 24 for others


def estimate_cost(path) -> float:
    """Estimated seconds of a groom's task, for ``plan_tasks``: from its strand and vertex counts read from
    the header (``io.peek.peek_counts``: a few bytes, or a byte scan of an OBJ), else from its file size.
    Relative costs are what matter; a missing or unreadable file gets the fixed part only."""
    from .io.peek import peek_counts

    path = Path(path)
    counts = peek_counts(path)
    if counts is None:
        try:
            size = path.stat().st_size
        except OSError:
            return COST_FIXED_S
        counts = (None, size // BYTES_PER_VERTEX.get(path.suffix.lower(), 24))
    strands, vertices = counts
    if strands is None:
        strands = max(1, vertices // VERTICES_PER_STRAND)
    return COST_FIXED_S + COST_PER_STRAND_VERTEX_S * float(strands) * float(vertices)


def plan_tasks(costs, workers: int, tail: int = 2) -> list[list[int]]:
    """Group grooms into tasks: guided self-scheduling on estimated costs (``estimate_cost``).

    Largest first; each task takes grooms, in that order, until its cost reaches remaining / (tail *
    workers) (at least one groom).  The first tasks are large, the last ones single small grooms, so the
    workers still finish together, while a dataset of many small grooms costs ~tail * workers * ln(n)
    tasks instead of n: Dask's per-task cost (~10 ms of scheduler and worker CPU, bench/results/batch.md)
    was a third of the work of a 70 ms USC style.  Returns lists of indices into ``costs``.
    """
    costs = np.asarray(costs, dtype=np.float64)
    costs = np.maximum(costs, 1e-9 * max(float(costs.max(initial=0.0)), 1.0))  # an empty file costs something
    order = np.argsort(-costs, kind="stable")
    remaining = float(costs.sum())
    share = max(int(tail) * max(int(workers), 1), 1)
    groups, k = [], 0
    while k < len(order):
        budget = remaining / share
        group, taken = [int(order[k])], float(costs[order[k]])
        k += 1
        while k < len(order) and taken + costs[order[k]] <= budget:
            group.append(int(order[k]))
            taken += float(costs[order[k]])
            k += 1
        remaining -= taken
        groups.append(group)
    return groups


def _worker_count(client, default: int) -> int:
    """The workers the scheduler has now, or the requested count where it has none yet (a cluster whose
    workers are still joining) or cannot say."""
    try:
        n = len(client.scheduler_info().get("workers", {}))
    except Exception:
        n = 0
    return n if n > 0 else max(int(default), 1)


def skipped_row(path, outdir) -> dict:
    """The summary row of a groom whose complete output set already exists (read back from it)."""
    row = _empty_row(path, outdir)
    out = Path(row["output"])
    try:
        report = json.loads((out / COMPLETE_MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        row.update(status="skipped", error=f"{out / COMPLETE_MARKER}: unreadable ({exc})")
        return row
    _row_from_report(row, report)
    row["status"] = "skipped"
    npz = out / "rest.npz"
    if npz.is_file():
        try:
            with np.load(npz) as z:
                row["q0_max"], row["q0_change_max"] = _q0_figures(z["rest_curvatures"], z["curvatures"])
        except (OSError, ValueError, KeyError):
            pass
    return row


# --------------------------------------------------------------------------------------------------
# the batch (runs in the client)


def _check_inputs(inputs) -> list[Path]:
    paths = [Path(p) for p in inputs]
    if not paths:
        raise GroomError("no input grooms given")
    seen: dict[str, Path] = {}
    for p in paths:
        if p.stem in seen:
            raise GroomError(f"{seen[p.stem]} and {p} would both write {p.stem}/: every input needs its own "
                             "file name (stem)")
        seen[p.stem] = p
    return paths


def _params(params):
    from .invert import InversionParams

    if params is None:
        return InversionParams()
    if isinstance(params, dict):
        from .api import inversion_params

        return inversion_params(**params)
    return params


def exit_code(rows) -> int:
    """0 when every groom was inverted or skipped, 1 when any had an input error, an unexpected error
    or lost its worker too often, else 2 (solver failures only)."""
    statuses = {r["status"] for r in rows}
    if statuses & {"input_error", "error", "worker_lost"}:
        return EXIT_USER_ERROR
    if "solver_failure" in statuses:
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def _cell(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v).replace("\n", " ")


def write_summary(summary: BatchSummary) -> tuple[Path, Path]:
    """OUTDIR/batch_summary.csv and .json, each written atomically."""
    from .io.atomic import atomic_write
    from .io.results import write_json

    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in summary.rows:
        w.writerow([_cell(r.get(c)) for c in COLUMNS])
    csv_path = atomic_write(summary.outdir / f"{SUMMARY_NAME}.csv", buf.getvalue())
    json_path = summary.outdir / f"{SUMMARY_NAME}.json"
    write_json(json_path, {"outdir": str(summary.outdir), "workers": summary.workers, "wall_s": summary.wall_s,
                           "client_cpu_s": summary.client_cpu_s, "counts": summary.counts,
                           "exit_code": summary.exit_code, "grooms": summary.rows})
    return csv_path, json_path


def _tidy(outdir: Path, names) -> None:
    """Remove what killed workers left beside the output sets (io.outset.recover: staging directories
    of processes that have ended)."""
    from .io.outset import recover

    for name in names:
        try:
            recover(outdir / name)
        except OSError:
            pass


def _restore_environ(saved: dict) -> None:
    """Set back the environment variables ``saved`` ({name: value or None})."""
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def _forkserver_context(head=None, units="m", params=None):
    """multiprocessing's forkserver for the local workers, started now (its preloading then runs while the
    caller goes on), or None where the platform has none (Windows: spawned workers).

    Spawned, every local worker process imported distributed and groomtool and loaded the numba kernels
    and the head mesh itself, the last two inside its first task (~3 s of CPU per worker on a 2-core
    machine, where the serial loop pays it once).  The forkserver does that once (``FORKSERVER_PRELOAD``,
    then ``_preload_in_forkserver``: ``warmup.warm_up`` with the batch's parameters, which loads the
    kernels such an inversion uses from numba's cache -- or compiles them once on a cold cache -- and the
    head), and the workers fork from it with all of it loaded.  It is started with the workers' one-thread environment (``THREAD_ENV``:
    numba and BLAS read it when imported) and lives as long as this process: later local clusters reuse
    it (and the head it loaded, if theirs is the same; another head is loaded by each worker).
    """
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():  # pragma: no cover - Windows
        return None
    from multiprocessing import forkserver

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(FORKSERVER_PRELOAD))
    try:  # distributed would set its own preload list (importing every optional package here first)
        import distributed.utils

        distributed.utils._forkserver_preload_set = True
    except (ImportError, AttributeError):  # pragma: no cover
        pass
    import base64
    import pickle

    preload = {"head": None if head is None else str(head), "units": units,
               "params": None if params is None else base64.b64encode(pickle.dumps(params)).decode("ascii")}
    spec = {PRELOAD_ENV: json.dumps(preload)}
    saved = {k: os.environ.get(k) for k in (*THREAD_ENV, PRELOAD_ENV)}
    os.environ.update({**THREAD_ENV, **spec})
    try:
        forkserver.ensure_running()
    except OSError:  # pragma: no cover - cannot start it: spawn the workers
        return None
    finally:
        _restore_environ(saved)
    return ctx


def _preload_in_forkserver() -> None:
    """In the forkserver (``PRELOAD_ENV`` set, see ``_forkserver_context``): load the kernels and the head,
    so that every worker forked from it starts with them.  Never raises (a failure costs time only: the
    workers then load what they need themselves)."""
    import base64
    import pickle

    from .warmup import warm_up

    spec = os.environ.pop(PRELOAD_ENV, None)  # not passed on to the workers
    if not spec:
        return
    try:
        config = json.loads(spec)
        params = pickle.loads(base64.b64decode(config["params"])) if config.get("params") else None
        warm_up(params, with_head=config.get("head") is not None)
        if config.get("head"):
            _load_head_cached(config["head"], config["units"])
    except Exception:  # pragma: no cover
        pass


def _local_cluster(workers: int, memory_limit, retries: int, start_method: str | None = "forkserver", head=None,
                   units="m", params=None):
    """A LocalCluster of ``workers`` one-thread processes (the batch's default).  ``start_method``
    "forkserver" (default, where the platform has it): the worker processes fork from a server preloaded
    with groomtool, its kernels and the ``head`` mesh (``_forkserver_context``); "spawn" or None:
    distributed's default (fresh interpreters).  A worker restarted after its process died is spawned."""
    import logging

    import dask
    from distributed import LocalCluster

    method = "spawn"
    if start_method == "forkserver" and _forkserver_context(head, units, params) is not None:
        method = "forkserver"
    with dask.config.set({"distributed.scheduler.allowed-failures": int(retries),
                          "distributed.worker.multiprocessing-method": method,
                          "distributed.nanny.pre-spawn-environ": THREAD_ENV, **LOCAL_CONFIG}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=memory_limit,
                            dashboard_address=":0", silence_logs=logging.ERROR, env=dict(THREAD_ENV))


def _progress_bar(total: int, skipped: int, quiet: bool):
    """The batch's bar, in the package's one form (``timing.progress``: its time left measured on the grooms
    after the first completed task, so the cluster's start-up does not inflate it), starting at the
    ``skipped`` grooms (resume) as tqdm's ``initial`` would (``timing.progress`` takes none)."""
    from .timing import progress

    bar = progress(total, "batch", quiet, unit="groom")
    if skipped and not bar.disable:
        bar.n = bar.initial = bar.last_print_n = skipped
        bar.refresh()
    return bar


def run_batch(inputs, outdir, head=None, params=None, *, units="m", scale: float = 1.0, up="y", repair=False,
              strand_length=None,
              formats=DEFAULT_FORMATS, workers: int = 2, scheduler: str | None = None, client=None,
              memory_limit="auto", retries: int = 3, resume: bool = True, quiet: bool = False) -> BatchSummary:
    """Invert every groom file in ``inputs`` into ``outdir/<stem>/`` on Dask; returns a
    :class:`BatchSummary` (also written as ``outdir/batch_summary.csv`` and ``.json``).

    head: head mesh path (read once per worker) or None; params: ``InversionParams`` or a dict for
    ``groomtool.api.inversion_params`` (e.g. ``{"contacts": "all"}``, lengths in metres);
    units/scale/up/repair/strand_length: how to read the inputs and the head (as ``groom invert``);
    formats: npz/obj/json/usd/abc/vtp/hair (json is always written: report.json marks a complete set).
    Where: ``client`` (a ``distributed.Client``), else ``scheduler`` (an address), else a LocalCluster
    of ``workers`` processes, one thread each, ``memory_limit`` each ("auto": the machine's memory
    shared out; "4GiB"; 0 for none) and ``retries`` reruns of a task whose worker died.
    resume: skip grooms whose output set is complete.  quiet: no progress bar.
    """
    from .io.common import unit_scale
    from .io.outset import check_target, resolve_target

    t0 = time.perf_counter()
    paths = _check_inputs(inputs)
    params = _params(params)
    if params.contacts == "head" and head is None:
        raise GroomError("contacts 'head' needs a head mesh (--head MESH)")
    if head is not None:
        head = Path(head).resolve()
        if not head.is_file():
            raise GroomError(f"{head}: no such head mesh")
    formats = tuple(dict.fromkeys(tuple(formats) + ("json",)))
    unknown = sorted(set(formats) - set(DEFAULT_FORMATS) - set(_extra_formats()))
    if unknown:
        raise GroomError(f"unknown output format(s) {', '.join(unknown)}")
    if "abc" in formats and importlib.util.find_spec("alembic3d") is None:  # once here, not once per groom
        from .io.alembic import INSTALL

        raise GroomError(f"--format abc needs the optional alembic3d package: {INSTALL}")

    outdir = resolve_target(outdir)  # the batch's root, holding one output set per groom
    if outdir.exists() and not outdir.is_dir():
        raise GroomError(f"{outdir}: exists and is not a directory: give a directory for the outputs")
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GroomError(f"{outdir}: cannot create the output directory: {exc.strerror or exc}") from None
    for p in paths:  # before any computation: every groom's output set can be written there
        check_target(outdir / p.stem, inputs=(p, head))
    if not (np.isfinite(scale) and scale > 0):
        raise GroomError(f"scale must be a positive number, got {scale:g}")
    load_options = {"units": unit_scale(units) * scale if scale != 1.0 else units, "up": up, "repair": repair,
                    "strand_length": strand_length, "units_name": units if isinstance(units, str) else None}

    rows: list[dict | None] = [None] * len(paths)
    todo = []
    for i, p in enumerate(paths):
        if resume and is_complete(outdir / p.stem):
            rows[i] = skipped_row(p, outdir)
        else:
            todo.append(i)
    if todo and client is None and scheduler is None:
        # the local workers' forkserver loads groomtool, its kernels and the head while this process goes on
        _forkserver_context(head, load_options["units"], params)
    if head is not None:  # a bad head fails the batch once, here, not every groom on the workers
        from .io import load_head

        load_head(head, units=unit_scale(units) * scale)

    bar = _progress_bar(len(paths), len(paths) - len(todo), quiet)
    where = "none needed"
    try:
        if todo:
            where = _run_tasks(paths, todo, rows, outdir, head, params, load_options, formats, workers,
                               scheduler, client, memory_limit, retries, bar)
    finally:
        bar.close()
        _tidy(outdir, [p.stem for p in paths])
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}
    summary = BatchSummary(rows=rows, outdir=outdir, wall_s=time.perf_counter() - t0, workers=where,
                           counts=counts, exit_code=exit_code(rows), client_cpu_s=_cpu_s())
    summary.csv_path, summary.json_path = write_summary(summary)
    return summary


def _run_tasks(paths, todo, rows, outdir, head, params, load_options, formats, workers, scheduler, client,
               memory_limit, retries, bar) -> str:
    from contextlib import ExitStack

    from distributed import Client, KilledWorker, as_completed

    with ExitStack() as stack:
        if client is None:
            if scheduler is not None:
                client = stack.enter_context(Client(scheduler))
                where = f"scheduler {scheduler}"
            else:
                # distributed's nanny writes its pre-spawn environment (NUMBA_NUM_THREADS=1, ...) into *this*
                # process's os.environ at every worker (re)start; put ours back when the cluster is gone, or the
                # caller's next numba compilation fails ("Cannot set NUMBA_NUM_THREADS ... once launched")
                stack.callback(_restore_environ, {k: os.environ.get(k) for k in THREAD_ENV})
                cluster = stack.enter_context(_local_cluster(workers, memory_limit, retries, head=head,
                                                             units=load_options["units"], params=params))
                client = stack.enter_context(Client(cluster))
                where = f"LocalCluster of {workers} worker processes, 1 thread each"
        else:
            where = f"client {client.scheduler.address}"
        head_arg = None if head is None else str(head)
        groups = plan_tasks([estimate_cost(paths[i]) for i in todo], workers=_worker_count(client, workers))
        futures = {}

        def submit(group, priority):
            names = [paths[i].stem for i in group]
            label = names[0] if len(group) == 1 else f"{names[0]}+{len(group) - 1}"
            args = [str(paths[i].resolve() if paths[i].exists() else paths[i]) for i in group]
            fut = client.submit(invert_many, args, str(outdir), head_arg, params, load_options, formats,
                                key=f"invert-{label}-{uuid.uuid4().hex[:8]}", pure=False, priority=priority)
            futures[fut] = group
            return fut

        # the planned order is largest first (priority), so that the last tasks are short and the workers
        # finish together
        for k, g in enumerate(groups):
            submit([todo[j] for j in g], len(groups) - k)
        failed = 0
        pending = as_completed(list(futures))
        for fut in pending:
            group = futures.pop(fut)
            try:
                got = fut.result()
            except Exception as exc:  # the task never returned: its worker died too often, or was lost
                if len(group) > 1:  # isolate the groom that kills its worker: rerun the group one by one
                    for i in group:
                        pending.add(submit([i], 0))
                    fut.release()
                    continue
                row = _empty_row(paths[group[0]], outdir)
                status = "worker_lost" if isinstance(exc, KilledWorker) else "error"
                row.update(status=status, error=f"{paths[group[0]]}: {type(exc).__name__}: {exc}")
                got = [row]
            for i, row in zip(group, got):
                rows[i] = row
                failed += row["status"] not in ("ok", "skipped")
            bar.set_postfix(failed=failed, refresh=False)
            bar.update(len(group))
            fut.release()
        return where


def print_summary(summary: BatchSummary, file=sys.stdout) -> None:
    c = summary.counts
    done = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in c.items() if v)
    print(f"groom batch: {len(summary.rows)} grooms in {summary.wall_s:.1f} s ({summary.workers}): {done}",
          file=file)
    print(f"  summary      {summary.csv_path}, {summary.json_path}", file=file)


if os.environ.get(PRELOAD_ENV):  # imported by the local workers' forkserver (FORKSERVER_PRELOAD)
    _preload_in_forkserver()
